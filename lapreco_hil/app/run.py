"""``lapreco run``: the live runtime on real (or simulated) devices until the source ends, ``seconds`` pass,
or Ctrl-C; then the outputs contract, with the live metrics in report.json. ``lapreco demo`` is this runtime
on simulated devices."""

from __future__ import annotations

import logging
import sys
from dataclasses import replace
from pathlib import Path

from lapreco_hil.app.handeye import describe_rig, require_hand_eye
from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import ConfigError, LaprecoError
from lapreco_hil.frontend import resolve_tracker
from lapreco_hil.outputs import check_output_dir, prepare_output_dir, write_outputs
from lapreco_hil.pose_sources import MarkerPoseSource, RobotPoseSource
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot, open_tracker
from lapreco_hil.runtime.live import LiveRun
from lapreco_hil.warp_device import resolve_device

log = logging.getLogger(__name__)


def rig_from(robot, grabber, camera_file: str | None = None, hand_eye_file: str | None = None,
             robot_model: str | None = None, tip_frame: str | None = None):
    """Lens and robot description: from files where given, else from what the devices know. A rig without a
    hand-eye cannot make camera poses: the ConfigError says the two commands that bring it up."""
    camera, description = describe_rig(robot, grabber, camera_file, hand_eye_file, robot_model, tip_frame)
    return camera, require_hand_eye(robot, grabber, description)


def run_live(robot, grabber, config: PipelineConfig, out: str, *, tracker: str = "auto", device: str = "auto",
             camera=None, description=None, record: str | None = None, seconds: float | None = None,
             progress: bool = True, total: int | None = None, report_fields: dict | None = None,
             on_stage_error: str = "stop", write: bool = True, on_live=None, marker=None,
             tracker_setup=None, mcap: str | None = None) -> dict:
    """Open devices, run live, write the outputs; ``robot``/``grabber`` are unopened drivers. ``write=False``
    (benchmarks) returns the live metrics and map statistics without writing files or rendering;
    ``on_live(live)`` is called with the LiveRun before it starts (a benchmark's sampler). A tracked scope
    instead of a robot: ``robot`` None, ``marker`` an unopened TrackerDriver and ``tracker_setup`` (a
    TrackerSetup with the hand-eye; its tool None: the tracker's only one). ``mcap``: also log the run to this
    MCAP file (fed beside the session recorder, encoded in its own thread; the map added at the end)."""
    from tqdm import tqdm

    from lapreco_hil.sessions.recorder import SessionRecorder, check_pose_coverage, session_meta_for
    from lapreco_hil.robot_models import urdf_path

    check_output_dir(out)
    config = _live_view_if_renderable(config)
    device = resolve_device(device)
    tracker = resolve_tracker(tracker, device)
    if marker is None:
        if camera is None or description is None:
            camera, description = rig_from(robot, grabber)
        poses = RobotPoseSource(robot, description, config.prior, offset_ns=_declared_offset_ns(robot))
        first, second = robot, grabber
    else:
        if camera is None:
            raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                              f"(from 'lapreco calibrate lens')")
        first, second = marker, grabber  # the tracker's bring-up first: frames passing meanwhile would be lost
    bar = tqdm(total=total, desc=f"live {Path(out).name}", unit="frame", file=sys.stderr, disable=not progress)
    recorder = mcap_log = None
    truth = _run_truth(grabber, robot, record, write)
    with first, second, bar:
        if marker is not None:
            from lapreco_hil.sessions.recorder import scope_tool

            tracker_setup = replace(tracker_setup, tool=scope_tool(marker, tracker_setup.tool))
            poses = MarkerPoseSource(tracker_setup, tracker=marker, offset_ns=_declared_offset_ns(marker))
        out_dir = prepare_output_dir(out)  # only once the devices are open: a run that never starts leaves nothing
        if record:
            # what 'lapreco record' writes, through the same recorder: events.csv, source, health, the ground truth
            # where it belongs to the poses (sessions/recorder.py); the console has the run's own health lines
            from lapreco_hil.sessions.recorder import tracked_session_meta

            if marker is not None:
                source = {"tracker": marker.url.raw, "grabber": grabber.url.raw}
                recorder = SessionRecorder(record, tracked_session_meta(grabber, camera, tracker_setup, source),
                                           grabber, marker, truth=truth, console=False)
            else:
                source = {"robot": robot.url.raw, "grabber": grabber.url.raw}
                recorder = SessionRecorder(record, session_meta_for(grabber, robot, camera, description, source),
                                           grabber, robot, urdf_file=urdf_path(description.urdf), truth=truth,
                                           console=False)
        try:
            receipts = _watch_receipts(poses)  # when its readings reached the run, on the host's clock
            if mcap:
                mcap_log = _mcap_logger(mcap, grabber, robot, camera, description, tracker_setup, poses)
            live = LiveRun(grabber, poses, camera, config, tracker=tracker, device=device, out_dir=out_dir,
                           recorder=_with_mcap(recorder, mcap_log), on_stage_error=on_stage_error, progress=bar)
            if on_live is not None:
                on_live(live)
            result, metrics = live.run(seconds)
            pose_device = marker if marker is not None else robot
            problem = _device_problem(pose_device)  # (before the devices close)
        except BaseException:
            if mcap_log is not None:
                mcap_log.close()  # the file finished as far as the run got
            raise
        finally:
            if recorder is not None:
                recorder.close()
    coverage = _pose_coverage(poses, pose_device, metrics["frames"]["in"], receipts)
    fields = {"command": "run", **(report_fields or {}), "runtime": "live", "pose_coverage": coverage.as_dict()}
    _warn_if_replay_outran_the_run(grabber, metrics)
    if marker is not None:
        fields.update({"tracker_tool": poses.tool, "marker_samples_refused": poses.rejected,
                       "marker_samples_refused_by_cause": dict(poses.rejected_by_cause),
                       "tracker_faults": poses.tracker_faults})
    if mcap_log is not None:
        fields["mcap"] = mcap_log.finish_stream()
    if not write:
        if mcap_log is not None:
            mcap_log.close()
        dense = live.dense_result.stats if live.dense_result is not None else None
        return {**fields, **metrics, **{k: result.stats[k] for k in ("tracks", "keyframes", "landmarks", "inliers")},
                "surface": "dense" if dense is not None else "alpha", "dense": dense}
    if record:
        fields["recorded_session"] = record
    recorded = f" and the recording is kept at {record}" if record else ""
    try:
        report = write_outputs(result, camera, config, out_dir, tracker=tracker, device=device,
                               truth=truth, report_fields=fields, metrics=metrics,
                               run_wall_s=metrics["wall_s"], dense=live.dense_result, surface_note=live.surface_note)
    except LaprecoError as exc:  # (too little mapped, say): the lost pose source is the cause to name
        check_pose_coverage("run", coverage, f"the outputs could not be written ({exc}){recorded}", problem=problem,
                            warn=False)
        raise
    finally:
        if mcap_log is not None:  # the map, once the outputs are written
            mcap_log.close(out_dir if (out_dir / "points.ply").is_file() else None)
    # a pose source lost partway: an error once everything is written (the command prints its summary first)
    check_pose_coverage("run", coverage, f"the outputs are in {out_dir}{recorded}", problem=problem, warn=False,
                        report=report)
    return report


