"""Where camera-pose priors come from: a robot's joint readings through its kinematics, camera poses given
directly (a calibrated stereo rig, poses computed elsewhere), or a tracked scope's marker poses (an optical /
EM tracker) with its hand-eye. All answer ``has_pose(t_ns)`` and
``prior_at(t_ns)``.

A frame gets a pose only when two samples around its time bracket it, no further apart than
``geometry.MAX_GAP_PERIODS`` median sample periods: a frame before the first sample, after the last or
inside a longer gap gets none (never a held or extrapolated one). ``has_pose(t_ns)`` counts such frames by
cause (``without_pose``) and ``warn_without_pose()`` logs one warning per cause with the count and the span.
"""

from __future__ import annotations

import bisect
import collections
import logging
import time
from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from lapreco_hil.config import PriorConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import AFTER_LAST, BEFORE_FIRST, IN_GAP, MAX_GAP_PERIODS, NO_POSE_CAUSES, \
    interpolate_pose, max_gap_ns, no_pose_cause
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.kinematics import CameraKinematics, NoPoseError, PoseAtTime, prismatic_joints
from lapreco_hil.robot_models import urdf_path
from lapreco_hil.types import MarkerSample, PosePrior, RobotDescription

log = logging.getLogger(__name__)

_CAUSE_TEXT = {BEFORE_FIRST: "before the first {what}", AFTER_LAST: "after the last {what}",
               IN_GAP: "in gaps between {what}s longer than {gap}"}


class FramesWithoutPose:
    """Frames that got no pose, counted by cause (geometry.NO_POSE_CAUSES) with the span of their times.

    A live stream cannot tell at a frame whether its readings have ended or only paused: such a frame is
    counted after the last reading, and moved to the gap count when later readings show it was inside one."""

    def __init__(self, what: str) -> None:
        self.what = what  # "joint reading", "camera pose"
        self.times: dict[str, list[int]] = {c: [] for c in NO_POSE_CAUSES}
        self.unsettled: list[int] = []  # counted after the last reading; no newer reading seen since
        self.first_frame_ns: int | None = None

    def seen(self, t_ns: int) -> None:
        if self.first_frame_ns is None:
            self.first_frame_ns = t_ns

    def add(self, cause: str, t_ns: int) -> None:
        self.times[cause].append(t_ns)
        if cause == AFTER_LAST:
            self.unsettled.append(t_ns)

    def resolve_after_last(self, cause_now) -> None:
        """Re-judge the frames counted after the last reading once newer readings came (``cause_now(t)``):
        those now inside a gap move to the gap count; the others stay (their reading came too late)."""
        still, moved = [], []
        for t in self.unsettled:
            cause = cause_now(t)
            (still if cause == AFTER_LAST else moved if cause == IN_GAP else []).append(t)
        self.unsettled = still
        if moved:
            gone = set(moved)
            self.times[AFTER_LAST] = [t for t in self.times[AFTER_LAST] if t not in gone]
            self.times[IN_GAP] = sorted(self.times[IN_GAP] + moved)

    def as_dict(self) -> dict[str, int]:
        return {c: len(self.times[c]) for c in NO_POSE_CAUSES}

    def warn(self, gap_ns: float) -> None:
        """One warning per cause: how many frames, and where in the video (seconds from its first frame)."""
        t0 = self.first_frame_ns or 0
        gap = f"{gap_ns * 1e-6:.0f} ms" if np.isfinite(gap_ns) else "a few sample periods"
        for cause in NO_POSE_CAUSES:
            times = self.times[cause]
            if times:
                n, lo, hi = len(times), min(times), max(times)
                log.warning("%d frames %s were skipped, not mapped (frames at %.3f..%.3f s of the video): no %s "
                            "brackets them, and a pose is never held or extrapolated", n,
                            _CAUSE_TEXT[cause].format(what=self.what, gap=gap), (lo - t0) * 1e-9, (hi - t0) * 1e-9,
                            self.what)


