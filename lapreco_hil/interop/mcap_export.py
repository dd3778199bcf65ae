"""Sessions and runs as MCAP files with Foxglove's schemas (protobuf), to open in Foxglove or any MCAP tool.

Topics (docs/interop.md has the table): each camera's frames as ``foxglove.CompressedImage`` (JPEG) and its
lens as ``foxglove.CameraCalibration``, the joint readings as ``foxglove.JointStates``, the transform tree as
``foxglove.FrameTransforms`` on ``/tf`` at every frame time (world -> base -> tip -> camera for a robot,
world -> tracker -> marker -> camera for a tracked scope, world -> camera for given poses; camera -> each other
camera of a rig), and with a run's result the map: ``/map/points`` (``foxglove.PointCloud``), ``/map/mesh``
(``foxglove.SceneUpdate`` with one triangle list) and ``/map/trajectory`` (``foxglove.PosesInFrame``). Log
and message times are the capture times (the session's clock); the map is logged at the first frame's time so
that it is in view for the whole playback.

:func:`export_mcap` writes a recorded session (and a result folder); :class:`LiveMcapLogger` is the same file
written during ``lapreco run --mcap``, fed by the live runtime's record stage, encoding in a thread of its own.
"""

from __future__ import annotations

import collections
import logging
import threading
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import Rig
from lapreco_hil.errors import ConfigError, OutputError
from lapreco_hil.geometry import inv_T, pose_from_tum, tum_values
from lapreco_hil.interop.camera_info import camera_info_fields

log = logging.getLogger(__name__)

WORLD, BASE, TIP, TRACKER, MARKER = "world", "base", "tip", "tracker", "marker"
TF_TOPIC = "/tf"
JOINTS_TOPIC = "/joint_states"
POINTS_TOPIC, MESH_TOPIC, TRAJECTORY_TOPIC = "/map/points", "/map/mesh", "/map/trajectory"
RESULT_FILES = ("points.ply", "mesh.ply", "trajectory.tum")


def camera_topics(rig: Rig, names) -> list[tuple[str, str, str]]:
    """Per camera of the rig: (image topic, calibration topic, frame id). One camera: /camera/...; a rig:
    /camera/<name>/..."""
    if len(rig) == 1:
        return [("/camera/image/compressed", "/camera/calibration", "camera")]
    return [(f"/camera/{n}/image/compressed", f"/camera/{n}/calibration", f"camera_{n}") for n in names]


