"""The constant offset between video timestamps and a pose source's (pose time = video time + offset): a robot's
joint readings, a tracked scope's marker poses, or camera poses given directly, each on a clock of its own.

Offline (``estimate_time_offset``): features are tracked through the session; for a candidate offset, the
camera poses at the frame times come from the pose source at the shifted times (joint readings through the
kinematics; a tracker's marker poses through the hand-eye, ``T_tracker_marker(t + offset) @ T_marker_camera``;
given camera poses as they are: ``PoseSeries``, interpolated on SE(3) as the pose sources do), and every pair of
frames some distance apart gets its epipolar geometry from those poses. The Sampson distances of the tracked
correspondences to it are smallest when the offset is right. A coarse grid over the search range finds the
basin; a robust least-squares fit (Cauchy loss) then refines the offset, for joint readings together with each
joint's backlash (a tracker sees the scope itself: it has no transmission to model).

Why the backlash: a geared joint's encoder sits on the motor, and the link trails or leads it by the play in
the transmission, on the side set by the direction of motion. That error is +-b while the joint moves one way
and -+b the other, so over a scan it correlates with the velocity, exactly as a time shift does
(``q(t + d) ~ q(t) + qdot d``). Left out of the model it is taken for a delay. A shift scales with the speed,
backlash does not (only its sign), which is what separates them in the fit. docs/calibration-handeye.md has
the measurements and what the uncertainty assumes.

Online (``TimeOffsetMonitor``): the image motion the tracker measures against the image motion the robot
predicts, over a sliding window; it says when the offset in use has drifted.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import CalibrationError
from lapreco_hil.frontend import make_frontend
from lapreco_hil.kinematics import CameraKinematics
from lapreco_hil.robot_models import urdf_path

log = logging.getLogger(__name__)

# backlash changes sides while the joint reverses; below this fraction of the joint's RMS speed in the
# session the side is taken as undecided (a smooth tanh switch): a reversal takes a small part of a scan
BACKLASH_SWITCH_FRACTION = 0.1
# joint velocities (the side of the backlash) from readings this far either side: long against the
# encoders' quantisation noise (one count per 5 ms reading is 0.02 rad/s), short against a reversal
VELOCITY_HALF_WINDOW_S = 0.04
# the readings are smoothed over this span: the joints' elastic wander is rough on the scale of one reading
# (it would make the fit's cost jagged in the offset), the scan's speed changes over seconds
SMOOTHING_S = 0.2
# frame pairs this many frames apart: a time shift moves both poses of a pair alike and shows only where the
# velocity differs between them, so pairs far apart in time (where tracks survive) carry most of the signal
PAIR_GAPS = (5, 10, 20, 40)
MIN_COMMON_TRACKS = 15
# the Cauchy loss's scale on Sampson distances (px): the tracker's noise is a fraction of a pixel, the
# robot's joint wander maps to about a pixel; beyond a few pixels a correspondence is a tracking error
CAUCHY_SCALE_PX = 1.0
# the uncertainty leaves out stretches of about this length in turn: it assumes the errors of the joint
# readings (and of the tracks) are unrelated between stretches this far apart
JACKKNIFE_BLOCK_S = 1.0
# draws of the arm's joint wander that measure its part of the uncertainty (when its time constant is given)
WANDER_SAMPLES = 8


@dataclass
class OffsetEstimate:
    offset_ns: int
    sigma_ns: int
    cost_at_zero_px: float
    cost_at_offset_px: float
    pairs: int
    grid_s: np.ndarray
    cost_px: np.ndarray
    backlash: np.ndarray  # per joint, SI units (rad or m): half the play, the link's side ahead of the motor
    # whose clock: "joints", "marker_poses" or "camera_poses" (a session's pose_source); only joints have backlash
    pose_source: str = "joints"

    def summary(self) -> dict:
        return {"offset_ms": self.offset_ns * 1e-6, "sigma_ms": self.sigma_ns * 1e-6, "pairs": self.pairs,
                "median_sampson_px_at_zero": self.cost_at_zero_px,
                "median_sampson_px_at_offset": self.cost_at_offset_px,
                "backlash": [float(b) for b in self.backlash], "pose_source": self.pose_source}


def signed_sampson_of_pairs(E: np.ndarray, owner: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                             f: float) -> np.ndarray:
    """Signed Sampson distances (pixels, for focal length f) of normalised correspondences x1 -> x2 (N, 2) to the
    essential matrix of their frame pair: E (P, 3, 3), ``owner`` (N,) each correspondence's pair; x2^T E x1 = 0
    for a perfect match. Written out per element: einsums over (N, 3, 3) were most of a time-offset fit's time."""
    e = E.reshape(-1, 9)[owner]
    x, y, u, v = x1[:, 0], x1[:, 1], x2[:, 0], x2[:, 1]
    l0 = e[:, 0] * x + e[:, 1] * y + e[:, 2]  # E h1
    l1 = e[:, 3] * x + e[:, 4] * y + e[:, 5]
    l2 = e[:, 6] * x + e[:, 7] * y + e[:, 8]
    m0 = e[:, 0] * u + e[:, 3] * v + e[:, 6]  # E^T h2
    m1 = e[:, 1] * u + e[:, 4] * v + e[:, 7]
    num = u * l0 + v * l1 + l2
    den = l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1
    return f * num / np.sqrt(np.maximum(den, 1e-18))