class RateLimitedWarning:
    """A console warning at most once per ``every_s`` seconds; the ones held back are counted into the next."""

    def __init__(self, logger: logging.Logger, every_s: float = 1.0) -> None:
        self.logger, self.every_s = logger, every_s
        self._last = -float("inf")
        self._held = 0

    def __call__(self, message: str, *args) -> bool:
        now = time.monotonic()
        if now - self._last < self.every_s:
            self._held += 1
            return False
        held, self._held, self._last = self._held, 0, now
        self.logger.warning(message + (f" ({held} more like it since the last warning)" if held else ""), *args)
        return True


def wait_for_sample_after(newest_ns, t_ns: int, wait_s: float, read_some) -> bool:
    """A live frame newer than the newest sample waits for the one after it: ``read_some(timeout_s)`` reads
    (returning whether anything came) until ``newest_ns()`` reaches ``t_ns`` or ``wait_s`` passes. False when
    the time passed (called after the first sample: there is a newest one)."""
    deadline = time.monotonic() + wait_s
    while newest_ns() < t_ns:
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        if not read_some(min(left, 0.01)):
            time.sleep(min(left, 0.002))  # (a reader that returns at once, without waiting)
    return True


class RobotPoseSource:
    """Joint samples from a RobotDriver -> FK of the camera at frame times, with the Jacobian covariance.

    Whatever the robot delivers is checked before it becomes a pose: a reading with a NaN or infinite joint,
    a joint beyond the URDF's limits (plus a margin for calibration slack), or a time that does not move
    forward is refused, counted and warned about on the console (rate limited); ``health`` shows it as
    degraded while refusals keep coming.

    A frame newer than the newest reading, by no more than the gap limit, waits up to ``reading_wait_s``
    for the reading after it (a live robot's next sample is due within a period); when none comes the frame
    has no pose, and later frames do not wait again until the robot delivers (a stream that ended costs one
    wait, not one per frame)."""

    source = "robot"  # what delivers the samples, in the live run's health lines and report
    limit_margin_rad = 0.05
    limit_margin_m = 0.005
    degraded_for_s = 0.25
    reading_wait_s = 0.1
    refusal_warning_every_s = 1.0

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
        self._warn_refusal = RateLimitedWarning(log, self.refusal_warning_every_s)
        self.without_pose = FramesWithoutPose("joint reading")
        self._taken: list = []  # accepted while a frame waited for a reading; handed on by the next poll()
        self._stalled = False  # the last wait for a reading came back empty

    def _refusal(self, s) -> tuple[str, str] | None:
        """(cause, message) when the sample cannot be a pose, else None; the message names the joint and value."""
        n = self.pose_at.kin.n_joints
        q = np.asarray(s.q)
        if q.shape != (n,):
            return "joint count", f"{q.shape[0] if q.ndim else 0} joint values, the robot model has {n} joints"
        bad = np.flatnonzero(~np.isfinite(q))
        if len(bad):
            i = int(bad[0])
            return "non-finite joint value", f"joint '{self._names[i]}' = {q[i]}"
        bad = np.flatnonzero((q < self._lower) | (q > self._upper))
        if len(bad):
            i = int(bad[0])
            return "beyond limits", (f"joint '{self._names[i]}' = {q[i]:.4g} beyond its limits "
                                     f"[{self._lower[i]:.4g}, {self._upper[i]:.4g}] (margin included)")
        last = self.pose_at.last_time_ns
        if last is not None and s.t_ns <= last:
            return "time did not move forward", f"time {s.t_ns} ns is not after the last reading's {last} ns"
        return None

    def _take(self, samples) -> list:
        good = []
        for s in samples:
            refusal = self._refusal(s)
            if refusal is not None:
                cause, message = refusal
                self.rejected += 1
                self.rejected_by_cause[cause] = self.rejected_by_cause.get(cause, 0) + 1
                self._last_refusal, self._last_refusal_wall = message, time.monotonic()
                self._warn_refusal("robot reading refused (%s): %s; %d refused so far", cause, message,
                                   self.rejected)
                continue
            self.pose_at.add(s)
            good.append(s)
        if good:
            self._stalled = False
            if self.without_pose.unsettled:
                self.without_pose.resolve_after_last(self.pose_at.no_pose_cause)
        return good

    def poll(self) -> list:
        """Take the robot's new samples, refusing (counting, warning about) what cannot be a pose; returns the
        accepted ones (a live run records them)."""
        good, self._taken = self._taken + self._take(self.robot.read(timeout_s=0.0)), []
        return good

    def _wait_for_reading_after(self, t_kin_ns: int) -> None:
        if not self._stalled:
            self._stalled = not wait_for_sample_after(lambda: self.pose_at.last_time_ns, t_kin_ns,
                                                      self.reading_wait_s, self._read_into_taken)

    def _read_into_taken(self, timeout_s: float) -> bool:
        got = self._take(self.robot.read(timeout_s=timeout_s))
        self._taken.extend(got)
        return bool(got)

    @property
    def last_refusal(self) -> str:
        """Why the newest refused reading was refused, with its value ("" before any refusal)."""
        return self._last_refusal

    @property
    def health(self) -> Health:
        if time.monotonic() - self._last_refusal_wall < self.degraded_for_s:
            return Health(HealthState.DEGRADED, f"{self.rejected} readings refused; last: {self._last_refusal}")
        return Health(HealthState.OK)

    def has_pose(self, t_ns: int | None = None) -> bool:
        """Whether frame time ``t_ns`` has a pose: two accepted readings bracket it, within the gap limit. A
        frame that has none is counted by cause (``without_pose``). Without a time: whether any reading came."""
        if t_ns is None:
            return len(self.pose_at) > 0
        self.without_pose.seen(t_ns)
        cause = self.pose_at.no_pose_cause(t_ns)
        t_kin = t_ns + self.pose_at.offset_ns
        # only a reading due within the gap limit can still bracket the frame: further out, none is awaited
        if cause == AFTER_LAST and t_kin - self.pose_at.last_time_ns <= self.pose_at.max_gap_ns:
            self._wait_for_reading_after(t_kin)
            cause = self.pose_at.no_pose_cause(t_ns)
        if cause is not None:
            self.without_pose.add(cause, t_ns)
        return cause is None

    def warn_without_pose(self) -> None:
        """One console warning per cause of frames without a pose (call at the end of a run)."""
        self.without_pose.warn(self.pose_at.max_gap_ns)

    @property
    def time_offset_ns(self) -> int:
        """The offset applied: joint time = frame time + this."""
        return self.pose_at.offset_ns

    def prior_at(self, t_ns: int) -> PosePrior:
        """The prior at frame time ``t_ns``; NoPoseError when ``has_pose(t_ns)`` is False."""
        return self.pose_at.prior_at(t_ns)


