"""Where camera-pose priors come from: a robot's joint readings through its kinematics, or camera poses
given directly (an external optical tracker, a calibrated stereo rig). Both answer ``prior_at(t_ns)``."""

from __future__ import annotations

import time

import numpy as np

from .config import PriorConfig
from .errors import ConfigError
from .geometry import SampledPoses
from .drivers.health import Health, HealthState
from .kinematics import CameraKinematics, PoseAtTime, prismatic_joints
from .robot_models import urdf_path
from .types import PosePrior, RobotDescription


class RobotPoseSource:
    """Joint samples from a RobotDriver -> FK of the camera at frame times, with the Jacobian covariance.

    Whatever the robot delivers is checked before it becomes a pose: a reading with a NaN or infinite joint,
    a joint beyond the URDF's limits (plus a margin for calibration slack), or a time that does not move
    forward is refused and counted; ``health`` shows it as degraded while refusals keep coming."""

    limit_margin_rad = 0.05
    limit_margin_m = 0.005
    degraded_for_s = 0.25

    def __init__(self, robot, description: RobotDescription, prior: PriorConfig, offset_ns: int = 0) -> None:
        self.robot = robot
        if description.T_tip_camera is None:
            raise ConfigError(f"robot '{getattr(getattr(robot, 'url', None), 'raw', robot)}' has no hand-eye "
                              f"(T_tip_camera; a calibration session has none): make one with 'lapreco calibrate "
                              f"handeye SESSION --board ... --out handeye.yaml' and pass --hand-eye handeye.yaml")
        kin = CameraKinematics(str(urdf_path(description.urdf)), description.tip_frame, description.T_tip_camera,
                               description.T_world_base)
        self.pose_at = PoseAtTime(kin, prior.joint_sigma, prior.floor_rot_sigma_rad, prior.floor_trans_sigma_m,
                                  offset_ns=offset_ns)
        margin = np.where(prismatic_joints(kin.model), self.limit_margin_m, self.limit_margin_rad)
        self._lower, self._upper = kin.info.limits.lower - margin, kin.info.limits.upper + margin
        self._names = kin.info.joint_names
        self.rejected = 0
        self.rejected_by_cause: dict[str, int] = {}
        self._last_refusal = ""
        self._last_refusal_wall = 0.0

    def _refusal(self, s) -> tuple[str, str] | None:
        """(cause, message) when the sample cannot be a pose, else None."""
        n = self.pose_at.kin.n_joints
        if s.q.shape != (n,):
            return "joint count", f"{s.q.shape[0] if s.q.ndim else 0} joints, the robot model has {n}"
        if not np.all(np.isfinite(s.q)):
            return "non-finite joint value", "non-finite joint value"
        bad = np.flatnonzero((s.q < self._lower) | (s.q > self._upper))
        if len(bad):
            i = int(bad[0])
            return "beyond limits", f"joint '{self._names[i]}' = {s.q[i]:.4g} beyond its limits"
        last = self.pose_at.last_time_ns
        if last is not None and s.t_ns <= last:
            return "time did not move forward", "time did not move forward"
        return None

    def poll(self) -> list:
        """Take the robot's new samples, refusing (and counting) what cannot be a pose; returns the accepted
        ones (a live run records them)."""
        samples = self.robot.read(timeout_s=0.0)
        good = []
        for s in samples:
            refusal = self._refusal(s)
            if refusal is not None:
                cause, message = refusal
                self.rejected += 1
                self.rejected_by_cause[cause] = self.rejected_by_cause.get(cause, 0) + 1
                self._last_refusal, self._last_refusal_wall = message, time.monotonic()
                continue
            self.pose_at.add(s)
            good.append(s)
        return good

    @property
    def health(self) -> Health:
        if time.monotonic() - self._last_refusal_wall < self.degraded_for_s:
            return Health(HealthState.DEGRADED, f"{self.rejected} readings refused; last: {self._last_refusal}")
        return Health(HealthState.OK)

    def has_pose(self) -> bool:
        """Whether a prior can be given yet: not before the robot's first accepted reading (a recording may
        start its video before the joint stream)."""
        return len(self.pose_at) > 0

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

    def has_pose(self) -> bool:
        return True

    def prior_at(self, t_ns: int) -> PosePrior:
        T = self.poses(t_ns + self.offset_ns)
        return PosePrior(T_world_camera=T.copy(), cov=self.cov.copy(), t_ns=t_ns)
