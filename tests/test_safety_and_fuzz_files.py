"""Safety (the app never commands motion, opens no network listener) and fuzzing of the file parsers
(session metadata, calibration YAML): random input gives the module's own clear error, nothing else."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from fuzz_settings import FUZZ, mutated
from hypothesis import example, given
from hypothesis import strategies as st

from lapreco_hil.calib.files import read_camera_yaml, read_handeye_yaml
from lapreco_hil.drivers.robot.joint_map import cia402_joint_map, dynamixel_joint_map
from lapreco_hil.config import load_config
from lapreco_hil.errors import CalibrationError, ConfigError, SessionError
from lapreco_hil.kinematics import CameraKinematics
from lapreco_hil.robot_models import urdf_path
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.sessions.format import meta_from_json



def _q(t_ns):
    return np.array([0.1, -0.2, 0.12, 0.3])


def test_drivers_only_read_they_never_command_motion():
    from dynamixel_sdk import PacketHandler  # noqa: F401  (the instructions below are the SDK's codes)

    from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator
    from lapreco_hil.simulators.dynamixel_emulator import INST_PING, INST_SYNC_READ, DynamixelChainEmulator

    with DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map("ecm"), _q) as emu:
        with open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=200", DeviceContext()) as robot:
            time.sleep(0.5)
            assert robot.read()
        assert set(emu.instructions) <= {INST_PING, INST_SYNC_READ}  # no Write, Reg Write, Sync Write, Action
    with CANopenDriveChainEmulator("safety", [1, 2, 3, 4], cia402_joint_map("ecm"), _q) as e:
        with open_robot("canopen://virtual/safety?nodes=1-4&rate=200", DeviceContext()) as robot:
            time.sleep(0.5)
            assert robot.read()
        written = set().union(*e.written.values())
        # only communication set-up (TPDO1 mapping, heartbeat time): never the controlword (0x6040), a target
        # (0x607A position, 0x60FF velocity, 0x6071 torque) or the mode of operation (0x6060)
        assert written <= {0x1800, 0x1A00, 0x1017}, sorted(hex(i) for i in written)


def _listening_inodes() -> set[str]:
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6", "/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for ln in lines:
            cols = ln.split()
            if table.endswith(("tcp", "tcp6")) and cols[3] != "0A":  # TCP LISTEN
                continue
            out.add(cols[9])
    return out


def test_no_network_listener_is_opened_by_a_run(tmp_path, warp_cpu):
    from lapreco_hil.app.demo import run_demo

    run_demo(scene="skull", frames=12, resolution=(256, 192), out=str(tmp_path), device=warp_cpu, tracker="opencv",
             progress=False)
    mine = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            mine.add(target[8:-1])
    assert not (mine & _listening_inodes())


SOURCE = "fuzz/session.json"

VALID = {"format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
         "camera": {"width": 64, "height": 48, "K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "dist": [0.1]},
         "pose_source": "camera_poses", "camera_poses": {"sigma_rotation_rad": 0.001, "sigma_translation_m": 0.0005},
         "time_offset_ns": 0, "complete": True}
VALID_JOINTS = {**VALID, "pose_source": "joints",
                "robot": {"urdf": "ecm", "tip_frame": "ecm_tip", "joint_names": ["yaw", "pitch", "insertion", "roll"],
                          "joint_units": ["angle", "angle", "length", "angle"],
                          "T_tip_camera": np.eye(4).tolist()}}

_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                     lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children,
                                                                                       max_size=5), max_leaves=20)


def assert_valid_meta(meta, doc) -> None:
    """What meta_from_json accepts is a session the rest of lapreco can use: every field in range, and it
    writes back to JSON that reads as the same metadata."""
    from lapreco_hil.sessions.format import ANGLE_UNITS, FORMAT, LENGTH_UNITS, POSE_SOURCES

    assert doc["format"] == FORMAT and doc["version"] == 1 and not isinstance(doc["version"], bool)
    assert meta.length_unit in LENGTH_UNITS and meta.angle_unit in ANGLE_UNITS
    cam = meta.camera
    assert isinstance(cam.width, int) and isinstance(cam.height, int)
    assert 1 <= cam.width <= 16384 and 1 <= cam.height <= 16384
    assert np.all(np.isfinite(cam.K)) and cam.fx > 0 and cam.fy > 0
    assert all(np.isfinite(v) for v in cam.dist) and np.isfinite(cam.fov_radius_px)
    assert meta.pose_source in POSE_SOURCES and isinstance(meta.time_offset_ns, int)
    assert meta.pose_sigma.rotation_rad > 0 and meta.pose_sigma.translation_m > 0
    assert isinstance(meta.complete, bool) and isinstance(meta.counts, dict) and isinstance(meta.source, dict)
    if meta.pose_source == "joints":
        assert meta.robot is not None and meta.joint_names and all(isinstance(n, str) and n for n in meta.joint_names)
    if meta.robot is not None:
        assert len(meta.joint_units) == len(meta.joint_names)
        assert set(meta.joint_units) <= {"angle", "length"} and len(meta.joint_scale) == len(meta.joint_names)
        for T in (meta.robot.T_tip_camera, meta.robot.T_world_base):
            R = T[:3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0
    again = meta_from_json(json.loads(json.dumps(meta.to_json())), SOURCE)
    assert again.camera == meta.camera and again.pose_source == meta.pose_source
    assert again.joint_names == meta.joint_names and again.joint_units == meta.joint_units
    assert again.pose_sigma == meta.pose_sigma and again.time_offset_ns == meta.time_offset_ns


def _read_or_refuse(doc):
    """The metadata, or None after checking the refusal is one SessionError line naming the file."""
    try:
        return meta_from_json(doc, SOURCE)
    except SessionError as exc:
        assert SOURCE in str(exc) and "\n" not in str(exc), str(exc)
        return None


def test_the_valid_metadata_reads_and_a_bad_one_is_refused():
    """Both outcomes of the fuzz tests below are reachable: the sources they mutate read and check valid, and
    one wrong field is refused naming the file and the field."""
    for doc in (VALID, VALID_JOINTS):
        meta = _read_or_refuse(json.loads(json.dumps(doc)))
        assert meta is not None
        assert_valid_meta(meta, doc)
    bad = {**VALID, "camera": {**VALID["camera"], "width": 0}}
    try:
        meta_from_json(bad, SOURCE)
    except SessionError as exc:
        assert str(exc).startswith(SOURCE) and "camera.width" in str(exc)
    else:
        raise AssertionError("a zero image width was accepted")


@FUZZ
@given(_JSON)
def test_random_session_metadata_gives_a_session_error(doc):
    meta = _read_or_refuse(doc)
    if meta is not None:  # (random JSON almost never names the format: then it must be a valid session)
        assert_valid_meta(meta, doc)


@st.composite
def _nested_mutation(draw, source: dict):
    """``source`` with one value anywhere in it (a top-level or a nested field, or a list element) replaced."""
    doc = json.loads(json.dumps(source))
    node = doc
    while True:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        key = draw(st.sampled_from(keys))
        if isinstance(node[key], (dict, list)) and node[key] and draw(st.booleans()):
            node = node[key]
            continue
        node[key] = draw(st.none() | st.booleans() | st.integers(-5, 5) | st.sampled_from([16384, 16385, 70000])
                         | st.floats() | st.floats(-2.0, 2.0) | st.text(max_size=6)
                         | st.lists(st.integers(-2, 2), max_size=4) | st.sampled_from(["m", "mm", "deg", "ns",
                                                                                      "joints", "angle"]))
        return doc


@FUZZ
@given(st.sampled_from([VALID, VALID_JOINTS]).flatmap(_nested_mutation))
# found by a full run (2026-12-07): an infinite distortion coefficient was accepted
@example({**VALID, "camera": {**VALID["camera"], "dist": [float("inf")]}})
def test_mutated_session_metadata_is_read_or_refused_clearly(doc):
    meta = _read_or_refuse(doc)
    if meta is not None:  # accepted: a usable session, whatever was changed
        assert_valid_meta(meta, doc)


@FUZZ
@given(st.binary(max_size=300))
def test_random_calibration_files_give_a_calibration_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("yaml") / "camera.yaml"
    path.write_bytes(data)
    try:
        camera = read_camera_yaml(path)
    except CalibrationError as exc:
        assert "camera.yaml" in str(exc)
    else:
        _assert_valid_camera(camera)
    try:
        hand_eye = read_handeye_yaml(path)
    except CalibrationError as exc:
        assert "camera.yaml" in str(exc)
    else:
        T = hand_eye["T_tip_camera"]
        assert T.shape == (4, 4) and np.all(np.isfinite(T)) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3),
                                                                            atol=1e-5)


def _assert_valid_camera(camera) -> None:
    assert camera.width > 0 and camera.height > 0 and camera.fx > 0 and camera.fy > 0
    assert np.all(np.isfinite(camera.K)) and all(np.isfinite(v) for v in camera.dist)


_VALID_CAMERA_YAML = b"""%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
"""


@FUZZ
@given(mutated(_VALID_CAMERA_YAML))
@example(_VALID_CAMERA_YAML.replace(b"---\nimage_width", b"-$-\n\x00mage_width"))  # found by the 100k run:
# a broken document start leaves a top level that is not a map, and OpenCV asserts on getNode
def test_mutated_calibration_files_are_read_or_refused_clearly(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("yaml") / "camera.yaml"
    path.write_bytes(data)
    try:
        camera = read_camera_yaml(path)
    except CalibrationError as exc:
        assert "camera.yaml" in str(exc)
    else:
        _assert_valid_camera(camera)


def test_the_valid_calibration_file_reads():  # the mutation source above is a file the reader accepts
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "camera.yaml"
        path.write_bytes(_VALID_CAMERA_YAML)
        assert read_camera_yaml(path).fx == 500.0


_ECM_URDF = urdf_path("ecm").read_bytes()


@FUZZ
@given(mutated(_ECM_URDF))
def test_mutated_urdf_loads_or_gives_one_clear_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("urdf") / "robot.urdf"
    path.write_bytes(data)
    try:
        kin = CameraKinematics(str(path), "ecm_tip", np.eye(4))
    except ConfigError as exc:
        assert "robot.urdf" in str(exc) and "\n" not in str(exc)
    else:
        assert np.all(np.isfinite(kin.camera_pose(np.clip(np.zeros(kin.n_joints), kin.info.limits.lower,
                                                            kin.info.limits.upper))))


_CONFIG = b"""[tracker]
max_features = 600
drift_check = true
[mapper]
window_keyframes = 6
[prior]
joint_sigma = [0.003, 0.003, 0.0003, 0.003]
[runtime]
surface_period_s = 1.5
"""


@FUZZ
@given(mutated(_CONFIG))
def test_mutated_config_loads_or_gives_one_clear_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("cfg") / "pipeline.toml"
    path.write_bytes(data)
    try:
        config = load_config(path)
    except ConfigError as exc:
        assert "pipeline.toml" in str(exc) and "\n" not in str(exc)
    else:
        _assert_valid_config(config)


def _assert_valid_config(config) -> None:
    """Every value of an accepted configuration has its declared type, and every number (a count, size,
    rate or threshold) is finite and non-negative."""
    import dataclasses
    import math
    import typing

    from lapreco_hil.config import PipelineConfig

    assert isinstance(config, PipelineConfig)
    todo = [config]
    while todo:
        node = todo.pop()
        hints = typing.get_type_hints(type(node))
        for f in dataclasses.fields(node):
            value, hint = getattr(node, f.name), hints[f.name]
            if dataclasses.is_dataclass(hint):
                assert isinstance(value, hint), f.name
                todo.append(value)
            elif hint is bool:
                assert isinstance(value, bool), f.name
            elif hint in (int, float):
                assert isinstance(value, hint) and not isinstance(value, bool), f.name
                assert math.isfinite(value) and value >= 0, (f.name, value)
            elif typing.get_origin(hint) is tuple:
                assert all(math.isfinite(v) and v >= 0 for v in value), (f.name, value)


def test_the_config_source_loads_valid(tmp_path):  # the mutation source above is a file the loader accepts
    path = tmp_path / "pipeline.toml"
    path.write_bytes(_CONFIG)
    config = load_config(path)
    _assert_valid_config(config)
    assert config.tracker.max_features == 600 and config.mapper.window_keyframes == 6