class PoseTrack:
    """Camera poses T_world_camera at strictly increasing times, growing as they come: the pose at a time is
    interpolated on SE(3) between the two around it (as ``geometry.SampledPoses``), and only where they are at
    most ``max_gap_ns`` apart (``no_pose_cause``). The gap limit is ``max_gap_periods`` median periods of the
    recent poses, or ``fixed_gap_ns`` (a table known in full). A live track holds at most twice ``capacity``
    poses (the oldest half is dropped); a table's (``capacity`` None) holds them all."""

    period_window = 256  # recent intervals kept for the median period

    def __init__(self, max_gap_periods: float = MAX_GAP_PERIODS, fixed_gap_ns: float | None = None,
                 capacity: int | None = None) -> None:
        self.max_gap_periods = max_gap_periods
        self.fixed_gap_ns = fixed_gap_ns
        self.capacity = capacity
        self._times: list[int] = []
        self._poses: list[np.ndarray] = []
        self._intervals: collections.deque[int] = collections.deque(maxlen=self.period_window)

    def add(self, t_ns: int, T_world_camera: np.ndarray) -> bool:
        """Append a pose; False (not added) when its time is not after the last one's."""
        if self._times and t_ns <= self._times[-1]:
            return False
        if self._times:
            self._intervals.append(t_ns - self._times[-1])
        self._times.append(int(t_ns))
        self._poses.append(np.asarray(T_world_camera, float))
        if self.capacity is not None and len(self._times) > 2 * self.capacity:
            del self._times[: self.capacity]
            del self._poses[: self.capacity]
        return True

    def __len__(self) -> int:
        return len(self._times)

    @property
    def t_ns(self) -> np.ndarray:
        return np.asarray(self._times, np.int64)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) the poses held, in the order of ``t_ns`` (the time-offset estimate interpolates them)."""
        return np.asarray(self._poses, float).reshape(-1, 4, 4)

    @property
    def last_time_ns(self) -> int | None:
        return self._times[-1] if self._times else None

    @property
    def max_gap_ns(self) -> float:
        if self.fixed_gap_ns is not None:
            return self.fixed_gap_ns
        if not self._intervals:
            return float("inf")
        return self.max_gap_periods * float(np.median(self._intervals))

    def no_pose_cause(self, t_ns: int) -> str | None:
        return no_pose_cause(self._times, t_ns, self.max_gap_ns)

    def __call__(self, t_ns: int) -> np.ndarray:
        times = self._times
        i = bisect.bisect_right(times, t_ns)
        if i == 0:
            return self._poses[0]
        if i >= len(times):
            return self._poses[-1]
        s = (t_ns - times[i - 1]) / (times[i] - times[i - 1])
        return interpolate_pose(self._poses[i - 1], self._poses[i], s)


class GivenPoseSource:
    """Camera poses T_world_camera known at times (an optical tracker): interpolated on SE(3) at frame
    times, with a fixed diagonal covariance. A frame outside the poses' span, or in a gap longer than
    ``max_gap_periods`` median periods, has no pose (counted in ``without_pose``)."""

    # what a robot pose source also answers (the live run's report reads both kinds alike): no robot, no refusals
    robot = None
    rejected = 0
    rejected_by_cause: Mapping[str, int] = MappingProxyType({})
    last_refusal = ""
    what = "camera pose"  # the kind of sample, in warnings and errors
    source = "camera poses"  # what delivers them, in the live run's health lines and report

    def __init__(self, t_ns: np.ndarray, poses: np.ndarray, sigma_rotation_rad: float, sigma_translation_m: float,
                 offset_ns: int = 0, max_gap_periods: float = MAX_GAP_PERIODS) -> None:
        if len(t_ns) == 0:
            raise ConfigError("no camera poses given")
        t = np.asarray(t_ns, np.int64)
        self._setup(sigma_rotation_rad, sigma_translation_m, offset_ns,
                    PoseTrack(max_gap_periods, fixed_gap_ns=max_gap_ns(t, max_gap_periods)))
        for ti, T in zip(t, np.asarray(poses, float)):
            self.track.add(int(ti), T)

    def _setup(self, sigma_rotation_rad: float, sigma_translation_m: float, offset_ns: int, track: PoseTrack) -> None:
        self.track = track
        self.offset_ns = offset_ns
        self.cov = np.diag([sigma_rotation_rad**2] * 3 + [sigma_translation_m**2] * 3)
        self.without_pose = FramesWithoutPose(self.what)

    @property
    def max_gap_ns(self) -> float:
        return self.track.max_gap_ns

    def poll(self) -> list:
        return []

    def no_pose_cause(self, t_ns: int) -> str | None:
        """Why frame time ``t_ns`` has no pose (geometry.NO_POSE_CAUSES), or None when it has one."""
        return self.track.no_pose_cause(t_ns + self.offset_ns)

    def has_pose(self, t_ns: int | None = None) -> bool:
        """Whether frame time ``t_ns`` has a pose; a frame that has none is counted by cause."""
        if t_ns is None:
            return len(self.track) > 0
        self.without_pose.seen(t_ns)
        cause = self.no_pose_cause(t_ns)
        if cause is not None:
            self.without_pose.add(cause, t_ns)
        return cause is None

    def warn_without_pose(self) -> None:
        self.without_pose.warn(self.max_gap_ns)

    @property
    def time_offset_ns(self) -> int:
        """The offset applied: pose time = frame time + this."""
        return self.offset_ns

    def prior_at(self, t_ns: int) -> PosePrior:
        """The prior at frame time ``t_ns``; NoPoseError when ``has_pose(t_ns)`` is False."""
        cause = self.no_pose_cause(t_ns)
        if cause is not None:
            raise NoPoseError(f"no camera pose at video time {t_ns} ns ({cause.replace('_', ' ')} of the given "
                              f"{self.what}s)", cause)
        T = self.track(t_ns + self.offset_ns)
        return PosePrior(T_world_camera=T.copy(), cov=self.cov.copy(), t_ns=t_ns)


# why a marker sample is refused (the keys of rejected_by_cause)
OUT_OF_VOLUME, RMS_ABOVE_LIMIT, NON_FINITE, TIME_NOT_FORWARD = ("out_of_volume", "rms_above_limit", "non_finite",
                                                                "time did not move forward")


class MarkerPoseSource(GivenPoseSource):
    """A tracked scope (an optical / EM tracker's marker on it): T_world_camera = T_world_tracker @
    T_tracker_marker(t + offset) @ T_marker_camera, from the scope's tool's samples only, interpolated on SE(3)
    as GivenPoseSource does, with the session's (or default) pose sigmas as the prior.

    Live it polls a TrackerDriver (``tracker``); offline it reads a session's marker table (``table``). A sample
    outside the tracker's characterised volume, with a marker-fit RMS above ``setup.max_rms_mm``, non-finite,
    or not after the last one is refused and counted by cause (``rejected_by_cause``), warned about (rate
    limited), and shown in ``health`` as degraded while refusals keep coming; the tool's MISSING replies are the
    driver's ``faults['missing']`` (``tracker_faults``). Like a robot's, a live frame newer than the newest sample
    waits up to ``sample_wait_s`` for the one after it."""

    source = "tracker"
    degraded_for_s = 0.25
    sample_wait_s = 0.1
    refusal_warning_every_s = 1.0
    live_capacity = 4096  # poses kept live (twice this at most): minutes at a tracker's 40-60 Hz
    what = "marker pose"

    def __init__(self, setup, tracker=None, table=None, T_marker_camera: np.ndarray | None = None,
                 offset_ns: int = 0, max_gap_periods: float = MAX_GAP_PERIODS) -> None:
        if (tracker is None) == (table is None):
            raise ValueError("MarkerPoseSource: give a tracker (live) or a marker table (offline), not both")
        T_mc = setup.T_marker_camera if T_marker_camera is None else np.asarray(T_marker_camera, float)
        if T_mc is None:
            raise ConfigError(f"the tracked scope (tool '{setup.tool}') has no hand-eye (T_marker_camera; a "
                              f"calibration session has none): make one with 'lapreco calibrate handeye-tracked "
                              f"--session S --board-tool TOOL --board BOARD --out handeye.yaml' and pass --hand-eye "
                              f"handeye.yaml")
        self.setup, self.tracker, self.tool = setup, tracker, setup.tool
        self.T_marker_camera = T_mc
        self._setup(setup.sigma.rotation_rad, setup.sigma.translation_m, offset_ns,
                    PoseTrack(max_gap_periods, capacity=None if table is not None else self.live_capacity))
        self.rejected = 0
        self.rejected_by_cause: dict[str, int] = {}
        self.other_tools = 0  # samples of other tools (a board's marker): not the scope's, not refused
        self._last_refusal = ""
        self._last_refusal_wall = -float("inf")
        self._warn_refusal = RateLimitedWarning(log, self.refusal_warning_every_s)
        self._taken: list = []  # read while a frame waited for a sample; handed on by the next poll()
        self._stalled = False
        if table is not None:
            self._take([MarkerSample(T, int(t), i, tool, float(rms), bool(inside)) for i, (t, tool, T, rms, inside)
                        in enumerate(zip(table.t_ns, table.tools, table.poses, table.rms_mm, table.in_volume))])
            if not len(self.track):
                causes = ", ".join(f"{n} {c}" for c, n in sorted(self.rejected_by_cause.items())) or "no rows"
                raise ConfigError(f"no usable pose of the scope's tool '{self.tool}' in the marker table ({causes}); "
                                  f"last refused: {self._last_refusal or '-'}")
            self.track.fixed_gap_ns = max_gap_ns(self.track.t_ns, max_gap_periods)

    # --- taking samples ---------------------------------------------------------------------------------------
    def _refusal(self, s) -> tuple[str, str] | None:
        T = np.asarray(s.T_tracker_marker, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.isfinite(s.rms_mm):
            return NON_FINITE, f"tool '{s.tool}' at {s.t_ns} ns: a non-finite pose or RMS"
        if not s.in_volume:
            return OUT_OF_VOLUME, f"tool '{s.tool}' at {s.t_ns} ns is outside the tracker's characterised volume"
        if s.rms_mm > self.setup.max_rms_mm:
            return RMS_ABOVE_LIMIT, (f"tool '{s.tool}' at {s.t_ns} ns: marker fit RMS {s.rms_mm:.3g} mm above "
                                     f"the limit {self.setup.max_rms_mm:.3g} mm")
        last = self.track.last_time_ns
        if last is not None and s.t_ns <= last:
            return TIME_NOT_FORWARD, f"time {s.t_ns} ns is not after the last sample's {last} ns"
        return None

    def _take(self, samples) -> list:
        """Accept the scope's good samples into the track (composed to camera poses); returns the accepted."""
        good = []
        for s in samples:
            if s.tool != self.tool:
                self.other_tools += 1
                continue
            refusal = self._refusal(s)
            if refusal is not None:
                cause, message = refusal
                self.rejected += 1
                self.rejected_by_cause[cause] = self.rejected_by_cause.get(cause, 0) + 1
                self._last_refusal, self._last_refusal_wall = message, time.monotonic()
                if self.tracker is not None:  # (offline, the counts are in the report)
                    self._warn_refusal("marker sample refused (%s): %s; %d refused so far", cause, message,
                                       self.rejected)
                continue
            self.track.add(s.t_ns, self.setup.T_world_tracker @ np.asarray(s.T_tracker_marker, float)
                           @ self.T_marker_camera)
            good.append(s)
        if good:
            self._stalled = False
            if self.without_pose.unsettled:
                self.without_pose.resolve_after_last(self.no_pose_cause)
        return good

    def poll(self) -> list:
        """Take the tracker's new samples (refusing what cannot be a pose); returns every sample read, of every
        tool and refused or not: a live run records what the device said, and a replay judges it again."""
        if self.tracker is None:
            return []
        new = self.tracker.read(timeout_s=0.0)
        self._take(new)
        out, self._taken = self._taken + new, []
        return out

    def _wait_for_sample_after(self, t_pose_ns: int) -> None:
        if not self._stalled:
            self._stalled = not wait_for_sample_after(lambda: self.track.last_time_ns, t_pose_ns,
                                                      self.sample_wait_s, self._read_into_taken)

    def _read_into_taken(self, timeout_s: float) -> bool:
        new = self.tracker.read(timeout_s=timeout_s)
        self._taken.extend(new)  # every sample read is recorded, accepted or not
        self._take(new)
        return bool(new)

    def has_pose(self, t_ns: int | None = None) -> bool:
        """Whether frame time ``t_ns`` has a pose (two accepted samples bracket it, within the gap limit); a
        frame that has none is counted by cause. Without a time: whether any sample was accepted."""
        if t_ns is None or self.tracker is None or not len(self.track):
            return super().has_pose(t_ns)
        self.without_pose.seen(t_ns)
        cause = self.no_pose_cause(t_ns)
        t_pose = t_ns + self.offset_ns
        if cause == AFTER_LAST and t_pose - self.track.last_time_ns <= self.max_gap_ns:
            self._wait_for_sample_after(t_pose)
            cause = self.no_pose_cause(t_ns)
        if cause is not None:
            self.without_pose.add(cause, t_ns)
        return cause is None

    # --- what the run reports ----------------------------------------------------------------------------------
    @property
    def last_refusal(self) -> str:
        """Why the newest refused sample was refused ("" before any refusal)."""
        return self._last_refusal

    @property
    def tracker_faults(self) -> dict[str, int]:
        """The driver's own counts (``missing``: replies without the tool, ``out_of_volume``, lost replies)."""
        return {k: int(v) for k, v in dict(self.tracker.faults).items() if v} if self.tracker is not None else {}

    @property
    def health(self) -> Health:
        if time.monotonic() - self._last_refusal_wall < self.degraded_for_s:
            return Health(HealthState.DEGRADED, f"{self.rejected} marker samples refused; last: {self._last_refusal}")
        if self.tracker is not None:
            h = self.tracker.health
            if h is not None and h.state is not HealthState.OK:
                return Health(h.state, f"tracker: {h.detail}")
        return Health(HealthState.OK)
