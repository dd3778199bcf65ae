"""MCAP export (read back with the mcap reader), ROS 2 bag import (bags written here with rosbags' writer, MCAP
and sqlite3, replayed to the same result as the session they were made from), the live MCAP log, and ROS
camera_info files (docs/interop.md)."""

from __future__ import annotations

import collections
import json
import shutil

import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.cli.main import main
from lapreco_hil.errors import CalibrationError, ConfigError, OutputError, SessionError
from lapreco_hil.geometry import pose_from_tum, tum_values
from lapreco_hil.sessions import Session

MODEL_JOINTS = ("yaw", "pitch", "insertion", "roll")  # the packaged ECM model's joints
DVRK_JOINTS = ("outer_yaw", "outer_pitch", "insertion", "outer_roll")


# --- fixtures ---------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def source(small_skull_session, tmp_path_factory):
    """The small simulated skull session with a lens ROS can describe (plumb_bob: the simulator's thin-prism
    terms set to zero), so that a bag carries the whole camera."""
    path = tmp_path_factory.mktemp("interop") / "source"
    shutil.copytree(small_skull_session, path)
    doc = json.loads((path / "session.json").read_text())
    doc["camera"]["dist"] = doc["camera"]["dist"][:5]
    (path / "session.json").write_text(json.dumps(doc))
    return path


@pytest.fixture(scope="module")
def source_result(source, tmp_path_factory):
    from lapreco_hil.app.replay import run_replay

    out = tmp_path_factory.mktemp("interop") / "source-result"
    report = run_replay(str(source), str(out), tracker="opencv", device="cpu", progress=False, surface="alpha")
    assert report["inliers"] > 10
    return out


