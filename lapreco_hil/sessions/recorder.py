"""Recording: frames and joint readings from live (or simulated) devices into a session, as they arrive."""

from __future__ import annotations

import collections
import logging
import sys
import time
from dataclasses import dataclass, field

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.errors import ConfigError, DeviceError
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

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0


class DeviceWatch:
    """Device faults and health changes while recording: each one a row of events.csv and one console
    warning (at most one per device and kind of event every ``warn_every_s``)."""

    def __init__(self, writer: SessionWriter, devices: dict, warn_every_s: float = 1.0) -> None:
        from lapreco_hil.pose_sources import RateLimitedWarning

        self.writer, self.devices = writer, devices  # name -> device (a grabber, a robot driver)
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
        self._warn[(name, event)]("record: %s %s: %s", name, event, detail or "(no detail)")


def record(grabber, robot, out: str, *, seconds: float | None = None, max_frames: int | None = None,
           camera: CameraModel | None = None, description: RobotDescription | None = None,
           source: dict | None = None, progress: bool = True, with_truth: bool = True,
           rig: Rig | None = None) -> RecordStats:
    """Record until the grabber ends, ``seconds`` of capture time have passed, ``max_frames`` were written,
    or Ctrl-C; the session is closed (complete) in every case. ``camera``/``rig``/``description`` override
    what the devices know (a real grabber does not know its lens: pass the calibration); ``camera`` replaces
    camera 0 of the grabber's rig. A grabber whose frames carry ``views`` (a stereo scope) is recorded as a
    version-2 session of its rig."""
    from tqdm import tqdm

    camera = camera or (rig.cameras[0] if rig is not None else None) or grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    description = description or robot.description
    if description is None:
        raise ConfigError(f"robot '{robot.url.raw}' has no robot model/hand-eye; pass --robot-model and "
                          f"--hand-eye handeye.yaml")
    truth = grabber.ground_truth if with_truth else None
    meta = session_meta_for(grabber, robot, camera, description, source, rig)
    stats = RecordStats(0, 0, 0, 0.0, 0.0, "end of source")
    bar = tqdm(total=max_frames, desc=f"record {out}", unit="frame", file=sys.stderr, disable=not progress)
    wall0 = time.perf_counter()
    robot_name, grabber_name = f"robot {robot.url.raw}", f"grabber {grabber.url.raw}"
    with SessionWriter(out, meta, urdf_path(description.urdf)) as writer, bar:
        if truth is not None and truth.surface is not None:
            writer.set_truth_surface(truth.surface)
        watch = DeviceWatch(writer, {robot_name: robot, grabber_name: grabber})
        first_t = last_t = None
        try:
            while True:
                frame = grabber.read(timeout_s=GRABBER_READ_TIMEOUT_S)
                if frame is None:
                    break
                stats.skipped_joint_samples += writer.add_joints(robot.read(timeout_s=0.0))
                writer.add_frame(frame)
                if truth is not None and truth.camera_pose is not None:
                    writer.add_true_pose(frame.t_ns, truth.camera_pose(frame.t_ns))
                first_t = frame.t_ns if first_t is None else first_t
                last_t = frame.t_ns
                stats.capture_span_s = (frame.t_ns - first_t) * 1e-9
                watch.check(frame.t_ns)
                bar.update(1)
                if max_frames is not None and writer.n_queued >= max_frames:
                    stats.stopped_by = "frame count"
                    break
                if seconds is not None and stats.capture_span_s >= seconds:
                    stats.stopped_by = "duration"
                    break
            # the readings captured just after the last frame: without them it has no pose on replay
            stats.skipped_joint_samples += writer.add_joints(robot.read(timeout_s=FINAL_READING_WAIT_S))
        except KeyboardInterrupt:
            stats.stopped_by = "interrupted"
        if last_t is not None:
            watch.check(last_t)
        stats.robot_faults = {k: int(v) for k, v in dict(robot.faults).items() if v}
        # readings the driver handed on (RobotDriver counts them)
        delivered = robot.readings_delivered
        writer.set_health({"robot_faults": stats.robot_faults, "robot_readings_delivered": delivered,
                           "joint_samples_not_recorded": stats.skipped_joint_samples,
                           "last_robot_problem": watch.last_problem.get(robot_name, ""),
                           "events": writer.n_events})
    stats.frames, stats.joint_samples = writer.n_frames, writer.n_joints  # after close: every frame on disk
    stats.events = writer.n_events
    stats.wall_s = time.perf_counter() - wall0
    by_driver = sum(stats.robot_faults.get(k, 0) for k in REFUSED_READING_FAULTS)
    refused = by_driver + stats.skipped_joint_samples
    last = writer.last_skipped_joints or watch.last_problem.get(robot_name, "")
    if stats.robot_faults or stats.skipped_joint_samples:
        faults = ", ".join(f"{k} {v}" for k, v in sorted(stats.robot_faults.items())) or "none"
        log.warning("record: robot %s: faults during the recording: %s; %d readings refused (%d by the driver, "
                    "%d not recorded); last: %s (each one in %s/%s)", robot.url.raw, faults, refused, by_driver,
                    stats.skipped_joint_samples, last or "-", out, EVENTS_FILE)
    _check_frames(grabber, out, stats, f"{stats.joint_samples} joint readings")
    if stats.frames and not stats.joint_samples:
        raise DeviceError(_no_joints_message(robot.url.raw, out, stats, delivered, refused, last))
    return stats


