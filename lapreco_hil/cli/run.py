"""``lapreco run``: arguments for :func:`lapreco_hil.app.run.run`, and its one-line summary."""

from __future__ import annotations

from lapreco_hil.cli.args import non_negative, positive


def cmd_run(args) -> int:
    from lapreco_hil.app.run import run, stop_on_signals
    from lapreco_hil.sessions.recorder import DeviceLostError

    stop_on_signals()
    try:
        report = run(args.robot, args.grabber, args.out, config_path=args.config, record=args.record,
                     seconds=args.seconds, view_every=args.view_every, tracker=args.tracker, device=args.device,
                     camera_file=args.camera, robot_model=args.robot_model, tip_frame=args.tip_frame,
                     hand_eye_file=args.hand_eye, progress=not args.no_progress, marker_url=args.marker,
                     tool=args.tool, mcap=args.mcap, surface=args.surface)
    except DeviceLostError as exc:  # the outputs are written: their summary, then the error line (exit 2)
        if exc.report is not None:
            _print_summary(exc.report)
        raise
    _print_summary(report)
    return 0


def _print_summary(report: dict) -> None:
    """The run's summary: frames, throughput, latency, points, the pose source's coverage of the frames where it
    left some without a reading (a gap, or the end: docs/reliability.md), and the tracking funnel."""
    f, lat = report["frames"], report["latency_ms"]
    before = f" ({f['passed_before_start']} passed before capture started)" if f.get("passed_before_start") else ""
    print(f"lapreco run: {f['in']} frames in{before}, {f['processed']} mapped, {f['dropped']} dropped; "
          f"{report['throughput_fps']:.1f} frames/s; latency p50 {lat.get('p50', float('nan')):.0f} ms, "
          f"p99 {lat.get('p99', float('nan')):.0f} ms; {report['inliers']} inlier points; outputs in {report['out']}")
    line = (report.get("pose_coverage") or {}).get("summary")
    if line:
        print(f"lapreco run: {line}")
    from lapreco_hil.cli.main import print_funnel

    print_funnel("run", report)


def add_parser(sub) -> None:
    run = sub.add_parser("run", help="the live pipeline on devices until the source ends, --seconds, or Ctrl-C")
    # exactly one of --robot / --marker (checked by app.run, which says so in one line)
    run.add_argument("--robot", default=None, help="robot URL (serial://, canopen://, sim://, replay://)")
    run.add_argument("--marker", default=None, help="instead of a robot, a tracker following the scope's marker "
                                                    "(ndi://... or a recorded marker session replay://S; needs "
                                                    "--hand-eye, which a recorded session may carry)")
    run.add_argument("--tool", default=None, help="with --marker: the scope's tool (default: the tracker's only one, "
                                                  "or a recorded session's tracker.tool)")
    run.add_argument("--grabber", required=True, help="grabber URL (v4l2://, sim://, replay://)")
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--config", default=None, help="pipeline configuration (TOML)")
    run.add_argument("--record", default=None, help="also record the session into this new folder")
    run.add_argument("--mcap", default=None, metavar="FILE",
                     help="also log frames, calibration, joints, /tf and at the end the map to this MCAP file "
                          "(Foxglove's schemas; docs/interop.md)")
    run.add_argument("--seconds", type=positive, default=None, help="stop after this many seconds (> 0)")
    run.add_argument("--view-every", type=non_negative, default=0.0,
                     help="render the live textured view every S seconds to OUT/live/*.png and OUT/live.mp4 "
                          "(0 = off)")
    run.add_argument("--tracker", default="auto", help="warp | opencv | auto")
    run.add_argument("--device", default="auto", help="Warp device: auto | cpu | cuda")
    run.add_argument("--camera", default=None, help="lens calibration (OpenCV YAML) when the grabber has none")
    run.add_argument("--robot-model", default=None, help="packaged robot model name or URDF path")
    run.add_argument("--tip-frame", default=None, help="the URDF link that holds the scope")
    run.add_argument("--hand-eye", default=None, help="hand-eye calibration (OpenCV YAML with T_tip_camera; with "
                                                      "--marker the scope marker's)")
    from lapreco_hil.cli.main import SURFACE_CHOICES, SURFACE_HELP

    run.add_argument("--surface", choices=SURFACE_CHOICES, default=None, help=SURFACE_HELP)
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.set_defaults(func=cmd_run)
