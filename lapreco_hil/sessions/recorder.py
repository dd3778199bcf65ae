"""Recording: frames and joint readings (or a tracker's marker poses) from live (or simulated) devices into a
session, as they arrive. ``SessionRecorder`` is what both ``lapreco record`` (``record``/``record_tracked``)
and ``lapreco run --record`` (the live runtime's Record stage) write through, so both leave the same session:
frames, pose samples, events.csv, session.json's source and health (with the pose source's coverage of the
frames), and the ground truth where it belongs to the recorded poses."""

from __future__ import annotations

import collections
import logging
import math
import sys
import time
from array import array
from dataclasses import dataclass, field

import numpy as np

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.errors import ConfigError, DeviceError
from lapreco_hil.geometry import max_gap_ns
from lapreco_hil.robot_models import urdf_path
from lapreco_hil.types import RobotDescription
from lapreco_hil.drivers.health import HealthState
from lapreco_hil.sessions.format import EVENTS_FILE, SessionMeta, TrackerSetup
from lapreco_hil.sessions.writer import SessionWriter

log = logging.getLogger(__name__)


@dataclass
class RecordStats:
    frames: int
    joint_samples: int
    skipped_joint_samples: int
    capture_span_s: float
    wall_s: float
    stopped_by: str
    robot_faults: dict = field(default_factory=dict)  # the robot driver's fault counts at the end
    events: int = 0  # rows of events.csv: faults and health changes seen while recording
    marker_samples: int = 0  # rows of marker_poses.csv (every tool's), in a tracked-scope session
    scope_samples: int = 0  # of them, the scope's tool's
    tracker_faults: dict = field(default_factory=dict)  # the tracker driver's fault counts at the end
    pose_coverage: "PoseCoverage | None" = None  # how the pose source's recorded samples cover the frames

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0


class DeviceWatch:
    """Device faults and health changes while recording: each one a row of events.csv and one console
    warning (at most one per device and kind of event every ``warn_every_s``)."""

    def __init__(self, writer: SessionWriter, devices: dict, warn_every_s: float = 1.0, console: bool = True) -> None:
        from lapreco_hil.pose_sources import RateLimitedWarning

        self.writer, self.devices = writer, devices  # name -> device (a grabber, a robot driver)
        self.console = console  # False: events.csv only (a live run shows each change through its health monitor)
        self._warn = collections.defaultdict(lambda: RateLimitedWarning(log, warn_every_s))
        self._state = {name: None for name in devices}
        self._started: set[str] = set()  # devices seen in a state other than "no reading yet" (stale)
        self._faults: dict[str, dict] = {name: {} for name in devices}
        self.last_problem: dict[str, str] = {}  # name -> the detail of its last fault, else its last other problem
        self.last_fault: dict[str, str] = {}  # name -> the detail of its last FAULTED state

    def check(self, t_ns: int) -> None:
        for name, dev in self.devices.items():
            health = dev.health
            if health is not None and health.state != self._state[name]:
                # a device that has not delivered yet (stale, then OK) is starting, not changing
                starting = name not in self._started and health.state in (HealthState.OK, HealthState.STALE)
                self._state[name] = health.state
                if health.state is not HealthState.STALE:
                    self._started.add(name)
                if not starting:
                    self._event(t_ns, name, f"health:{health.state.value}", health.detail)
            if health is not None and health.state is not HealthState.OK and health.detail:
                # a device's own fault (limits, EMCY) says more than a late reply: it is kept over them
                if health.state is HealthState.FAULTED or name not in self.last_fault:
                    self.last_problem[name] = health.detail
                if health.state is HealthState.FAULTED:
                    self.last_fault[name] = health.detail
            faults = dict(dev.faults)
            for kind, count in faults.items():
                new = count - self._faults[name].get(kind, 0)
                if new > 0:
                    detail = f"{new} more, {count} in all"
                    if health is not None and health.detail:
                        detail += f"; {health.detail}"
                    self._event(t_ns, name, f"fault:{kind}", detail)
            self._faults[name] = faults

    def _event(self, t_ns: int, name: str, event: str, detail: str) -> None:
        self.writer.add_event(t_ns, name, event, detail)
        if self.console:
            self._warn[(name, event)]("record: %s %s: %s", name, event, detail or "(no detail)")


# a pose source counts as lost when none of its readings was received during this long at the end of the capture
# (or its gap limit, MAX_GAP_PERIODS of its median reading periods, where that is longer), on the host's clock: a
# late reply or two at the very end of a recording is not a lost device, a robot whose cable came out is
LOST_AFTER_S = 0.25