def skew_matrices(t: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(t))
    return np.stack([np.stack([z, -t[:, 2], t[:, 1]], 1), np.stack([t[:, 2], z, -t[:, 0]], 1),
                     np.stack([-t[:, 1], t[:, 0], z], 1)], 1)


def track_session(session, config: PipelineConfig, device: str = "cpu", tracker: str = "opencv"):
    """Observations of every frame (undistorted pixels keyed by track id)."""
    frontend = make_frontend(tracker, session.meta.camera, config.tracker, device)
    return [frontend.process(session.frame(i)) for i in range(len(session))]


def _uniform_grid(t_ns: np.ndarray, what: str) -> tuple[int, np.ndarray, float, np.ndarray]:
    """(t0_ns, the samples' times in s from t0, the grid step, the grid): a uniform grid at the samples' median
    interval (drivers' and trackers' samples jitter a little)."""
    t_ns = np.asarray(t_ns, np.int64)
    if len(t_ns) < 2:
        raise CalibrationError(f"the time offset needs at least two {what}")
    t0_ns = int(t_ns[0])
    raw_t = (t_ns - t0_ns) * 1e-9
    dt = float(np.median(np.diff(raw_t)))
    return t0_ns, raw_t, dt, np.arange(0.0, raw_t[-1] + 1e-12, dt)


def _smoothed_on_grid(values: np.ndarray, dt: float, smoothing_s: float) -> np.ndarray:
    """Values on a uniform grid (N, ...) smoothed by a local quadratic fit over ``smoothing_s`` (zero phase: no
    delay of its own); unchanged where the window holds too few samples."""
    from scipy.signal import savgol_filter

    window = int(round(smoothing_s / dt)) | 1
    return savgol_filter(values, window, 2, axis=0, mode="interp") if 3 < window < len(values) else values


class JointTrack:
    """Joint readings as a smooth function of time: positions smoothed by a local quadratic fit over
    SMOOTHING_S (zero phase: no delay of its own), and the side each joint's backlash is on (from its
    velocity)."""

    def __init__(self, t_ns: np.ndarray, q: np.ndarray) -> None:
        self.t0_ns, raw_t, dt, self.t_s = _uniform_grid(t_ns, "joint readings")
        q = np.asarray(q, float)
        uniform = np.column_stack([np.interp(self.t_s, raw_t, q[:, j]) for j in range(q.shape[1])])
        self.q = _smoothed_on_grid(uniform, dt, SMOOTHING_S)
        h = VELOCITY_HALF_WINDOW_S
        velocity = (self._interp(self.t_s + h) - self._interp(self.t_s - h)) / (2 * h)
        rms = np.sqrt(np.mean(velocity**2, axis=0))
        self.switch_speed = np.maximum(rms * BACKLASH_SWITCH_FRACTION, 1e-12)
        self._velocity = velocity

    def _interp(self, t_s: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t_s, self.t_s, self.q[:, j]) for j in range(self.q.shape[1])])

    def at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions (N, n), backlash sides in [-1, 1] (N, n)) at kinematics times."""
        t_s = (np.asarray(t_ns, np.int64) - self.t0_ns) * 1e-9
        v = np.column_stack([np.interp(t_s, self.t_s, self._velocity[:, j]) for j in range(self.q.shape[1])])
        return self._interp(t_s), np.tanh(v / self.switch_speed)


class PoseSeries:
    """Camera poses T_world_camera sampled at increasing times (a tracker's marker poses through the hand-eye, or
    camera poses given directly) as a smooth function of time, as ``JointTrack`` makes of joint readings: on a
    uniform grid at the samples' median interval (SE(3) interpolation between the two samples around each grid
    time: slerp on the rotation, linear on the translation, as the pose sources interpolate), smoothed by a
    local quadratic fit over ``smoothing_s`` (zero phase: no delay of its own; translation and rotation
    quaternion alike, then renormalised). A tracker's noise is independent from sample to sample, which made
    the fit's cost jagged in the offset and its jackknife blind to the error (a noisy tracked scope: -12 ms
    +- 0.9 ms at a true 0). Before the first sample or after the last, held at that end."""

    def __init__(self, t_ns: np.ndarray, poses: np.ndarray, smoothing_s: float = SMOOTHING_S) -> None:
        from scipy.spatial.transform import Rotation

        from lapreco_hil.geometry import interpolate_poses

        poses = np.asarray(poses, float)
        if np.any(np.diff(np.asarray(t_ns, np.int64)) <= 0):
            raise CalibrationError("the poses' times must increase")
        self.t0_ns, raw_t, dt, self.t_s = _uniform_grid(t_ns, "poses")
        i = np.clip(np.searchsorted(raw_t, self.t_s, side="right") - 1, 0, len(raw_t) - 2)
        u = np.clip((self.t_s - raw_t[i]) / (raw_t[i + 1] - raw_t[i]), 0.0, 1.0)
        uniform = interpolate_poses(poses[i], poses[i + 1], u)
        quat = Rotation.from_matrix(uniform[:, :3, :3]).as_quat()
        flip = np.cumprod(np.r_[1.0, np.sign(np.sum(quat[1:] * quat[:-1], axis=1) + 1e-300)])
        quat = _smoothed_on_grid(quat * flip[:, None], dt, smoothing_s)
        uniform[:, :3, :3] = Rotation.from_quat(quat / np.linalg.norm(quat, axis=1, keepdims=True)).as_matrix()
        uniform[:, :3, 3] = _smoothed_on_grid(uniform[:, :3, 3], dt, smoothing_s)
        self.poses = uniform

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses at times ``t_ns`` (the series' clock)."""
        from lapreco_hil.geometry import interpolate_poses

        if len(self.t_s) == 1:
            return np.repeat(self.poses, len(np.atleast_1d(t_ns)), axis=0)
        t = np.clip((np.asarray(t_ns, np.int64) - self.t0_ns) * 1e-9, 0.0, self.t_s[-1])
        i = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        u = np.clip((t - self.t_s[i]) / (self.t_s[i + 1] - self.t_s[i]), 0.0, 1.0)
        return interpolate_poses(self.poses[i], self.poses[i + 1], u)


