"""The ``lapreco`` command. Every LaprecoError becomes one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import json
import logging
import sys

from .. import __version__
from ..errors import ConfigError, LaprecoError


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution '{text}' must look like 640x480") from None
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"resolution '{text}' out of range (64..8192 per side)")
    return w, h


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"'{text}' must be at least 1")
    return n


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lapreco", description=__doc__)
    parser.add_argument("--version", action="version", version=f"lapreco-hil {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="simulated robot + simulated grabber through the pipeline, with accuracy "
                                        "against ground truth")
    demo.add_argument("--scene", default="skull", help="skull | liver | apple | uterus | board (default: skull)")
    demo.add_argument("--frames", type=_positive_int, default=150, help="frames to simulate (default: 150)")
    demo.add_argument("--resolution", type=_resolution, default=(640, 480), help="WxH (default: 640x480)")
    demo.add_argument("--fps", type=float, default=25.0, help="simulated frame rate (default: 25)")
    demo.add_argument("--out", default="lapreco-demo", help="output folder (default: ./lapreco-demo)")
    demo.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda (default: auto)")
    demo.add_argument("--tracker", default="auto",
                      help="front-end: warp | opencv | auto (default: auto = warp on a GPU, opencv on a CPU)")
    demo.add_argument("--no-drift-check", dest="drift_check", action="store_const", const=False, default=None,
                      help="switch off the Zinsser drift check (for the seed's four-way comparison)")
    demo.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    demo.add_argument("--seed", type=int, default=0, help="simulation seed (default: 0)")
    demo.add_argument("--robot-link", choices=("direct", "serial", "canopen"), default="direct",
                      help="read the simulated robot directly, or through the real Dynamixel (serial) or CANopen "
                           "driver talking to a device emulator (default: direct)")
    demo.add_argument("--sim-speed", type=float, default=0.2,
                      help="with a serial/canopen link: simulated time per real second (default: 0.2)")
    demo.add_argument("--sequential", action="store_true",
                      help="one frame at a time through every stage (deterministic) instead of the live runtime")
    demo.add_argument("--view-every", type=float, default=0.0,
                      help="render the live textured view every S seconds (OUT/live/*.png, OUT/live.mp4)")
    demo.add_argument("--instrument", action="store_true",
                      help="a moving instrument in view (it is not part of the true surface)")
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    demo.set_defaults(func=_cmd_demo)

    dev = sub.add_parser("devices", help="list the serial ports, CAN interfaces and video devices this machine sees")
    dev.set_defaults(func=_cmd_devices)

    rec = sub.add_parser("record", help="record frames and joint readings from devices into a session")
    rec.add_argument("--robot", required=True, help="robot URL, e.g. serial:///dev/ttyUSB0?ids=1,2,3,4 or sim://skull")
    rec.add_argument("--grabber", required=True, help="grabber URL, e.g. v4l2:///dev/video0 or sim://skull")
    rec.add_argument("--out", required=True, help="new session folder")
    rec.add_argument("--seconds", type=float, default=None, help="stop after this much capture time")
    rec.add_argument("--frames", type=_positive_int, default=None, help="stop after this many frames")
    rec.add_argument("--camera", default=None, help="lens calibration (OpenCV YAML) when the grabber has none")
    rec.add_argument("--robot-model", default=None, help="packaged robot model name or URDF path")
    rec.add_argument("--tip-frame", default=None, help="the URDF link that holds the scope")
    rec.add_argument("--hand-eye", default=None, help="hand-eye calibration (OpenCV YAML with T_tip_camera)")
    rec.add_argument("--device", default="auto", help="Warp device for simulated devices: auto | cpu | cuda")
    rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    rec.set_defaults(func=_cmd_record)

    simrec = sub.add_parser("sim-record", help="record a simulated session with ground truth")
    simrec.add_argument("--scene", default="skull", help="skull | liver | apple | uterus | board (default: skull)")
    simrec.add_argument("--out", required=True, help="new session folder")
    simrec.add_argument("--frames", type=_positive_int, default=150, help="frames (default: 150)")
    simrec.add_argument("--resolution", type=_resolution, default=(640, 480), help="WxH (default: 640x480)")
    simrec.add_argument("--fps", type=float, default=25.0, help="frame rate (default: 25)")
    simrec.add_argument("--seed", type=int, default=0, help="simulation seed (default: 0)")
    simrec.add_argument("--device", default="auto", help="Warp device for rendering: auto | cpu | cuda")
    simrec.add_argument("--robot-link", choices=("direct", "serial", "canopen"), default="direct",
                        help="record the robot through the real Dynamixel/CANopen driver and a device emulator")
    simrec.add_argument("--sim-speed", type=float, default=0.2,
                        help="with a serial/canopen link: simulated time per real second (default: 0.2)")
    simrec.add_argument("--instrument", action="store_true", help="a moving instrument in view")
    simrec.add_argument("--kinematics-offset-ms", type=float, default=0.0,
                        help="stamp the robot's readings this late (a known video-kinematics offset to recover)")
    simrec.add_argument("--no-progress", action="store_true", help="no progress bar")
    simrec.set_defaults(func=_cmd_sim_record)

    rep = sub.add_parser("replay", help="run the pipeline on a recorded session; writes the outputs contract")
    rep.add_argument("session", help="session folder (docs/session-format.md)")
    rep.add_argument("--out", required=True, help="output folder")
    rep.add_argument("--tracker", default="auto", help="warp | opencv | auto (default: auto)")
    rep.add_argument("--no-drift-check", dest="drift_check", action="store_const", const=False, default=None,
                     help="switch off the Zinsser drift check")
    pace = rep.add_mutually_exclusive_group()
    pace.add_argument("--as-fast-as-possible", dest="realtime", action="store_false", default=False,
                      help="do not wait between frames (default)")
    pace.add_argument("--realtime", dest="realtime", action="store_true",
                      help="hand frames on at their recorded rate")
    rep.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    rep.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    rep.add_argument("--camera", default=None, help="use this lens calibration (OpenCV YAML) instead of the session's")
    rep.add_argument("--hand-eye", default=None, help="use this hand-eye (OpenCV YAML) instead of the session's")
    rep.add_argument("--time-offset-ms", type=float, default=None,
                     help="video-to-kinematics offset instead of the session's time_offset_ns")
    rep.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep.set_defaults(func=_cmd_replay)

    ev = sub.add_parser("evaluate", help="ICP of a run's points to a ground-truth surface: RMS, scale, coverage")
    ev.add_argument("outdir", help="a run's output folder (points.ply, trajectory.tum, report.json)")
    ev.add_argument("--truth", required=True, help="ground-truth surface mesh in the world frame, metres (PLY, "
                                                   "OBJ, STL, VTK)")
    ev.add_argument("--coverage-mm", type=float, default=3.0, help="coverage radius (default 3 mm)")
    ev.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ev.set_defaults(func=_cmd_evaluate)

    cmp_ = sub.add_parser("compare", help="the seed's four-way comparison (Warp/OpenCV x drift check) on a session")
    cmp_.add_argument("session", help="a session (with ground truth for the ICP error)")
    cmp_.add_argument("--out", required=True, help="output folder: one run per variant, comparison.md/.json, "
                                                   "tracking_time.png")
    cmp_.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    cmp_.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    cmp_.add_argument("--no-progress", action="store_true", help="no progress bar")
    cmp_.set_defaults(func=_cmd_compare)

    from .calibrate import add_parsers as add_calibrate_parsers
    from .run import add_parser as add_run_parser

    add_run_parser(sub)
    add_calibrate_parsers(sub, _positive_int)

    bench = sub.add_parser("bench", help="benchmarks (figures for docs/benchmarks.md)")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    bench_ba = bench_sub.add_parser("ba", help="one local BA window: 10 keyframes x 2000 points, 5%% outliers")
    bench_ba.add_argument("--repeats", type=_positive_int, default=3)
    bench_ba.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_ba.set_defaults(func=_cmd_bench_ba)
    bench_fe = bench_sub.add_parser("frontend", help="Warp front-end vs the OpenCV baseline, per stage")
    bench_fe.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_fe.add_argument("--resolution", type=_resolution, nargs="+", default=[(1920, 1080)])
    bench_fe.add_argument("--features", type=_positive_int, nargs="+", default=[2000])
    bench_fe.add_argument("--frames", type=_positive_int, default=40)
    bench_fe.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_fe.set_defaults(func=_cmd_bench_frontend)
    bench_p = bench_sub.add_parser("pipeline", help="the live runtime in real time: sustained fps, drops, latency")
    bench_p.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_p.add_argument("--resolution", type=_resolution, default=None,
                         help="WxH (default: 1920x1080 on a GPU, 384x288 on a CPU)")
    bench_p.add_argument("--fps", type=float, default=None, help="frame rate (default: 60 on a GPU, 25 on a CPU)")
    bench_p.add_argument("--seconds", type=float, default=20.0, help="duration (default 20)")
    bench_p.add_argument("--features", type=_positive_int, default=None,
                         help="tracked features (default: 2000 on a GPU, 800 on a CPU)")
    bench_p.add_argument("--source", choices=("auto", "sim", "replay"), default="auto",
                         help="replay (auto): a session recorded first, replayed in real time; sim: the simulated "
                              "world rendered live (its ray caster shares the machine with the pipeline)")
    bench_p.add_argument("--session", default=None,
                         help="replay this recorded session in real time (resolution and fps are the session's)")
    bench_p.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    bench_p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_p.set_defaults(func=_cmd_bench_pipeline)
    bench_k = bench_sub.add_parser("soak", help="the live runtime for a long time: memory growth, latency drift")
    bench_k.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_k.add_argument("--minutes", type=float, default=30.0, help="duration (default 30)")
    bench_k.add_argument("--resolution", type=_resolution, default=(320, 240), help="WxH (default 320x240)")
    bench_k.add_argument("--fps", type=float, default=10.0, help="frame rate (default 10)")
    bench_k.add_argument("--features", type=_positive_int, default=400)
    bench_k.add_argument("--scene", default="skull")
    bench_k.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    bench_k.add_argument("--sample-s", type=float, default=10.0, help="seconds between samples")
    bench_k.add_argument("--json", default=None, help="also write the figures (and every sample) to this JSON file; "
                         "samples also go to JSON.samples.jsonl as they are taken")
    bench_k.set_defaults(func=_cmd_bench_soak)
    bench_r = bench_sub.add_parser("robot", help="robot drivers on their emulators: sample rate, jitter, latency")
    bench_r.add_argument("--link", nargs="+", choices=("serial", "canopen"), default=["serial", "canopen"])
    bench_r.add_argument("--rate", type=float, nargs="+", default=[100.0, 500.0])
    bench_r.add_argument("--seconds", type=float, default=5.0)
    bench_r.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_r.set_defaults(func=_cmd_bench_robot)
    bench_s = bench_sub.add_parser("session", help="session write (crash-safe) and read throughput")
    bench_s.add_argument("--resolution", type=_resolution, nargs="+", default=[(640, 480), (1920, 1080)])
    bench_s.add_argument("--frames", type=_positive_int, default=60)
    bench_s.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_s.set_defaults(func=_cmd_bench_session)
    return parser


def _cmd_bench_pipeline(args) -> int:
    from ..bench.pipeline import format_table, run
    from ..warp_device import resolve_device

    device = resolve_device(args.device)
    gpu = device.startswith("cuda")
    result = run(device, args.resolution or ((1920, 1080) if gpu else (384, 288)), args.fps or (60.0 if gpu else 25.0),
                 args.seconds, args.features or (2000 if gpu else 800), args.source, args.tracker,
                 session=args.session)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_soak(args) -> int:
    from ..bench.soak import format_table, run
    from ..warp_device import resolve_device

    result = run(resolve_device(args.device), args.resolution, args.fps, args.minutes, args.features, args.scene,
                 args.tracker, args.sample_s, stream=f"{args.json}.samples.jsonl" if args.json else None)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_robot(args) -> int:
    from ..bench.robot import format_table, run

    result = run(args.link, args.rate, args.seconds)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_session(args) -> int:
    from ..bench.session import format_table, run

    result = run(args.resolution, frames=args.frames)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _write_json(path: str | None, result: dict) -> None:
    if path:
        from ..outputs import write_json

        write_json(path, result)


def _cmd_bench_frontend(args) -> int:
    from ..bench.frontend import format_table, run
    from ..warp_device import resolve_device

    device = resolve_device(args.device)
    result = run(device, args.resolution, args.features, frames=args.frames)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_ba(args) -> int:
    from ..bench.ba import format_table, run

    result = run(repeats=args.repeats)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_evaluate(args) -> int:
    from pathlib import Path

    import numpy as np
    import pyvista as pv

    from ..evaluation.compare import read_points_ply, read_tum
    from ..evaluation.icp import evaluate_points

    out = Path(args.outdir)
    points_file = out / "points.ply"
    if not points_file.is_file():
        raise ConfigError(f"{points_file}: missing; give a run's output folder (lapreco demo/replay/run --out)")
    truth_path = Path(args.truth)
    if not truth_path.is_file():
        raise ConfigError(f"{truth_path}: no such ground-truth mesh")
    try:
        truth = pv.read(str(truth_path))
    except Exception as exc:  # VTK raises several kinds for a file it cannot parse
        raise ConfigError(f"{truth_path}: cannot read the mesh ({exc})") from None
    if truth.n_points == 0 or truth.n_cells == 0:
        raise ConfigError(f"{truth_path}: the mesh is empty")
    poses = K = size = None
    if (out / "trajectory.tum").is_file() and (out / "report.json").is_file():
        cam = json.loads((out / "report.json").read_text()).get("camera")
        if cam:
            _, poses = read_tum(out / "trajectory.tum")
            K, size = np.array(cam["K"]), (cam["width"], cam["height"])
    result = evaluate_points(read_points_ply(points_file), truth, poses, K, size, args.coverage_mm)
    if "error" in result:
        raise ConfigError(f"{points_file}: {result['error']}")
    icp = result["icp"]
    cov = result.get("coverage", {}).get("covered_fraction")
    print(f"lapreco evaluate: {result['points']} points; after similarity ICP RMS {icp['rms_mm']:.3f} mm, median "
          f"{icp['median_mm']:.3f} mm, p95 {icp['p95_mm']:.3f} mm, scale {icp['scale']:.4f}; coverage "
          f"{'n/a' if cov is None else f'{cov:.0%}'} of the visible true surface within {args.coverage_mm:g} mm; "
          f"before alignment RMS {result['unaligned']['rms_mm']:.3f} mm")
    _write_json(args.json, result)
    return 0


def _cmd_compare(args) -> int:
    from ..evaluation.compare import format_markdown, run_comparison
    from ..warp_device import resolve_device

    result = run_comparison(args.session, args.out, device=resolve_device(args.device), config_path=args.config,
                            progress=not args.no_progress)
    print(format_markdown(result))
    return 0


def _cmd_devices(args) -> int:
    from ..drivers.discovery import discover, format_devices

    print(format_devices(discover()))
    return 0


def _cmd_record(args) -> int:
    from ..registry import DeviceContext, open_grabber, open_robot
    from ..sessions.recorder import record
    from ..warp_device import resolve_device

    context = DeviceContext(device=resolve_device(args.device))
    robot, grabber = open_robot(args.robot, context), open_grabber(args.grabber, context)
    from .run import rig_from

    camera, description = rig_from(robot, grabber, args.camera, args.hand_eye, args.robot_model, args.tip_frame)
    with robot, grabber:
        stats = record(grabber, robot, args.out, seconds=args.seconds, max_frames=args.frames, camera=camera,
                       description=description, source={"robot": args.robot, "grabber": args.grabber},
                       progress=not args.no_progress)
    _print_record(args.out, stats)
    return 0


def _print_record(out: str, stats) -> None:
    print(f"lapreco record: {stats.frames} frames and {stats.joint_samples} joint samples "
          f"({stats.capture_span_s:.2f} s of capture) in {stats.wall_s:.1f} s = {stats.frames_per_s:.1f} frames/s; "
          f"stopped by {stats.stopped_by}; session in {out}")


def _cmd_sim_record(args) -> int:
    from ..registry import DeviceContext, open_grabber, open_robot
    from ..sessions.recorder import record
    from ..warp_device import resolve_device

    device = resolve_device(args.device)
    w, h = args.resolution
    url = f"sim://{args.scene}?width={w}&height={h}&fps={args.fps}&seed={args.seed}"
    if args.instrument:
        url += "&instrument=1"
    if args.robot_link != "direct":
        url += f"&speed={args.sim_speed}"
    context = DeviceContext(device=device)
    robot = open_robot(url + f"&link={args.robot_link}&offset_ms={args.kinematics_offset_ms}", context)
    grabber = open_grabber(url + f"&frames={args.frames}", context)
    with robot, grabber:
        stats = record(grabber, robot, args.out, max_frames=args.frames, progress=not args.no_progress,
                       source={"simulator": url, "scene": args.scene, "seed": args.seed,
                               "robot_link": args.robot_link})
    _print_record(args.out, stats)
    return 0


def _cmd_replay(args) -> int:
    from .replay import run_replay

    report = run_replay(args.session, args.out, tracker=args.tracker, device=args.device,
                        config_path=args.config, drift_check=args.drift_check, realtime=args.realtime,
                        progress=not args.no_progress, camera_file=args.camera, hand_eye_file=args.hand_eye,
                        time_offset_ms=args.time_offset_ms)
    _print_run("replay", report)
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_demo

    report = run_demo(scene=args.scene, frames=args.frames, resolution=args.resolution, fps=args.fps,
                      out=args.out, device=args.device, tracker=args.tracker, config_path=args.config,
                      seed=args.seed, progress=not args.no_progress, drift_check=args.drift_check,
                      robot_link=args.robot_link, sim_speed=args.sim_speed, instrument=args.instrument,
                      runtime="sequential" if args.sequential else "live", view_every=args.view_every)
    _print_run("demo", report)
    return 0


def _print_run(command: str, report: dict) -> None:
    acc = report.get("accuracy", {})
    pts = acc.get("points_to_surface", {})
    line = (f"lapreco {command}: {report['frames']['processed']} frames in {report['wall_s']:.1f} s; "
            f"{report['inliers']} inlier points")
    if acc:
        line += (f", RMS to true surface {_fmt(pts.get('rms_mm'))} mm; camera position RMS raw "
                 f"{_fmt(acc.get('camera_raw_fk', {}).get('position_rms_mm'))} mm -> refined "
                 f"{_fmt(acc.get('camera_refined', {}).get('position_rms_mm'))} mm")
    print(line + f"; outputs in {report['out']}")


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except LaprecoError as exc:
        print(f"lapreco: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lapreco: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