class Receipts:
    """When the frames and the pose source's readings of a recording or a run reached the host (its monotonic
    clock), in the order the capture loop received them. Whether a pose source was lost is judged on these, not on
    the readings' stamps: a device's clock may be offset from the video's (by seconds, in public datasets), and an
    offset not declared would make readings that came to the very end look as if they had stopped early."""

    def __init__(self) -> None:
        self.first_frame_ns = self.last_frame_ns = None  # host monotonic ns
        self.first_reading_ns = self.last_reading_ns = None
        self.frames_after_reading = 0  # frames received after the last reading was

    def frame(self) -> None:
        now = time.monotonic_ns()
        self.first_frame_ns = now if self.first_frame_ns is None else self.first_frame_ns
        self.last_frame_ns = now
        self.frames_after_reading += 1

    def reading(self) -> None:
        now = time.monotonic_ns()
        self.first_reading_ns = now if self.first_reading_ns is None else self.first_reading_ns
        self.last_reading_ns = now
        self.frames_after_reading = 0

    def figures(self) -> dict:
        """PoseCoverage's host-clock fields (none when no frame or no reading was received)."""
        if self.last_frame_ns is None or self.last_reading_ns is None:
            return {}
        return {"silent_received_s": max(0, self.last_frame_ns - self.last_reading_ns) * 1e-9,
                "late_received_s": max(0, self.first_reading_ns - self.first_frame_ns) * 1e-9,
                "after_received": self.frames_after_reading}


