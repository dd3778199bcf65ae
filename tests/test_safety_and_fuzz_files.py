"""Safety (the app never commands motion, opens no network listener) and fuzzing of the file parsers
(session metadata, calibration YAML): random input gives the module's own clear error, nothing else."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from fuzz_settings import EXAMPLES, FUZZ, mutated
from hypothesis import example, given
from hypothesis import strategies as st

from lapreco_hil.calib.files import read_camera_yaml, read_handeye_yaml
from lapreco_hil.drivers.robot.joint_map import JointMap
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

    with DynamixelChainEmulator([1, 2, 3, 4], JointMap.for_model("ecm"), _q) as emu:
        with open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=200", DeviceContext()) as robot:
            time.sleep(0.5)
            assert robot.read()
        assert set(emu.instructions) <= {INST_PING, INST_SYNC_READ}  # no Write, Reg Write, Sync Write, Action
    with CANopenDriveChainEmulator("safety", [1, 2, 3, 4], JointMap.for_model("ecm", counts_per_rev=16384), _q) as e:
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


@FUZZ
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children,
                                                                                        max_size=5), max_leaves=20))
def test_random_session_metadata_gives_a_session_error(doc):
    try:
        meta_from_json(doc, "fuzz/session.json")
    except SessionError as exc:
        assert "fuzz/session.json" in str(exc)


VALID = {"format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
         "camera": {"width": 64, "height": 48, "K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "dist": [0.1]},
         "pose_source": "camera_poses"}


@FUZZ
@given(st.sampled_from(sorted(VALID)), st.none() | st.integers(-5, 5) | st.text(max_size=5) | st.floats()
       | st.lists(st.integers(), max_size=3) | st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
def test_mutated_session_metadata_is_read_or_refused_clearly(key, value):
    doc = json.loads(json.dumps(VALID))
    doc[key] = value
    try:
        meta = meta_from_json(doc, "fuzz/session.json")
    except SessionError as exc:
        assert "fuzz/session.json" in str(exc)
    else:
        assert meta.camera.width == 64


@FUZZ
@given(st.binary(max_size=300))
def test_random_calibration_files_give_a_calibration_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("yaml") / "camera.yaml"
    path.write_bytes(data)
    for reader in (read_camera_yaml, read_handeye_yaml):
        try:
            reader(path)
        except CalibrationError as exc:
            assert "camera.yaml" in str(exc)


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
        assert camera.width > 0 and np.all(np.isfinite(camera.K))


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
        load_config(path)
    except ConfigError as exc:
        assert "pipeline.toml" in str(exc) and "\n" not in str(exc)
