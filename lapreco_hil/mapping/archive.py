"""The archive of a long run's retired landmarks: final positions, colours and inlier labels in flat arrays."""

from __future__ import annotations

import numpy as np


class LandmarkArchive:
    """Landmarks of retired keyframes: final positions, colours and inlier labels in flat arrays."""

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._joined = None
        self.observations = 0
        self.inlier_observations = 0

    def add(self, ids: np.ndarray, points: np.ndarray, colors: np.ndarray, inlier: np.ndarray) -> None:
        if len(ids):
            self._parts.append((ids, points, colors, inlier))
            self._joined = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ids, points, colours, inlier) of every archived landmark, oldest first."""
        if self._joined is None:
            if self._parts:
                self._joined = tuple(np.concatenate(a) for a in zip(*self._parts))
                self._parts = [self._joined]
            else:
                self._joined = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, bool))
        return self._joined

    def __len__(self) -> int:
        return len(self.arrays()[0])