def _stamp(t_ns: int):
    from google.protobuf.timestamp_pb2 import Timestamp

    return Timestamp(seconds=int(t_ns) // 1_000_000_000, nanos=int(t_ns) % 1_000_000_000)


def _pose(T: np.ndarray):
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

    tx, ty, tz, qx, qy, qz, qw = tum_values(T)
    return Pose(position=Vector3(x=tx, y=ty, z=tz), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


# --- the transform tree at a time ------------------------------------------------------------------------------

class JointsTree:
    """world -> base (T_world_base) -> tip (forward kinematics of the joints interpolated at the frame time)
    -> camera (the hand-eye, when known: a calibration session has none)."""

    def __init__(self, urdf_file, tip_frame: str, T_tip_camera, T_world_base, offset_ns: int = 0,
                 capacity: int = 4096) -> None:
        from lapreco_hil.kinematics import CameraKinematics, PoseAtTime

        self.T_world_base = np.eye(4) if T_world_base is None else np.asarray(T_world_base, float)
        self.T_tip_camera = None if T_tip_camera is None else np.asarray(T_tip_camera, float)
        kin = CameraKinematics(str(urdf_file), tip_frame, np.eye(4) if T_tip_camera is None else T_tip_camera,
                               self.T_world_base)
        self.kin = kin
        # a live run keeps the recent readings; a session's are all kept (capacity: at least their number)
        self.samples = PoseAtTime(kin, np.zeros(kin.n_joints), 0.0, 0.0, offset_ns=offset_ns, capacity=capacity)

    def add(self, samples) -> None:
        self.samples.extend(samples)

    def covered(self, t_ns: int) -> bool:
        """Whether a reading at or after this frame time has come (live: its transforms can be made)."""
        last = self.samples.last_time_ns
        return last is not None and last >= t_ns + self.samples.offset_ns

    def at(self, t_ns: int, camera_frame: str) -> list[tuple[str, str, np.ndarray]]:
        if self.samples.no_pose_cause(t_ns) is not None:
            return []
        q = self.samples.q_at(t_ns + self.samples.offset_ns)
        T_base_tip = inv_T(self.T_world_base) @ self.kin.tip_pose(q)
        out = [(WORLD, BASE, self.T_world_base), (BASE, TIP, T_base_tip)]
        if self.T_tip_camera is not None:
            out.append((TIP, camera_frame, self.T_tip_camera))
        return out


class PosesTree:
    """world -> camera from given camera poses, or world -> tracker -> marker -> camera from a tracked scope's
    marker poses (``T_marker_camera`` None: a calibration session, the chain ends at the marker)."""

    def __init__(self, offset_ns: int = 0, T_world_tracker=None, T_marker_camera=None, tracked: bool = False,
                 tool: str | None = None, max_rms_mm: float = float("inf"), fixed_gap_ns: float | None = None) -> None:
        from lapreco_hil.pose_sources import PoseTrack

        self.track = PoseTrack(fixed_gap_ns=fixed_gap_ns, capacity=None if fixed_gap_ns is not None else 4096)
        self.offset_ns, self.tracked, self.tool, self.max_rms_mm = offset_ns, tracked, tool, max_rms_mm
        self.T_world_tracker = np.eye(4) if T_world_tracker is None else np.asarray(T_world_tracker, float)
        self.T_marker_camera = None if T_marker_camera is None else np.asarray(T_marker_camera, float)

    def add(self, samples) -> None:
        """Marker samples (the scope's tool's, inside the volume and within the RMS limit, as the replay takes
        them), or (t_ns, T_world_camera) pairs."""
        for s in samples:
            if not self.tracked:
                self.track.add(*s)
            elif s.tool == self.tool and s.in_volume and s.rms_mm <= self.max_rms_mm:
                self.track.add(s.t_ns, s.T_tracker_marker)

    def covered(self, t_ns: int) -> bool:
        last = self.track.last_time_ns
        return last is not None and last >= t_ns + self.offset_ns

    def at(self, t_ns: int, camera_frame: str) -> list[tuple[str, str, np.ndarray]]:
        t = t_ns + self.offset_ns
        if self.track.no_pose_cause(t) is not None:
            return []
        T = self.track(t)
        if not self.tracked:
            return [(WORLD, camera_frame, T)]
        out = [(WORLD, TRACKER, self.T_world_tracker), (TRACKER, MARKER, T)]
        if self.T_marker_camera is not None:
            out.append((MARKER, camera_frame, self.T_marker_camera))
        return out


def session_tree(session):
    """The transform tree of a session, filled with all its samples."""
    from lapreco_hil.geometry import max_gap_ns
    from lapreco_hil.robot_models import urdf_path

    meta = session.meta
    if meta.pose_source == "joints":
        r = session.robot
        tree = JointsTree(urdf_path(r.urdf), r.tip_frame, r.T_tip_camera, r.T_world_base, meta.time_offset_ns,
                          capacity=max(4096, len(session.joint_samples)))
        tree.add(session.joint_samples)
        return tree
    if meta.pose_source == "marker_poses":
        from lapreco_hil.types import MarkerSample

        tr, table = meta.tracker, session.markers
        tree = PosesTree(meta.time_offset_ns, tr.T_world_tracker, tr.T_marker_camera, tracked=True, tool=tr.tool,
                         max_rms_mm=tr.max_rms_mm)
        tree.add(MarkerSample(T, int(t), i, tool, float(rms), bool(inside)) for i, (t, tool, T, rms, inside)
                 in enumerate(zip(table.t_ns, table.tools, table.poses, table.rms_mm, table.in_volume)))
        return tree
    tree = PosesTree(meta.time_offset_ns, fixed_gap_ns=max_gap_ns(session.pose_t_ns))
    tree.add(zip(session.pose_t_ns.tolist(), session.poses))
    return tree


# --- the writer ----------------------------------------------------------------------------------------------

class McapLogger:
    """An MCAP file of Foxglove messages for one rig: call ``log_frame``, ``log_joints``, ``log_transforms``
    and ``log_result`` in time order, then ``close`` (or use it as a context manager). ``counts`` holds the
    messages written per topic."""

    def __init__(self, path: str | Path, rig: Rig, camera_names=("camera",), joint_names=(), jpeg_quality: int = 90,
                 allow_lossy_calibration: bool = True) -> None:
        from mcap_protobuf.writer import Writer

        self.path = Path(path)
        if self.path.is_dir():
            raise OutputError(f"'{self.path}' is a folder; --mcap/--out takes a file name such as run.mcap")
        self.rig, self.joint_names = rig, tuple(joint_names)
        self.topics = camera_topics(rig, camera_names)
        self.jpeg = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        self.counts: collections.Counter[str] = collections.Counter()
        self.calibrations = []
        self.dropped_terms: tuple[str, ...] = ()
        for cam in rig.cameras:
            fields = camera_info_fields(cam, allow_dropping=allow_lossy_calibration)
            self.dropped_terms = self.dropped_terms or fields.dropped
            self.calibrations.append(fields)
        if self.dropped_terms:
            log.warning("%s: the camera's thin-prism terms (%s) have no ROS/Foxglove model; its calibration is "
                        "written as rational_polynomial without them (the images are as recorded)", self.path,
                        ", ".join(self.dropped_terms))
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise OutputError(f"cannot write '{self.path}' ({exc.strerror}); choose another file") from None
        self._writer = Writer(self._file)
        # the other cameras of a rig hang off camera 0
        self.rig_transforms = [(self.topics[0][2], self.topics[k][2], np.asarray(rig.T_cam0_cam[k], float))
                               for k in range(1, len(rig))]
        self.closed = False

    def __enter__(self) -> "McapLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def camera_frame(self) -> str:
        return self.topics[0][2]

    def _write(self, topic: str, message, t_ns: int) -> None:
        self._writer.write_message(topic, message, log_time=int(t_ns), publish_time=int(t_ns))
        self.counts[topic] += 1

    def log_frame(self, frame) -> None:
        """Every camera's image of the frame (JPEG) and its calibration, at the frame's capture time."""
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        stamp = _stamp(frame.t_ns)
        for k, (image_topic, calib_topic, frame_id) in enumerate(self.topics):
            ok, buf = cv2.imencode(".jpg", frame.image_of(k), self.jpeg)
            if not ok:
                raise OutputError(f"{self.path}: cannot encode frame seq {frame.seq} as JPEG")
            self._write(image_topic, CompressedImage(timestamp=stamp, frame_id=frame_id, data=buf.tobytes(),
                                                     format="jpeg"), frame.t_ns)
            c = self.calibrations[k]
            self._write(calib_topic, CameraCalibration(timestamp=stamp, frame_id=frame_id, width=c.width,
                                                       height=c.height, distortion_model=c.distortion_model,
                                                       D=c.D, K=c.K, R=c.R, P=c.P), frame.t_ns)

    def log_joints(self, t_ns: int, q) -> None:
        from foxglove_schemas_protobuf.JointState_pb2 import JointState
        from foxglove_schemas_protobuf.JointStates_pb2 import JointStates

        joints = [JointState(name=n, position=float(v)) for n, v in zip(self.joint_names, np.asarray(q, float))]
        self._write(JOINTS_TOPIC, JointStates(timestamp=_stamp(t_ns), joints=joints), t_ns)

    def log_transforms(self, t_ns: int, transforms) -> None:
        """(parent, child, T_parent_child) triples, with the rig's camera -> camera transforms, on /tf."""
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
        from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
        from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

        stamp, items = _stamp(t_ns), []
        for parent, child, T in [*transforms, *self.rig_transforms]:
            tx, ty, tz, qx, qy, qz, qw = tum_values(T)
            items.append(FrameTransform(timestamp=stamp, parent_frame_id=parent, child_frame_id=child,
                                        translation=Vector3(x=tx, y=ty, z=tz),
                                        rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)))
        self._write(TF_TOPIC, FrameTransforms(transforms=items), t_ns)

    def log_result(self, result_dir: str | Path, t_ns: int) -> dict:
        """A run's map (its output folder: points.ply, mesh.ply, trajectory.tum) in the world frame, at
        ``t_ns``; returns the points, triangles and poses written."""
        result_dir = Path(result_dir)
        missing = [n for n in RESULT_FILES if not (result_dir / n).is_file()]
        if missing:
            raise ConfigError(f"{result_dir}: no {', '.join(missing)}; --result takes a run's output folder "
                              f"('lapreco replay/run --out DIR')")
        points, colors = _read_ply_points(result_dir / "points.ply")
        self._write(POINTS_TOPIC, _point_cloud(points, colors, t_ns), t_ns)
        vertices, vcolors, faces = _read_ply_mesh(result_dir / "mesh.ply")
        self._write(MESH_TOPIC, _scene_update(vertices, vcolors, faces, t_ns), t_ns)
        poses = _read_tum(result_dir / "trajectory.tum")
        from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

        self._write(TRAJECTORY_TOPIC, PosesInFrame(timestamp=_stamp(t_ns), frame_id=WORLD,
                                                   poses=[_pose(T) for T in poses]), t_ns)
        return {"points": len(points), "triangles": len(faces), "trajectory_poses": len(poses)}

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()


def _read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import pyvista as pv

    try:
        cloud = pv.read(str(path))
    except Exception as exc:  # VTK raises several kinds for a bad file
        raise ConfigError(f"{path}: cannot read the point cloud ({exc})") from None
    points = np.asarray(cloud.points, np.float64).reshape(-1, 3)
    rgb = cloud.point_data.get("RGB") if cloud.n_points else None
    colors = np.asarray(rgb, np.uint8).reshape(-1, 3) if rgb is not None else np.full((len(points), 3), 200, np.uint8)
    return points, colors


def _read_ply_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import pyvista as pv

    try:
        mesh = pv.read(str(path))
    except Exception as exc:
        raise ConfigError(f"{path}: cannot read the mesh ({exc})") from None
    if mesh.n_points == 0 or mesh.n_cells == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int64)
    mesh = mesh.triangulate()
    faces = mesh.faces.reshape(-1, 4)[:, 1:] if mesh.faces.size else np.zeros((0, 3), np.int64)
    rgb = mesh.point_data.get("RGB")
    colors = np.asarray(rgb, np.uint8).reshape(-1, 3) if rgb is not None else np.full((mesh.n_points, 3), 200, np.uint8)
    return np.asarray(mesh.points, np.float64), colors, faces


