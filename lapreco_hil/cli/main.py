"""The ``lapreco`` command: parses arguments, calls lapreco_hil.app and prints the result. Every LaprecoError,
and every refused argument, becomes one line on stderr and exit status 2. Nothing imports this package."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from lapreco_hil import __version__
from lapreco_hil.errors import ConfigError, LaprecoError
from lapreco_hil.cli.args import (ArgumentParser, finite, integer, non_negative, number_list, positive, positive_int,
                                  resolution, seed)

_positive_int = positive_int  # the calibration parsers take it as an argument
SURFACE_CHOICES = ("auto", "dense", "alpha")
SURFACE_HELP = ("the surface: dense (multi-view stereo fused in a TSDF: mesh.ply and dense.ply), alpha (the sparse "
                "points' alpha shape) or auto (dense offline and live on CUDA, alpha live on the CPU) (default: the "
                "config's [surface] mode, auto)")


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="lapreco", description=__doc__)
    parser.add_argument("--version", action="version", version=f"lapreco-hil {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="simulated robot + simulated grabber through the pipeline, with accuracy "
                                        "against ground truth")
    demo.add_argument("--scene", default="skull", help="skull | liver | apple | uterus | board (default: skull)")
    demo.add_argument("--frames", type=positive_int, default=150, help="frames to simulate (default: 150)")
    demo.add_argument("--stereo", type=positive, default=None, metavar="BASELINE_MM",
                      help="a stereo scope with this baseline in mm (4-5.5 typical); default: mono")
    demo.add_argument("--resolution", type=resolution, default=(640, 480), help="WxH (default: 640x480)")
    demo.add_argument("--fps", type=positive, default=25.0, help="simulated frame rate, > 0 (default: 25)")
    demo.add_argument("--out", default="lapreco-demo", help="output folder (default: ./lapreco-demo)")
    demo.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda (default: auto)")
    demo.add_argument("--tracker", default="auto",
                      help="front-end: warp | opencv | auto (default: auto = warp on a GPU, opencv on a CPU)")
    demo.add_argument("--no-drift-check", dest="drift_check", action="store_const", const=False, default=None,
                      help="switch off the Zinsser drift check (for the seed's four-way comparison)")
    demo.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    demo.add_argument("--seed", type=seed, default=0, help="simulation seed, 0..2^31-1 (default: 0)")
    demo.add_argument("--robot-link", choices=("direct", "serial", "canopen"), default="direct",
                      help="read the simulated robot directly, or through the real Dynamixel (serial) or CANopen "
                           "driver talking to a device emulator (default: direct)")
    demo.add_argument("--sim-speed", type=positive, default=0.2,
                      help="with a serial/canopen link: simulated time per real second (default: 0.2)")
    demo.add_argument("--sequential", action="store_true",
                      help="one frame at a time through every stage (deterministic) instead of the live runtime")
    demo.add_argument("--view-every", type=non_negative, default=0.0,
                      help="render the live textured view every S seconds (OUT/live/*.png, OUT/live.mp4; 0 = off)")
    demo.add_argument("--instrument", action="store_true",
                      help="a moving instrument in view (it is not part of the true surface)")
    demo.add_argument("--surface", choices=SURFACE_CHOICES, default=None, help=SURFACE_HELP)
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    demo.set_defaults(func=_cmd_demo)

    dev = sub.add_parser("devices", help="list the serial ports, CAN interfaces and video devices this machine sees")
    dev.add_argument("--probe", metavar="URL", default=None, help="instead, open this robot or tracker URL and read it")
    dev.add_argument("--seconds", type=positive, default=2.0, help="with --probe: read for this long (default 2)")
    dev.add_argument("--device", default="auto", help="with --probe: Warp device for simulated devices")
    dev.set_defaults(func=_cmd_devices)

    rec = sub.add_parser("record", help="record frames and joint readings (or a tracked scope's marker poses) from "
                                        "devices into a session")
    source = rec.add_mutually_exclusive_group(required=True)
    source.add_argument("--robot", help="robot URL, e.g. serial:///dev/ttyUSB0?ids=1,2,3,4 or sim://skull")
    source.add_argument("--marker", help="instead of a robot, a tracker following the scope's marker, e.g. "
                                         "ndi:///dev/ttyUSB0?tools=8700339.rom")
    rec.add_argument("--tool", default=None, help="with --marker: the scope's tool (default: the tracker's only one)")
    rec.add_argument("--grabber", required=True, help="grabber URL, e.g. v4l2:///dev/video0 or sim://skull")
    rec.add_argument("--out", required=True, help="new session folder")
    rec.add_argument("--seconds", type=positive, default=None, help="stop after this much capture time (s, > 0)")
    rec.add_argument("--frames", type=positive_int, default=None, help="stop after this many frames")
    rec.add_argument("--camera", default=None, help="lens calibration (OpenCV YAML) when the grabber has none")
    rec.add_argument("--robot-model", default=None, help="packaged robot model name or URDF path")
    rec.add_argument("--tip-frame", default=None, help="the URDF link that holds the scope")
    rec.add_argument("--hand-eye", default=None, help="hand-eye calibration (OpenCV YAML with T_tip_camera; with "
                                                      "--marker the scope marker's, T_marker_camera)")
    rec.add_argument("--device", default="auto", help="Warp device for simulated devices: auto | cpu | cuda")
    rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    rec.set_defaults(func=_cmd_record)

    simrec = sub.add_parser("sim-record", help="record a simulated session with ground truth")
    simrec.add_argument("--scene", default="skull", help="skull | liver | apple | uterus | board (default: skull)")
    simrec.add_argument("--out", required=True, help="new session folder")
    simrec.add_argument("--frames", type=positive_int, default=150, help="frames (default: 150)")
    simrec.add_argument("--resolution", type=resolution, default=(640, 480), help="WxH (default: 640x480)")
    simrec.add_argument("--fps", type=positive, default=25.0, help="frame rate, > 0 (default: 25)")
    simrec.add_argument("--seed", type=seed, default=0, help="simulation seed, 0..2^31-1 (default: 0)")
    simrec.add_argument("--device", default="auto", help="Warp device for rendering: auto | cpu | cuda")
    simrec.add_argument("--robot-link", choices=("direct", "serial", "canopen"), default="direct",
                        help="record the robot through the real Dynamixel/CANopen driver and a device emulator")
    simrec.add_argument("--sim-speed", type=positive, default=0.2,
                        help="with a serial/canopen link: simulated time per real second (default: 0.2)")
    simrec.add_argument("--instrument", action="store_true", help="a moving instrument in view")
    simrec.add_argument("--kinematics-offset-ms", type=finite, default=0.0,
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
    rep.add_argument("--time-offset-ms", type=finite, default=None,
                     help="video-to-kinematics offset instead of the session's time_offset_ns")
    rep.add_argument("--surface", choices=SURFACE_CHOICES, default=None, help=SURFACE_HELP)
    rep.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep.set_defaults(func=_cmd_replay)

    ev = sub.add_parser("evaluate", help="a run's points against a ground-truth surface: RMS unaligned and after "
                                         "rigid ICP, the scale similarity ICP would need, coverage")
    ev.add_argument("outdir", help="a run's output folder (points.ply, trajectory.tum, report.json)")
    ev.add_argument("--truth", required=True, help="ground-truth surface mesh in the world frame (PLY, OBJ, STL, "
                                                   "VTK), or a session folder (its truth/surface.ply)")
    ev.add_argument("--truth-unit", choices=("m", "mm"), default=None,
                    help="the mesh's length unit (default: a session's truth in its session.json's unit, any other "
                         "mesh in metres)")
    ev.add_argument("--coverage-mm", type=positive, default=3.0, help="coverage radius, > 0 (default 3 mm)")
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

    from lapreco_hil.cli.calibrate import add_parsers as add_calibrate_parsers
    from lapreco_hil.cli.run import add_parser as add_run_parser

    add_run_parser(sub)
    add_calibrate_parsers(sub, _positive_int)

    # --- interop: lapreco export mcap, lapreco import rosbag (lapreco_hil/cli/interop.py) ---
    from lapreco_hil.cli.interop import add_parsers as add_interop_parsers

    add_interop_parsers(sub)
    # --- end interop ---
    # --- lapreco batch (issue 24): sessions of a folder as Ray tasks; its own module, lapreco_hil/cli/batch.py ---
    from lapreco_hil.cli.batch import add_parser as add_batch_parser

    add_batch_parser(sub)
    # --- end lapreco batch ---
    # --- lapreco emulate: one device emulator on its own; its own module, lapreco_hil/cli/emulate.py ---
    from lapreco_hil.cli.emulate import add_parser as add_emulate_parser

    add_emulate_parser(sub)
    # --- end lapreco emulate ---

    bench = sub.add_parser("bench", help="benchmarks (figures for docs/benchmarks.md)")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    bench_ba = bench_sub.add_parser("ba", help="one local BA window (10 keyframes x 2000 points, 5%% outliers) by GTSAM "
                                   "and the Schur solver, and a final BA over 300 keyframes")
    bench_ba.add_argument("--repeats", type=positive_int, default=3)
    bench_ba.add_argument("--device", default="cpu", help="Warp device of the Schur solver's kernels: cpu (default), "
                          "cuda, cuda:N or auto")
    bench_ba.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_ba.set_defaults(func=_cmd_bench_ba)
    bench_dn = bench_sub.add_parser("dense", help="the dense surface per keyframe: depth map, TSDF integration, meshing")
    bench_dn.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_dn.add_argument("--resolution", type=resolution, action="append", default=None,
                          help="WxH, repeatable (default: 1920x1080 and 384x288)")
    bench_dn.add_argument("--views", type=positive_int, default=4, help="source views per depth map (default 4)")
    bench_dn.add_argument("--repeats", type=positive_int, default=5)
    bench_dn.add_argument("--method", choices=("sweep", "patchmatch"), action="append", default=None,
                          help="[depth] method of the depth maps, repeatable (default: both)")
    bench_dn.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_dn.set_defaults(func=_cmd_bench_dense)
    bench_fe = bench_sub.add_parser("frontend", help="Warp front-end vs the OpenCV baseline, per stage")
    bench_fe.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_fe.add_argument("--resolution", type=resolution, nargs="+", default=[(1920, 1080)])
    bench_fe.add_argument("--features", type=positive_int, nargs="+", default=[2000])
    bench_fe.add_argument("--frames", type=positive_int, default=40)
    bench_fe.add_argument("--warp-only", action="store_true",
                          help="the Warp rows alone, without the OpenCV baseline's (slow at 4K on the CPU)")
    bench_fe.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_fe.set_defaults(func=_cmd_bench_frontend)
    bench_t = bench_sub.add_parser("tracking", help="the front-ends on real frames moved by known homographies: "
                                                    "error, share within 1 px, survival")
    bench_t.add_argument("--tracker", choices=("warp", "opencv", "all"), default="all")
    bench_t.add_argument("--device", choices=("cpu", "cuda", "all"), default="all",
                         help="Warp device (default all: the CPU, and CUDA when there is one); OpenCV runs on the CPU")
    bench_t.add_argument("--speeds", type=number_list(ge=0.0), default=[0.0, 10.0, 20.0, 40.0, 60.0, 80.0],
                         help="median image motion, px per frame, comma-separated (default 0,10,20,40,60,80)")
    bench_t.add_argument("--frames", type=integer(ge=2), default=32, help="frames per speed and real frame (default 32)")
    bench_t.add_argument("--predict", choices=("on", "off", "both"), default="off",
                         help="start tracks where a perfect pose source predicts them (on: with each track's depth, "
                              "and with only a depth range; both: also off) (default off)")
    bench_t.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_t.set_defaults(func=_cmd_bench_tracking)
    bench_p = bench_sub.add_parser("pipeline", help="the live runtime in real time: sustained fps, drops, latency")
    bench_p.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_p.add_argument("--resolution", type=resolution, default=None,
                         help="WxH (default: 1920x1080 on a GPU, 384x288 on a CPU)")
    bench_p.add_argument("--fps", type=positive, default=None, help="frame rate (default: 60 on a GPU, 25 on a CPU)")
    bench_p.add_argument("--seconds", type=positive, default=20.0, help="duration, s (default 20)")
    bench_p.add_argument("--features", type=positive_int, default=None,
                         help="tracked features (default: 2000 on a GPU, 800 on a CPU)")
    bench_p.add_argument("--source", choices=("auto", "sim", "replay"), default="auto",
                         help="replay (auto): a session recorded first, replayed in real time; sim: the simulated "
                              "world rendered live (its ray caster shares the machine with the pipeline)")
    bench_p.add_argument("--session", default=None,
                         help="replay this recorded session in real time (resolution and fps are the session's)")
    bench_p.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    bench_p.add_argument("--surface", choices=SURFACE_CHOICES, default="auto", help=SURFACE_HELP)
    bench_p.add_argument("--config", default=None,
                         help="pipeline configuration (TOML) under the bench's own features and surface mode")
    bench_p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_p.set_defaults(func=_cmd_bench_pipeline)
    bench_k = bench_sub.add_parser("soak", help="the live runtime for a long time: memory growth, latency drift")
    bench_k.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    bench_k.add_argument("--minutes", type=positive, default=30.0, help="duration (default 30)")
    bench_k.add_argument("--resolution", type=resolution, default=(320, 240), help="WxH (default 320x240)")
    bench_k.add_argument("--fps", type=positive, default=10.0, help="frame rate (default 10)")
    bench_k.add_argument("--features", type=positive_int, default=400)
    bench_k.add_argument("--scene", default="skull")
    bench_k.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    bench_k.add_argument("--surface", choices=("auto", "dense", "alpha"), default="auto",
                         help="the surface (default auto: dense on CUDA, alpha on the CPU); dense soaks the live dense "
                         "stage too")
    bench_k.add_argument("--sample-s", type=positive, default=10.0, help="seconds between samples")
    bench_k.add_argument("--json", default=None, help="also write the figures (and every sample) to this JSON file; "
                         "samples also go to JSON.samples.jsonl as they are taken")
    bench_k.set_defaults(func=_cmd_bench_soak)
    bench_r = bench_sub.add_parser("robot", help="robot drivers on their emulators: sample rate, jitter, latency")
    bench_r.add_argument("--link", nargs="+", choices=("serial", "canopen"), default=["serial", "canopen"])
    bench_r.add_argument("--rate", type=positive, nargs="+", default=[100.0, 500.0], help="sample rates, Hz")
    bench_r.add_argument("--seconds", type=positive, default=5.0, help="per link and rate (default 5)")
    bench_r.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_r.set_defaults(func=_cmd_bench_robot)
    bench_s = bench_sub.add_parser("session", help="session write (crash-safe) and read throughput")
    bench_s.add_argument("--resolution", type=resolution, nargs="+", default=[(640, 480), (1920, 1080)])
    bench_s.add_argument("--frames", type=positive_int, default=60)
    bench_s.add_argument("--json", default=None, help="also write the figures to this JSON file")
    bench_s.set_defaults(func=_cmd_bench_session)
    return parser


def _write_json(path: str | None, result: dict) -> None:
    if path:
        from lapreco_hil.outputs import write_json

        write_json(path, result)


def _cmd_bench_pipeline(args) -> int:
    from lapreco_hil.app.bench import bench_pipeline
    from lapreco_hil.bench.pipeline import format_table

    result = bench_pipeline(args.device, args.resolution, args.fps, args.seconds, args.features, args.source,
                            args.tracker, session=args.session, surface=args.surface, config=args.config)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_soak(args) -> int:
    from lapreco_hil.app.bench import bench_soak
    from lapreco_hil.bench.soak import format_table

    result = bench_soak(args.device, args.resolution, args.fps, args.minutes, args.features, args.scene,
                        args.tracker, args.sample_s, stream=f"{args.json}.samples.jsonl" if args.json else None,
                        surface=args.surface)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_robot(args) -> int:
    from lapreco_hil.app.bench import bench_robot
    from lapreco_hil.bench.robot import format_table

    result = bench_robot(args.link, args.rate, args.seconds)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_session(args) -> int:
    from lapreco_hil.app.bench import bench_session
    from lapreco_hil.bench.session import format_table

    result = bench_session(args.resolution, frames=args.frames)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_frontend(args) -> int:
    from lapreco_hil.app.bench import bench_frontend
    from lapreco_hil.bench.frontend import format_table

    result = bench_frontend(args.device, args.resolution, args.features, frames=args.frames,
                            baseline=not args.warp_only)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_tracking(args) -> int:
    from lapreco_hil.app.bench import bench_tracking
    from lapreco_hil.bench.tracking import format_table

    trackers = ("warp", "opencv") if args.tracker == "all" else (args.tracker,)
    result = bench_tracking(trackers, args.device, args.speeds, frames=args.frames, predict=args.predict)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_ba(args) -> int:
    from lapreco_hil.app.bench import bench_ba
    from lapreco_hil.bench.ba import format_table

    result = bench_ba(repeats=args.repeats, device=args.device)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def _cmd_bench_dense(args) -> int:
    from lapreco_hil.app.bench import bench_dense
    from lapreco_hil.bench import dense, fusion

    result = bench_dense(device=args.device, resolutions=args.resolution, views=args.views, repeats=args.repeats,
                         methods=tuple(args.method or ("sweep", "patchmatch")))
    for row in result["rows"]:
        for depth in row["depth_by_method"].values():
            print(dense.format_table(depth))
        print(fusion.format_table(row["fusion"]))
    _write_json(args.json, result)
    return 0


def _cmd_evaluate(args) -> int:
    from lapreco_hil.app.evaluate import evaluate

    result = evaluate(args.outdir, args.truth, args.coverage_mm, args.truth_unit)
    raw, icp, sim, cov = result["unaligned"], result["icp"], result["similarity"], result["coverage"]
    flat = result["relief"]["flat"]
    covered = cov["covered_fraction"]
    coverage = (f"{covered:.0%} of the visible true surface within {args.coverage_mm:g} mm" if covered is not None
                else f"n/a: {cov['why']}")
    print(f"lapreco evaluate: {result['points']} points; before alignment RMS {raw['rms_mm']:.3f} mm, median "
          f"{raw['median_mm']:.3f} mm, p95 {raw['p95_mm']:.3f} mm; after rigid ICP (scale fixed at 1) RMS "
          f"{icp['rms_mm']:.3f} mm, median {icp['median_mm']:.3f} mm, p95 {icp['p95_mm']:.3f} mm (moved "
          f"{icp['rotation_deg']:.2f} deg, {icp['translation_mm']:.2f} mm{'; not pinned: flat truth' if flat else ''})"
          f"; coverage {coverage}")
    print(f"lapreco evaluate: similarity ICP (an extra, not the accuracy: the scale the map would need) scale "
          f"{sim['scale']:.4f}, RMS {sim['rms_mm']:.3f} mm{' (meaningless on a flat truth)' if flat else ''}")
    surface = result.get("surface")
    if surface and "dense" in surface:
        sp, de = surface["sparse"], surface["dense"]
        print(f"lapreco evaluate: dense surface: {de['points']} points, RMS {_fmt(de['rms_mm'])} mm, median "
              f"{_fmt(de['median_mm'])} mm, {_pct(de['beyond_5mm'])} beyond 5 mm; coverage within "
              f"{surface['radius_mm']:g} mm of the seen true surface: sparse {_pct(sp['coverage'])}, dense "
              f"{_pct(de['coverage'])}")
    _write_json(args.json, result)
    return 0


def _cmd_compare(args) -> int:
    from lapreco_hil.app.compare import run_comparison
    from lapreco_hil.evaluation.compare import format_markdown
    from lapreco_hil.warp_device import resolve_device

    result = run_comparison(args.session, args.out, device=resolve_device(args.device), config_path=args.config,
                            progress=not args.no_progress)
    print(format_markdown(result))
    return 0


def _cmd_devices(args) -> int:
    from lapreco_hil.app.devices import list_devices, probe

    print(probe(args.probe, args.seconds, args.device) if args.probe else list_devices())
    return 0


def _cmd_record(args) -> int:
    from lapreco_hil.app.record import record_session

    from lapreco_hil.app.handeye import calibrate_next_step

    if args.marker:
        return _cmd_record_tracked(args)
    recording = record_session(args.robot, args.grabber, args.out, seconds=args.seconds, frames=args.frames,
                               camera_file=args.camera, robot_model=args.robot_model, tip_frame=args.tip_frame,
                               hand_eye_file=args.hand_eye, device=args.device, progress=not args.no_progress)
    _print_record(args.out, recording.stats)
    if recording.calibration_only:
        print(calibrate_next_step(args.out))
    return 0


def _cmd_record_tracked(args) -> int:
    from lapreco_hil.app.record import record_tracked_session

    if args.robot_model or args.tip_frame:
        raise ConfigError("--robot-model and --tip-frame describe a robot; with --marker give --tool (the scope's "
                          "tool) and --hand-eye")
    recording = record_tracked_session(args.marker, args.grabber, args.out, tool=args.tool, seconds=args.seconds,
                                       frames=args.frames, camera_file=args.camera, hand_eye_file=args.hand_eye,
                                       device=args.device, progress=not args.no_progress)
    st = recording.stats
    print(f"lapreco record: {st.frames} frames and {st.marker_samples} marker poses ({st.scope_samples} of the "
          f"scope's tool; {st.capture_span_s:.2f} s of capture) in {st.wall_s:.1f} s = {st.frames_per_s:.1f} "
          f"frames/s; stopped by {st.stopped_by}; session in {args.out}")
    if recording.calibration_only:
        print(f"no hand-eye: {args.out} is a calibration session (marker poses, no T_marker_camera); next: lapreco "
              f"calibrate handeye-tracked --session {args.out} --board-tool TOOL --board BOARD --out handeye.yaml "
              f"(TOOL: the board marker's tool, recorded with the scope's; BOARD: the board in view), then pass "
              f"--hand-eye handeye.yaml")
    return 0


def _print_record(out: str, stats) -> None:
    print(f"lapreco record: {stats.frames} frames and {stats.joint_samples} joint samples "
          f"({stats.capture_span_s:.2f} s of capture) in {stats.wall_s:.1f} s = {stats.frames_per_s:.1f} frames/s; "
          f"stopped by {stats.stopped_by}; session in {out}")


def _cmd_sim_record(args) -> int:
    from lapreco_hil.app.record import sim_record

    stats = sim_record(args.scene, args.out, frames=args.frames, resolution=args.resolution, fps=args.fps,
                       seed=args.seed, device=args.device, robot_link=args.robot_link, sim_speed=args.sim_speed,
                       instrument=args.instrument, kinematics_offset_ms=args.kinematics_offset_ms,
                       progress=not args.no_progress)
    _print_record(args.out, stats)
    return 0


def _cmd_replay(args) -> int:
    from lapreco_hil.app.replay import run_replay

    report = run_replay(args.session, args.out, tracker=args.tracker, device=args.device,
                        config_path=args.config, drift_check=args.drift_check, realtime=args.realtime,
                        progress=not args.no_progress, camera_file=args.camera, hand_eye_file=args.hand_eye,
                        time_offset_ms=args.time_offset_ms, surface=args.surface)
    _print_run("replay", report)
    return 0


def _cmd_demo(args) -> int:
    from lapreco_hil.app.demo import run_demo

    report = run_demo(scene=args.scene, frames=args.frames, resolution=args.resolution, fps=args.fps,
                      out=args.out, device=args.device, tracker=args.tracker, config_path=args.config,
                      seed=args.seed, progress=not args.no_progress, drift_check=args.drift_check,
                      robot_link=args.robot_link, sim_speed=args.sim_speed, instrument=args.instrument,
                      runtime="sequential" if args.sequential else "live", view_every=args.view_every,
                      stereo_baseline_mm=args.stereo, surface=args.surface)
    _print_run("demo", report)
    return 0


def print_funnel(command: str, report: dict) -> None:
    """The tracking funnel, stage by stage, naming the stage that lost most of the points."""
    if report.get("funnel"):
        from lapreco_hil.funnel import Funnel

        print(f"lapreco {command}: funnel: {Funnel(dict(report['funnel'])).summary()}")
    # the file (a replay's session.json) or device (a run's grabber) whose rig is wrong
    source = str(Path(report["session"]) / "session.json") if report.get("session") else report.get("grabber")
    for fit in report.get("rig_check") or ():
        if fit.get("problem"):  # said at the start too; repeated here, where a run's few points are read
            print(f"lapreco {command}: warning: {source + ': ' if source else ''}{fit['problem']}")


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
    dense = report.get("dense")
    if dense:
        line = (f"lapreco {command}: dense surface: {dense['points']} points, {dense['mesh_triangles']} triangles from "
                f"{dense['keyframes_fused']} keyframes")
        surface = acc.get("surface") or {}
        if "dense" in surface:
            line += (f"; RMS to true surface {_fmt(surface['dense']['rms_mm'])} mm; coverage within "
                     f"{surface['radius_mm']:g} mm: sparse {_pct(surface['sparse']['coverage'])}, dense "
                     f"{_pct(surface['dense']['coverage'])}")
        print(line)
    print_funnel(command, report)


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def _pct(v) -> str:
    return "n/a" if v is None else f"{v:.0%}"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a refused argument (its one line is already printed)
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    # each change of a device's health is news on the console, its recovery ("robot: ok again", INFO) too
    logging.getLogger("lapreco_hil.runtime.health").setLevel(logging.INFO)
    from lapreco_hil.app.noise import route_third_party_output

    route_third_party_output()
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