@dataclass(frozen=True)
class PoseCoverage:
    """How one pose source's readings cover the frames of a recording or a live run. A frame has a pose only
    between two readings at most the gap limit apart (``geometry.no_pose_cause``): the others come before its
    first reading, in a gap, or after its last one. Times are capture times on the frames' clock: the readings'
    stamps as recorded less the declared ``time_offset_ns`` (pose time = video time + offset), so an offset not
    declared shows as frames before the first or after the last reading (a warning, never a failure). The gaps'
    number and longest are known where the readings' times are (a recording), not in a live run.

    Whether the source was ``lost`` is judged on the host's clock instead (``Receipts``): ``silent_received_s``,
    how long before the end of the capture its last reading was received; ``late_received_s``, how long after the
    first frame its first was; ``after_received``, the frames received after its last reading (None: not known)."""

    kind: str  # "robot" | "tracker"
    url: str
    frames: int
    before_first: int = 0
    in_gap: int = 0
    after_last: int = 0
    first_frame_ns: int | None = None
    last_frame_ns: int | None = None
    first_reading_ns: int | None = None
    last_reading_ns: int | None = None
    gap_limit_ns: float = math.inf
    gap_frames_ns: tuple[int, int] | None = None  # the first and the last frame in a gap
    gaps: int | None = None  # gaps longer than the gap limit with a frame in them
    longest_gap_ns: tuple[int, int] | None = None  # (start, end) of the longest of them
    time_offset_ns: int = 0  # the declared offset taken off the readings' stamps
    silent_received_s: float | None = None  # host clock: its last reading received this long before the last frame
    late_received_s: float | None = None  # host clock: its first reading received this long after the first frame
    after_received: int | None = None  # host clock: frames received after its last reading was

    @property
    def device(self) -> str:
        return f"{self.kind} {self.url}"

    @property
    def silent_s(self) -> float:
        """How long before the last frame its last reading is stamped, on the frames' clock (0 when after)."""
        if self.last_frame_ns is None or self.last_reading_ns is None:
            return 0.0
        return max(0.0, (self.last_frame_ns - self.last_reading_ns) * 1e-9)

    @property
    def lost_after_s(self) -> float:
        gap_s = self.gap_limit_ns * 1e-9 if math.isfinite(self.gap_limit_ns) else 0.0
        return max(LOST_AFTER_S, gap_s)

    @property
    def lost(self) -> bool:
        """No reading of it was received, on the host's clock, during the last ``lost_after_s`` of the capture
        (``silent_received_s``); its stamps do not decide (a clock offset would). A source that delivered nothing
        at all, or one whose receipts are not known, is not judged here (each command says the first with its own
        error)."""
        return self.silent_received_s is not None and self.silent_received_s > self.lost_after_s

    def _offset_hint(self) -> str:
        return (f"its clock is likely offset from the video's by more than the time offset applied "
                f"({self.time_offset_ns * 1e-6:.0f} ms); measure it with 'lapreco calibrate time-offset' on a "
                f"recording")

    @property
    def late_start(self) -> bool:
        """Its first reading came well after the first frame (not a device merely opened a moment later)."""
        if self.first_reading_ns is None or self.first_frame_ns is None:
            return self.before_first > 0
        return (self.first_reading_ns - self.first_frame_ns) * 1e-9 > self.lost_after_s

    def _at(self, t_ns: int | None) -> float:
        """Seconds after the first frame."""
        if t_ns is None:
            return 0.0
        return (t_ns - (t_ns if self.first_frame_ns is None else self.first_frame_ns)) * 1e-9

    def summary(self) -> str | None:
        """One line on the frames its readings do not cover (None when they cover every frame, but for a few at
        the start)."""
        parts = []
        if self.lost:
            parts.append(f"{self.after_last} of {self.frames} frames come after its last reading (at "
                         f"{self._at(self.last_reading_ns):.2f} s; none received in the last "
                         f"{self.silent_received_s:.2f} s of the capture: lost)")
        elif self.after_last and self.silent_received_s is not None:
            parts.append(f"{self.after_last} of {self.frames} frames come after its last reading (at "
                         f"{self._at(self.last_reading_ns):.2f} s), though its readings were received to the end "
                         f"of the capture: {self._offset_hint()}")
        elif self.after_last:
            parts.append(f"{self.after_last} of {self.frames} frames come after its last reading (at "
                         f"{self._at(self.last_reading_ns):.2f} s; none in the last {self.silent_s:.2f} s)")
        if self.in_gap:
            gap_ms = f"{self.gap_limit_ns * 1e-6:.0f} ms" if math.isfinite(self.gap_limit_ns) else "its gap limit"
            text = f"{self.in_gap} of {self.frames} frames fall in "
            if self.gaps is not None and self.longest_gap_ns is not None:
                lo, hi = self.longest_gap_ns
                text += (f"{self.gaps} gap{'s' if self.gaps != 1 else ''} between its readings longer than {gap_ms} "
                         f"(the longest {(hi - lo) * 1e-9:.2f} s, from {self._at(lo):.2f} s)")
            else:
                lo, hi = self.gap_frames_ns or (self.first_frame_ns, self.first_frame_ns)
                text += (f"gaps between its readings longer than {gap_ms} (frames at {self._at(lo):.2f}.."
                         f"{self._at(hi):.2f} s)")
            parts.append(text + ", after which its readings resumed")
        if self.before_first and self.late_start:
            on_time = self.late_received_s is not None and self.late_received_s <= self.lost_after_s
            parts.append(f"{self.before_first} of {self.frames} frames come before its first reading (at "
                         f"{self._at(self.first_reading_ns):.2f} s)"
                         + (f", though its readings were received from the start of the capture: "
                            f"{self._offset_hint()}" if on_time else ""))
        return f"{self.device}: " + "; ".join(parts) if parts else None

    def lost_message(self, command: str, kept: str, problem: str = "") -> str:
        """The one-line error of a lost pose source: the device, what happened, what to do, where the data is."""
        # (the frames its stamps leave without a pose, as the summary counts them; those received after its last
        # reading where the stamps, on a clock offset by more than declared, seem to cover every frame)
        after = self.after_last if self.after_last or self.after_received is None else self.after_received
        return (f"{command}: {self.kind} '{self.url}' stopped delivering readings: none received in the last "
                f"{self.silent_received_s or 0.0:.2f} s of the capture ({after} of {self.frames} frames come after "
                f"its last reading and have no pose; that reading is stamped {self._at(self.last_reading_ns):.2f} s "
                f"after the first frame{'; last problem: ' + problem if problem else ''}); check its cable and "
                f"power, then 'lapreco devices --probe {self.url}'; {kept}")

    def as_dict(self) -> dict:
        """session.json's health.pose_coverage and report.json's pose_coverage."""
        def at(t_ns):
            return None if t_ns is None else round(self._at(t_ns), 3) + 0.0  # (never -0.0)

        return {"device": self.device, "frames": self.frames, "before_first": self.before_first,
                "in_gap": self.in_gap, "after_last": self.after_last, "first_reading_s": at(self.first_reading_ns),
                "last_reading_s": at(self.last_reading_ns), "silent_at_end_s": round(self.silent_s, 3),
                "time_offset_ms": round(self.time_offset_ns * 1e-6, 3) + 0.0,
                "received_silent_at_end_s": None if self.silent_received_s is None else
                round(self.silent_received_s, 3),
                "lost": self.lost, "gaps": self.gaps,
                "longest_gap_s": None if self.longest_gap_ns is None else
                round((self.longest_gap_ns[1] - self.longest_gap_ns[0]) * 1e-9, 3),
                "gap_limit_ms": round(self.gap_limit_ns * 1e-6, 3) if math.isfinite(self.gap_limit_ns) else None,
                "summary": self.summary()}


