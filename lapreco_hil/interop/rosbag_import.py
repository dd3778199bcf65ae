"""A ROS 2 bag (MCAP or sqlite3) as a lapreco session, read with rosbags' AnyReader (which also opens ROS 1
bags; not tested here).

What becomes what (docs/interop.md):

- the image topic (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8, bgra8; or sensor_msgs/CompressedImage: JPEG,
  PNG) -> the frames, stored losslessly as PNG (a JPEG stream keeps its JPEG losses);
- the camera_info topic (sensor_msgs/CameraInfo: plumb_bob, rational_polynomial) -> the session's camera
  (or a lens file given instead);
- the joints topic (sensor_msgs/JointState) -> joints.csv, each of the robot model's joints found by name;
- or the poses topic (geometry_msgs/PoseStamped) -> the pose source: ``poses_frame="tip"`` (the dVRK's
  ``measured_cp``: the tip in the robot's base) is a marker-pose session whose "marker" is the tip and whose
  hand-eye is T_tip_camera; ``poses_frame="camera"`` is a camera-pose session (T_world_camera).

Capture times are the messages' header stamps (``stamps="log"``: the bag's receive times, for drivers that
leave the stamp empty). ROS units are SI, as a session's in metres and radians.
"""

from __future__ import annotations

import logging
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.errors import CalibrationError, ConfigError, LaprecoError, SessionError
from lapreco_hil.interop.camera_info import camera_from_camera_info

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
# sensor_msgs/image_encodings -> (channels, OpenCV conversion to BGR or None)
ENCODINGS = {"bgr8": (3, None), "rgb8": (3, cv2.COLOR_RGB2BGR), "mono8": (1, cv2.COLOR_GRAY2BGR),
             "8UC1": (1, cv2.COLOR_GRAY2BGR), "8UC3": (3, None), "bgra8": (4, cv2.COLOR_BGRA2BGR),
             "rgba8": (4, cv2.COLOR_RGBA2BGR)}
POSES_FRAMES = ("tip", "camera")
STAMPS = ("header", "log")
DEFAULT_TIP_FRAMES = {"ecm": "ecm_tip"}


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)  # the standard messages, for bags that carry no definitions


class _Bag:
    """An open bag: its topics by name, and messages of one or more topics as (topic, time, message)."""

    def __init__(self, path: Path, reader) -> None:
        self.path, self.reader = path, reader
        self.connections: dict[str, list] = {}
        for c in reader.connections:
            self.connections.setdefault(c.topic, []).append(c)

    def topics_text(self) -> str:
        items = [f"{t} ({cs[0].msgtype}, {sum(c.msgcount for c in cs)} messages)"
                 for t, cs in sorted(self.connections.items())]
        return ", ".join(items) if items else "none"

    def topic(self, name: str, types: tuple[str, ...], what: str) -> str:
        if name not in self.connections:
            raise SessionError(f"{self.path}: no topic '{name}' ({what}); the bag's topics: {self.topics_text()}")
        msgtype = self.connections[name][0].msgtype
        if msgtype not in types:
            raise SessionError(f"{self.path}: topic '{name}' carries {msgtype}; the {what} must be "
                               f"{' or '.join(types)}")
        return msgtype

    def messages(self, topics: list[str]):
        conns = [c for t in topics for c in self.connections[t]]
        for c, t_ns, raw in self.reader.messages(connections=conns):
            yield c.topic, int(t_ns), self.reader.deserialize(raw, c.msgtype)

    def count(self, topic: str) -> int:
        return sum(c.msgcount for c in self.connections[topic])


def _stamp_ns(msg, log_ns: int, stamps: str, where: str) -> int:
    if stamps == "log":
        return log_ns
    t = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    if t <= 0:
        raise SessionError(f"{where}: a message with an empty header stamp; the driver did not stamp it: import "
                           f"with --stamps log (the bag's receive times)")
    return t


