"""How much of the scope's view holds tracks: the front-end's health beyond "tracks / no tracks".

An instrument or a blood stain over part of the view leaves tracks elsewhere, so a count of tracks says little
(re-detection refills the budget where texture is left). What changes is how much of the field of view the
tracks span: a grid of cells over the undistorted image, counting only cells whose centre lies inside the
scope's circular field of view. The view is *partial* while the covered share falls below a fraction of what
this run normally covers (a high percentile over a long window, so a passing occlusion does not lower it;
a scene that is darker overall does, after the window)."""

from __future__ import annotations

import collections

import numpy as np

from lapreco_hil.camera import CameraModel


class ViewCoverage:
    def __init__(self, camera: CameraModel, cells: tuple[int, int] = (8, 6), partial_below: float = 0.6,
                 window_frames: int = 1500, min_frames: int = 25) -> None:
        self.cols, self.rows = cells
        self.width, self.height = camera.width, camera.height
        self.partial_below = partial_below
        self.min_frames = min_frames
        cx = (np.arange(self.cols) + 0.5) * camera.width / self.cols
        cy = (np.arange(self.rows) + 0.5) * camera.height / self.rows
        gx, gy = np.meshgrid(cx, cy)
        rays = np.column_stack([gx.ravel(), gy.ravel(), np.ones(gx.size)]) @ np.linalg.inv(camera.K).T
        uv = np.rint(camera.project(rays)).astype(int)  # where each undistorted cell centre lies in the frame
        fov = camera.fov_mask()
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        inside[inside] = fov[uv[inside, 1], uv[inside, 0]] > 0
        self.in_view = inside.reshape(self.rows, self.cols)
        self._history: collections.deque[float] = collections.deque(maxlen=window_frames)
        self.share = 0.0
        self.partial = False

    def update(self, uv: np.ndarray) -> bool:
        """Take one frame's track positions (undistorted pixels); returns whether the view is partial."""
        cells = np.zeros((self.rows, self.cols), bool)
        if len(uv):
            ix = np.clip((uv[:, 0] * self.cols / self.width).astype(int), 0, self.cols - 1)
            iy = np.clip((uv[:, 1] * self.rows / self.height).astype(int), 0, self.rows - 1)
            cells[iy, ix] = True
        self.share = float((cells & self.in_view).sum() / max(self.in_view.sum(), 1))
        self._history.append(self.share)
        if len(self._history) < self.min_frames:
            self.partial = False
        else:
            normal = float(np.percentile(np.fromiter(self._history, float), 90))
            self.partial = 0 < self.share < self.partial_below * normal
        return self.partial
