"""The one interface every frame source implements (V4L2 grabber, simulated grabber, session replay)."""

from __future__ import annotations

import abc

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.types import Frame
from lapreco_hil.drivers.device import Device


class Grabber(Device):
    """Delivers frames stamped with their capture time."""

    # frames per second the source delivers when it knows (None: unknown until frames arrive)
    nominal_fps: float | None = None

    @abc.abstractmethod
    def read(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame, or None when the source has ended."""

    @property
    def camera(self) -> CameraModel | None:
        """The calibrated camera when the source knows it (simulator, session); None for a bare grabber."""
        return None

    @property
    def rig(self) -> Rig | None:
        """All the cameras whose images a frame carries (``Frame.views``) with their extrinsics; a mono source
        is a rig of one (its ``camera``). None when the camera is not known."""
        camera = self.camera
        return Rig.mono(camera) if camera is not None else None

    @property
    def ground_truth(self):
        """A GroundTruth (true surface, true camera poses) when the source has one (simulator, session)."""
        return None
