from .base import RobotDriver

__all__ = ["RobotDriver"]
