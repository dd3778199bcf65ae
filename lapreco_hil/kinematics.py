"""Robot kinematics with Pinocchio: URDF + hand-eye -> camera pose, its covariance, and pose at a time.

The camera is added to the Pinocchio model as an operational frame placed at ``T_tip_camera`` on the tip
link, so FK and the manipulator Jacobian of the camera come from one model.
"""

from __future__ import annotations

import bisect
import collections

import numpy as np
import pinocchio as pin

from lapreco_hil.errors import ConfigError, LaprecoError
from lapreco_hil.geometry import AFTER_LAST, BEFORE_FIRST, MAX_GAP_PERIODS, interpolate_pose, make_T, no_pose_cause
from lapreco_hil.types import JointLimits, JointSample, PosePrior, RobotInfo


def prismatic_joints(model: "pin.Model") -> np.ndarray:
    """(nq,) bool: which joints of a Pinocchio model are prismatic (positions in metres, not radians)."""
    return np.array([j.shortname().startswith("JointModelP") and "Planar" not in j.shortname()
                     for j in model.joints[1:]])


def load_urdf_model(urdf_file) -> "pin.Model":
    """A Pinocchio model from a URDF file, checked first: readable UTF-8, well-formed XML with a <robot>
    root, finite joint limits (lower <= upper) and finite placements. Anything else is one ConfigError
    naming the file and the problem (Pinocchio's own parser is handed only well-formed text)."""
    import xml.etree.ElementTree as ET

    path = str(urdf_file)
    try:
        text = open(path, "rb").read().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read URDF ({exc.strerror}); check the path") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: URDF is not UTF-8 text (byte {exc.start}); fix or re-export the file") from None
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ConfigError(f"{path}: URDF is not well-formed XML ({exc}); fix the file") from None
    if root.tag != "robot":
        raise ConfigError(f"{path}: URDF root element is <{root.tag}>, expected <robot>")
    try:
        model = pin.buildModelFromXML(text)
    except (RuntimeError, ValueError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot load URDF ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    lower, upper = model.lowerPositionLimit, model.upperPositionLimit
    for i, name in enumerate(model.names[1:]):
        if i < len(lower) and not (np.isfinite(lower[i]) and np.isfinite(upper[i]) and lower[i] <= upper[i]):
            raise ConfigError(f"{path}: joint '{name}' has limits [{lower[i]}, {upper[i]}]; give finite limits "
                              f"with lower <= upper")
    for name, placement in zip(model.names[1:], model.jointPlacements[1:]):
        if not np.all(np.isfinite(placement.homogeneous)):
            raise ConfigError(f"{path}: joint '{name}' has a non-finite origin; fix its <origin>")
    return model


class CameraKinematics:
    """FK of the camera frame: T_world_camera = T_world_base * FK_tip(q) * T_tip_camera."""

    def __init__(self, urdf_file: str, tip_frame: str, T_tip_camera: np.ndarray,
                 T_world_base: np.ndarray | None = None) -> None:
        self.model = load_urdf_model(urdf_file)
        if not self.model.existFrame(tip_frame):
            names = [f.name for f in self.model.frames]
            raise ConfigError(f"{urdf_file}: no frame '{tip_frame}' (frames: {', '.join(names)})")
        tip_id = self.model.getFrameId(tip_frame)
        tip = self.model.frames[tip_id]
        placement = tip.placement * pin.SE3(T_tip_camera[:3, :3].copy(), T_tip_camera[:3, 3].copy())
        self.camera_frame = self.model.addFrame(
            pin.Frame("camera", tip.parentJoint, tip_id, placement, pin.FrameType.OP_FRAME))
        self.tip_frame = tip_id
        self.data = self.model.createData()
        self.T_world_base = np.eye(4) if T_world_base is None else np.asarray(T_world_base, float)
        self.T_tip_camera = np.asarray(T_tip_camera, float)
        if self.model.nq != self.model.nv:
            raise ConfigError(f"{urdf_file}: only revolute/prismatic joints are supported (nq != nv)")
        self.info = RobotInfo(
            name=self.model.name,
            joint_names=tuple(self.model.names[1:]),
            limits=JointLimits(self.model.lowerPositionLimit.copy(), self.model.upperPositionLimit.copy()),
        )

    @property
    def n_joints(self) -> int:
        return self.model.nq

    def _fk(self, q: np.ndarray, frame: int) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        pin.framesForwardKinematics(self.model, self.data, q)
        M = self.data.oMf[frame]
        return self.T_world_base @ make_T(M.rotation, M.translation)

    def tip_pose(self, q: np.ndarray) -> np.ndarray:
        return self._fk(q, self.tip_frame)

    def camera_pose(self, q: np.ndarray) -> np.ndarray:
        return self._fk(q, self.camera_frame)

    def camera_covariance(self, q: np.ndarray, joint_sigma: np.ndarray, floor_rot: float,
                          floor_trans: float) -> np.ndarray:
        """6x6 covariance of the camera pose in GTSAM's tangent order (rotation, translation), camera frame,
        from independent joint errors: Sigma = J diag(sigma^2) J^T + floor. A rotation error at the RCM
        moves a camera far from it: the Jacobian carries that leverage into correlated terms."""
        q = np.asarray(q, dtype=float)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        J = pin.getFrameJacobian(self.model, self.data, self.camera_frame, pin.ReferenceFrame.LOCAL)
        J = np.vstack([J[3:], J[:3]])  # pinocchio: (linear, angular); GTSAM Pose3: (angular, linear)
        sigma = np.asarray(joint_sigma, float)
        if sigma.shape != (self.n_joints,):
            raise ConfigError(f"prior.joint_sigma has {sigma.size} values; the robot has {self.n_joints} joints")
        cov = J @ np.diag(sigma**2) @ J.T
        cov += np.diag([floor_rot**2] * 3 + [floor_trans**2] * 3)
        return cov


class NoPoseError(LaprecoError):
    """No joint readings bracket the requested time (before the first, after the last, or in a gap);
    ``cause`` is one of geometry.NO_POSE_CAUSES."""

    def __init__(self, message: str, cause: str) -> None:
        super().__init__(message)
        self.cause = cause


_CAUSE_WORDS = {BEFORE_FIRST: "before the first joint reading", AFTER_LAST: "after the last joint reading"}


class PoseAtTime:
    """Joint samples in a bounded buffer; the camera pose at any requested time.

    The pose at t is FK at the two samples that bracket t, interpolated on SE(3); ``offset_ns`` is the
    known video-to-kinematics offset (kinematics time = video time + offset). A time that no two samples
    bracket, or that falls in a gap longer than ``max_gap_periods`` median sample periods, has no pose
    (``no_pose_cause`` says why; ``prior_at`` raises NoPoseError): a pose is never held or extrapolated.
    """

    # intervals between recent samples kept for the median sample period
    period_window = 256

    def __init__(self, kinematics: CameraKinematics, joint_sigma, floor_rot: float, floor_trans: float,
                 offset_ns: int = 0, capacity: int = 4096, max_gap_periods: float = MAX_GAP_PERIODS) -> None:
        self.kin = kinematics
        self.max_gap_periods = max_gap_periods
        self._intervals: collections.deque[int] = collections.deque(maxlen=self.period_window)
        self.joint_sigma = np.asarray(joint_sigma, float)
        self.floor_rot = floor_rot
        self.floor_trans = floor_trans
        self.offset_ns = offset_ns
        self.capacity = capacity
        # plain lists, searched with bisect; the oldest half is dropped when full (amortised O(1) per sample)
        self._samples: list[JointSample] = []
        self._times: list[int] = []

    def add(self, sample: JointSample) -> None:
        if self._times and sample.t_ns <= self._times[-1]:
            return  # out of order or duplicate: the newest sample wins, time never runs backwards
        if self._times:
            self._intervals.append(sample.t_ns - self._times[-1])
        self._samples.append(sample)
        self._times.append(sample.t_ns)
        if len(self._times) > 2 * self.capacity:
            del self._samples[: self.capacity]
            del self._times[: self.capacity]

    def extend(self, samples) -> None:
        for s in samples:
            self.add(s)

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def last_time_ns(self) -> int | None:
        return self._times[-1] if self._times else None

    @property
    def max_gap_ns(self) -> float:
        """The longest interval between readings that a pose is interpolated across (``max_gap_periods``
        times the median interval of the recent readings)."""
        if not self._intervals:
            return float("inf")
        return self.max_gap_periods * float(np.median(self._intervals))

    def no_pose_cause(self, t_ns: int) -> str | None:
        """Why video time ``t_ns`` has no pose (geometry.NO_POSE_CAUSES), or None when it has one."""
        return self._cause(t_ns + self.offset_ns)

    def _cause(self, t_kin_ns: int) -> str | None:
        return no_pose_cause(self._times, t_kin_ns, self.max_gap_ns)

    def joints_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, float]:
        """(q before, q after, fraction) bracketing kinematics time t_ns; NoPoseError when no two readings
        within ``max_gap_ns`` of each other bracket it."""
        cause = self._cause(t_ns)
        if cause is not None:
            if not self._samples:
                where = "no joint readings received yet: is the robot connected?"
            elif cause in _CAUSE_WORDS:
                where = (f"kinematics time {t_ns} ns is {_CAUSE_WORDS[cause]} "
                         f"({self._times[0]}..{self._times[-1]} ns)")
            else:
                where = (f"kinematics time {t_ns} ns falls in a gap between joint readings longer than "
                         f"{self.max_gap_ns * 1e-6:.1f} ms")
            raise NoPoseError(f"no camera pose: {where}", cause)
        times = self._times
        i = bisect.bisect_left(times, t_ns)
        if times[i] == t_ns:
            s = self._samples[i]
            return s.q, s.q, 0.0
        a, b = self._samples[i - 1], self._samples[i]
        return a.q, b.q, (t_ns - a.t_ns) / (b.t_ns - a.t_ns)

    def q_at(self, t_ns: int) -> np.ndarray:
        """Joint positions at kinematics time t_ns, linearly interpolated between the readings around it."""
        qa, qb, s = self.joints_at(t_ns)
        return qa + s * (qb - qa)

    def prior_at(self, t_ns: int) -> PosePrior:
        qa, qb, s = self.joints_at(t_ns + self.offset_ns)
        Ta = self.kin.camera_pose(qa)
        T = Ta if s == 0.0 else interpolate_pose(Ta, self.kin.camera_pose(qb), s)
        q = qa + s * (qb - qa)
        cov = self.kin.camera_covariance(q, self.joint_sigma, self.floor_rot, self.floor_trans)
        return PosePrior(T_world_camera=T, cov=cov, t_ns=t_ns)