def coverage_of(kind: str, url: str, frame_times, reading_times, *, time_offset_ns: int = 0,
                receipts: Receipts | None = None) -> PoseCoverage:
    """The coverage of frames at ``frame_times`` by readings stamped ``reading_times`` (both increasing), with the
    gap limit ``geometry.max_gap_ns`` takes from the readings; the readings' stamps are on the frames' clock once
    ``time_offset_ns`` (pose time = video time + offset) is taken off. ``receipts``: when both reached the host,
    what decides ``lost``."""
    f = np.asarray(frame_times, np.int64)
    r = np.asarray(reading_times, np.int64) - np.int64(time_offset_ns)
    gap = max_gap_ns(r)
    host = receipts.figures() if receipts is not None else {}
    first_f, last_f = (int(f[0]), int(f[-1])) if len(f) else (None, None)
    if len(f) == 0 or len(r) == 0:
        return PoseCoverage(kind, url, len(f), before_first=len(f), first_frame_ns=first_f, last_frame_ns=last_f,
                            first_reading_ns=int(r[0]) if len(r) else None,
                            last_reading_ns=int(r[-1]) if len(r) else None, gap_limit_ns=gap,
                            time_offset_ns=int(time_offset_ns), **host)
    before, after = f < r[0], f > r[-1]
    j = np.searchsorted(r, f)  # r[j - 1] < f <= r[j] for the frames inside
    exact = r[np.minimum(j, len(r) - 1)] == f
    i = np.clip(j, 1, max(len(r) - 1, 1))
    in_gap = ~before & ~after & ~exact & ((r[np.minimum(i, len(r) - 1)] - r[i - 1]) > gap)
    gap_times, gap_starts = f[in_gap], np.unique(i[in_gap])  # a gap: the readings i - 1 and i around its frames
    longest = None
    if len(gap_starts):
        k = int(gap_starts[np.argmax(r[gap_starts] - r[gap_starts - 1])])
        longest = (int(r[k - 1]), int(r[k]))
    return PoseCoverage(kind, url, len(f), int(before.sum()), int(in_gap.sum()), int(after.sum()), first_f, last_f,
                        int(r[0]), int(r[-1]), gap,
                        (int(gap_times[0]), int(gap_times[-1])) if len(gap_times) else None,
                        gaps=len(gap_starts), longest_gap_ns=longest, time_offset_ns=int(time_offset_ns), **host)


class DeviceLostError(DeviceError):
    """A pose source stopped delivering partway (``PoseCoverage.lost``); raised once everything is saved.
    ``coverage``: its PoseCoverage; ``stats`` (a recording's RecordStats) or ``report`` (a run's report)."""

    def __init__(self, message: str, coverage: PoseCoverage, *, stats: "RecordStats | None" = None,
                 report: dict | None = None) -> None:
        super().__init__(message)
        self.coverage, self.stats, self.report = coverage, stats, report


def check_pose_coverage(command: str, coverage: PoseCoverage | None, kept: str, *, problem: str = "",
                        warn: bool = True, **context) -> None:
    """The end of a recording or run: one warning on the frames the pose source's readings do not cover (a gap
    it recovered from, or the end), and a DeviceLostError when it was lost (``context``: its stats/report)."""
    if coverage is None:
        return
    line = coverage.summary()
    if warn and line:
        log.warning("%s: %s", command, line)
    if coverage.lost:
        raise DeviceLostError(coverage.lost_message(command, kept, problem), coverage, **context)


def _truth_owner(device):
    """What a device's data comes from when it is a simulated world's (``world``) or a session's (``session``)."""
    return getattr(device, "world", None) or getattr(device, "session", None)


