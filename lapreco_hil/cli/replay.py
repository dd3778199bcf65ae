"""``lapreco replay SESSION --out DIR``: a recorded session through the pipeline, deterministically."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ..config import load_config
from ..frontend import resolve_tracker
from ..offline import reconstruct
from ..outputs import prepare_output_dir
from ..pose_sources import GivenPoseSource, RobotPoseSource
from ..registry import DeviceContext, open_grabber, open_robot
from ..warp_device import resolve_device


def run_replay(session: str, out: str, tracker: str = "auto", device: str = "auto", config_path: str | None = None,
               drift_check: bool | None = None, realtime: bool = False, progress: bool = True) -> dict:
    config = load_config(config_path)
    if drift_check is not None:
        config = replace(config, tracker=replace(config.tracker, drift_check=drift_check))
    device = resolve_device(device)
    tracker = resolve_tracker(tracker, device)
    context = DeviceContext(device=device)
    url = f"replay://{Path(session).as_posix()}?pace={'realtime' if realtime else 'afap'}"
    grabber = open_grabber(url, context)  # reads and checks the whole session (but not the images) first
    meta = grabber.session.meta
    out_dir = prepare_output_dir(out)
    if meta.pose_source == "joints":
        robot = open_robot(url, context)
        poses = RobotPoseSource(robot, robot.description, config.prior, offset_ns=meta.time_offset_ns)
    else:
        robot = None
        s = grabber.session
        poses = GivenPoseSource(s.pose_t_ns, s.poses, meta.pose_sigma.rotation_rad, meta.pose_sigma.translation_m,
                                offset_ns=meta.time_offset_ns)
    fields = {"command": "replay", "session": str(session), "pose_source": meta.pose_source,
              "session_complete": meta.complete, "pace": "realtime" if realtime else "afap"}
    with grabber:
        if robot is not None:
            robot.open()
        try:
            return reconstruct(grabber, poses, meta.camera, config, out_dir, tracker=tracker, device=device,
                               truth=grabber.ground_truth, progress=progress, total=len(grabber),
                               label=f"replay {Path(session).name}", report_fields=fields)
        finally:
            if robot is not None:
                robot.close()