# driver fault counters that stand for a reading received and refused (not one lost on the link)
REFUSED_READING_FAULTS = ("out_of_limits",)
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
        return (f"record: robot '{url}' delivered {n} readings but none was usable (0 joint samples kept, "
                f"{refused} refused: {faults}; last: {last or 'no detail'}); {kept}; {probe} (joint map, "
                f"limits, units)")
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
    faults and health changes. A tracker that delivered no pose of the scope's tool is a DeviceError after the
    session is closed (its frames are kept)."""
    from tqdm import tqdm

    camera = camera or (rig.cameras[0] if rig is not None else None) or grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    truth = grabber.ground_truth if with_truth else None
    meta = tracked_session_meta(grabber, camera, setup, source, rig)
    stats = RecordStats(0, 0, 0, 0.0, 0.0, "end of source")
    bar = tqdm(total=max_frames, desc=f"record {out}", unit="frame", file=sys.stderr, disable=not progress)
    wall0 = time.perf_counter()
    tracker_name, grabber_name = f"tracker {tracker.url.raw}", f"grabber {grabber.url.raw}"
    seen_tools: collections.Counter[str] = collections.Counter()

    def take(samples) -> None:
        seen_tools.update(s.tool for s in samples)
        stats.skipped_joint_samples += writer.add_marker_samples(samples)

    with SessionWriter(out, meta) as writer, bar:
        if truth is not None and truth.surface is not None:
            writer.set_truth_surface(truth.surface)
        watch = DeviceWatch(writer, {tracker_name: tracker, grabber_name: grabber})
        first_t = last_t = None
        try:
            while True:
                frame = grabber.read(timeout_s=GRABBER_READ_TIMEOUT_S)
                if frame is None:
                    break
                take(tracker.read(timeout_s=0.0))
                writer.add_frame(frame)
                if truth is not None and truth.camera_pose is not None:
                    writer.add_true_pose(frame.t_ns, truth.camera_pose(frame.t_ns))
                first_t = frame.t_ns if first_t is None else first_t
                last_t = frame.t_ns
                stats.capture_span_s = (frame.t_ns - first_t) * 1e-9
                watch.check(frame.t_ns)
                bar.update(1)
                if max_frames is not None and writer.n_queued >= max_frames:
                    stats.stopped_by = "frame count"
                    break
                if seconds is not None and stats.capture_span_s >= seconds:
                    stats.stopped_by = "duration"
                    break
            take(tracker.read(timeout_s=FINAL_READING_WAIT_S))  # the poses just after the last frame
        except KeyboardInterrupt:
            stats.stopped_by = "interrupted"
        if last_t is not None:
            watch.check(last_t)
        stats.tracker_faults = {k: int(v) for k, v in dict(tracker.faults).items() if v}
        writer.set_health({"tracker_faults": stats.tracker_faults, "marker_samples_by_tool": dict(seen_tools),
                           "marker_samples_not_recorded": stats.skipped_joint_samples,
                           "last_tracker_problem": watch.last_problem.get(tracker_name, ""),
                           "events": writer.n_events})
    stats.frames, stats.marker_samples = writer.n_frames, writer.n_markers
    stats.scope_samples, stats.events = seen_tools.get(setup.tool, 0), writer.n_events
    stats.wall_s = time.perf_counter() - wall0
    if stats.tracker_faults:
        log.warning("record: tracker %s: faults during the recording: %s (each one in %s/%s)", tracker.url.raw,
                    ", ".join(f"{k} {v}" for k, v in sorted(stats.tracker_faults.items())), out, EVENTS_FILE)
    _check_frames(grabber, out, stats, f"{stats.marker_samples} marker poses")
    if stats.frames and not stats.scope_samples:
        faults = "; ".join(f"{k} {v}" for k, v in sorted(stats.tracker_faults.items())) or "no faults counted"
        others = ", ".join(f"{t} {n}" for t, n in sorted(seen_tools.items())) or "none"
        raise DeviceError(f"record: tracker '{tracker.url.raw}' delivered no pose of the scope's tool "
                          f"'{setup.tool}' during {stats.frames} frames (poses of other tools: {others}; {faults}); "
                          f"the frames are saved in {out}, but a replay needs the scope's poses; next: check the "
                          f"marker is in view with 'lapreco devices --probe {tracker.url.raw}'")
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
