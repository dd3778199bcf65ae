"""Where each track should land in the next frame: the pose source gives the camera's motion between frames,
the map gives each track's depth (its landmark's), and the front-end starts Lucas-Kanade at the projection
(or, for a track with no depth yet, searches its epipolar line over the scene's depth range).

Fast scope motion moves tissue tens of pixels per frame; started from the same pixel, LK's pyramid loses it.
"""

from __future__ import annotations

import numpy as np

from lapreco_hil.geometry import inv_T
from lapreco_hil.types import FrameMotion

# the depth range searched along an epipolar line is the map's own range widened by these factors
NEAR_MARGIN, FAR_MARGIN = 0.5, 2.0


class MotionPredictor:
    """FrameMotion for each new frame from the previous frame's pose and track depths (``mapper``: the
    mapper's ``frames`` and ``track_depths``) and the new frame's pose prior."""

    def __init__(self, mapper, scene_depth_m: tuple[float, float]) -> None:
        self.mapper = mapper
        self.scene_depth_m = (float(scene_depth_m[0]), float(scene_depth_m[1]))

    def motion(self, T_world_camera: np.ndarray) -> FrameMotion | None:
        """The motion from the last mapped frame into a frame whose prior pose is ``T_world_camera``; None
        before the first frame."""
        frames = self.mapper.frames
        if not frames:
            return None
        prev = frames[-1]
        T_cur_prev = inv_T(T_world_camera) @ prev.T_prior  # the robot's relative motion (its errors drift slowly)
        T_prev = prev.T_refined if prev.T_refined is not None else prev.T_prior
        ids, depth = self.mapper.track_depths(prev.track_ids, T_prev)
        return FrameMotion(T_cur_prev, ids, depth, self.depth_range(depth))

    def depth_range(self, depth: np.ndarray) -> tuple[float, float]:
        """The map's depth range (5th to 95th percentile, widened) once it has points, else the scene's."""
        if len(depth) < 10:
            return self.scene_depth_m
        near, far = np.percentile(depth, [5, 95])
        return float(max(near * NEAR_MARGIN, 1e-3)), float(far * FAR_MARGIN)