def _run_truth(grabber, robot, record: str | None, write: bool):
    """The ground truth of a run's recording and accuracy figures: a tracked scope's (robot None) is the grabber's;
    a robot's only where it belongs to the robot's readings (sessions/recorder.py, ``recorded_truth``)."""
    if not (record or write):
        return None
    if robot is None:
        return grabber.ground_truth
    from lapreco_hil.sessions.recorder import recorded_truth

    return recorded_truth(grabber, robot, "the recording and report.json's accuracy" if record else
                          "report.json's accuracy")


def _device_problem(device) -> str:
    """A device's state now when it is not OK ("stale: no reading for 0.3 s"), else ""."""
    from lapreco_hil.drivers.health import HealthState

    health = getattr(device, "health", None)
    if health is None or health.state is HealthState.OK:
        return ""
    return f"{health.state.value}: {health.detail}" if health.detail else health.state.value


def _watch_receipts(poses):
    """The host-clock receipts of a live run (sessions/recorder.py, ``Receipts``): the tracking stage polls the
    pose source once a frame, so each ``poll()`` is a frame reaching it, and one that returns readings their
    receipt. Whether the source was lost is judged on these, not on its stamps (its clock may be offset)."""
    from lapreco_hil.sessions.recorder import Receipts

    receipts, poll = Receipts(), poses.poll

    def poll_and_note() -> list:
        samples = poll()
        receipts.frame()
        if samples:
            receipts.reading()
        return samples

    poses.poll = poll_and_note
    return receipts


