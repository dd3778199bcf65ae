"""The one interface every robot back-end implements (real Dynamixel/CANopen drivers and simulators)."""

from __future__ import annotations

from lapreco_hil.types import JointSample, RobotDescription, RobotInfo
from lapreco_hil.drivers.device import SampleStream


class RobotDriver(SampleStream[JointSample]):
    """Reads joint positions (SI units) with capture timestamps. Reading only: never commands motion."""

    info: RobotInfo
    # URDF, tip link and hand-eye when the back-end knows them (simulator, session); else from configuration
    description: RobotDescription | None = None