def read_mcap(path) -> dict[str, list]:
    """topic -> [(log_time, schema name, decoded protobuf message)] in log-time order."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = collections.defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out[channel.topic].append((message.log_time, schema.name, decoded))
    return out


def tf_matrix(transform) -> np.ndarray:
    t, q = transform.translation, transform.rotation
    return pose_from_tum([t.x, t.y, t.z, q.x, q.y, q.z, q.w])


def pipeline_pose(session: Session, t_ns: int) -> np.ndarray:
    """The camera pose the pipeline gives a frame (FK at the readings around it, interpolated on SE(3))."""
    from lapreco_hil.kinematics import CameraKinematics, PoseAtTime
    from lapreco_hil.robot_models import urdf_path

    r = session.robot
    kin = CameraKinematics(str(urdf_path(r.urdf)), r.tip_frame, r.T_tip_camera, r.T_world_base)
    poses = PoseAtTime(kin, np.zeros(kin.n_joints), 0.0, 0.0)
    poses.extend(session.joint_samples)
    return poses.prior_at(t_ns).T_world_camera


# --- MCAP export ------------------------------------------------------------------------------------------------

def test_export_reads_back_with_the_mcap_reader(source, source_result, tmp_path):
    import pyvista as pv

    session = Session(source)
    out = tmp_path / "session.mcap"
    assert main(["export", "mcap", str(source), "--result", str(source_result), "--out", str(out),
                 "--no-progress"]) == 0
    msgs = read_mcap(out)
    n = len(session)
    expected = {"/camera/image/compressed": ("foxglove.CompressedImage", n),
                "/camera/calibration": ("foxglove.CameraCalibration", n), "/tf": ("foxglove.FrameTransforms", n),
                "/joint_states": ("foxglove.JointStates", len(session.joint_samples)),
                "/map/points": ("foxglove.PointCloud", 1), "/map/mesh": ("foxglove.SceneUpdate", 1),
                "/map/trajectory": ("foxglove.PosesInFrame", 1)}
    assert {t: (m[0][1], len(m)) for t, m in msgs.items()} == expected
    frame_times = session.frame_t_ns.tolist()
    for topic in ("/camera/image/compressed", "/camera/calibration", "/tf"):
        assert [t for t, _, _ in msgs[topic]] == frame_times, topic
    # images: the frames, within JPEG's losses, stamped with their capture times
    for i, (t, _, image) in enumerate(msgs["/camera/image/compressed"]):
        decoded = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
        assert image.format == "jpeg" and image.timestamp.ToNanoseconds() == t
        assert np.abs(decoded.astype(int) - session.frame(i).image.astype(int)).mean() < 3.0
    cam = session.camera
    calib = msgs["/camera/calibration"][0][2]
    assert (calib.width, calib.height, calib.distortion_model) == (cam.width, cam.height, "plumb_bob")
    np.testing.assert_array_equal(np.reshape(calib.K, (3, 3)), cam.K)
    np.testing.assert_array_equal(calib.D, cam.dist_array[:5])
    # the tf chain world -> base -> tip -> camera is the pipeline's camera pose at each frame time
    for t, _, tf in msgs["/tf"]:
        chain = {(x.parent_frame_id, x.child_frame_id): tf_matrix(x) for x in tf.transforms}
        assert list(chain) == [("world", "base"), ("base", "tip"), ("tip", "camera")]
        T = chain["world", "base"] @ chain["base", "tip"] @ chain["tip", "camera"]
        T_pipeline = pipeline_pose(session, t)
        assert np.abs(T[:3, 3] - T_pipeline[:3, 3]).max() < 2e-6  # q interpolated vs SE(3): micrometres
        assert np.abs(T[:3, :3] - T_pipeline[:3, :3]).max() < 1e-5
    # joints: every reading, by name
    t, _, js = msgs["/joint_states"][5]
    assert t == session.joint_samples[5].t_ns and [j.name for j in js.joints] == list(MODEL_JOINTS)
    np.testing.assert_allclose([j.position for j in js.joints], session.joint_samples[5].q, rtol=0, atol=1e-12)
    # the map: as many points as points.ply, where points.ply has them
    ply = pv.read(str(source_result / "points.ply"))
    cloud = msgs["/map/points"][0][2]
    assert cloud.frame_id == "world" and len(cloud.data) == cloud.point_stride * ply.n_points
    xyz = np.frombuffer(cloud.data, np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)]))["xyz"]
    np.testing.assert_allclose(xyz, ply.points, atol=1e-6)
    mesh = pv.read(str(source_result / "mesh.ply"))
    triangles = msgs["/map/mesh"][0][2].entities[0].triangles[0]
    assert len(triangles.points) == mesh.n_points and len(triangles.indices) == 3 * mesh.n_cells
    tum = [ln for ln in (source_result / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(msgs["/map/trajectory"][0][2].poses) == len(tum)


def test_export_of_a_thin_prism_lens_names_the_dropped_terms(small_skull_session, tmp_path):
    from lapreco_hil.interop.mcap_export import export_mcap

    result = export_mcap(small_skull_session, tmp_path / "s.mcap")
    assert result["calibration_terms_dropped"] == ["s1", "s3"]  # the simulator's lens has s1, s3
    calib = read_mcap(tmp_path / "s.mcap")["/camera/calibration"][0][2]
    assert calib.distortion_model == "rational_polynomial"
    np.testing.assert_array_equal(calib.D, Session(small_skull_session).camera.dist_array[:8])


def test_export_refuses_a_folder_without_a_result_and_a_folder_as_file(source, tmp_path):
    from lapreco_hil.interop.mcap_export import export_mcap

    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match=r"empty: no points\.ply, mesh\.ply, trajectory\.tum; --result"):
        export_mcap(source, tmp_path / "x.mcap", result_dir=tmp_path / "empty")
    assert not (tmp_path / "x.mcap").exists()
    with pytest.raises(OutputError, match="is a folder"):
        export_mcap(source, tmp_path / "empty")


def test_live_logger_waits_for_the_readings_after_each_frame(source, tmp_path):
    """Fed as the live Record stage feeds it (a frame before the readings that cover it), the log has every
    frame's transforms, equal to the export's."""
    from lapreco_hil.interop.mcap_export import RecorderFanOut, export_mcap, live_logger_for

    session = Session(source)
    logger = live_logger_for(tmp_path / "live.mcap", session.rig, ("camera",), description=session.robot,
                             joint_names=MODEL_JOINTS)
    samples = session.joint_samples
    fan = RecorderFanOut(None, logger)
    j = 0
    for i in range(len(session)):
        fan.add_frame(session.frame(i))
        batch = []
        while j < len(samples) and samples[j].t_ns <= session.frame_t_ns[i]:
            batch.append(samples[j])
            j += 1
        fan.add_joints(batch)
    fan.add_joints(samples[j:])
    summary = logger.close()
    assert summary["error"] is None and summary["dropped_frames"] == 0
    assert summary["frames_without_transforms"] == 0
    live = read_mcap(tmp_path / "live.mcap")
    export_mcap(source, tmp_path / "export.mcap")
    exported = read_mcap(tmp_path / "export.mcap")
    assert {t: len(m) for t, m in live.items()} == {t: len(m) for t, m in exported.items()}
    for (t1, _, a), (t2, _, b) in zip(live["/tf"], exported["/tf"]):
        assert t1 == t2 and [(x.parent_frame_id, x.child_frame_id) for x in a.transforms] == \
            [(x.parent_frame_id, x.child_frame_id) for x in b.transforms]
        for x, y in zip(a.transforms, b.transforms):
            np.testing.assert_array_equal(tf_matrix(x), tf_matrix(y))


def test_export_of_a_stereo_rig(source, tmp_path):
    """A version-2 session of two cameras: each camera's topics and frame, the right one 5 mm along x of the
    left on /tf."""
    from lapreco_hil.interop.mcap_export import export_mcap

    stereo = tmp_path / "stereo"
    shutil.copytree(source, stereo)
    doc = json.loads((stereo / "session.json").read_text())
    cam = doc.pop("camera")
    cam.pop("fov_radius_px")
    right = np.eye(4)
    right[0, 3] = 0.005
    doc.update(version=2, rig={"cameras": [{"name": "left", **cam}, {"name": "right", **cam}],
                               "T_cam0_cam": [np.eye(4).tolist(), right.tolist()]})
    (stereo / "session.json").write_text(json.dumps(doc))
    rows = (stereo / "frames.csv").read_text().splitlines()[1:]
    (stereo / "frames.csv").write_text("seq,t_ns,camera,file\n" + "".join(
        f"{r.split(',')[0]},{r.split(',')[1]},{k},{r.split(',')[2]}\n" for r in rows for k in (0, 1)))
    result = export_mcap(stereo, tmp_path / "stereo.mcap")
    n = len(rows)
    assert result["topics"] == {"/camera/left/image/compressed": n, "/camera/left/calibration": n,
                                "/camera/right/image/compressed": n, "/camera/right/calibration": n, "/tf": n,
                                "/joint_states": len(Session(source).joint_samples)}
    msgs = read_mcap(tmp_path / "stereo.mcap")
    assert msgs["/camera/right/calibration"][0][2].frame_id == "camera_right"
    last = msgs["/tf"][0][2].transforms[-1]
    assert (last.parent_frame_id, last.child_frame_id) == ("camera_left", "camera_right")
    np.testing.assert_allclose(tf_matrix(last), right, atol=1e-12)


@pytest.mark.slow
def test_lapreco_run_logs_live_to_mcap(source, tmp_path):
    out, mcap = tmp_path / "run", tmp_path / "run.mcap"
    url = f"replay://{source.as_posix()}"
    assert main(["run", "--robot", url, "--grabber", url, "--out", str(out), "--mcap", str(mcap), "--tracker",
                 "opencv", "--device", "cpu", "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    msgs = read_mcap(mcap)
    n_in = report["frames"]["in"]
    logged = report["mcap"]["topics"]["/camera/image/compressed"]
    # a logger that falls behind (JPEG encoding on a loaded machine) drops frames and counts them, never the run's
    assert report["mcap"]["error"] is None
    assert logged == n_in - report["mcap"]["dropped_frames"] - report["frames"]["dropped_record"] > 0
    assert len(msgs["/camera/image/compressed"]) == logged
    assert [t for t, _, _ in msgs["/tf"]] == [t for t, _, _ in msgs["/camera/image/compressed"]]
    import pyvista as pv

    cloud = msgs["/map/points"][0][2]
    assert len(cloud.data) // cloud.point_stride == pv.read(str(out / "points.ply")).n_points == report["inliers"]


# --- ROS 2 bags ---------------------------------------------------------------------------------------------------

def write_bag(path, frames, camera: CameraModel, *, storage="mcap", image="rgb8", distortion_model="plumb_bob",
              joints=None, joint_names=MODEL_JOINTS, poses=None, camera_info=True):
    """A ROS 2 bag as a camera driver and a robot would record it: per frame an image and a camera_info on
    /camera/left/..., joint readings on /ECM/measured_js, poses on /ECM/measured_cp; header stamps = capture
    times. ``frames``: [(t_ns, BGR image)]; ``joints``: [(t_ns, q)]; ``poses``: [(t_ns, T)]."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]

    def header(t, frame_id):
        return Header(stamp=Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), frame_id=frame_id)

    def image_msg(t, bgr):
        if image in ("png", "jpeg"):
            ok, buf = cv2.imencode("." + ("jpg" if image == "jpeg" else "png"), bgr)
            return T["sensor_msgs/msg/CompressedImage"](header=header(t, "camera"), format=image,
                                                       data=buf.ravel().astype(np.uint8))
        pixels = {"rgb8": lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), "bgr8": lambda: bgr,
                  "mono8": lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)}.get(image, lambda: bgr)()
        channels = 1 if pixels.ndim == 2 else 3
        return T["sensor_msgs/msg/Image"](header=header(t, "camera"), height=pixels.shape[0], width=pixels.shape[1],
                                          encoding=image, is_bigendian=0, step=pixels.shape[1] * channels,
                                          data=np.ascontiguousarray(pixels).ravel())

    n_coeffs = {"plumb_bob": 5, "rational_polynomial": 8}.get(distortion_model, 5)
    c = camera
    info = dict(height=c.height, width=c.width, distortion_model=distortion_model,
                d=np.array(c.dist[:n_coeffs], float), k=np.array([c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1], float),
                r=np.eye(3).ravel(), p=np.array([c.fx, 0, c.cx, 0, 0, c.fy, c.cy, 0, 0, 0, 1, 0], float),
                binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        image_type = T["sensor_msgs/msg/CompressedImage" if image in ("png", "jpeg") else "sensor_msgs/msg/Image"]
        topic = "/camera/left/image_raw" + ("/compressed" if image in ("png", "jpeg") else "")
        conn = {"image": w.add_connection(topic, image_type.__msgtype__, typestore=ts)}
        if camera_info:
            conn["info"] = w.add_connection("/camera/left/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        if joints is not None:
            conn["joints"] = w.add_connection("/ECM/measured_js", "sensor_msgs/msg/JointState", typestore=ts)
        if poses is not None:
            conn["poses"] = w.add_connection("/ECM/measured_cp", "geometry_msgs/msg/PoseStamped", typestore=ts)
        events = [(t, 0, i) for i, (t, _) in enumerate(frames)]
        events += [(t, 1, i) for i, (t, _) in enumerate(joints or [])]
        events += [(t, 2, i) for i, (t, _) in enumerate(poses or [])]
        for t, kind, i in sorted(events):
            if kind == 0:
                msg = image_msg(t, frames[i][1])
                w.write(conn["image"], t, ts.serialize_cdr(msg, msg.__msgtype__))
                if camera_info:
                    msg = T["sensor_msgs/msg/CameraInfo"](header=header(t, "camera"), **info)
                    w.write(conn["info"], t, ts.serialize_cdr(msg, msg.__msgtype__))
            elif kind == 1:
                q = np.asarray(joints[i][1], float)
                order = [3, 1, 0, 2]  # a driver's own name order: the import matches names, not positions
                msg = T["sensor_msgs/msg/JointState"](header=header(t, ""), name=[joint_names[k] for k in order],
                                                      position=q[order], velocity=np.zeros(0), effort=np.zeros(0))
                w.write(conn["joints"], t, ts.serialize_cdr(msg, msg.__msgtype__))
            else:
                tx, ty, tz, qx, qy, qz, qw = tum_values(poses[i][1])
                Point, Quaternion = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
                pose = T["geometry_msgs/msg/Pose"](position=Point(x=tx, y=ty, z=tz),
                                                   orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
                msg = T["geometry_msgs/msg/PoseStamped"](header=header(t, "ECM_base"), pose=pose)
                w.write(conn["poses"], t, ts.serialize_cdr(msg, msg.__msgtype__))
    return path


def session_frames(session: Session):
    return [(int(session.frame_t_ns[i]), session.frame(i).image) for i in range(len(session))]


def session_joints(session: Session):
    return [(s.t_ns, s.q) for s in session.joint_samples]


@pytest.fixture(scope="module")
def hand_eye_file(source, tmp_path_factory):
    from lapreco_hil.calib.files import write_handeye_yaml

    path = tmp_path_factory.mktemp("interop") / "handeye.yaml"
    r = Session(source).robot
    write_handeye_yaml(path, r.T_tip_camera, "ecm", r.tip_frame)
    return path


def test_an_imported_mcap_bag_is_the_session_and_replays_to_the_same_result(source, source_result, hand_eye_file,
                                                                            tmp_path):
    from lapreco_hil.app.replay import run_replay

    src = Session(source)
    bag = write_bag(tmp_path / "bag", session_frames(src), src.camera, storage="mcap", image="rgb8",
                    joints=session_joints(src), joint_names=DVRK_JOINTS)
    out = tmp_path / "imported"
    assert main(["import", "rosbag", str(bag), "--image-topic", "/camera/left/image_raw", "--camera-info-topic",
                 "/camera/left/camera_info", "--joints-topic", "/ECM/measured_js", "--joint-names",
                 ",".join(DVRK_JOINTS), "--hand-eye", str(hand_eye_file), "--fov-radius",
                 repr(src.camera.fov_radius_px), "--out", str(out), "--no-progress"]) == 0
    imp = Session(out)
    assert imp.camera == src.camera and imp.meta.joint_names == MODEL_JOINTS
    np.testing.assert_array_equal(imp.frame_t_ns, src.frame_t_ns)
    np.testing.assert_array_equal(imp.frame_seq, src.frame_seq)
    for i in range(len(src)):
        np.testing.assert_array_equal(imp.frame(i).image, src.frame(i).image)
    assert [s.t_ns for s in imp.joint_samples] == [s.t_ns for s in src.joint_samples]
    np.testing.assert_array_equal([s.q for s in imp.joint_samples], [s.q for s in src.joint_samples])
    np.testing.assert_array_equal(imp.robot.T_tip_camera, src.robot.T_tip_camera)
    assert imp.robot.tip_frame == src.robot.tip_frame

    report = run_replay(str(out), str(tmp_path / "result"), tracker="opencv", device="cpu", progress=False,
                        surface="alpha")
    before = json.loads((source_result / "report.json").read_text())
    assert report["inliers"] == before["inliers"] and report["funnel"] == before["funnel"]
    a = np.loadtxt(source_result / "trajectory.tum")
    b = np.loadtxt(tmp_path / "result" / "trajectory.tum")
    assert a.shape == b.shape and np.abs(a - b).max() < 1e-6


def test_a_sqlite3_bag_of_png_images_and_a_rational_lens(source, tmp_path):
    src = Session(source)
    c = src.camera
    rational = CameraModel(c.width, c.height, c.fx, c.fy, c.cx, c.cy, (*c.dist[:5], 0.012, -0.004, 0.0007))
    bag = write_bag(tmp_path / "bag", session_frames(src)[:4], rational, storage="sqlite3", image="png",
                    distortion_model="rational_polynomial", joints=session_joints(src))
    assert any(p.suffix == ".db3" for p in bag.iterdir())
    from lapreco_hil.interop.rosbag_import import import_rosbag

    result = import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw/compressed", "/ECM/measured_js",
                           "/camera/left/camera_info")
    assert result["frames"] == 4 and result["calibration_session"]  # no hand-eye given: a calibration session
    imp = Session(tmp_path / "s")
    assert imp.camera == rational and imp.robot.T_tip_camera is None
    for i in range(4):
        np.testing.assert_array_equal(imp.frame(i).image, src.frame(i).image)
    # exported, a calibration session's tree ends at the tip (no hand-eye yet); the lens goes out as it came in
    from lapreco_hil.interop.mcap_export import export_mcap

    export_mcap(tmp_path / "s", tmp_path / "s.mcap")
    msgs = read_mcap(tmp_path / "s.mcap")
    assert [(x.parent_frame_id, x.child_frame_id) for x in msgs["/tf"][0][2].transforms] == [("world", "base"),
                                                                                           ("base", "tip")]
    calib = msgs["/camera/calibration"][0][2]
    assert calib.distortion_model == "rational_polynomial" and tuple(calib.D) == rational.dist[:8]


@pytest.mark.parametrize("encoding", ["jpeg", "mono8", "bgr8"])
def test_image_encodings(source, tmp_path, encoding):
    src = Session(source)
    frames = session_frames(src)[:2]
    bag = write_bag(tmp_path / "bag.mcap", frames, src.camera, image=encoding, joints=session_joints(src))
    from lapreco_hil.interop.rosbag_import import import_rosbag

    topic = "/camera/left/image_raw" + ("/compressed" if encoding == "jpeg" else "")
    import_rosbag(bag, tmp_path / "s", topic, "/ECM/measured_js", "/camera/left/camera_info")
    imp = Session(tmp_path / "s")
    for i, (_, bgr) in enumerate(frames):
        got = imp.frame(i).image.astype(int)
        if encoding == "mono8":
            np.testing.assert_array_equal(got, cv2.cvtColor(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR))
        elif encoding == "jpeg":
            assert np.abs(got - bgr.astype(int)).mean() < 3.0
        else:
            np.testing.assert_array_equal(got, bgr)


def test_pose_stamped_makes_a_marker_or_camera_pose_session(source, hand_eye_file, tmp_path):
    """The dVRK's measured_cp (the tip in the base) with the hand-eye, or camera poses: the camera pose the
    imported session gives each frame is the source's."""
    from lapreco_hil.interop.rosbag_import import import_rosbag
    from lapreco_hil.kinematics import CameraKinematics
    from lapreco_hil.pose_sources import GivenPoseSource, MarkerPoseSource
    from lapreco_hil.robot_models import urdf_path

    src = Session(source)
    r = src.robot
    kin = CameraKinematics(str(urdf_path(r.urdf)), r.tip_frame, r.T_tip_camera, r.T_world_base)
    tips = [(s.t_ns, kin.tip_pose(s.q)) for s in src.joint_samples]
    cams = [(s.t_ns, kin.camera_pose(s.q)) for s in src.joint_samples]
    frames = session_frames(src)[:3]
    for kind, poses in (("tip", tips), ("camera", cams)):
        bag = write_bag(tmp_path / f"{kind}.mcap", frames, src.camera, poses=poses)
        out = tmp_path / f"s-{kind}"
        result = import_rosbag(bag, out, "/camera/left/image_raw", None, "/camera/left/camera_info",
                               "/ECM/measured_cp", hand_eye=hand_eye_file, poses_frame=kind)
        imp = Session(out)
        assert result["pose_source"] == imp.meta.pose_source == {"tip": "marker_poses", "camera": "camera_poses"}[kind]
        if kind == "tip":
            assert imp.meta.tracker.tool == "ECM/measured_cp"
            source_ = MarkerPoseSource(imp.meta.tracker, table=imp.markers)
        else:
            source_ = GivenPoseSource(imp.pose_t_ns, imp.poses, 0.002, 0.0005)
        for t, _ in frames:
            T = source_.prior_at(t).T_world_camera
            expected = pipeline_pose(src, t)
            assert np.abs(T[:3, 3] - expected[:3, 3]).max() < 1e-7
            assert np.abs(T[:3, :3] - expected[:3, :3]).max() < 1e-6
        # exported: the tree of a tracked scope (world -> tracker -> marker -> camera) or of given poses
        from lapreco_hil.interop.mcap_export import export_mcap

        export_mcap(out, tmp_path / f"{kind}-export.mcap")
        tfs = read_mcap(tmp_path / f"{kind}-export.mcap")["/tf"]
        assert [t for t, _, _ in tfs] == [t for t, _ in frames]
        for t, _, tf in tfs:
            chain = [(x.parent_frame_id, x.child_frame_id, tf_matrix(x)) for x in tf.transforms]
            names = [("world", "tracker"), ("tracker", "marker"), ("marker", "camera")] if kind == "tip" else \
                [("world", "camera")]
            assert [c[:2] for c in chain] == names
            T = np.linalg.multi_dot([np.eye(4)] + [c[2] for c in chain])
            assert np.abs(T - source_.prior_at(t).T_world_camera).max() < 1e-9


@pytest.fixture
def tiny_bag(tmp_path):
    """Three 16x12 frames with camera_info and joints: for the refusals."""
    cam = CameraModel(16, 12, 20.0, 20.0, 8.0, 6.0)
    frames = [(1_000_000_000 + 40_000_000 * i, np.full((12, 16, 3), 40 * i, np.uint8)) for i in range(3)]
    joints = [(1_000_000_000 + 10_000_000 * i, np.array([0.0, 0.1, 0.1, 0.0])) for i in range(12)]
    return write_bag(tmp_path / "tiny", frames, cam, joints=joints), cam, frames, joints


def test_refusals_name_the_topic_and_what_to_do(tiny_bag, tmp_path, capsys):
    from lapreco_hil.interop.rosbag_import import import_rosbag

    bag, cam, frames, joints = tiny_bag
    args = ["import", "rosbag", str(bag), "--image-topic", "/camera/left/image_raw", "--camera-info-topic",
            "/camera/left/camera_info", "--joints-topic", "/ECM/measured_js", "--out", str(tmp_path / "s")]
    bad_topic = [a if a != "/ECM/measured_js" else "/PSM1/measured_js" for a in args]
    assert main(bad_topic + ["--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no topic '/PSM1/measured_js' (joints topic); the bag's topics: " \
        "/ECM/measured_js (sensor_msgs/msg/JointState, 12 messages), /camera/left/camera_info" in err
    assert not (tmp_path / "s").exists()
    with pytest.raises(SessionError, match="topic '/camera/left/camera_info' carries sensor_msgs/msg/CameraInfo; "
                                           "the image topic must be"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/camera_info", "/ECM/measured_js", "/camera/left/camera_info")
    with pytest.raises(SessionError, match=r"no joint 'Yaw' in the JointState \(it has roll, pitch, yaw, "
                                           r"insertion\); pass --joint-names"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js", "/camera/left/camera_info",
                      joint_names=("Yaw", "pitch", "insertion", "roll"))
    with pytest.raises(ConfigError, match="give one pose source"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js", "/camera/left/camera_info",
                      "/ECM/measured_cp")
    with pytest.raises(ConfigError, match="no camera: give --camera-info-topic"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js", None)
    assert not (tmp_path / "s").exists()  # nothing is left behind by a refused import
    with pytest.raises(SessionError, match="not a readable ROS bag"):
        (tmp_path / "junk.mcap").write_bytes(b"not a bag")
        import_rosbag(tmp_path / "junk.mcap", tmp_path / "s", "/a", "/b", "/c")


def test_unknown_encoding_and_no_camera_info_messages(tmp_path):
    from lapreco_hil.interop.rosbag_import import import_rosbag

    cam = CameraModel(16, 12, 20.0, 20.0, 8.0, 6.0)
    frames = [(1_000_000_000 + 40_000_000 * i, np.zeros((12, 16, 3), np.uint8)) for i in range(2)]
    joints = [(1_000_000_000 + 10_000_000 * i, np.zeros(4)) for i in range(8)]
    bag = write_bag(tmp_path / "enc", frames, cam, image="16UC1", joints=joints)
    with pytest.raises(SessionError, match=r"topic '/camera/left/image_raw': unknown image encoding '16UC1'; "
                                           r"import reads bgr8, rgb8, mono8"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js", "/camera/left/camera_info")
    assert not (tmp_path / "s").exists()
    bag = write_bag(tmp_path / "noinfo", frames, cam, joints=joints, camera_info=False)
    with pytest.raises(SessionError, match=r"no topic '/camera/left/camera_info' \(camera_info topic\)"):
        import_rosbag(bag, tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js", "/camera/left/camera_info")
    # a camera_info topic that never got a message
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    with Writer(tmp_path / "empty", version=9) as w:
        w.add_connection("/camera/left/camera_info", "sensor_msgs/msg/CameraInfo",
                         typestore=get_typestore(Stores.ROS2_HUMBLE))
        w.add_connection("/camera/left/image_raw", "sensor_msgs/msg/Image", typestore=get_typestore(Stores.ROS2_HUMBLE))
        w.add_connection("/ECM/measured_js", "sensor_msgs/msg/JointState", typestore=get_typestore(Stores.ROS2_HUMBLE))
    with pytest.raises(SessionError, match="no CameraInfo message; pass --camera camera.yaml instead"):
        import_rosbag(tmp_path / "empty", tmp_path / "s", "/camera/left/image_raw", "/ECM/measured_js",
                      "/camera/left/camera_info")


# --- camera_info --------------------------------------------------------------------------------------------------

ROS_YAML = """image_width: 640
image_height: 480
camera_name: left
camera_matrix:
  rows: 3
  cols: 3
  data: [500.5, 0, 319.25, 0, 501.5, 241.75, 0, 0, 1]
distortion_model: rational_polynomial
distortion_coefficients:
  rows: 1
  cols: 8
  data: [-0.25, 0.08, 0.001, -0.0005, -0.01, 0.002, 0.0003, -0.0001]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [500.5, 0, 319.25, 0, 0, 501.5, 241.75, 0, 0, 0, 1, 0]
"""


def test_camera_info_yaml_read_by_the_lens_loader_and_written_back(tmp_path):
    """A file as camera_calibration_parsers writes it is read wherever a lens file is taken (OpenCV or ROS,
    told apart from the file), and written back the same."""
    from lapreco_hil.calib.files import read_camera_yaml, write_camera_yaml
    from lapreco_hil.interop.camera_info import read_camera_info_yaml, write_camera_info_yaml

    (tmp_path / "left.yaml").write_text(ROS_YAML)
    cam = read_camera_yaml(tmp_path / "left.yaml")
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (640, 480, 500.5, 501.5, 319.25, 241.75)
    assert cam.dist[:8] == (-0.25, 0.08, 0.001, -0.0005, -0.01, 0.002, 0.0003, -0.0001) and not any(cam.dist[8:])
    write_camera_info_yaml(tmp_path / "again.yaml", cam, "left")
    assert read_camera_info_yaml(tmp_path / "again.yaml") == cam
    write_camera_yaml(tmp_path / "opencv.yaml", cam)  # and next to it, OpenCV's
    assert read_camera_yaml(tmp_path / "opencv.yaml") == cam
    # a file missing a key: one line naming the file and the key (whichever key is missing)
    for key, cut in (("image_height", "image_height: 480\n"),
                     ("distortion_model", "distortion_model: rational_polynomial\n"),
                     ("camera_matrix", ROS_YAML[ROS_YAML.index("camera_matrix"):ROS_YAML.index("distortion_model")])):
        (tmp_path / "cut.yaml").write_text(ROS_YAML.replace(cut, ""))
        with pytest.raises(CalibrationError, match=rf"cut\.yaml: missing (or non-integer )?'{key}'") as info:
            read_camera_yaml(tmp_path / "cut.yaml")
        assert "\n" not in str(info.value)


def test_camera_info_fields_both_ways():
    from lapreco_hil.interop.camera_info import camera_from_camera_info, camera_info_fields

    cam = CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5, (-0.2, 0.05, 0.001, 0.002, -0.01))
    f = camera_info_fields(cam)
    assert f.distortion_model == "plumb_bob" and len(f.D) == 5 and f.K == (50.0, 0, 31.5, 0, 51.0, 23.5, 0, 0, 1)
    assert camera_from_camera_info(64, 48, f.distortion_model, f.D, f.K, "here") == cam
    assert camera_from_camera_info(64, 48, "", [], f.K, "here") == CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5)
    with pytest.raises(CalibrationError, match="here: the camera is uncalibrated"):
        camera_from_camera_info(64, 48, "plumb_bob", f.D, [0.0] * 9, "here")
    with pytest.raises(CalibrationError, match="distortion_model 'equidistant' is not one of plumb_bob, "
                                               "rational_polynomial"):
        camera_from_camera_info(64, 48, "equidistant", [0.1, 0.0, 0.0, 0.0], f.K, "here")
    prism = CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5, (0.0,) * 8 + (0.001,))
    with pytest.raises(CalibrationError, match="no thin-prism model"):
        camera_info_fields(prism)
    assert camera_info_fields(prism, allow_dropping=True).dropped == ("s1",)
