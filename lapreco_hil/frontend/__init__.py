"""Front-ends: frame in, observations (undistorted track positions) out.

``make_frontend(name, camera, config)`` picks one by name: ``opencv`` (pyramidal LK + Shi-Tomasi, the
comparison baseline).
"""

from __future__ import annotations

from typing import Protocol

from ..camera import CameraModel
from ..config import TrackerConfig
from ..errors import ConfigError
from ..types import Frame, Observations


class FrontEnd(Protocol):
    def process(self, frame: Frame) -> Observations:
        ...


def make_frontend(name: str, camera: CameraModel, config: TrackerConfig) -> FrontEnd:
    if name == "opencv":
        from .opencv import OpenCVFrontEnd

        return OpenCVFrontEnd(camera, config)
    raise ConfigError(f"unknown tracker '{name}' (known: opencv)")
