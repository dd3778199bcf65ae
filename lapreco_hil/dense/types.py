"""What passes between the dense surface's parts: a keyframe as multi-view stereo sees it, and its depth map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KeyframeView:
    """One keyframe's image with its refined pose, undistorted to the pinhole ``K`` (the mapper's one model for
    every view). A stereo partner is a view of its own (its pose is T_world_cam0 @ T_cam0_cam)."""

    kf_id: int
    colour: np.ndarray  # (H, W, 3) uint8 RGB, undistorted
    K: np.ndarray  # (3, 3)
    T_world_camera: np.ndarray  # (4, 4)
    # (H, W) bool, True where the pixel may be used: the lens's field of view after undistortion; None: all
    mask: np.ndarray | None = None
    # (near, far) metres in this camera that its sparse landmarks span (with a margin); None: unknown
    depth_range_m: tuple[float, float] | None = None
    reference: int | None = None  # a stereo partner: its rig's reference keyframe id (as Keyframe.reference)

    @property
    def size(self) -> tuple[int, int]:
        return self.colour.shape[1], self.colour.shape[0]


@dataclass
class DepthMap:
    """A keyframe's depth along its optical axis (z in the camera, metres), 0 where unknown, with a confidence
    in [0, 1] per pixel; ``K``/``T_world_camera`` are the ones it was computed with (fusion takes a map out
    again with these when bundle adjustment moves the keyframe)."""

    kf_id: int
    depth_m: np.ndarray  # (H, W) float32
    confidence: np.ndarray  # (H, W) float32
    K: np.ndarray
    T_world_camera: np.ndarray
    stats: dict | None = None  # how many pixels each check kept (a funnel), timings

    @property
    def valid(self) -> np.ndarray:
        return self.depth_m > 0
