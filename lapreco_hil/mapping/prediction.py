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


def depths_in_front(ids: np.ndarray, points: np.ndarray, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids, z) of the world ``points`` that lie in front of the camera at ``T_world_camera``."""
    T_cw = inv_T(T_world_camera)
    z = np.asarray(points, float).reshape(-1, 3) @ T_cw[2, :3] + T_cw[2, 3]
    return np.asarray(ids, np.int64)[z > 0], z[z > 0]


def depth_span(z: np.ndarray, min_points: int = 8) -> tuple[float, float] | None:
    """The depths a keyframe's landmarks span (2nd to 98th percentile of ``z``, the positive ones) with a margin
    (x0.8, x1.25): where dense stereo searches; None for fewer than ``min_points``."""
    z = np.asarray(z, float)
    z = z[z > 0]
    if len(z) < min_points:
        return None
    return float(0.8 * np.percentile(z, 2)), float(1.25 * np.percentile(z, 98))


def frame_motion(T_world_prev: np.ndarray, T_world_cur: np.ndarray, track_ids: np.ndarray, depth_m: np.ndarray,
                 scene_depth_m: tuple[float, float]) -> FrameMotion:
    """The motion from a frame at ``T_world_prev`` into one at ``T_world_cur`` (pose priors: the robot's relative
    motion is good even where its absolute pose is not), with the depths known for ``track_ids``."""
    return FrameMotion(inv_T(T_world_cur) @ T_world_prev, np.asarray(track_ids, np.int64), np.asarray(depth_m, float),
                       depth_range(depth_m, scene_depth_m))


def depth_range(depth: np.ndarray, scene_depth_m: tuple[float, float]) -> tuple[float, float]:
    """The map's depth range (5th to 95th percentile, widened) once it has points, else the scene's."""
    if len(depth) < 10:
        return (float(scene_depth_m[0]), float(scene_depth_m[1]))
    near, far = np.percentile(depth, [5, 95])
    return float(max(near * NEAR_MARGIN, 1e-3)), float(far * FAR_MARGIN)


class TrackPoints:
    """The world points of tracks, as the mapper last sent them (live: the mapper runs in another process), for
    the tracking stage's predictions. Bounded: only the tracks of the newest message are kept."""

    def __init__(self) -> None:
        self._ids = np.zeros(0, np.int64)
        self._points = np.zeros((0, 3))

    def update(self, ids: np.ndarray, points: np.ndarray) -> None:
        order = np.argsort(ids)
        self._ids, self._points = np.asarray(ids, np.int64)[order], np.asarray(points, float)[order]  # one swap

    def depths(self, track_ids: np.ndarray, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids, z in the camera at ``T_world_camera``) of those of ``track_ids`` with a point in front of it."""
        ids, points = self._ids, self._points
        if not len(ids) or not len(track_ids):
            return np.zeros(0, np.int64), np.zeros(0)
        at = np.clip(np.searchsorted(ids, track_ids), 0, len(ids) - 1)
        known = ids[at] == track_ids
        return depths_in_front(np.asarray(track_ids)[known], points[at[known]], T_world_camera)


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
        T_prev = prev.T_refined if prev.T_refined is not None else prev.T_prior
        ids, depth = self.mapper.track_depths(prev.track_ids, T_prev)
        return frame_motion(prev.T_prior, T_world_camera, ids, depth, self.scene_depth_m)
