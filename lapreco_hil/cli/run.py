"""``lapreco run``: the live runtime on real (or simulated) devices until the source ends, ``--seconds`` pass,
or Ctrl-C; then the outputs contract, with the live metrics in report.json. ``lapreco demo`` is this runtime
on simulated devices."""

from __future__ import annotations

import logging
import sys
from dataclasses import replace
from pathlib import Path

from ..calib.files import read_camera_yaml, read_handeye_yaml
from ..config import PipelineConfig
from ..errors import ConfigError
from ..frontend import resolve_tracker
from ..offline import write_outputs
from ..outputs import prepare_output_dir
from ..pose_sources import RobotPoseSource
from ..registry import DeviceContext, open_grabber, open_robot
from ..runtime.live import LiveRun
from ..types import RobotDescription
from ..warp_device import resolve_device


def rig_from(robot, grabber, camera_file: str | None = None, hand_eye_file: str | None = None,
             robot_model: str | None = None, tip_frame: str | None = None):
    """Lens and robot description: from files where given, else from what the devices know."""
    camera = read_camera_yaml(camera_file) if camera_file else grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    description = robot.description
    if hand_eye_file or robot_model or tip_frame:
        he = read_handeye_yaml(hand_eye_file) if hand_eye_file else {}
        base = description or RobotDescription("", "", None)
        description = replace(base, urdf=robot_model or he.get("robot_model") or base.urdf,
                              tip_frame=tip_frame or he.get("tip_frame") or base.tip_frame,
                              T_tip_camera=he["T_tip_camera"] if he else base.T_tip_camera)
    if description is None or not description.urdf or not description.tip_frame or description.T_tip_camera is None:
        raise ConfigError(f"robot '{robot.url.raw}' has no robot model/hand-eye; pass --robot-model, --tip-frame "
                          f"and --hand-eye handeye.yaml")
    return camera, description


def run_live(robot, grabber, config: PipelineConfig, out: str, *, tracker: str = "auto", device: str = "auto",
             camera=None, description=None, record: str | None = None, seconds: float | None = None,
             progress: bool = True, total: int | None = None, report_fields: dict | None = None,
             on_stage_error: str = "stop", write: bool = True, on_live=None) -> dict:
    """Open devices, run live, write the outputs; ``robot``/``grabber`` are unopened drivers. ``write=False``
    (benchmarks) returns the live metrics and map statistics without writing files or rendering;
    ``on_live(live)`` is called with the LiveRun before it starts (a benchmark's sampler)."""
    from tqdm import tqdm

    from ..sessions.recorder import session_meta_for
    from ..sessions.writer import SessionWriter
    from ..robot_models import urdf_path

    out_dir = prepare_output_dir(out)
    device = resolve_device(device)
    tracker = resolve_tracker(tracker, device)
    if camera is None or description is None:
        camera, description = rig_from(robot, grabber)
    poses = RobotPoseSource(robot, description, config.prior)
    bar = tqdm(total=total, desc=f"live {Path(out).name}", unit="frame", file=sys.stderr, disable=not progress)
    recorder = None
    with robot, grabber, bar:
        if record:
            recorder = SessionWriter(record, session_meta_for(grabber, robot, camera, description),
                                     urdf_path(description.urdf))
        try:
            live = LiveRun(grabber, poses, camera, config, tracker=tracker, device=device, out_dir=out_dir,
                           recorder=recorder, on_stage_error=on_stage_error, progress=bar)
            if on_live is not None:
                on_live(live)
            result, metrics = live.run(seconds)
        finally:
            if recorder is not None:
                recorder.close()
    fields = {"command": "run", **(report_fields or {}), "runtime": "live"}
    if not write:
        return {**fields, **metrics, **{k: result.stats[k] for k in ("tracks", "keyframes", "landmarks", "inliers")}}
    if record:
        fields["recorded_session"] = record
    return write_outputs(result, camera, config, out_dir, tracker=tracker, device=device,
                         truth=grabber.ground_truth, report_fields=fields, metrics=metrics,
                         run_wall_s=metrics["wall_s"])


def _stop_on_signals() -> None:
    """Ctrl-C (SIGINT) and SIGTERM (a supervisor stopping the run) both end the run cleanly, as
    KeyboardInterrupt: outputs written, devices closed, recording complete. Set explicitly because a process
    started in the background by a non-interactive shell inherits SIGINT ignored, and Python then never
    raises KeyboardInterrupt."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, stop)


def cmd_run(args) -> int:
    _stop_on_signals()
    # each change of a device's health is news on the console, its recovery ("robot: ok again", INFO) too
    logging.getLogger("lapreco_hil.runtime.health").setLevel(logging.INFO)
    from ..config import load_config

    config = load_config(args.config)
    if args.view_every:
        config = replace(config, runtime=replace(config.runtime, view_period_s=args.view_every))
    context = DeviceContext(device=resolve_device(args.device))
    robot, grabber = open_robot(args.robot, context), open_grabber(args.grabber, context)
    camera, description = rig_from(robot, grabber, args.camera, args.hand_eye, args.robot_model, args.tip_frame)
    report = run_live(robot, grabber, config, args.out, tracker=args.tracker, device=args.device, camera=camera,
                      description=description, record=args.record, seconds=args.seconds,
                      progress=not args.no_progress,
                      report_fields={"robot": args.robot, "grabber": args.grabber})
    f, lat = report["frames"], report["latency_ms"]
    print(f"lapreco run: {f['in']} frames in, {f['processed']} mapped, {f['dropped']} dropped; "
          f"{report['throughput_fps']:.1f} frames/s; latency p50 {lat.get('p50', float('nan')):.0f} ms, "
          f"p99 {lat.get('p99', float('nan')):.0f} ms; {report['inliers']} inlier points; outputs in {report['out']}")
    return 0


def add_parser(sub) -> None:
    run = sub.add_parser("run", help="the live pipeline on devices until the source ends, --seconds, or Ctrl-C")
    run.add_argument("--robot", required=True, help="robot URL (serial://, canopen://, sim://, replay://)")
    run.add_argument("--grabber", required=True, help="grabber URL (v4l2://, sim://, replay://)")
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    run.add_argument("--record", default=None, help="also record the session into this new folder")
    run.add_argument("--seconds", type=float, default=None, help="stop after this many seconds")
    run.add_argument("--view-every", type=float, default=0.0,
                     help="render the live textured view every S seconds to OUT/live/*.png and OUT/live.mp4")
    run.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    run.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    run.add_argument("--camera", default=None, help="lens calibration (OpenCV YAML) when the grabber has none")
    run.add_argument("--robot-model", default=None, help="packaged robot model name or URDF path")
    run.add_argument("--tip-frame", default=None, help="the URDF link that holds the scope")
    run.add_argument("--hand-eye", default=None, help="hand-eye calibration (OpenCV YAML with T_tip_camera)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.set_defaults(func=cmd_run)