def recorded_truth(grabber, robot, into: str = "the session"):
    """The grabber's ground truth when it belongs to the robot's readings: the grabber's simulated world (or
    replayed session) is the one the robot reads (``sim://`` for both, or ``sim://...&link=serial|canopen``: the
    simulated robot through a real driver). Else None, with one warning: a simulated camera beside a real robot
    shows the simulator's scope, not where the robot holds it, so accuracy against that truth would be
    meaningless."""
    truth = grabber.ground_truth
    if truth is None or (truth.surface is None and truth.camera_pose is None):
        return None
    owner = _truth_owner(grabber)
    if owner is not None and _truth_owner(robot) is owner:
        return truth
    log.warning("the ground truth of grabber '%s' (the true camera poses and surface of its world) is left out "
                "of %s: the joint readings come from robot '%s', which does not move that world, so accuracy "
                "against it would be meaningless; for ground truth, open the robot in the same world (--robot "
                "sim://SCENE, or sim://SCENE?link=serial|canopen for the simulated robot through a real driver)",
                grabber.url.raw, into, robot.url.raw)
    return None


class SessionRecorder:
    """A recording's session, whoever feeds it: ``lapreco record``'s loop or the live run's Record stage (which
    calls ``add_frame``, ``add_joints`` and ``close`` from one thread). It writes the frames, the pose source's
    samples (joint readings, or every tool's marker poses), the ground truth it is given (``truth``: see
    ``recorded_truth``), the devices' faults and health changes into events.csv as it goes (``DeviceWatch``; on
    the console too unless ``console`` is False), and at the close session.json's ``health``: the devices' fault
    counts and the pose source's coverage of the frames (``PoseCoverage``)."""

    def __init__(self, out, meta: SessionMeta, grabber, device, *, urdf_file=None, truth=None,
                 console: bool = True) -> None:
        self.writer = SessionWriter(out, meta, urdf_file)
        self.grabber, self.device, self.truth = grabber, device, truth
        self.kind = "tracker" if meta.pose_source == "marker_poses" else "robot"
        self.tool = meta.tracker.tool if meta.tracker is not None else None
        self.device_name, self.grabber_name = f"{self.kind} {device.url.raw}", f"grabber {grabber.url.raw}"
        try:
            if truth is not None and truth.surface is not None:
                self.writer.set_truth_surface(truth.surface)
        except BaseException:
            self.writer.close()
            raise
        self.watch = DeviceWatch(self.writer, {self.device_name: device, self.grabber_name: grabber}, console=console)
        self.skipped = 0  # pose samples the writer did not record (non-finite, time not forward)
        self.seen_tools: collections.Counter[str] = collections.Counter()  # marker samples by tool
        self.faults: dict = {}
        self.coverage: PoseCoverage | None = None
        self._frame_times = array("q")
        self.receipts = Receipts()  # when the frames and the pose samples reached it, on the host's clock
        self.closed = False

    def __enter__(self) -> "SessionRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def add_frame(self, frame) -> None:
        self.receipts.frame()  # (as it reaches the recorder: before any wait for the PNG encoders)
        self.writer.add_frame(frame)
        if self.truth is not None and self.truth.camera_pose is not None:
            self.writer.add_true_pose(frame.t_ns, self.truth.camera_pose(frame.t_ns))
        self._frame_times.append(int(frame.t_ns))
        self.watch.check(frame.t_ns)

    def add_joints(self, samples) -> int:
        """The pose source's samples (joint readings, or MarkerSamples); returns how many were not recorded."""
        if self.kind == "tracker":
            self.seen_tools.update(s.tool for s in samples)
        # a reading received (the device delivers): the robot's any, the tracker's of the scope's tool
        if any(self.kind == "robot" or s.tool == self.tool for s in samples):
            self.receipts.reading()
        skipped = self.writer.add_joints(samples)
        self.skipped += skipped
        return skipped

    def close(self) -> None:
        """Session.json's health (fault counts, the pose source's coverage), then the session closed, complete."""
        if self.closed:
            return
        self.closed = True
        try:
            writer, device = self.writer, self.device
            if self._frame_times:
                self.watch.check(self._frame_times[-1])
            self.faults = {k: int(v) for k, v in dict(device.faults).items() if v}
            # the frames against the pose samples the session holds (what a replay's poses will come from), their
            # stamps with the session's declared offset; lost or not by when they were received
            self.coverage = coverage_of(self.kind, device.url.raw, self._frame_times, writer.pose_times,
                                        time_offset_ns=writer.meta.time_offset_ns, receipts=self.receipts)
            problem = self.watch.last_problem.get(self.device_name, "")
            if self.kind == "robot":
                health = {"robot_faults": self.faults, "robot_readings_delivered": device.readings_delivered,
                          "joint_samples_not_recorded": self.skipped, "last_robot_problem": problem}
            else:
                health = {"tracker_faults": self.faults, "marker_samples_by_tool": dict(self.seen_tools),
                          "marker_samples_not_recorded": self.skipped, "last_tracker_problem": problem}
            writer.set_health({**health, "events": writer.n_events, "pose_coverage": self.coverage.as_dict()})
        finally:
            self.writer.close()

    def fill(self, stats: RecordStats) -> None:
        """A closed recording's figures into ``stats`` (every frame on disk by now)."""
        w = self.writer
        stats.frames, stats.joint_samples, stats.marker_samples = w.n_frames, w.n_joints, w.n_markers
        stats.skipped_joint_samples, stats.events, stats.pose_coverage = self.skipped, w.n_events, self.coverage
        if self.kind == "robot":
            stats.robot_faults = self.faults
        else:
            stats.tracker_faults, stats.scope_samples = self.faults, self.seen_tools.get(self.tool, 0)