def _pose_coverage(poses, device, frames_in: int, receipts=None):
    """How the pose source's accepted readings covered the frames that reached it (its ``without_pose`` counts,
    after-the-last ones moved to the gaps when readings resumed; its times less the offset it applies), as the
    recorder judges a recording's: lost or not by ``receipts`` (``_watch_receipts``), on the host's clock."""
    from lapreco_hil.geometry import AFTER_LAST, BEFORE_FIRST, IN_GAP
    from lapreco_hil.sessions.recorder import PoseCoverage

    times = poses.without_pose.times
    before, after, gaps = times[BEFORE_FIRST], times[AFTER_LAST], times[IN_GAP]
    # a robot's readings, or a tracker's poses (an empty PoseAtTime is falsy: no reading accepted at all)
    track = poses.pose_at if hasattr(poses, "pose_at") else poses.track
    last = track.last_time_ns
    return PoseCoverage("robot" if poses.robot is not None else getattr(poses, "source", "tracker"),
                        device.url.raw, frames_in, before_first=len(before), in_gap=len(gaps),
                        after_last=len(after), first_frame_ns=poses.without_pose.first_frame_ns,
                        last_frame_ns=max(after) if after else None,
                        # (a live track keeps its recent readings only: its first came just after this frame)
                        first_reading_ns=max(before) if before else poses.without_pose.first_frame_ns,
                        last_reading_ns=None if last is None else last - poses.time_offset_ns,
                        gap_limit_ns=track.max_gap_ns, gap_frames_ns=(min(gaps), max(gaps)) if gaps else None,
                        time_offset_ns=poses.time_offset_ns,
                        **(receipts.figures() if receipts is not None else {}))


def _warn_if_replay_outran_the_run(grabber, metrics: dict) -> None:
    """A session replayed as a live source at ``pace=afap`` hands its frames on as fast as it reads them; a live
    run keeps up with real time only, so it drops the rest at capture (counted, but easy to take for a slow
    machine). Say so, with the two ways to have every frame."""
    dropped = int(metrics.get("frames", {}).get("dropped_capture", 0) or 0)
    if dropped and grabber.url.scheme == "replay" and not getattr(grabber, "realtime", True):
        log.warning("%d frames dropped at capture: '%s' hands frames on as fast as it reads them (pace=afap), faster "
                    "than a live run maps them; add '?pace=realtime' to both URLs, or use 'lapreco replay' (every "
                    "frame, deterministic)", dropped, grabber.url.raw)


def _mcap_logger(path: str, grabber, robot, camera, description, tracker_setup, poses):
    """``lapreco run --mcap``: the live MCAP log of this rig (lapreco_hil/interop/mcap_export.py)."""
    from lapreco_hil.interop.mcap_export import live_logger_for
    from lapreco_hil.sessions.format import default_camera_names
    from lapreco_hil.sessions.recorder import recorded_rig

    rig = recorded_rig(getattr(grabber, "rig", None), camera)
    return live_logger_for(path, rig, default_camera_names(len(rig)), description=description,
                           joint_names=robot.info.joint_names if robot is not None else (),
                           tracker_setup=tracker_setup if robot is None else None,
                           offset_ns=getattr(poses, "time_offset_ns", 0))


def _with_mcap(recorder, mcap_log):
    """The session recorder, the MCAP log, or both behind one (the live Record stage feeds one recorder)."""
    if mcap_log is None:
        return recorder
    from lapreco_hil.interop.mcap_export import RecorderFanOut

    return RecorderFanOut(recorder, mcap_log)


def _live_view_if_renderable(config: PipelineConfig) -> PipelineConfig:
    """The live view renders with VTK, which crashes the process where it has no renderer: off, with a warning."""
    if config.runtime.view_period_s <= 0:
        return config
    from lapreco_hil.surface.render import ENABLE_RENDERING, offscreen_unavailable

    why = offscreen_unavailable()
    if why is None:
        return config
    log.warning("live view off: %s; to enable rendering, %s", why, ENABLE_RENDERING)
    return replace(config, runtime=replace(config.runtime, view_period_s=0.0))


