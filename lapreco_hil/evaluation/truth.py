"""Ground truth a source may carry: the true surface and the true camera poses (simulator, session)."""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from ..geometry import interpolate_pose


@dataclass(frozen=True)
class SampledPoses:
    """True T_world_camera at known times; interpolated on SE(3) in between, clamped at the ends."""

    t_ns: np.ndarray  # (N,) int64, strictly increasing
    poses: np.ndarray  # (N, 4, 4)

    def __call__(self, t_ns: int) -> np.ndarray:
        times = self.t_ns
        i = bisect.bisect_right(times, t_ns)
        if i == 0:
            return self.poses[0]
        if i >= len(times):
            return self.poses[-1]
        s = (t_ns - times[i - 1]) / (times[i] - times[i - 1])
        return interpolate_pose(self.poses[i - 1], self.poses[i], s)


@dataclass(frozen=True)
class GroundTruth:
    """``surface``: a pyvista PolyData in the world frame (metres) or None; ``camera_pose``: a callable
    t_ns -> true T_world_camera, or None."""

    surface: object | None = None
    camera_pose: object | None = None
