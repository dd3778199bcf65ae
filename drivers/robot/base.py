"""The one interface every robot back-end implements (real Dynamixel/CANopen drivers and simulators)."""

from __future__ import annotations

import abc

from lapreco_hil.types import JointSample, RobotDescription, RobotInfo
from lapreco_hil.drivers.device import Device


class RobotDriver(Device):
    """Reads joint positions (SI units) with capture timestamps. Reading only: never commands motion.

    A back-end implements ``_read``; ``read`` counts what it delivers (``readings_delivered``), so a caller
    can tell a robot that delivered nothing from one whose every reading was refused (see ``faults``)."""

    info: RobotInfo
    # URDF, tip link and hand-eye when the back-end knows them (simulator, session); else from configuration
    description: RobotDescription | None = None
    _readings_delivered: int = 0

    @abc.abstractmethod
    def _read(self, timeout_s: float | None) -> list[JointSample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""

    def read(self, timeout_s: float | None = None) -> list[JointSample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""
        samples = self._read(timeout_s)
        self._readings_delivered += len(samples)
        return samples

    @property
    def readings_delivered(self) -> int:
        """How many samples ``read`` has handed out since this object was made."""
        return self._readings_delivered
