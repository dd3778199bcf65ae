"""The ``lapreco`` command. Every LaprecoError becomes one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import logging
import sys

from .. import __version__
from ..errors import LaprecoError, OutputError


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
    demo.add_argument("--scene", default="skull", help="skull | liver | apple (default: skull)")
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
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    demo.set_defaults(func=_cmd_demo)

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
    return parser


def _write_json(path: str | None, result: dict) -> None:
    import json

    if not path:
        return
    try:
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(result, fh, indent=2)
    except OSError as exc:
        raise OutputError(f"cannot write benchmark JSON '{path}' ({exc.strerror})") from None


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


def _cmd_demo(args) -> int:
    from .demo import run_demo

    report = run_demo(scene=args.scene, frames=args.frames, resolution=args.resolution, fps=args.fps,
                      out=args.out, device=args.device, tracker=args.tracker, config_path=args.config,
                      seed=args.seed, progress=not args.no_progress, drift_check=args.drift_check)
    acc = report.get("accuracy", {})
    pts = acc.get("points_to_surface", {})
    print(f"lapreco demo: {report['frames']['processed']} frames in {report['wall_s']:.1f} s; "
          f"{report['inliers']} inlier points, RMS to true surface {_fmt(pts.get('rms_mm'))} mm; "
          f"camera position RMS raw FK {_fmt(acc.get('camera_raw_fk', {}).get('position_rms_mm'))} mm -> refined "
          f"{_fmt(acc.get('camera_refined', {}).get('position_rms_mm'))} mm; outputs in {report['out']}")
    return 0


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