def _read_tum(path: Path) -> list[np.ndarray]:
    poses = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            try:
                poses.append(pose_from_tum([float(v) for v in line.split()[1:8]]))
            except (ValueError, IndexError):
                raise ConfigError(f"{path}: line {lineno}: not 't tx ty tz qx qy qz qw'") from None
    return poses


def _point_cloud(points: np.ndarray, colors: np.ndarray, t_ns: int):
    """x, y, z float32 and red, green, blue, alpha uint8: 16 bytes a point."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    packed = np.zeros(len(points), np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)]))
    packed["xyz"] = points
    packed["rgba"][:, :3] = colors
    packed["rgba"][:, 3] = 255
    F32, U8 = PackedElementField.NumericType.FLOAT32, PackedElementField.NumericType.UINT8
    fields = [PackedElementField(name=n, offset=4 * i, type=F32) for i, n in enumerate("xyz")]
    fields += [PackedElementField(name=n, offset=12 + i, type=U8)
               for i, n in enumerate(("red", "green", "blue", "alpha"))]
    return PointCloud(timestamp=_stamp(t_ns), frame_id=WORLD, pose=_pose(np.eye(4)), point_stride=16,
                      fields=fields, data=packed.tobytes())


def _scene_update(vertices: np.ndarray, colors: np.ndarray, faces: np.ndarray, t_ns: int):
    from foxglove_schemas_protobuf.Color_pb2 import Color
    from foxglove_schemas_protobuf.Point3_pb2 import Point3
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive

    rgba = np.hstack([np.asarray(colors, float) / 255.0, np.ones((len(colors), 1))])
    triangles = TriangleListPrimitive(pose=_pose(np.eye(4)), points=[Point3(x=x, y=y, z=z) for x, y, z in vertices],
                                      colors=[Color(r=r, g=g, b=b, a=a) for r, g, b, a in rgba],
                                      indices=np.asarray(faces, np.int64).ravel().tolist())
    entity = SceneEntity(timestamp=_stamp(t_ns), frame_id=WORLD, id="mesh", triangles=[triangles])
    return SceneUpdate(entities=[entity])


# --- a recorded session --------------------------------------------------------------------------------------

def export_mcap(session_dir: str | Path, out_path: str | Path, result_dir: str | Path | None = None,
                jpeg_quality: int = 90, progress: bool = False) -> dict:
    """A session (docs/session-format.md) as an MCAP file, with a run's result (its output folder) when given.
    Returns the messages written per topic, the frames without transforms (no pose at their time) and, with a
    result, the points, triangles and poses of the map."""
    import sys

    from tqdm import tqdm

    from lapreco_hil.sessions import Session

    session = Session(session_dir)
    meta = session.meta
    tree = session_tree(session)
    if result_dir is not None:  # before writing anything: a wrong folder leaves no half-written file
        missing = [n for n in RESULT_FILES if not (Path(result_dir) / n).is_file()]
        if missing:
            raise ConfigError(f"{result_dir}: no {', '.join(missing)}; --result takes a run's output folder "
                              f"('lapreco replay/run --out DIR')")
    # frames and joint readings in time order: MCAP readers and Foxglove play a file best written in order
    events = [(int(t), 0, i) for i, t in enumerate(session.frame_t_ns)]
    events += [(s.t_ns, 1, i) for i, s in enumerate(session.joint_samples)]
    events.sort()
    without_tf = 0
    mcap = McapLogger(out_path, session.rig, meta.camera_names, meta.joint_names, jpeg_quality)
    try:
        map_stats = mcap.log_result(result_dir, int(session.frame_t_ns[0])) if result_dir is not None else {}
        for t, kind, i in tqdm(events, desc=f"mcap {Path(out_path).name}", unit="msg", file=sys.stderr,
                               disable=not progress):
            if kind == 1:
                mcap.log_joints(t, session.joint_samples[i].q)
                continue
            mcap.log_frame(session.frame(i))
            transforms = tree.at(t, mcap.camera_frame)
            without_tf += not transforms
            if transforms or mcap.rig_transforms:
                mcap.log_transforms(t, transforms)
    except BaseException:
        mcap.close()
        Path(out_path).unlink(missing_ok=True)  # a failed export leaves no half-written file
        raise
    mcap.close()
    counts, dropped = dict(mcap.counts), mcap.dropped_terms
    return {"file": str(out_path), "topics": counts, "frames": len(session), "frames_without_transforms": without_tf,
            "calibration_terms_dropped": list(dropped), **({"map": map_stats} if map_stats else {})}


# --- a live run ------------------------------------------------------------------------------------------------

class LiveMcapLogger:
    """The MCAP file of ``lapreco run --mcap``, fed like a session recorder (``add_frame``, ``add_joints``: the
    live runtime's Record stage hands it what it records). It never slows the run: items go into a bounded
    queue of its own (the oldest frame dropped and counted when full) and one thread encodes and writes them.
    A frame's transforms wait until a pose sample at or after its time has come (its pose is interpolated, as
    the pipeline's); ``close(result_dir)`` writes what is left and, given the run's output folder, the map."""

    def __init__(self, path: str | Path, rig: Rig, tree, camera_names=("camera",), joint_names=(),
                 jpeg_quality: int = 90, queue_frames: int = 8) -> None:
        self.mcap = McapLogger(path, rig, camera_names, joint_names, jpeg_quality)
        self.tree, self.queue_frames = tree, queue_frames
        self.joints = bool(joint_names)
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._done = False
        self._pending: collections.deque[int] = collections.deque()  # frame times waiting for their pose
        self.first_t_ns: int | None = None
        self.dropped_frames = self.frames_without_transforms = 0
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="mcap-logger", daemon=True)
        self._thread.start()

    def _put(self, item, is_frame: bool) -> None:
        with self._cond:
            if is_frame and sum(kind == "frame" for kind, _ in self._q) >= self.queue_frames:
                oldest = next(i for i, (kind, _) in enumerate(self._q) if kind == "frame")
                del self._q[oldest]
                self.dropped_frames += 1
            self._q.append(item)
            self._cond.notify()

    def add_frame(self, frame) -> None:
        self._put(("frame", frame), True)

    def add_joints(self, samples) -> int:
        self._put(("samples", list(samples)), False)
        return 0

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._q and not self._done:
                    self._cond.wait(0.2)
                if not self._q:
                    return
                kind, item = self._q.popleft()
            if self.error is not None:
                continue  # a failed file is not written further; the run goes on (the error is reported)
            try:
                self._handle(kind, item)
            except Exception as exc:  # a full disk must not stop the run: one error, the file left as it is
                self.error = f"{type(exc).__name__}: {exc}"
                log.error("MCAP log '%s' stopped: %s", self.mcap.path, self.error)

    def _handle(self, kind: str, item) -> None:
        if kind == "frame":
            if self.first_t_ns is None:
                self.first_t_ns = item.t_ns
            self.mcap.log_frame(item)
            self._pending.append(item.t_ns)
        else:
            self.tree.add(item)
            if self.joints:
                for s in item:
                    self.mcap.log_joints(s.t_ns, s.q)
        self._flush_transforms(final=False)

    def _flush_transforms(self, final: bool) -> None:
        while self._pending and (final or self.tree.covered(self._pending[0])):
            t = self._pending.popleft()
            transforms = self.tree.at(t, self.mcap.camera_frame)
            self.frames_without_transforms += not transforms
            if transforms or self.mcap.rig_transforms:
                self.mcap.log_transforms(t, transforms)

    def finish_stream(self) -> dict:
        """Write what is queued and the transforms still waiting; returns the counts (for report.json)."""
        with self._cond:
            self._done = True
            self._cond.notify()
        self._thread.join()
        if self.error is None:
            try:
                self._flush_transforms(final=True)
            except Exception as exc:
                self.error = f"{type(exc).__name__}: {exc}"
        return self.summary()

    def summary(self) -> dict:
        return {"file": str(self.mcap.path), "topics": dict(self.mcap.counts), "dropped_frames": self.dropped_frames,
                "frames_without_transforms": self.frames_without_transforms, "error": self.error}

    def close(self, result_dir: str | Path | None = None) -> dict:
        """Finish the stream, add the map from ``result_dir`` (a run's output folder), close the file."""
        if not self._done:
            self.finish_stream()
        try:
            if result_dir is not None and self.error is None and self.first_t_ns is not None:
                self.mcap.log_result(result_dir, self.first_t_ns)
        finally:
            self.mcap.close()
        return self.summary()


class RecorderFanOut:
    """Several recorders behind the one the live runtime's Record stage feeds (a session and an MCAP log)."""

    def __init__(self, *recorders) -> None:
        self.recorders = [r for r in recorders if r is not None]

    def add_frame(self, frame) -> None:
        for r in self.recorders:
            r.add_frame(frame)

    def add_joints(self, samples) -> int:
        return max([r.add_joints(samples) for r in self.recorders] or [0])


def live_logger_for(path: str | Path, rig: Rig, camera_names, *, description=None, joint_names=(),
                    tracker_setup=None, offset_ns: int = 0, jpeg_quality: int = 90) -> LiveMcapLogger:
    """The live MCAP log of a robot run (``description``: URDF, tip, hand-eye) or a tracked one
    (``tracker_setup``)."""
    from lapreco_hil.robot_models import urdf_path

    if tracker_setup is not None:
        tree = PosesTree(offset_ns, tracker_setup.T_world_tracker, tracker_setup.T_marker_camera, tracked=True,
                         tool=tracker_setup.tool, max_rms_mm=tracker_setup.max_rms_mm)
        joint_names = ()
    else:
        tree = JointsTree(urdf_path(description.urdf), description.tip_frame, description.T_tip_camera,
                          description.T_world_base, offset_ns)
    return LiveMcapLogger(path, rig, tree, camera_names, joint_names, jpeg_quality)