def record(grabber, robot, out: str, *, seconds: float | None = None, max_frames: int | None = None,
           camera: CameraModel | None = None, description: RobotDescription | None = None,
           source: dict | None = None, progress: bool = True, with_truth: bool = True,
           rig: Rig | None = None) -> RecordStats:
    """Record until the grabber ends, ``seconds`` of capture time have passed, ``max_frames`` were written,
    or Ctrl-C; the session is closed (complete) in every case. ``camera``/``rig``/``description`` override
    what the devices know (a real grabber does not know its lens: pass the calibration); ``camera`` replaces
    camera 0 of the grabber's rig. A grabber whose frames carry ``views`` (a stereo scope) is recorded as a
    version-2 session of its rig. The grabber's ground truth is recorded only where it belongs to the robot's
    readings (``recorded_truth``). A robot lost partway (its readings ended well before the frames did) is a
    DeviceLostError once the session is closed: nothing recorded is lost."""
    from tqdm import tqdm

    camera = camera or (rig.cameras[0] if rig is not None else None) or grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    description = description or robot.description
    if description is None:
        raise ConfigError(f"robot '{robot.url.raw}' has no robot model/hand-eye; pass --robot-model and "
                          f"--hand-eye handeye.yaml")
    truth = recorded_truth(grabber, robot) if with_truth else None
    meta = session_meta_for(grabber, robot, camera, description, source, rig)
    stats = RecordStats(0, 0, 0, 0.0, 0.0, "end of source")
    bar = tqdm(total=max_frames, desc=f"record {out}", unit="frame", file=sys.stderr, disable=not progress)
    wall0 = time.perf_counter()
    recorder = SessionRecorder(out, meta, grabber, robot, urdf_file=urdf_path(description.urdf), truth=truth)
    _record_loop(recorder, grabber, robot, stats, bar, seconds, max_frames)
    stats.wall_s = time.perf_counter() - wall0
    recorder.fill(stats)
    by_driver = sum(stats.robot_faults.get(k, 0) for k in REFUSED_READING_FAULTS)
    refused = by_driver + stats.skipped_joint_samples
    writer = recorder.writer
    last = writer.last_skipped_joints or recorder.watch.last_problem.get(recorder.device_name, "")
    if stats.robot_faults or stats.skipped_joint_samples:
        faults = ", ".join(f"{k} {v}" for k, v in sorted(stats.robot_faults.items())) or "none"
        log.warning("record: robot %s: faults during the recording: %s; %d readings refused (%d by the driver, "
                    "%d not recorded); last: %s (each one in %s/%s)", robot.url.raw, faults, refused, by_driver,
                    stats.skipped_joint_samples, last or "-", out, EVENTS_FILE)
    _check_frames(grabber, out, stats, f"{stats.joint_samples} joint readings")
    if stats.frames and not stats.joint_samples:
        raise DeviceError(_no_joints_message(robot.url.raw, out, stats, robot.readings_delivered, refused, last))
    check_pose_coverage("record", stats.pose_coverage, f"the recording is kept at {out}", stats=stats,
                        problem=recorder.watch.last_problem.get(recorder.device_name, ""))
    return stats