def stop_on_signals() -> None:
    """Ctrl-C (SIGINT) and SIGTERM (a supervisor stopping the run) both end the run cleanly, as
    KeyboardInterrupt: outputs written, devices closed, recording complete. Set explicitly because a process
    started in the background by a non-interactive shell inherits SIGINT ignored, and Python then never
    raises KeyboardInterrupt."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, stop)


def run(robot_url: str | None, grabber_url: str, out: str, *, config_path: str | None = None,
        record: str | None = None, seconds: float | None = None, view_every: float = 0.0, tracker: str = "auto",
        device: str = "auto", camera_file: str | None = None, robot_model: str | None = None,
        tip_frame: str | None = None, hand_eye_file: str | None = None, progress: bool = True,
        marker_url: str | None = None, tool: str | None = None, mcap: str | None = None,
        surface: str | None = None) -> dict:
    """``lapreco run``: devices by URL (a robot, or a tracker ``marker_url`` following the scope's marker, with
    its hand-eye), the rig from files or the devices, live until the end; the report. ``surface``: "dense" or
    "alpha" instead of the configuration's [surface] mode."""
    from lapreco_hil.config import load_config

    if (robot_url is None) == (marker_url is None):
        raise ConfigError("lapreco run: give exactly one pose source: --robot URL (a robot holding the scope) or "
                          "--marker URL (a tracker following the scope's marker, e.g. ndi:///dev/ttyUSB0), "
                          f"{'not both' if robot_url else 'got neither'}")
    config = load_config(config_path)
    if surface is not None:
        config = replace(config, surface=replace(config.surface, mode=surface))
    if view_every:
        config = replace(config, runtime=replace(config.runtime, view_period_s=view_every))
    context = DeviceContext(device=resolve_device(device))
    if marker_url is not None:
        return _run_tracked(marker_url, grabber_url, out, config, context, tool=tool, hand_eye_file=hand_eye_file,
                            camera_file=camera_file, record=record, seconds=seconds, tracker=tracker,
                            device=device, progress=progress, mcap=mcap)
    robot, grabber = open_robot(robot_url, context), open_grabber(grabber_url, context)
    camera, description = rig_from(robot, grabber, camera_file, hand_eye_file, robot_model, tip_frame)
    return run_live(robot, grabber, config, out, tracker=tracker, device=device, camera=camera,
                    description=description, record=record, seconds=seconds, progress=progress,
                    report_fields={"robot": robot_url, "grabber": grabber_url}, mcap=mcap)


def _recorded_session(device):
    """The session a ``replay://`` robot or tracker plays, else None."""
    return getattr(device, "session", None) if getattr(device, "url", None) is not None \
        and device.url.scheme == "replay" else None


def _declared_offset_ns(device) -> int:
    """The pose source's clock offset a recorded session declares (``time_offset_ns``); 0 for a live device (its
    offset is watched, and applied once calibrated)."""
    recorded = _recorded_session(device)
    return int(recorded.meta.time_offset_ns) if recorded is not None else 0


def _run_tracked(marker_url: str, grabber_url: str, out: str, config: PipelineConfig, context: DeviceContext, *,
                 tool: str | None, hand_eye_file: str | None, camera_file: str | None, record: str | None,
                 seconds: float | None, tracker: str, device: str, progress: bool, mcap: str | None = None) -> dict:
    """``lapreco run --marker``: the scope's pose from a tracker and the hand-eye T_marker_camera."""
    from lapreco_hil.app.record import tracker_setup
    from lapreco_hil.calib.files import read_camera_yaml

    marker, grabber = open_tracker(marker_url, context), open_grabber(grabber_url, context)
    recorded = _recorded_session(marker)
    if recorded is not None and recorded.meta.tracker is not None:
        # a recorded tracked scope: the session's tracker placement, RMS limit and sigmas, and its hand-eye unless
        # one is given
        setup = recorded.meta.tracker
        if hand_eye_file:
            setup = replace(setup, T_marker_camera=tracker_setup(setup.tool, hand_eye_file).T_marker_camera)
        setup = replace(setup, tool=tool or setup.tool)
    else:
        setup = tracker_setup(tool, hand_eye_file) if hand_eye_file else None
    if setup is None or setup.T_marker_camera is None:
        raise ConfigError(f"lapreco run --marker {marker_url}: the scope's hand-eye is missing (T_marker_camera): "
                          f"pass --hand-eye handeye.yaml (from 'lapreco calibrate handeye-tracked')")
    camera = read_camera_yaml(camera_file) if camera_file else grabber.camera
    return run_live(None, grabber, config, out, tracker=tracker, device=device, camera=camera, record=record,
                    seconds=seconds, progress=progress, marker=marker, tracker_setup=setup, mcap=mcap,
                    report_fields={"marker": marker_url, "grabber": grabber_url, "hand_eye_file": hand_eye_file})
