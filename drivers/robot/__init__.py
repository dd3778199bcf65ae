from lapreco_hil.drivers.robot.base import RobotDriver

__all__ = ["RobotDriver"]