class _JointPoses:
    """Camera poses from joint readings through the kinematics, with each joint's backlash as unknowns."""

    def __init__(self, kinematics: CameraKinematics, joints: JointTrack) -> None:
        self.kin, self.joints = kinematics, joints
        self.n_backlash = joints.q.shape[1]

    def camera_poses(self, t_ns: np.ndarray, backlash: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        q, side = self.joints.at(t_ns)
        q = q + side * backlash  # the link is where the motor reads plus the play on the side of motion
        if dq is not None:
            q = q + dq
        return np.array([self.kin.camera_pose(qk) for qk in q]).reshape(-1, 4, 4)


class _SeriesPoses:
    """Camera poses interpolated in a PoseSeries: nothing to fit but the offset."""

    n_backlash = 0

    def __init__(self, series: PoseSeries) -> None:
        self.series = series

    def camera_poses(self, t_ns: np.ndarray, backlash: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        return self.series.at(t_ns)


@dataclass
class _Pairs:
    first: np.ndarray  # (P,) frame index of each pair's earlier frame
    second: np.ndarray  # (P,)
    owner: np.ndarray  # (M,) pair of each correspondence
    x1: np.ndarray  # (M, 2) normalised coordinates in the earlier frame
    x2: np.ndarray  # (M, 2)


def _frame_pairs(obs, K: np.ndarray, gaps, min_common: int) -> _Pairs:
    Kinv = np.linalg.inv(K)
    first, second, owner, x1s, x2s = [], [], [], [], []
    for gap in gaps:
        for i in range(0, len(obs) - gap):
            a, b = obs[i], obs[i + gap]
            common, ia, ib = np.intersect1d(a.track_ids, b.track_ids, return_indices=True)
            if len(common) < min_common:
                continue
            owner.append(np.full(len(common), len(first)))
            first.append(i)
            second.append(i + gap)
            x1s.append((np.column_stack([a.uv[ia], np.ones(len(ia))]) @ Kinv.T)[:, :2])
            x2s.append((np.column_stack([b.uv[ib], np.ones(len(ib))]) @ Kinv.T)[:, :2])
    if not first:
        return _Pairs(np.zeros(0, int), np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2)))
    return _Pairs(np.array(first), np.array(second), np.concatenate(owner), np.concatenate(x1s),
                  np.concatenate(x2s))


