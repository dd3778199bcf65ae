"""``lapreco calibrate lens|stereo|handeye|handeye-tracked|time-offset``: the calibration workflows, writing OpenCV YAML that
the rest of the app reads (``record``/``replay --camera``, ``--hand-eye``) and, for the time offset, the
session's own ``time_offset_ns``. Lens and stereo run in ``lapreco_hil.app.calibrate``; this module parses
and prints."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lapreco_hil.cli.args import non_negative, positive
from lapreco_hil.errors import CalibrationError
from lapreco_hil.outputs import write_json

log = logging.getLogger(__name__)


def add_parsers(sub, positive_int) -> None:
    cal = sub.add_parser("calibrate", help="lens, hand-eye and video-kinematics time-offset calibration")
    cal_sub = cal.add_subparsers(dest="calibration", required=True)

    boards = ("chessboard:9x6:0.025 (inner corners, square m), charuco:10x7:0.004:0.003[:DICT_5X5_100], "
              "circles:25x18:0.005[:8,5+16,5] (dots per row x rows, pitch m, large dots), acircles:4x11:0.02, "
              "or viking")
    models = ("auto", "k1k2p1p2", "standard", "paper", "rational", "full")
    lens = cal_sub.add_parser("lens", help="lens intrinsics and distortion from board images")
    lens.add_argument("images", nargs="+", help="board images (or a session's frames/*.png)")
    lens.add_argument("--board", required=True, help=boards)
    lens.add_argument("--model", default="auto", choices=models,
                      help="distortion model (default: auto = the simplest of standard, rational, full whose "
                           "error on held-out views is within 5%% of the best)")
    lens.add_argument("--out", required=True, help="camera.yaml to write (OpenCV FileStorage)")
    lens.add_argument("--ros-out", default=None, help="also write a ROS camera_info YAML")
    lens.add_argument("--camera-name", default="camera", help="camera_name in the ROS camera_info YAML")
    lens.add_argument("--json", default=None, help="also write the report as JSON")
    lens.set_defaults(func=cmd_lens)

    st = cal_sub.add_parser("stereo", help="a stereo rig (both lenses and T_cam0_cam1) from board image pairs")
    st.add_argument("--left", nargs="+", required=True, help="camera 0's board images")
    st.add_argument("--right", nargs="+", required=True, help="camera 1's, taken with them, in the same order")
    st.add_argument("--board", required=True, help=boards)
    st.add_argument("--model", default="auto", choices=models, help="each camera's distortion model")
    st.add_argument("--refine-intrinsics", action="store_true",
                    help="refine both lenses with the rig (default: each lens as calibrated alone, fixed)")
    st.add_argument("--out", required=True, help="rig.yaml to write (OpenCV FileStorage)")
    st.add_argument("--json", default=None, help="also write the report as JSON")
    st.set_defaults(func=cmd_stereo)

    he = cal_sub.add_parser("handeye", help="T_tip_camera from a session of joint readings and board views")
    he.add_argument("session", help="a session with joint readings (pose_source 'joints') looking at a board")
    he.add_argument("--board", required=True, help="the board, as for 'calibrate lens'")
    he.add_argument("--camera", default=None, help="lens calibration (default: the session's camera)")
    he.add_argument("--stride", type=positive_int, default=5, help="use every Nth frame as a station (default 5)")
    he.add_argument("--refine", default="poses", choices=("poses", "joints"),
                    help="poses (default): free tip poses with a prior of a few mrad; joints: the joint errors "
                         "are the unknowns, as --joint-wander-s and --backlash describe the arm")
    he.add_argument("--joint-wander-s", type=non_negative, default=0.0,
                    help="with --refine joints: how long a deflection of the links from their readings lasts "
                         "(s; elastic joints, cable stretch); 0 (default): independent at every station")
    he.add_argument("--backlash", type=backlash_list, default=None,
                    help="with --refine joints: the half-play of each joint's transmission (rad or m), one value "
                         "or one per joint, comma-separated; default: none")
    he.add_argument("--out", required=True, help="handeye.yaml to write (OpenCV FileStorage)")
    he.add_argument("--json", default=None, help="also write the report as JSON")
    he.set_defaults(func=cmd_handeye)

    ht = cal_sub.add_parser("handeye-tracked",
                            help="an optically tracked scope's hand-eye (camera -> scope marker) and the board "
                                 "pattern on its marker, from tracked board views")
    ht.add_argument("--session", default=None,
                    help="instead of the files below, a tracked-scope session ('lapreco record --marker', "
                         "marker_poses.csv) looking at the board; needs --board-tool")
    ht.add_argument("--board-tool", default=None, help="with --session: the board marker's tool name")
    ht.add_argument("--stride", type=positive_int, default=5,
                    help="with --session: use every Nth frame as a view (default 5)")
    ht.add_argument("--scope-poses", nargs="+", metavar="FILE", default=None,
                    help="per view, the scope marker's 4x4 pose in the tracker's frame (text, mm); files or a "
                         "quoted glob, in view order (names sorted by their numbers)")
    ht.add_argument("--board-poses", nargs="+", metavar="FILE", default=None,
                    help="per view, the board marker's 4x4 pose in the tracker's frame (text, mm), likewise")
    ht.add_argument("--left", nargs="+", metavar="IMAGE", default=None, help="per view, the (left) camera's image")
    ht.add_argument("--right", nargs="+", metavar="IMAGE", default=None,
                    help="per view, the right camera's image (a stereo scope: one hand-eye plus the rig)")
    ht.add_argument("--board", required=True, help="the printed pattern, as for 'calibrate lens' (e.g. viking)")
    ht.add_argument("--camera", default=None, help="the (left) camera's lens (OpenCV YAML or ROS camera_info); "
                                                   "with --session the session's")
    ht.add_argument("--camera-right", default=None, help="the right camera's lens, with --right")
    ht.add_argument("--no-leave-one-out", action="store_true",
                    help="skip the leave-one-view-out triangulation figure (stereo only; one calibration per view)")
    ht.add_argument("--out", required=True, help="handeye.yaml to write (T_tip_camera = T_scopemarker_camera)")
    ht.add_argument("--json", default=None, help="also write the report as JSON")
    ht.set_defaults(func=cmd_handeye_tracked)

    to = cal_sub.add_parser("time-offset", help="offset between the video's and the pose source's timestamps "
                                                 "(joint readings, a tracker's marker poses or given camera poses)")
    to.add_argument("session", help="a session of any pose source (joints, marker_poses, camera_poses) over a "
                                    "textured scene, the camera moving")
    to.add_argument("--search-ms", type=positive, default=1000.0, help="search +- this many ms (default 1000)")
    to.add_argument("--apply", action="store_true", help="write the estimate into the session's time_offset_ns")
    to.add_argument("--hand-eye", default=None,
                    help="hand-eye (OpenCV YAML) in place of the session's own: T_tip_camera for joint readings, "
                         "T_marker_camera for a tracked scope (as 'calibrate handeye-tracked' writes it)")
    to.add_argument("--joint-wander-s", type=non_negative, default=0.0,
                    help="joint readings only: the arm's joint-error time constant (s), if known: the uncertainty "
                         "then adds the "
                         "offset's spread under such wander of the pipeline's joint sigma; 0 (default): the "
                         "uncertainty is the block jackknife alone")
    to.add_argument("--json", default=None, help="also write the report as JSON")
    to.set_defaults(func=cmd_time_offset)


def backlash_list(text: str) -> tuple[float, ...]:
    """An argparse type: comma-separated non-negative numbers (rad or m per joint)."""
    return tuple(non_negative(v) for v in text.split(","))


def _write_json(path: str | None, doc: dict) -> None:
    if path:
        write_json(path, doc)


def _print_lens(prefix: str, result) -> None:
    for s in result.scores:
        held = "not fitted: " + (s.error or "") if s.held_out_rms_px is None else f"held out {s.held_out_rms_px:.3f} px"
        fitted = "" if s.fit_rms_px is None else f", fitted {s.fit_rms_px:.3f} px"
        mark = "  <- chosen" if s.model == result.model else ""
        print(f"{prefix}model {s.model:<8} ({s.coefficients:>2} coefficients): {held}{fitted}{mark}")
    for name, why in result.rejected.items():
        print(f"{prefix}rejected {name}: {why}")
    sd = result.std
    print(f"{prefix}std: fx {sd['fx']:.2f} fy {sd['fy']:.2f} cx {sd['cx']:.2f} cy {sd['cy']:.2f} px")


def cmd_lens(args) -> int:
    from lapreco_hil.app.calibrate import run_lens_calibration

    run = run_lens_calibration(args.images, args.board, args.out, args.model, args.ros_out, args.camera_name)
    result = run.result
    _print_lens("  ", result)
    worst = max(result.per_view_rms_px.items(), key=lambda kv: kv[1])
    cam = result.camera
    print(f"lapreco calibrate lens: {len(result.per_view_rms_px)} of {run.images} views, model {result.model}, "
          f"RMS {result.rms_px:.3f} px (worst view {Path(worst[0]).name}: {worst[1]:.3f} px); "
          f"fx {cam.fx:.1f} fy {cam.fy:.1f} cx {cam.cx:.1f} cy {cam.cy:.1f}; wrote {', '.join(run.written)}")
    _write_json(args.json, result.summary())
    return 0


def cmd_stereo(args) -> int:
    from lapreco_hil.app.calibrate import run_stereo_calibration

    run = run_stereo_calibration(args.left, args.right, args.board, args.out, args.model, args.refine_intrinsics)
    for tag, lens in (("camera 0", run.lens0), ("camera 1", run.lens1)):
        print(f"  {tag}: model {lens.model}, RMS {lens.rms_px:.3f} px, {len(lens.per_view_rms_px)} views")
        _print_lens("    ", lens)
    r = run.result
    print(f"lapreco calibrate stereo: {len(r.pairs)} pairs, RMS {r.rms_px:.3f} px, rectified epipolar error "
          f"{r.rectified_epipolar_error_px:.3f} px, baseline {float(np.linalg.norm(r.T)) * 1e3:.2f} mm; "
          f"wrote {args.out}")
    _write_json(args.json, {**r.summary(), "cam0_lens": run.lens0.summary(), "cam1_lens": run.lens1.summary()})
    return 0


def cmd_handeye(args) -> int:
    from lapreco_hil.app.handeye import calibrate_hand_eye_session

    result = calibrate_hand_eye_session(args.session, args.board, args.out, camera_file=args.camera,
                                        stride=args.stride, json_file=args.json, refinement=args.refine,
                                        joint_wander_s=args.joint_wander_s, backlash=args.backlash)
    for name, m in result["methods"].items():
        print(f"  {name:<11} station consistency: rotation {m['rotation_rms_deg']:.3f} deg, "
              f"translation {m['translation_rms_mm']:.3f} mm")
    for name, why in result["failed_methods"].items():
        print(f"  {name:<11} failed: {why}")
    ref, agree = result["refined"], result["agreement"]
    print(f"  refined ({result['refinement']}) station consistency: rotation {ref['rotation_rms_deg']:.3f} deg, "
          f"translation {ref['translation_rms_mm']:.3f} mm; reprojection RMS {ref['reprojection_rms_px']:.3f} px")
    print(f"  methods agree within {agree['rotation_deg']:.3f} deg / {agree['translation_mm']:.3f} mm")
    for w in result["warnings"]:
        print(f"  warning: {w}")
    print(f"lapreco calibrate handeye: {result['stations']} stations; T_tip_camera written to {args.out}")
    return 0


def cmd_handeye_tracked(args) -> int:
    from lapreco_hil.app.handeye_tracked import calibrate_tracked, calibrate_tracked_session

    files = {"--scope-poses": args.scope_poses, "--board-poses": args.board_poses, "--left": args.left,
             "--camera": args.camera, "--right": args.right, "--camera-right": args.camera_right}
    if args.session:
        given = [k for k, v in files.items() if v]
        if given or not args.board_tool:
            raise CalibrationError(f"with --session give --board-tool (the board marker's tool) and no per-view "
                                   f"files{' (got ' + ', '.join(given) + ')' if given else ''}")
        r = calibrate_tracked_session(args.session, args.board, args.board_tool, args.out, stride=args.stride,
                                      json_file=args.json, leave_one_out=not args.no_leave_one_out)
    else:
        missing = [k for k in ("--scope-poses", "--board-poses", "--left", "--camera") if not files[k]]
        if missing:
            raise CalibrationError(f"give {', '.join(missing)} (per-view files), or --session S --board-tool NAME")
        r = calibrate_tracked(args.scope_poses, args.board_poses, args.left, args.board, args.camera, args.out,
                              right=args.right, camera_right_file=args.camera_right, json_file=args.json,
                              leave_one_out=not args.no_leave_one_out)
    for side, cam in r["per_camera"].items():
        agree = cam["agreement"]
        for name, m in cam["methods"].items():
            print(f"  {side:<5} {name:<11} view consistency: rotation {m['rotation_rms_deg']:.3f} deg, "
                  f"translation {m['translation_rms_mm']:.3f} mm")
        for name, why in cam["failed_methods"].items():
            print(f"  {side:<5} {name:<11} failed: {why}")
        print(f"  {side:<5} methods agree within {agree['rotation_deg']:.3f} deg / {agree['translation_mm']:.3f} mm")
    rms = ", ".join(f"{side} {v:.2f} px" for side, v in r["reprojection_rms_px"].items())
    print(f"  refined: reprojection RMS {rms} (dot noise {r['sigma_px']:.2f} px, robust scale); tracker poses "
          f"moved {r['tracker_correction_rms_deg']:.3f} deg / {r['tracker_correction_rms_mm']:.3f} mm RMS")
    if r["T_left_right"] is not None:
        print(f"  rig: baseline {np.linalg.norm(r['T_left_right'][:3, 3]) * 1e3:.2f} mm")
    loo = r.get("leave_one_view_out")
    if loo:
        for name, e in loo["per_view"].items():
            print(f"  held out {name}: {e['dots']} dots, mean {e['mean_mm']:.2f} mm, RMS {e['rms_mm']:.2f} mm, "
                  f"max {e['max_mm']:.2f} mm, offset {e['offset_mm']:.2f} mm")
        print(f"  leave-one-view-out: {loo['dots']} dots triangulated from tracker poses x hand-eye lie "
              f"{loo['mean_mm']:.2f} mm (mean) / {loo['rms_mm']:.2f} mm (RMS) from the grid")
    for w in r["warnings"]:
        print(f"  warning: {w}")
    print(f"lapreco calibrate handeye-tracked: {r['views']} views; T_scopemarker_camera written to {args.out}")
    return 0


# whose clock the offset is to, by the session's pose_source
TIME_OFFSET_CLOCKS = {"joints": "kinematics", "marker_poses": "tracker", "camera_poses": "pose"}


def cmd_time_offset(args) -> int:
    from lapreco_hil.app.handeye import estimate_session_time_offset

    s = estimate_session_time_offset(args.session, args.search_ms, apply=args.apply, hand_eye_file=args.hand_eye,
                                     json_file=args.json, joint_wander_s=args.joint_wander_s)
    joints = s.get("pose_source", "joints") == "joints"
    clock = TIME_OFFSET_CLOCKS.get(s.get("pose_source"), "pose")
    print(f"lapreco calibrate time-offset: {clock} time = video time + {s['offset_ms']:.1f} ms "
          f"(+- {s['sigma_ms']:.1f} ms, {s['pairs']} frame pairs; median Sampson distance "
          f"{s['median_sampson_px_at_zero']:.3f} px at 0 -> {s['median_sampson_px_at_offset']:.3f} px)")
    if not joints:
        print("  the uncertainty is a block jackknife over 1 s stretches: it assumes the pose errors are unrelated "
              "that far apart")
    elif not args.joint_wander_s:
        print("  the uncertainty is a block jackknife over 1 s stretches: it assumes the joint errors are unrelated "
              "that far apart; if the arm's joints wander slowly, give --joint-wander-s")
    if args.apply:
        print(f"  applied: {s['applied_to']} time_offset_ns = {round(s['offset_ms'] * 1e6)}")
    return 0
