"""Front-ends: frame in, observations (undistorted track positions) out.

``make_frontend(name, camera, config, device)`` picks one by name: ``warp`` (the GPU front-end, Warp kernels
on CUDA or the CPU device) or ``opencv`` (pyramidal LK + Shi-Tomasi, the comparison baseline).
"""

from __future__ import annotations

from typing import Protocol

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.types import Frame, Observations


class FrontEnd(Protocol):
    def process(self, frame: Frame) -> Observations:
        ...


TRACKERS = ("auto", "warp", "opencv")


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
