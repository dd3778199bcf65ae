"""``lapreco export mcap`` and ``lapreco import rosbag``: arguments for lapreco_hil.interop, and their one-line
summaries (docs/interop.md)."""

from __future__ import annotations

from lapreco_hil.cli.args import integer, non_negative


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip())


def cmd_export_mcap(args) -> int:
    from lapreco_hil.interop.mcap_export import export_mcap

    result = export_mcap(args.session, args.out, result_dir=args.result, jpeg_quality=args.jpeg_quality,
                         progress=not args.no_progress)
    topics = ", ".join(f"{t} {n}" for t, n in sorted(result["topics"].items()))
    line = f"lapreco export mcap: {result['frames']} frames; messages: {topics}; written to {result['file']}"
    if result["frames_without_transforms"]:
        line += f" ({result['frames_without_transforms']} frames without a pose have no /tf)"
    print(line)
    return 0


def cmd_import_rosbag(args) -> int:
    from lapreco_hil.interop.rosbag_import import import_rosbag

    result = import_rosbag(args.bag, args.out, args.image_topic, args.joints_topic, args.camera_info_topic,
                           args.poses_topic, robot_model=args.robot_model, tip_frame=args.tip_frame,
                           hand_eye=args.hand_eye, joint_names=_names(args.joint_names) if args.joint_names else None,
                           poses_frame=args.poses_frame, camera_file=args.camera, fov_radius_px=args.fov_radius,
                           stamps=args.stamps, progress=not args.no_progress)
    print(f"lapreco import rosbag: {result['frames']} frames and {result['pose_samples']} pose samples "
          f"({result['pose_source']}; {result['pose_samples_skipped']} skipped); camera from {result['camera']}; "
          f"session in {result['session']}")
    if result["calibration_session"]:
        print(f"no hand-eye: {result['session']} is a calibration session; pass --hand-eye handeye.yaml to import "
              f"a session that replays, or calibrate from it ('lapreco calibrate handeye')")
    return 0


def add_parsers(sub) -> None:
    export = sub.add_parser("export", help="write a session (and a run's result) for other tools")
    export_sub = export.add_subparsers(dest="export", required=True)
    mcap = export_sub.add_parser("mcap", help="a session as an MCAP file with Foxglove's schemas (open in Foxglove)")
    mcap.add_argument("session", help="session folder (docs/session-format.md)")
    mcap.add_argument("--out", required=True, help="the MCAP file to write, e.g. session.mcap")
    mcap.add_argument("--result", default=None, help="also the map of a run: its output folder (points.ply, "
                                                      "mesh.ply, trajectory.tum)")
    mcap.add_argument("--jpeg-quality", type=integer(ge=1, le=100), default=90, help="1..100 (default 90)")
    mcap.add_argument("--no-progress", action="store_true", help="no progress bar")
    mcap.set_defaults(func=cmd_export_mcap)

    imp = sub.add_parser("import", help="make a session from another tool's recording")
    imp_sub = imp.add_subparsers(dest="import_", required=True)
    bag = imp_sub.add_parser("rosbag", help="a ROS 2 bag (MCAP or sqlite3) as a session")
    bag.add_argument("bag", help="the bag: a rosbag2 folder, or its .mcap / .db3 file")
    bag.add_argument("--out", required=True, help="new session folder")
    bag.add_argument("--image-topic", required=True, help="sensor_msgs/Image or CompressedImage, e.g. "
                                                          "/camera/left/image_raw")
    bag.add_argument("--camera-info-topic", default=None, help="sensor_msgs/CameraInfo, e.g. /camera/left/camera_info")
    bag.add_argument("--camera", default=None,
                     help="instead of camera_info: a lens file (OpenCV or ROS camera_info YAML)")
    bag.add_argument("--joints-topic", default=None, help="sensor_msgs/JointState, e.g. /ECM/measured_js")
    bag.add_argument("--poses-topic", default=None, help="instead of joints: geometry_msgs/PoseStamped, e.g. "
                                                         "/ECM/measured_cp")
    bag.add_argument("--poses-frame", choices=("tip", "camera"), default="tip",
                     help="what the poses give: the robot's tip in its base (dVRK measured_cp; the hand-eye makes "
                          "the camera) or the camera in the world (default tip)")
    bag.add_argument("--robot-model", default="ecm", help="packaged robot model name or URDF path (default ecm)")
    bag.add_argument("--tip-frame", default=None, help="the URDF link that holds the scope (ecm: ecm_tip)")
    bag.add_argument("--hand-eye", default=None, help="hand-eye calibration (OpenCV YAML with T_tip_camera); "
                                                      "without it: a calibration session")
    bag.add_argument("--joint-names", default=None,
                     help="the bag's names of the model's joints in its order, comma-separated (default: the "
                          "model's names)")
    bag.add_argument("--fov-radius", type=non_negative, default=0.0,
                     help="the scope's circular field of view, radius in pixels about (cx, cy) (camera_info has "
                          "none; default 0 = the whole image)")
    bag.add_argument("--stamps", choices=("header", "log"), default="header",
                     help="capture times: the messages' header stamps, or the bag's receive times (default header)")
    bag.add_argument("--no-progress", action="store_true", help="no progress bar")
    bag.set_defaults(func=cmd_import_rosbag)
