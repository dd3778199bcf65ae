"""``lapreco replay SESSION --out DIR``: a recorded session through the pipeline, deterministically."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

from lapreco_hil.calib.files import read_camera_yaml, read_handeye_yaml
from lapreco_hil.config import load_config
from lapreco_hil.errors import CalibrationError
from lapreco_hil.frontend import resolve_tracker
from lapreco_hil.offline import reconstruct
from lapreco_hil.outputs import check_output_dir, prepare_output_dir
from lapreco_hil.pose_sources import GivenPoseSource, MarkerPoseSource, RobotPoseSource
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.warp_device import resolve_device

log = logging.getLogger(__name__)


def check_session_rig(session) -> list[dict]:
    """A stereo session's rig judged against its first frame's images (``calib.rig_check``): each problem found
    is logged as one warning line; the figures of every pair go to report.json (``rig_check``)."""
    from lapreco_hil.calib.rig_check import check_rig

    rig = session.meta.rig
    if not rig.is_stereo or len(session) == 0:
        return []
    frame = session.frame(0)
    fits = check_rig(rig, (frame.image,) + tuple(frame.views))
    for fit in fits:
        if fit.problem:
            log.warning("%s: %s", Path(session.folder) / "session.json", fit.problem)
    return [fit.summary() for fit in fits]


def run_replay(session: str, out: str, tracker: str = "auto", device: str = "auto", config_path: str | None = None,
               drift_check: bool | None = None, realtime: bool = False, progress: bool = True,
               camera_file: str | None = None, hand_eye_file: str | None = None,
               time_offset_ms: float | None = None, surface: str | None = None) -> dict:
    """``camera_file`` / ``hand_eye_file`` (OpenCV YAML from ``lapreco calibrate``) and ``time_offset_ms``
    replace what the session says; ``surface`` ("dense" or "alpha") the configuration's [surface] mode."""
    config = load_config(config_path)
    if surface is not None:
        config = replace(config, surface=replace(config.surface, mode=surface))
    check_output_dir(out)
    if drift_check is not None:
        config = replace(config, tracker=replace(config.tracker, drift_check=drift_check))
    device = resolve_device(device)
    tracker = resolve_tracker(tracker, device)
    context = DeviceContext(device=device)
    url = f"replay://{Path(session).as_posix()}?pace={'realtime' if realtime else 'afap'}"
    grabber = open_grabber(url, context)  # reads and checks the whole session (but not the images) first
    meta = grabber.session.meta
    camera = read_camera_yaml(camera_file) if camera_file else meta.camera
    if (camera.width, camera.height) != (meta.camera.width, meta.camera.height):
        raise CalibrationError(f"{camera_file}: calibrated for {camera.width}x{camera.height}, the session's frames "
                               f"are {meta.camera.width}x{meta.camera.height}")
    offset_ns = meta.time_offset_ns if time_offset_ms is None else int(round(time_offset_ms * 1e6))
    # a version-1 pair of frames with their poses: one frame of a rig of two (Session.pair_frames_as_rig)
    if meta.pose_source == "camera_poses" and grabber.session.pair_frames_as_rig(camera, offset_ns):
        meta = grabber.session.meta
    if meta.pose_source == "joints":
        robot = open_robot(url, context)
        description = robot.description
        if hand_eye_file:
            description = replace(description, T_tip_camera=read_handeye_yaml(hand_eye_file)["T_tip_camera"])
        poses = RobotPoseSource(robot, description, config.prior, offset_ns=offset_ns)
    elif meta.pose_source == "marker_poses":
        robot = None
        # the hand-eye file's T_tip_camera is the scope marker's (calibrate handeye-tracked writes it so)
        T_marker_camera = read_handeye_yaml(hand_eye_file)["T_tip_camera"] if hand_eye_file else None
        poses = MarkerPoseSource(meta.tracker, table=grabber.session.markers, T_marker_camera=T_marker_camera,
                                 offset_ns=offset_ns)
    else:
        if hand_eye_file:
            raise CalibrationError(f"session '{session}' gives camera poses directly; a hand-eye does not apply")
        robot = None
        s = grabber.session
        poses = GivenPoseSource(s.pose_t_ns, s.poses, meta.pose_sigma.rotation_rad, meta.pose_sigma.translation_m,
                                offset_ns=offset_ns)
    fields = {"command": "replay", "session": str(session), "pose_source": meta.pose_source,
              "time_offset_ms": offset_ns * 1e-6, "camera_file": camera_file, "hand_eye_file": hand_eye_file,
              "session_complete": meta.complete, "pace": "realtime" if realtime else "afap",
              # tables shorter than session.json's counts (Session.shortfall): {table: {recorded, found}}
              "session_shortfall": grabber.session.shortfall,
              # a stereo rig's extrinsics against its first frame: inverted, the wrong unit, not fitting
              "rig_check": check_session_rig(grabber.session)}
    if grabber.session.pair_as_rig:  # two frames read as one frame of a rig of two (Session.pair_frames_as_rig)
        seq, t_ns = grabber.session.second_frame
        fields["two_frames_as_rig"] = {"second_frame_seq": seq, "second_frame_t_ns": t_ns}
    if meta.pose_source == "marker_poses":
        fields.update({"tracker_tool": poses.tool, "marker_samples_refused": poses.rejected,
                       "marker_samples_refused_by_cause": dict(poses.rejected_by_cause)})
    with grabber:
        if robot is not None:
            robot.open()
        try:
            out_dir = prepare_output_dir(out)  # once the session is open: a failed replay leaves no folder
            return reconstruct(grabber, poses, camera, config, out_dir, tracker=tracker, device=device,
                               truth=grabber.ground_truth, progress=progress, total=len(grabber),
                               label=f"replay {Path(session).name}", report_fields=fields)
        finally:
            if robot is not None:
                robot.close()