class _EpipolarModel:
    """Signed Sampson distances of every correspondence for parameters (offset s, then the pose source's own:
    backlash per joint for joint readings, none for a pose series)."""

    def __init__(self, obs, source, K: np.ndarray, pairs: _Pairs):
        self.frame_t_ns = np.array([o.t_ns for o in obs], np.int64)
        self.source, self.pairs = source, pairs
        self.n_backlash = source.n_backlash
        self.f = float(K[0, 0])
        used = np.unique(np.concatenate([pairs.first, pairs.second]))
        self.used = used

    def poses(self, offset_s: float, backlash: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        T = np.zeros((len(self.frame_t_ns), 4, 4))
        T[self.used] = self.source.camera_poses(self.frame_t_ns[self.used] + int(round(offset_s * 1e9)), backlash,
                                                None if dq is None else dq[self.used])
        return T

    def residuals(self, params: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        P = self.poses(params[0], params[1:], dq)
        p = self.pairs
        Ta, Tb = P[p.first], P[p.second]
        # camera b in camera a: x_a ~ R x_b + t  =>  x_a^T [t]x R x_b = 0
        R = np.einsum("pji,pjk->pik", Ta[:, :3, :3], Tb[:, :3, :3])
        t = np.einsum("pji,pj->pi", Ta[:, :3, :3], Tb[:, :3, 3] - Ta[:, :3, 3])
        E = skew_matrices(t) @ R  # maps x_b to the epipolar line in a
        return signed_sampson_of_pairs(E.transpose(0, 2, 1), p.owner, p.x1, p.x2, self.f)

    def robust_cost(self, params: np.ndarray) -> float:
        r = self.residuals(params) / CAUCHY_SCALE_PX
        return float(np.mean(np.log1p(r * r)))

    def pair_medians(self, params: np.ndarray) -> np.ndarray:
        r = np.abs(self.residuals(params))
        order = np.lexsort((r, self.pairs.owner))
        counts = np.bincount(self.pairs.owner, minlength=len(self.pairs.first))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        return np.array([np.median(r[order][s:s + c]) for s, c in zip(starts, counts)])


def estimate_time_offset(session, config: PipelineConfig | None = None, search_s: float = 1.0,
                         device: str = "cpu", obs=None, T_tip_camera: np.ndarray | None = None,
                         wander_time_s: float = 0.0) -> OffsetEstimate:
    """The offset of a session's pose source (pose time = video time + offset), whichever it is: joint readings
    (through the robot's kinematics), a tracked scope's marker poses (through its hand-eye T_marker_camera, the
    samples the replay would refuse left out) or camera poses given directly. ``obs`` (the tracker's observations
    of every frame) can be given to skip tracking; ``T_tip_camera`` replaces the session's hand-eye (a
    calibration session has none; for marker poses it is T_marker_camera, as ``calibrate handeye-tracked``
    writes it); ``wander_time_s``: the arm's joint-error time constant, if known (``estimate_from_tracks``;
    joint readings only)."""
    if not (math.isfinite(search_s) and search_s > 0):
        raise CalibrationError(f"the time-offset search range must be a positive number of ms, got "
                               f"{search_s * 1e3:g}")
    where = f"session '{session.folder}'"
    source = session.meta.pose_source
    if source != "joints":
        if wander_time_s:
            raise CalibrationError(f"{where} has {source.replace('_', ' ')}, not joint readings: the joints' wander "
                                   f"time constant (--joint-wander-s) does not apply")
        series = session_pose_series(session, T_tip_camera)
        obs = obs if obs is not None else track_session(session, config or PipelineConfig(), device)
        return estimate_from_pose_series(obs, series, session.meta.camera.K, session.frame_period_ns, search_s,
                                         pose_source=source, where=where)
    robot = session.robot
    if T_tip_camera is not None:
        robot = replace(robot, T_tip_camera=np.asarray(T_tip_camera, float))
    if robot.T_tip_camera is None:
        raise CalibrationError(f"session '{session.folder}' has no hand-eye (T_tip_camera); calibrate it first "
                               f"('lapreco calibrate handeye') and pass it with --hand-eye")
    kin = CameraKinematics(str(urdf_path(robot.urdf)), robot.tip_frame, robot.T_tip_camera, robot.T_world_base)
    joints = JointTrack(np.array([j.t_ns for j in session.joint_samples], np.int64),
                        np.array([j.q for j in session.joint_samples]))
    obs = obs if obs is not None else track_session(session, config or PipelineConfig(), device)
    return estimate_from_tracks(obs, kin, joints, session.meta.camera.K, session.frame_period_ns, search_s,
                                wander_time_s=wander_time_s, where=where)


def session_pose_series(session, T_marker_camera: np.ndarray | None = None) -> PoseSeries:
    """The camera poses of a session without joint readings, on the pose source's own clock: a tracked scope's
    (``T_world_tracker @ T_tracker_marker @ T_marker_camera``, its tool's samples only and those the replay
    refuses left out; ``T_marker_camera`` in place of the session's) or the given camera poses."""
    where = f"session '{session.folder}'"
    if session.meta.pose_source == "marker_poses":
        setup, table = session.meta.tracker, session.markers
        T_mc = setup.T_marker_camera if T_marker_camera is None else np.asarray(T_marker_camera, float)
        if T_mc is None:
            raise CalibrationError(f"{where}: the tracked scope has no hand-eye (T_marker_camera): pass --hand-eye "
                                   f"handeye.yaml (from 'lapreco calibrate handeye-tracked')")
        # the scope's samples a replay accepts (pose_sources.MarkerPoseSource's rule: finite, in the volume, the
        # marker fit within max_rms_mm, time increasing); calib does not import the pose sources
        keep = np.array([tool == setup.tool for tool in table.tools], bool) & np.asarray(table.in_volume, bool) \
            & np.isfinite(table.rms_mm) & (np.asarray(table.rms_mm, float) <= setup.max_rms_mm) \
            & np.all(np.isfinite(table.poses.reshape(len(table.poses), -1)), axis=1)
        t_ns, poses = np.asarray(table.t_ns, np.int64)[keep], np.asarray(table.poses, float)[keep]
        later = np.r_[True, t_ns[1:] > np.maximum.accumulate(t_ns)[:-1]] if len(t_ns) else np.zeros(0, bool)
        t_ns, poses = t_ns[later], poses[later]
        if len(t_ns) < 2:
            raise CalibrationError(f"{where}: {len(t_ns)} usable marker pose of the scope's tool '{setup.tool}'; "
                                   f"the time offset needs the scope moving")
        return PoseSeries(t_ns, setup.T_world_tracker @ poses @ T_mc)
    if T_marker_camera is not None:
        raise CalibrationError(f"{where} gives camera poses directly; a hand-eye does not apply")
    if len(session.pose_t_ns) < 2:
        raise CalibrationError(f"{where}: {len(session.pose_t_ns)} camera pose; the time offset needs the camera "
                               f"moving")
    return PoseSeries(session.pose_t_ns, session.poses)


def estimate_from_tracks(obs, kinematics: CameraKinematics, joints: JointTrack, K: np.ndarray, period_ns: int,
                         search_s: float = 1.0, model_backlash: bool = True, joint_sigma=None,
                         wander_time_s: float = 0.0, wander_samples: int = WANDER_SAMPLES,
                         where: str = "") -> OffsetEstimate:
    """From joint readings. The uncertainty is a delete-a-block jackknife over time (``JACKKNIFE_BLOCK_S``). If
    the arm's joint errors are known to wander slowly, ``wander_time_s`` (their time constant, s) and
    ``joint_sigma`` (1 sigma per joint, SI; default: the pipeline's prior) add the fit's spread under
    ``wander_samples`` draws of such wander, which a short session's jackknife cannot see. 0 (default) leaves
    that part out."""
    if not (math.isfinite(wander_time_s) and wander_time_s >= 0):
        raise CalibrationError(f"the joints' wander time constant must be >= 0 s, got {wander_time_s!r}")
    if joint_sigma is None:
        joint_sigma = _default_joint_sigma(joints.q.shape[1])
    wander = (np.asarray(joint_sigma, float), wander_time_s, wander_samples) \
        if wander_samples > 0 and wander_time_s > 0 else None
    return _estimate(obs, _JointPoses(kinematics, joints), K, period_ns, search_s, model_backlash, wander,
                     "joints", where)


def estimate_from_pose_series(obs, series: PoseSeries, K: np.ndarray, period_ns: int, search_s: float = 1.0,
                              pose_source: str = "camera_poses", where: str = "") -> OffsetEstimate:
    """From camera poses sampled on the pose source's clock (a tracker's marker poses through the hand-eye, or
    given camera poses): the offset alone is fitted. The uncertainty is the block jackknife over time; it
    assumes the poses' errors (and the tracks') are unrelated between stretches ``JACKKNIFE_BLOCK_S`` apart."""
    return _estimate(obs, _SeriesPoses(series), K, period_ns, search_s, False, None, pose_source, where)


def _estimate(obs, source, K: np.ndarray, period_ns: int, search_s: float, model_backlash: bool, wander,
              pose_source: str, where: str) -> OffsetEstimate:
    pairs = _frame_pairs(obs, K, PAIR_GAPS, MIN_COMMON_TRACKS)
    if len(pairs.first) < 5:
        raise CalibrationError(f"{where}: only {len(pairs.first)} frame pairs share {MIN_COMMON_TRACKS}+ tracks; "
                               f"the time offset needs a moving camera over a textured scene")
    model = _EpipolarModel(obs, source, K, pairs)
    n = model.n_backlash
    zero_b = np.zeros(n)
    period_s = period_ns * 1e-9
    # the basin: a grid at half a frame period, then a tenth of one around its best point
    coarse = np.arange(-search_s, search_s + 1e-12, period_s / 2)
    coarse_cost = np.array([model.robust_cost(np.r_[o, zero_b]) for o in coarse])
    best = coarse[int(np.argmin(coarse_cost))]
    fine = np.arange(best - period_s, best + period_s + 1e-12, period_s / 10)
    fine_cost = np.array([model.robust_cost(np.r_[o, zero_b]) for o in fine])
    start = fine[int(np.argmin(fine_cost))]
    free = n if model_backlash else 0
    offset_s, backlash = _fit(model, start, free, period_s, where)
    within_s = _jackknife_sigma(model, free, period_s, offset_s)
    wander_s = 0.0
    if wander is not None:
        joint_sigma, wander_time_s, wander_samples = wander
        wander_s = _wander_sigma(model, np.r_[offset_s, backlash], free, joint_sigma, period_s, wander_time_s,
                                 wander_samples)
    sigma_s = float(np.hypot(within_s, wander_s))
    grid = np.concatenate([coarse, fine])
    order = np.argsort(grid)
    params = np.r_[offset_s, backlash]
    log.info("time offset (%s) %.1f ms +- %.1f ms from %d frame pairs; backlash %s", pose_source, offset_s * 1e3,
             sigma_s * 1e3, len(pairs.first), np.array2string(backlash, precision=5))
    return OffsetEstimate(int(round(offset_s * 1e9)), int(round(sigma_s * 1e9)),
                          float(np.median(model.pair_medians(np.r_[0.0, zero_b]))),
                          float(np.median(model.pair_medians(params))), len(pairs.first), grid[order],
                          np.concatenate([coarse_cost, fine_cost])[order], backlash, pose_source)


def _fit(model: _EpipolarModel, start_s: float, free: int, period_s: float, where: str = "",
         pair_mask: np.ndarray | None = None, dq: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Offset (s) and backlash (per joint) by robust least squares from the grid's best offset."""
    from scipy.optimize import least_squares

    n = model.n_backlash
    keep = None if pair_mask is None else pair_mask[model.pairs.owner]

    # unknowns from zero (least_squares sizes its first step by |x0|): the offset's change from the start, in
    # ms, and the backlash in mrad (mm), so that the steps are alike
    def fun(x: np.ndarray) -> np.ndarray:
        r = model.residuals(np.r_[start_s + x[0] * 1e-3, x[1:] * 1e-3, np.zeros(n - free)], dq)
        return r if keep is None else r[keep]

    last = {}  # least_squares asks for the residuals, then the Jacobian, at the same point

    def at(x: np.ndarray) -> np.ndarray:
        if last.get("x") is None or not np.array_equal(last["x"], x):
            last["x"], last["r"] = x.copy(), fun(x)
        return last["r"]

    def jac(x: np.ndarray) -> np.ndarray:  # forward differences with absolute steps (0.05 ms, 0.01 mrad)
        r0 = at(x)
        columns = []
        for k, h in enumerate(np.r_[0.05, np.full(free, 0.01)]):
            step = np.zeros(len(x))
            step[k] = h
            columns.append((fun(x + step) - r0) / h)
        return np.column_stack(columns)

    fit = least_squares(at, np.zeros(1 + free), jac=jac, loss="cauchy", f_scale=CAUCHY_SCALE_PX, max_nfev=60)
    offset_s, backlash = start_s + fit.x[0] * 1e-3, np.r_[fit.x[1:] * 1e-3, np.zeros(n - free)]
    if abs(offset_s - start_s) > 2 * period_s:  # a fit that ran off its basin is no better than the grid
        log.warning("%s: the refined offset left the grid's basin; keeping the grid's %.1f ms", where,
                    start_s * 1e3)
        return start_s, np.zeros(n)
    return offset_s, backlash


def _jackknife_sigma(model: _EpipolarModel, free: int, period_s: float, offset_s: float) -> float:
    """The offset's standard error by a delete-a-block jackknife over time. The robot's joint wander is common
    to every pair that touches a frame and lasts a fraction of a second, so the pairs are far from
    independent: leaving out contiguous stretches of the session sees the spread that wander causes."""
    t = (model.frame_t_ns - model.frame_t_ns[0]) * 1e-9
    blocks = int(np.clip(round(t[-1] / JACKKNIFE_BLOCK_S), 4, 10))
    edges = np.linspace(0.0, t[-1] + 1e-9, blocks + 1)
    estimates = []
    for b in range(blocks):
        inside = (t >= edges[b]) & (t < edges[b + 1])
        mask = ~(inside[model.pairs.first] | inside[model.pairs.second])
        if mask.sum() < 5:
            continue
        estimates.append(_fit(model, offset_s, free, period_s, pair_mask=mask)[0])
    k = len(estimates)
    if k < 2:
        return float("nan")
    e = np.array(estimates)
    return float(np.sqrt((k - 1) / k * np.sum((e - e.mean()) ** 2)))


def _default_joint_sigma(n: int) -> np.ndarray:
    from lapreco_hil.config import PriorConfig

    sigma = np.asarray(PriorConfig().joint_sigma, float)
    return sigma if sigma.shape == (n,) else np.full(n, float(np.max(sigma)))


def _wander_sigma(model: _EpipolarModel, params: np.ndarray, free: int, joint_sigma: np.ndarray,
                  period_s: float, wander_time_s: float, samples: int = WANDER_SAMPLES, seed: int = 0) -> float:
    """The offset's spread under the robot's joint wander (an Ornstein-Uhlenbeck deflection of joint_sigma
    per joint with time constant wander_time_s, as elastic joints wander): wander drawn at the frame times,
    added to the readings, and the fit repeated. A shift and a slow wander look alike over a short session,
    which the spread within the session (the jackknife) cannot see."""
    n = model.n_backlash
    t = (model.frame_t_ns - model.frame_t_ns[0]) * 1e-9
    a = np.exp(-np.diff(t, prepend=t[0]) / wander_time_s)
    rng = np.random.default_rng(seed)
    shifts = []
    for _ in range(samples):
        dq = np.empty((len(t), n))
        dq[0] = rng.standard_normal(n) * joint_sigma
        for i in range(1, len(t)):
            dq[i] = a[i] * dq[i - 1] + np.sqrt(1 - a[i] ** 2) * rng.standard_normal(n) * joint_sigma
        shifts.append(_fit(model, params[0], free, period_s, dq=dq)[0])
    return float(np.std(shifts))


# --- online ------------------------------------------------------------------------------------------------------

# a drift is called one only when it is this many standard errors of the offset (and the threshold) away
DRIFT_SIGNIFICANCE = 3.0
# the monitor smooths both motion signals in time by a Gaussian of this sigma (s) before lining them up: motion from
# joint readings differentiated over one frame carries noise that biased the shift (a simulated arm's read -140 ms
# at a true 0; docs/calibration-handeye.md), and one zero-phase filter on both keeps their timing
MONITOR_SMOOTHING_S = 0.1


def _smoothed(t_s: np.ndarray, values: np.ndarray, sigma_s: float) -> np.ndarray:
    """``values`` (N, C) sampled at times ``t_s`` (N,), each replaced by its Gaussian-weighted mean over time
    (zero phase, for irregular samples too); sigma 0: unchanged."""
    if sigma_s <= 0 or len(t_s) < 2:
        return values
    w = np.exp(-0.5 * ((t_s[:, None] - t_s[None, :]) / sigma_s) ** 2)
    return (w @ values) / w.sum(axis=1, keepdims=True)


def _correlation_time(residual: np.ndarray) -> float:
    """Samples per independent one in a residual series (N, C): 1 + 2 x the sum of its autocorrelations up to the
    first that is not positive, averaged over the components; 1 for white residuals."""
    taus = []
    for x in residual.T:
        x = x - np.mean(x)
        v = float(np.mean(x * x))
        if v <= 0.0:
            continue
        tau = 1.0
        for k in range(1, len(x) // 2):
            rho = float(np.mean(x[:-k] * x[k:])) / v
            if rho <= 0.0:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return float(np.mean(taus)) if taus else 1.0


@dataclass(frozen=True)
class OffsetReading:
    """The monitor's current view: the offset its window supports, how far that is from the applied one,
    and whether that is beyond the threshold (only when the window has enough motion to tell)."""

    offset_ns: int | None
    drift_ns: int | None
    drifted: bool
    samples: int
    motion_px_s: float  # RMS of the measured image motion in the window: too little and nothing is decided
    # the offset's standard error (Gauss-Newton: the residual's spread over the predicted motion's change; None:
    # no change at all); a drift within DRIFT_SIGNIFICANCE of it is not called one (a window of smooth motion pins
    # no offset)
    uncertainty_ns: int | None = None
    # a drift beyond the threshold that is not called one, and why (its uncertainty; the likelihood-ratio test)
    not_called_because: str | None = None


class TimeOffsetMonitor:
    """The video-kinematics offset over a sliding window, for a live run.

    Feed it, per frame, the image motion the tracker measured (``add_measured``: a 2-vector in px/s, e.g. the
    median displacement of the tracks since the previous frame over the frame interval, stamped at the
    middle of that interval, video clock) and, as the robot reports, the image motion its kinematics
    predicts (``add_predicted``: the same quantity from the camera's FK velocity, stamped on the kinematics
    clock). The offset is the shift that best lines the two motion signals up, both smoothed alike in time
    (``smoothing_s``), by the median squared mismatch over a grid, refined by a parabola; ``reading()`` says
    whether it is more than ``drift_threshold_ns`` from the offset in use (and beyond its uncertainty). Motion signals carry a shift in their changes, so the window must hold some
    acceleration: a camera moving at constant speed (or not at all) gives no reading.
    """

    def __init__(self, applied_offset_ns: int = 0, window_s: float = 10.0, search_s: float = 0.5,
                 step_s: float = 0.002, drift_threshold_ns: int = 20_000_000, min_samples: int = 50,
                 min_motion_px_s: float = 5.0, smoothing_s: float = MONITOR_SMOOTHING_S) -> None:
        for name, v in (("window_s", window_s), ("search_s", search_s), ("step_s", step_s)):
            if not (math.isfinite(v) and v > 0):
                raise CalibrationError(f"TimeOffsetMonitor: {name} must be a positive number, got {v!r}")
        self.applied_offset_ns = int(applied_offset_ns)
        self.window_ns = int(window_s * 1e9)
        self.search_s, self.step_s = search_s, step_s
        self.drift_threshold_ns = int(drift_threshold_ns)
        self.min_samples, self.min_motion_px_s = min_samples, min_motion_px_s
        if not (math.isfinite(smoothing_s) and smoothing_s >= 0):
            raise CalibrationError(f"TimeOffsetMonitor: smoothing_s must be >= 0, got {smoothing_s!r}")
        self.smoothing_s = smoothing_s
        self._measured: deque[tuple[int, float, float]] = deque()
        self._predicted: deque[tuple[int, float, float]] = deque()

    def add_measured(self, t_video_ns: int, motion_px_s) -> None:
        m = np.asarray(motion_px_s, float)
        if m.shape == (2,) and np.all(np.isfinite(m)):
            self._measured.append((int(t_video_ns), float(m[0]), float(m[1])))
            self._trim()

    def add_predicted(self, t_kinematics_ns: int, motion_px_s) -> None:
        m = np.asarray(motion_px_s, float)
        if m.shape == (2,) and np.all(np.isfinite(m)):
            if self._predicted and t_kinematics_ns <= self._predicted[-1][0]:
                return  # the kinematics clock only goes forward; a repeat or an old sample is dropped
            self._predicted.append((int(t_kinematics_ns), float(m[0]), float(m[1])))
            self._trim()

    def _trim(self) -> None:
        if self._measured:
            newest = self._measured[-1][0]
            while self._measured and self._measured[0][0] < newest - self.window_ns:
                self._measured.popleft()
            # predictions are kept for the window plus the search on either side
            horizon = newest + self.applied_offset_ns - self.window_ns - int(2 * self.search_s * 1e9)
            while len(self._predicted) > 2 and self._predicted[1][0] < horizon:
                self._predicted.popleft()

    def reading(self) -> OffsetReading:
        meas = np.array(self._measured, float).reshape(-1, 3)
        pred = np.array(self._predicted, float).reshape(-1, 3)
        motion = float(np.sqrt(np.mean(np.sum(meas[:, 1:] ** 2, axis=1)))) if len(meas) else 0.0
        if len(meas) < self.min_samples or len(pred) < 2 or motion < self.min_motion_px_s:
            return OffsetReading(None, None, False, len(meas), motion)
        base = self.applied_offset_ns * 1e-9
        shifts = np.arange(base - self.search_s, base + self.search_s + 1e-12, self.step_s)
        tv = (meas[:, 0] - pred[0, 0]) * 1e-9
        tp = (pred[:, 0] - pred[0, 0]) * 1e-9
        meas = np.column_stack([meas[:, 0], _smoothed(tv, meas[:, 1:], self.smoothing_s)])
        pred = np.column_stack([pred[:, 0], _smoothed(tp, pred[:, 1:], self.smoothing_s)])
        cost = np.full(len(shifts), np.nan)
        for k, d in enumerate(shifts):
            tk = tv + d
            inside = (tk >= tp[0]) & (tk <= tp[-1])
            if inside.sum() < self.min_samples:
                continue
            px = np.interp(tk[inside], tp, pred[:, 1])
            py = np.interp(tk[inside], tp, pred[:, 2])
            # the median of squared mismatches: a few frames of bad tracking do not move it
            cost[k] = np.median((meas[inside, 1] - px) ** 2 + (meas[inside, 2] - py) ** 2)
        if np.all(np.isnan(cost)):
            return OffsetReading(None, None, False, len(meas), motion)
        k = int(np.nanargmin(cost))
        offset_s = shifts[k]
        if 0 < k < len(shifts) - 1 and np.all(np.isfinite(cost[k - 1:k + 2])):
            c0, c1, c2 = cost[k - 1:k + 2]
            denom = c0 - 2 * c1 + c2
            if denom > 0:
                offset_s += 0.5 * self.step_s * (c0 - c2) / denom
        offset_ns = int(round(offset_s * 1e9))
        drift = offset_ns - self.applied_offset_ns
        min_cost = float(np.nanmin(cost))
        sigma_ns, n_independent = self._uncertainty_ns(tv + offset_s, tp, pred, meas[:, 1:], min_cost)
        not_called = None
        if abs(drift) > self.drift_threshold_ns:
            if sigma_ns is None or abs(drift) <= DRIFT_SIGNIFICANCE * sigma_ns:
                not_called = f"within {DRIFT_SIGNIFICANCE:g} standard errors"
            elif not self._offset_in_use_refuted(shifts, cost, base, n_independent):
                not_called = "a shift within the threshold of the offset in use fits nearly as well"
        drifted = abs(drift) > self.drift_threshold_ns and not_called is None
        return OffsetReading(offset_ns, drift, drifted, len(meas), motion, sigma_ns, not_called)

    def _offset_in_use_refuted(self, shifts: np.ndarray, cost: np.ndarray, base_s: float,
                               n_independent: float) -> bool:
        """Whether every shift within the drift threshold of the offset in use fits the window worse than the best
        by more than DRIFT_SIGNIFICANCE standard errors (a likelihood-ratio test: chi^2 grows by 2 n (c - c_min) /
        c_min over n independent 2-D residuals). With noisy predictions the cost has several minima of nearly one
        depth, and the best can jump between them from one reading to the next (a simulated arm's -52 and +28 ms
        at a true 0): a second minimum near the offset in use keeps it."""
        near = np.abs(shifts - base_s) <= self.drift_threshold_ns * 1e-9
        finite = near & np.isfinite(cost)
        c_min = float(np.nanmin(cost))
        if not finite.any() or c_min <= 0.0:
            return bool(not finite.any() and c_min > 0.0)
        chi2_near = 2.0 * n_independent * (float(np.min(cost[finite])) - c_min) / c_min
        return chi2_near > DRIFT_SIGNIFICANCE ** 2

    @staticmethod
    def _uncertainty_ns(tk: np.ndarray, tp: np.ndarray, pred: np.ndarray, meas: np.ndarray,
                        min_cost: float) -> tuple[int | None, float]:
        """The standard error of the shift at its optimum: a residual of variance s^2 per component against a
        predicted motion whose rate of change is a(t) pins the shift to s / sqrt(sum |a|^2). The residual's
        variance comes from the cost (the median of a 2-D Gaussian's squared length is 2 ln 2 of its variance),
        and counts once per run of correlated residuals (their integrated autocorrelation time: the smoothing,
        a backlash's lag, a joint's wander). None where the predicted motion does not change at all. Also the
        number of independent residuals (the samples over their correlation time)."""
        inside = (tk >= tp[0]) & (tk <= tp[-1])
        t = tk[inside]
        h = 0.01  # s: the rate of change over the predicted motion's own smoothing scale, not its sample noise
        rate = np.column_stack([(np.interp(t + h, tp, pred[:, c]) - np.interp(t - h, tp, pred[:, c])) / (2 * h)
                                for c in (1, 2)])
        residual = meas[inside] - np.column_stack([np.interp(t, tp, pred[:, c]) for c in (1, 2)])
        tau = _correlation_time(residual)
        information = float(np.sum(rate ** 2))
        if information <= 0.0:
            return None, len(t) / tau
        variance = max(min_cost, 0.0) / (2.0 * math.log(2.0)) * tau
        return int(round(math.sqrt(variance / information) * 1e9)), len(t) / tau