def _record_loop(recorder: "SessionRecorder", grabber, device, stats: RecordStats, bar, seconds: float | None,
                 max_frames: int | None) -> None:
    """``record``'s and ``record_tracked``'s loop: each frame with the pose samples read before it, until the
    grabber ends, ``seconds`` of capture, ``max_frames`` or Ctrl-C; the recorder is closed in every case."""
    with recorder, bar:
        first_t = None
        try:
            while True:
                frame = grabber.read(timeout_s=GRABBER_READ_TIMEOUT_S)
                if frame is None:
                    break
                recorder.add_joints(device.read(timeout_s=0.0))
                recorder.add_frame(frame)
                first_t = frame.t_ns if first_t is None else first_t
                stats.capture_span_s = (frame.t_ns - first_t) * 1e-9
                bar.update(1)
                if max_frames is not None and recorder.writer.n_queued >= max_frames:
                    stats.stopped_by = "frame count"
                    break
                if seconds is not None and stats.capture_span_s >= seconds:
                    stats.stopped_by = "duration"
                    break
            # the samples captured just after the last frame: without them it has no pose on replay
            recorder.add_joints(device.read(timeout_s=FINAL_READING_WAIT_S))
        except KeyboardInterrupt:
            stats.stopped_by = "interrupted"


# driver fault counters that stand for a reading received and refused (not one lost on the link)
# (out of the joint limits; a servo whose hardware error status flags its motor encoder)
REFUSED_READING_FAULTS = ("out_of_limits", "refused_encoder_error")
# a grabber that delivers no frame for this long has ended the recording
GRABBER_READ_TIMEOUT_S = 1.0
# how long the end of a recording waits for the readings captured just after its last frame
FINAL_READING_WAIT_S = 0.05


def _check_frames(grabber, out: str, stats: RecordStats, poses: str) -> None:
    """A recording that ended with no frame (the grabber delivered none, or none within a read's timeout) is a
    DeviceError, not an empty session ended by exit 0; one that Ctrl-C stopped before its first frame is not."""
    if stats.frames or stats.stopped_by == "interrupted":
        return
    faults = "; ".join(f"{k} {v}" for k, v in sorted(dict(grabber.faults).items()) if v) or "no faults counted"
    raise DeviceError(f"record: grabber '{grabber.url.raw}' delivered no frame (none within "
                      f"{GRABBER_READ_TIMEOUT_S:g} s of the start or of the last; {faults}); the session {out} holds "
                      f"0 frames and {poses}; next: check the grabber with 'lapreco devices --probe "
                      f"{grabber.url.raw}' (cable, format, another program holding it)")


def _no_joints_message(url: str, out: str, stats: RecordStats, delivered: int | None, refused: int,
                       last: str) -> str:
    kept = f"the {stats.frames} frames are saved in {out}, but a replay needs joint readings"
    probe = f"next: check the robot with 'lapreco devices --probe {url}'"
    faults = "; ".join(f"{k} {v}" for k, v in sorted(stats.robot_faults.items())) or "no faults counted"
    if refused or delivered:
        n = delivered if delivered else refused
        check = "(joint map, limits, units)"
        if stats.robot_faults.get("refused_encoder_error", 0):  # the device flags its encoder: a hardware fault
            check = ("(a hardware fault, not the joint map: a servo flags an encoder error, so its positions are "
                     "not trustworthy; check the servo named in the last fault, its Hardware Error Status, address "
                     "70, its encoder, cable and power, then power-cycle or reboot it)")
        return (f"record: robot '{url}' delivered {n} readings but none was usable (0 joint samples kept, "
                f"{refused} refused: {faults}; last: {last or 'no detail'}); {kept}; {probe} {check}")
    return (f"record: robot '{url}' delivered no readings during {stats.frames} frames ({faults}"
            f"{'; last: ' + last if last else ''}); {kept}; {probe}")


def tracked_session_meta(grabber, camera: CameraModel, setup: TrackerSetup, source: dict | None = None,
                         rig: Rig | None = None) -> SessionMeta:
    """The metadata of a tracked-scope recording (pose_source "marker_poses"); ``setup.T_marker_camera`` None
    makes a calibration session."""
    rig = rig or recorded_rig(grabber.rig, camera)
    return SessionMeta(camera=rig.cameras[0], rig=rig, pose_source="marker_poses", tracker=setup,
                       nominal_fps=grabber.nominal_fps, source=source or {})


def scope_tool(tracker, tool: str | None) -> str:
    """The scope's tool among an open tracker's: the one named, or the tracker's only one."""
    tools = tuple(tracker.tools)
    if tool is None:
        if len(tools) == 1:
            return tools[0]
        raise ConfigError(f"tracker '{tracker.url.raw}' tracks {len(tools)} tools ({', '.join(tools) or 'none'}); "
                          f"say which one is on the scope with --tool NAME")
    if tool not in tools:
        raise ConfigError(f"tracker '{tracker.url.raw}' has no tool '{tool}'; its tools: {', '.join(tools) or 'none'} "
                          f"(a passive tool is named after its .rom file, a wired one 'handle 0A')")
    return tool


