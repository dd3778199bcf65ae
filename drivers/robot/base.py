"""The one interface every robot back-end implements (real Dynamixel/CANopen drivers and simulators)."""

from __future__ import annotations

import abc

from ...types import JointSample, RobotDescription, RobotInfo
from ..health import Health


class RobotDriver(abc.ABC):
    """Reads joint positions (SI units) with capture timestamps. Reading only: never commands motion."""

    info: RobotInfo
    # URDF, tip link and hand-eye when the back-end knows them (simulator, session); else from configuration
    description: RobotDescription | None = None

    @abc.abstractmethod
    def open(self) -> None:
        """Connect; raises a DeviceError naming the device when it cannot."""

    @abc.abstractmethod
    def close(self) -> None:
        """Disconnect and stop any reader thread; safe to call twice."""

    @abc.abstractmethod
    def read(self, timeout_s: float | None = None) -> list[JointSample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""

    @property
    @abc.abstractmethod
    def health(self) -> Health:
        ...

    def __enter__(self) -> "RobotDriver":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