def image_from_message(msg, msgtype: str, where: str) -> np.ndarray:
    """A sensor_msgs Image or CompressedImage as a BGR uint8 image."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise SessionError(f"{where}: cannot decode a CompressedImage (format '{msg.format}'); JPEG and PNG "
                               f"are read")
        return image
    if msg.encoding not in ENCODINGS:
        raise SessionError(f"{where}: unknown image encoding '{msg.encoding}'; import reads "
                           f"{', '.join(ENCODINGS)} (8-bit colour or grey)")
    channels, conversion = ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    if step < w * channels or data.size < h * step:
        raise SessionError(f"{where}: an Image of {w}x{h} {msg.encoding} with step {step} holds {data.size} bytes; "
                           f"the message is malformed")
    image = data[:h * step].reshape(h, step)[:, :w * channels].reshape(h, w, channels)
    if conversion is None:
        return np.ascontiguousarray(image)
    return cv2.cvtColor(image, conversion)


def _pose_matrix(pose, where: str) -> np.ndarray:
    from lapreco_hil.geometry import pose_from_tum

    p, q = pose.position, pose.orientation
    try:
        return pose_from_tum([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    except ValueError as exc:
        raise SessionError(f"{where}: a PoseStamped whose {exc}") from None


def _joint_order(msg_names, wanted: tuple[str, ...], where: str) -> np.ndarray | None:
    """Index of each wanted joint in the message (None: the message has no names and the right count)."""
    names = list(msg_names)
    if not names:
        return None
    index = {n: i for i, n in enumerate(names)}
    for n in wanted:
        if n not in index:
            raise SessionError(f"{where}: no joint '{n}' in the JointState (it has {', '.join(names)}); pass "
                               f"--joint-names with the bag's names of the robot model's joints, in its order "
                               f"({', '.join(wanted)})")
    return np.array([index[n] for n in wanted])


def import_rosbag(bag: str | Path, out: str | Path, image_topic: str, joints_topic: str | None = None,
                  camera_info_topic: str | None = None, poses_topic: str | None = None, *,
                  robot_model: str = "ecm", tip_frame: str | None = None,
                  hand_eye: str | Path | np.ndarray | None = None,
                  joint_names: tuple[str, ...] | None = None, poses_frame: str = "tip", camera_file: str | None = None,
                  fov_radius_px: float = 0.0, stamps: str = "header", progress: bool = False) -> dict:
    """The bag ``bag`` as a new session folder ``out``. Exactly one pose source: ``joints_topic`` (with
    ``robot_model``, ``tip_frame`` and the hand-eye ``hand_eye``: a handeye.yaml or a 4x4 T_tip_camera; without
    it the session is a calibration session) or ``poses_topic`` (``poses_frame`` tip or camera). The camera is
    the first camera_info message, or ``camera_file`` (OpenCV YAML or ROS camera_info YAML); ROS has no field
    of view, so ``fov_radius_px`` gives the scope's circle. ``joint_names``: the bag's names of the model's
    joints, in the model's order (default: the model's own names). Returns what was written."""
    from rosbags.highlevel import AnyReader

    bag = Path(bag)
    if (joints_topic is None) == (poses_topic is None):
        raise ConfigError("import rosbag: give one pose source, --joints-topic (sensor_msgs/JointState) or "
                          "--poses-topic (geometry_msgs/PoseStamped); a session holds one"
                          + (", not both" if joints_topic else ""))
    if poses_frame not in POSES_FRAMES:
        raise ConfigError(f"import rosbag: --poses-frame '{poses_frame}': use one of {', '.join(POSES_FRAMES)}")
    if stamps not in STAMPS:
        raise ConfigError(f"import rosbag: --stamps '{stamps}': use one of {', '.join(STAMPS)}")
    if camera_info_topic is None and camera_file is None:
        raise ConfigError("import rosbag: no camera: give --camera-info-topic (sensor_msgs/CameraInfo) or --camera "
                          "camera.yaml")
    if not bag.exists():
        raise SessionError(f"{bag}: no such bag (a rosbag2 folder, or its .mcap / .db3 file)")
    try:
        reader = AnyReader([bag], default_typestore=_typestore())
        reader.open()
    except Exception as exc:  # rosbags raises its own error kinds for a folder or file it cannot read
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SessionError(f"{bag}: not a readable ROS bag ({why})") from None
    out = Path(out)
    existed = out.exists()
    try:
        return _import(_Bag(bag, reader), out, image_topic, joints_topic, camera_info_topic, poses_topic,
                       robot_model=robot_model, tip_frame=tip_frame, hand_eye=hand_eye, joint_names=joint_names,
                       poses_frame=poses_frame, camera_file=camera_file, fov_radius_px=fov_radius_px,
                       stamps=stamps, progress=progress)
    except LaprecoError:
        if not existed and out.is_dir():  # a failed import leaves no half-made session behind
            shutil.rmtree(out, ignore_errors=True)
        raise
    finally:
        reader.close()


def _camera(bag: _Bag, topic: str | None, camera_file: str | None, fov_radius_px: float) -> tuple[CameraModel, str]:
    from dataclasses import replace

    from lapreco_hil.calib.files import read_camera_yaml

    if camera_file is not None:
        camera, origin = read_camera_yaml(camera_file), str(camera_file)
    else:
        bag.topic(topic, (CAMERA_INFO_TYPE,), "camera_info topic")
        where = f"{bag.path}: topic '{topic}'"
        first = next((m for _, _, m in bag.messages([topic])), None)
        if first is None:
            raise SessionError(f"{where}: no CameraInfo message; pass --camera camera.yaml instead")
        if max(first.binning_x, 1) > 1 or max(first.binning_y, 1) > 1:
            raise CalibrationError(f"{where}: binned camera_info (binning {first.binning_x}x{first.binning_y}); "
                                   f"pass --camera with the calibration of the images as recorded")
        # (a ROS 1 CameraInfo spells them D and K)
        D, K = getattr(first, "d", getattr(first, "D", ())), getattr(first, "k", getattr(first, "K", ()))
        camera = camera_from_camera_info(first.width, first.height, first.distortion_model, D, K, where)
        origin = topic
    if fov_radius_px:
        camera = replace(camera, fov_radius_px=float(fov_radius_px))
    return camera, origin


def _hand_eye(hand_eye) -> tuple[np.ndarray | None, str | None]:
    """(T_tip_camera, the tip frame the file names) from a handeye.yaml or a 4x4 (None: no hand-eye)."""
    from lapreco_hil.calib.files import read_handeye_yaml

    if isinstance(hand_eye, (str, Path)):
        he = read_handeye_yaml(hand_eye)
        return he["T_tip_camera"], he.get("tip_frame")
    return (None if hand_eye is None else np.asarray(hand_eye, float)), None


def _robot(robot_model: str, tip_frame: str | None, hand_eye):
    """(RobotDescription, URDF path, the model's joint names, their units)."""
    from lapreco_hil.kinematics import load_urdf_model, prismatic_joints
    from lapreco_hil.robot_models import urdf_path
    from lapreco_hil.types import RobotDescription

    T_tip_camera, he_tip_frame = _hand_eye(hand_eye)
    tip_frame = tip_frame or he_tip_frame
    urdf = urdf_path(robot_model)
    tip_frame = tip_frame or DEFAULT_TIP_FRAMES.get(robot_model)
    if not tip_frame:
        raise ConfigError(f"robot model '{robot_model}': pass --tip-frame (the URDF link that holds the scope)")
    model = load_urdf_model(urdf)
    if not model.existFrame(tip_frame):
        raise ConfigError(f"{urdf}: no link '{tip_frame}' (--tip-frame); its frames: "
                          f"{', '.join(f.name for f in model.frames)}")
    names = tuple(model.names[1:])
    units = tuple("length" if p else "angle" for p in prismatic_joints(model))
    return RobotDescription(robot_model, tip_frame, T_tip_camera), urdf, names, units


def _import(bag: _Bag, out: Path, image_topic, joints_topic, camera_info_topic, poses_topic, *, robot_model,
            tip_frame, hand_eye, joint_names, poses_frame, camera_file, fov_radius_px, stamps, progress) -> dict:
    from tqdm import tqdm

    from lapreco_hil.sessions.format import SessionMeta, TrackerSetup
    from lapreco_hil.sessions.writer import SessionWriter
    from lapreco_hil.types import Frame, JointSample, MarkerSample

    image_type = bag.topic(image_topic, IMAGE_TYPES, "image topic")
    pose_topic = joints_topic or poses_topic
    bag.topic(pose_topic, (JOINT_STATE_TYPE,) if joints_topic else (POSE_TYPE,),
              "joints topic" if joints_topic else "poses topic")
    camera, camera_origin = _camera(bag, camera_info_topic, camera_file, fov_radius_px)
    source = {"rosbag": str(bag.path), "image_topic": image_topic, "camera": camera_origin, "stamps": stamps}
    urdf = None
    if joints_topic:
        description, urdf, model_joints, units = _robot(robot_model, tip_frame, hand_eye)
        bag_joints = tuple(joint_names) if joint_names else model_joints
        if len(bag_joints) != len(model_joints):
            raise ConfigError(f"--joint-names gives {len(bag_joints)} names; robot model '{robot_model}' has "
                              f"{len(model_joints)} joints ({', '.join(model_joints)})")
        meta = SessionMeta(camera=camera, pose_source="joints", robot=description, joint_names=model_joints,
                           joint_units=units, source={**source, "joints_topic": joints_topic,
                                                      "joint_names_in_bag": list(bag_joints)})
    elif poses_frame == "camera":
        meta = SessionMeta(camera=camera, pose_source="camera_poses", source={**source, "poses_topic": poses_topic})
    else:
        T = _hand_eye(hand_eye)[0]  # T_tip_camera: the "marker" is the tip
        tool = poses_topic.strip("/") or "pose"
        meta = SessionMeta(camera=camera, pose_source="marker_poses",
                           tracker=TrackerSetup(tool=tool, T_marker_camera=T),
                           source={**source, "poses_topic": poses_topic, "poses_frame": "tip"})

    n_frames = n_samples = skipped = 0
    index = None
    bar = tqdm(total=bag.count(image_topic), desc=f"import {bag.path.name}", unit="frame", file=sys.stderr,
               disable=not progress)
    with SessionWriter(out, meta, urdf_file=urdf) as writer, bar:
        last_frame_t = None
        for topic, log_ns, msg in bag.messages([image_topic, pose_topic]):
            where = f"{bag.path}: topic '{topic}'"
            t = _stamp_ns(msg, log_ns, stamps, where)
            if topic == image_topic:
                image = image_from_message(msg, image_type, where)
                if image.shape[:2] != (camera.height, camera.width):
                    raise SessionError(f"{where}: image is {image.shape[1]}x{image.shape[0]}, the camera "
                                       f"({camera_origin}) is {camera.width}x{camera.height}")
                if last_frame_t is not None and t <= last_frame_t:
                    raise SessionError(f"{where}: frame stamp {t} ns is not after the previous frame's "
                                       f"{last_frame_t} ns; import with --stamps log if the driver's stamps are "
                                       f"not capture times")
                writer.add_frame(Frame(image=image, t_ns=t, seq=n_frames))
                last_frame_t = t
                n_frames += 1
                bar.update(1)
            elif joints_topic:
                if index is None:
                    index = _joint_order(msg.name, bag_joints, where)
                    if index is None and len(msg.position) != len(bag_joints):
                        raise SessionError(f"{where}: a JointState without names and {len(msg.position)} "
                                           f"positions; robot model '{robot_model}' has {len(bag_joints)} joints")
                elif list(msg.name) and len(msg.name) != len(index):
                    index = _joint_order(msg.name, bag_joints, where)
                q = np.asarray(msg.position, float)
                q = q if index is None else q[index]
                skipped += writer.add_joints([JointSample(q, t, n_samples)])
                n_samples += 1
            else:
                T = _pose_matrix(msg.pose, where)
                if poses_frame == "camera":
                    writer.add_camera_pose(t, T)
                else:
                    skipped += writer.add_marker_samples([MarkerSample(T, t, n_samples, meta.tracker.tool, 0.0, True)])
                n_samples += 1
    if n_frames == 0:
        raise SessionError(f"{bag.path}: topic '{image_topic}' has no images")
    if n_samples == 0:
        raise SessionError(f"{bag.path}: topic '{pose_topic}' has no messages; the session has no poses")
    if skipped:
        log.warning("%s: %d of %d pose samples were not imported (%s)", bag.path, skipped, n_samples,
                    writer.last_skipped_joints)
    return {"session": str(out), "frames": n_frames, "pose_source": meta.pose_source, "pose_samples": n_samples,
            "pose_samples_skipped": skipped, "camera": camera_origin,
            "calibration_session": meta.pose_source != "camera_poses" and not _has_hand_eye(meta)}


def _has_hand_eye(meta) -> bool:
    if meta.pose_source == "joints":
        return meta.robot.T_tip_camera is not None
    return meta.tracker.T_marker_camera is not None
