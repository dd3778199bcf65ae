"""Front-ends: frame in, observations (undistorted track positions) out.

``make_frontend(name, camera, config, device)`` picks one by name: ``warp`` (the GPU front-end, Warp kernels
on CUDA or the CPU device) or ``opencv`` (pyramidal LK + Shi-Tomasi, the comparison baseline).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.config import TrackerConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import inv_T
from lapreco_hil.types import Frame, FrameMotion, Observations


class FrontEnd(Protocol):
    def process(self, frame: Frame, motion: FrameMotion | None = None) -> Observations:
        """Track into ``frame`` (camera 0's image), each track started where ``motion`` predicts it (None: where
        it was), and detect new corners; the observations carry this frame's funnel counts."""
        ...

    def match_view(self, image: np.ndarray, camera: CameraModel, T_other_this: np.ndarray,
                   camera_index: int = 1) -> Observations:
        """The current tracks found in another camera's simultaneous image (a stereo partner), searched along
        their epipolar lines (``T_other_this`` maps this camera's points into the other's): undistorted pixels
        of ``camera``'s pinhole K, the same track ids, ``camera=camera_index``."""
        ...


TRACKERS = ("auto", "warp", "opencv")


def track_capacity(config: TrackerConfig) -> int:
    """The most tracks a front-end holds: ``max_features``, at fast motion more (``track_budget``)."""
    return int(config.max_features * config.fast_features_scale)


def track_budget(config: TrackerConfig, motion_px: float | None) -> int:
    """How many tracks a frame keeps (new corners fill up to it): ``max_features``, or ``track_capacity`` where
    its pose prediction moves the tracks at least ``fast_motion_px`` (``motion_px``: the median predicted
    motion, None without a prediction). A point is an inlier once seen at three instants; at fast motion every
    frame is a keyframe and a track lives about two of them, so the slots, not the image, limit the map
    (docs/results.md, "Fast motion")."""
    if motion_px is not None and motion_px >= config.fast_motion_px:
        return track_capacity(config)
    return config.max_features


def resolve_tracker(name: str, device: str) -> str:
    """``auto``: the Warp front-end on a GPU; on a CPU-only machine the OpenCV baseline, which is faster there
    than Warp's CPU device (that device is for testing the kernels, not for speed)."""
    if name not in TRACKERS:
        raise ConfigError(f"unknown tracker '{name}' (known: {', '.join(TRACKERS)})")
    if name == "auto":
        return "warp" if device.startswith("cuda") else "opencv"
    return name


def make_frontend(name: str, camera: CameraModel, config: TrackerConfig, device: str | None = None) -> FrontEnd:
    if name == "opencv":
        from lapreco_hil.frontend.opencv import OpenCVFrontEnd

        return OpenCVFrontEnd(camera, config)
    if name == "warp":
        from lapreco_hil.frontend.warp import WarpFrontEnd

        return WarpFrontEnd(camera, config, device)
    raise ConfigError(f"unknown tracker '{name}' (known: opencv, warp)")


def partner_views(frontend, frame, rig: Rig | None):
    """A callable giving the frame's tracks as the rig's other cameras saw them (None for a mono frame): the
    mapper calls it for keyframes only."""
    if rig is None or not rig.is_stereo or not frame.views:
        return None

    def partners() -> list:
        return [frontend.match_view(frame.image_of(k), rig.cameras[k], inv_T(rig.T_cam0_cam[k]), k)
                for k in range(1, min(len(rig), frame.n_cameras))]

    return partners