def record_tracked(grabber, tracker, out: str, setup: TrackerSetup, *, seconds: float | None = None,
                   max_frames: int | None = None, camera: CameraModel | None = None, source: dict | None = None,
                   progress: bool = True, with_truth: bool = True, rig: Rig | None = None) -> RecordStats:
    """Record frames and every tool's marker poses (``tracker``: an OPEN TrackerDriver; ``setup.tool`` is the
    scope's) into a marker_poses session, as ``record`` does a robot's joints: events.csv gets the tracker's
    faults and health changes. A tracker that delivered no pose of the scope's tool, or whose scope poses ended
    well before the frames did, is a DeviceError after the session is closed (its frames are kept)."""
    from tqdm import tqdm

    camera = camera or (rig.cameras[0] if rig is not None else None) or grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    # (no tracker is part of a simulated world: a simulated grabber's truth is kept, as the tests that drive a
    # tracker emulator from it rely on)
    truth = grabber.ground_truth if with_truth else None
    meta = tracked_session_meta(grabber, camera, setup, source, rig)
    stats = RecordStats(0, 0, 0, 0.0, 0.0, "end of source")
    bar = tqdm(total=max_frames, desc=f"record {out}", unit="frame", file=sys.stderr, disable=not progress)
    wall0 = time.perf_counter()
    recorder = SessionRecorder(out, meta, grabber, tracker, truth=truth)
    _record_loop(recorder, grabber, tracker, stats, bar, seconds, max_frames)
    stats.wall_s = time.perf_counter() - wall0
    recorder.fill(stats)
    if stats.tracker_faults:
        log.warning("record: tracker %s: faults during the recording: %s (each one in %s/%s)", tracker.url.raw,
                    ", ".join(f"{k} {v}" for k, v in sorted(stats.tracker_faults.items())), out, EVENTS_FILE)
    _check_frames(grabber, out, stats, f"{stats.marker_samples} marker poses")
    if stats.frames and not stats.scope_samples:
        faults = "; ".join(f"{k} {v}" for k, v in sorted(stats.tracker_faults.items())) or "no faults counted"
        others = ", ".join(f"{t} {n}" for t, n in sorted(recorder.seen_tools.items())) or "none"
        raise DeviceError(f"record: tracker '{tracker.url.raw}' delivered no pose of the scope's tool "
                          f"'{setup.tool}' during {stats.frames} frames (poses of other tools: {others}; {faults}); "
                          f"the frames are saved in {out}, but a replay needs the scope's poses; next: check the "
                          f"marker is in view with 'lapreco devices --probe {tracker.url.raw}'")
    check_pose_coverage("record", stats.pose_coverage, f"the recording is kept at {out}", stats=stats,
                        problem=recorder.watch.last_problem.get(recorder.device_name, ""))
    return stats


def session_meta_for(grabber, robot, camera: CameraModel, description: RobotDescription,
                     source: dict | None = None, rig: Rig | None = None) -> SessionMeta:
    """The metadata of a recording: ``rig`` when given, else the grabber's rig with ``camera`` as its camera 0
    (a rig of one, ``camera``, when the grabber knows no rig or a rig of one)."""
    rig = rig or recorded_rig(grabber.rig, camera)
    return SessionMeta(camera=rig.cameras[0], rig=rig, pose_source="joints", robot=description,
                       joint_names=tuple(robot.info.joint_names),
                       joint_units=_joint_units(description, len(robot.info.joint_names)),
                       nominal_fps=grabber.nominal_fps, source=source or {})


def recorded_rig(grabber_rig: Rig | None, camera: CameraModel) -> Rig:
    """The grabber's rig with ``camera`` (a calibration given for camera 0) in place of its camera 0."""
    if grabber_rig is None or len(grabber_rig) == 1:
        return Rig.mono(camera)
    return Rig((camera, *grabber_rig.cameras[1:]), grabber_rig.T_cam0_cam, grabber_rig.sigma_rotation_rad,
               grabber_rig.sigma_translation_m)


def _joint_units(description: RobotDescription, n: int) -> tuple[str, ...]:
    """'length' for prismatic joints, 'angle' for the others, read from the URDF."""
    import pinocchio as pin

    from lapreco_hil.kinematics import prismatic_joints

    model = pin.buildModelFromUrdf(str(urdf_path(description.urdf)))
    units = tuple("length" if p else "angle" for p in prismatic_joints(model))
    if len(units) != n:
        raise ConfigError(f"robot model '{description.urdf}' has {len(units)} joints, the robot reports {n}")
    return units
