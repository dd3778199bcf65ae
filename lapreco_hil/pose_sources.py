"""Where camera-pose priors come from: a robot's joint readings through its kinematics, or camera poses
given directly (an external optical tracker, a calibrated stereo rig). Both answer ``prior_at(t_ns)``."""

from __future__ import annotations

import numpy as np

from .config import PriorConfig
from .errors import ConfigError
from .geometry import SampledPoses
from .kinematics import CameraKinematics, PoseAtTime
from .robot_models import urdf_path
from .types import PosePrior, RobotDescription


class RobotPoseSource:
    """Joint samples from a RobotDriver -> FK of the camera at frame times, with the Jacobian covariance."""

    def __init__(self, robot, description: RobotDescription, prior: PriorConfig, offset_ns: int = 0) -> None:
        self.robot = robot
        kin = CameraKinematics(str(urdf_path(description.urdf)), description.tip_frame, description.T_tip_camera,
                               description.T_world_base)
        self.pose_at = PoseAtTime(kin, prior.joint_sigma, prior.floor_rot_sigma_rad, prior.floor_trans_sigma_m,
                                  offset_ns=offset_ns)
        self.rejected = 0

    def poll(self) -> list:
        """Take the robot's new samples (a reading with a NaN or infinite joint, or a time that does not move
        forward, is refused and counted in ``rejected``); returns the accepted ones (a live run records them)."""
        samples = self.robot.read(timeout_s=0.0)
        good = []
        for s in samples:
            last = self.pose_at.last_time_ns
            if not np.all(np.isfinite(s.q)) or s.q.shape != (self.pose_at.kin.n_joints,) or \
                    (last is not None and s.t_ns <= last):
                self.rejected += 1
                continue
            self.pose_at.add(s)
            good.append(s)
        return good

    def prior_at(self, t_ns: int) -> PosePrior:
        return self.pose_at.prior_at(t_ns)


class GivenPoseSource:
    """Camera poses T_world_camera known at times (an optical tracker): interpolated on SE(3) at frame
    times, clamped at the ends, with a fixed diagonal covariance."""

    def __init__(self, t_ns: np.ndarray, poses: np.ndarray, sigma_rotation_rad: float, sigma_translation_m: float,
                 offset_ns: int = 0) -> None:
        if len(t_ns) == 0:
            raise ConfigError("no camera poses given")
        self.poses = SampledPoses(np.asarray(t_ns, np.int64), np.asarray(poses, float))
        self.offset_ns = offset_ns
        self.cov = np.diag([sigma_rotation_rad**2] * 3 + [sigma_translation_m**2] * 3)

    def poll(self) -> list:
        return []

    def prior_at(self, t_ns: int) -> PosePrior:
        T = self.poses(t_ns + self.offset_ns)
        return PosePrior(T_world_camera=T.copy(), cov=self.cov.copy(), t_ns=t_ns)
