"""``lapreco calibrate lens|handeye|time-offset``: the calibration workflows, writing OpenCV YAML that the
rest of the app reads (``record``/``replay --camera``, ``--hand-eye``) and, for the time offset, the
session's own ``time_offset_ns``."""

from __future__ import annotations

import logging
from pathlib import Path


from ..calib.boards import parse_board
from ..calib.files import write_camera_yaml
from ..outputs import write_json

log = logging.getLogger(__name__)


def add_parsers(sub, positive_int) -> None:
    cal = sub.add_parser("calibrate", help="lens, hand-eye and video-kinematics time-offset calibration")
    cal_sub = cal.add_subparsers(dest="calibration", required=True)

    lens = cal_sub.add_parser("lens", help="lens intrinsics and distortion from board images")
    lens.add_argument("images", nargs="+", help="board images (or a session's frames/*.png)")
    lens.add_argument("--board", required=True, help="chessboard:9x6:0.025 (inner corners, square m) or "
                                                     "charuco:10x7:0.004:0.003[:DICT_5X5_100]")
    lens.add_argument("--model", default="paper", choices=("paper", "standard", "rational", "full"),
                      help="distortion model (default: paper = radial k1..k3, tangential, thin prism)")
    lens.add_argument("--out", required=True, help="camera.yaml to write (OpenCV FileStorage)")
    lens.add_argument("--json", default=None, help="also write the report as JSON")
    lens.set_defaults(func=cmd_lens)

    he = cal_sub.add_parser("handeye", help="T_tip_camera from a session of joint readings and board views")
    he.add_argument("session", help="a session with joint readings (pose_source 'joints') looking at a board")
    he.add_argument("--board", required=True, help="the board, as for 'calibrate lens'")
    he.add_argument("--camera", default=None, help="lens calibration (default: the session's camera)")
    he.add_argument("--stride", type=positive_int, default=5, help="use every Nth frame as a station (default 5)")
    he.add_argument("--out", required=True, help="handeye.yaml to write (OpenCV FileStorage)")
    he.add_argument("--json", default=None, help="also write the report as JSON")
    he.set_defaults(func=cmd_handeye)

    to = cal_sub.add_parser("time-offset", help="offset between video and kinematics timestamps")
    to.add_argument("session", help="a session with joint readings over a textured scene, the camera moving")
    to.add_argument("--search-ms", type=float, default=1000.0, help="search +- this many ms (default 1000)")
    to.add_argument("--apply", action="store_true", help="write the estimate into the session's time_offset_ns")
    to.add_argument("--hand-eye", default=None, help="hand-eye (OpenCV YAML) in place of the session's own")
    to.add_argument("--json", default=None, help="also write the report as JSON")
    to.set_defaults(func=cmd_time_offset)


def _write_json(path: str | None, doc: dict) -> None:
    if path:
        write_json(path, doc)


def cmd_lens(args) -> int:
    from ..calib.lens import calibrate_lens, load_images, save_check_image

    board = parse_board(args.board)
    images = load_images(args.images)
    result = calibrate_lens(images, board, args.model)
    write_camera_yaml(args.out, result.camera, {"rms_px": result.rms_px, "model": result.model,
                                                "views": len(result.per_view_rms_px)})
    check = Path(args.out).with_suffix(".check.png")
    save_check_image(check, result, images)
    for name, why in result.rejected.items():
        print(f"  rejected {name}: {why}")
    worst = max(result.per_view_rms_px.items(), key=lambda kv: kv[1])
    print(f"lapreco calibrate lens: {len(result.per_view_rms_px)} of {len(images)} views, model {result.model}, "
          f"RMS {result.rms_px:.3f} px (worst view {Path(worst[0]).name}: {worst[1]:.3f} px); "
          f"fx {result.camera.fx:.1f} fy {result.camera.fy:.1f} cx {result.camera.cx:.1f} cy {result.camera.cy:.1f}; "
          f"wrote {args.out} and {check}")
    _write_json(args.json, result.summary())
    return 0


def cmd_handeye(args) -> int:
    from ..app.handeye import calibrate_hand_eye_session

    result = calibrate_hand_eye_session(args.session, args.board, args.out, camera_file=args.camera,
                                        stride=args.stride, json_file=args.json)
    for name, m in result["methods"].items():
        print(f"  {name:<11} station consistency: rotation {m['rotation_rms_deg']:.3f} deg, "
              f"translation {m['translation_rms_mm']:.3f} mm")
    for name, why in result["failed_methods"].items():
        print(f"  {name:<11} failed: {why}")
    ref, agree = result["refined"], result["agreement"]
    print(f"  refined     station consistency: rotation {ref['rotation_rms_deg']:.3f} deg, translation "
          f"{ref['translation_rms_mm']:.3f} mm; reprojection RMS {ref['reprojection_rms_px']:.3f} px")
    print(f"  methods agree within {agree['rotation_deg']:.3f} deg / {agree['translation_mm']:.3f} mm")
    for w in result["warnings"]:
        print(f"  warning: {w}")
    print(f"lapreco calibrate handeye: {result['stations']} stations; T_tip_camera written to {args.out}")
    return 0


def cmd_time_offset(args) -> int:
    from ..app.handeye import estimate_session_time_offset

    s = estimate_session_time_offset(args.session, args.search_ms, apply=args.apply, hand_eye_file=args.hand_eye,
                                     json_file=args.json)
    print(f"lapreco calibrate time-offset: kinematics time = video time + {s['offset_ms']:.1f} ms "
          f"(+- {s['sigma_ms']:.1f} ms, {s['pairs']} frame pairs; median Sampson distance "
          f"{s['median_sampson_px_at_zero']:.3f} px at 0 -> {s['median_sampson_px_at_offset']:.3f} px)")
    if args.apply:
        print(f"  applied: {s['applied_to']} time_offset_ns = {round(s['offset_ms'] * 1e6)}")
    return 0
