"""The device contract: every back-end declares what callers use, parses its URL into a typed config that
refuses unknown parameters (one shared mechanism), discovers its own devices, and stamps on the run's one
clock (a simulated grabber with a real robot stamps on the host's clock, so a recording of them replays)."""

from __future__ import annotations

import itertools
import re
import time
from collections.abc import Mapping

import numpy as np
import pytest

from lapreco_hil.drivers.device import Discovery, FiniteSource, RecordedSource
from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.drivers.robot.joint_map import cia402_joint_map, dynamixel_joint_map
from lapreco_hil.errors import ConfigError, DeviceError
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

_channels = itertools.count()
SMALL = "width=64&height=48&fps=10"


# --- typed URL configs ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("url, opener", [
    ("serial:///dev/x?colour=red", open_robot),
    ("canopen://virtual/ch?colour=red", open_robot),
    ("v4l2:///dev/video0?colour=red", open_grabber),
    ("sim://skull?colour=red", open_robot),
    ("sim://skull?colour=red", open_grabber),
    ("replay://nowhere?colour=red", open_grabber),
    ("replay://nowhere?colour=red", open_robot),
])
def test_every_back_end_refuses_an_unknown_parameter_and_lists_the_known_ones(url, opener):
    with pytest.raises(ConfigError, match=rf"^device URL '{re.escape(url)}': unknown parameter 'colour' \(known: \w+, "):
        opener(url, DeviceContext())


def test_the_serial_error_lists_its_own_parameters_first():
    with pytest.raises(ConfigError) as exc:
        open_robot("serial:///dev/x?colour=red", DeviceContext())
    assert str(exc.value).startswith("device URL 'serial:///dev/x?colour=red': unknown parameter 'colour' "
                                     "(known: baud, ids, ")
    assert "rate" in str(exc.value) and "map" in str(exc.value)


@pytest.mark.parametrize("url, message", [
    ("serial:///dev/x?ids=0,1,2,252", None),  # Dynamixel Protocol 2.0: 0..252
    ("serial:///dev/x?ids=1,2,3,253", "id 253 outside Dynamixel Protocol 2.0's range 0..252"),
    ("canopen://virtual/ch?nodes=1,2,3,127", None),  # CANopen: 1..127
    ("canopen://virtual/ch?nodes=0-3", "id 0 outside CANopen's range 1..127"),
    ("canopen://virtual/ch?nodes=125-128", "id 128 outside CANopen's range 1..127"),
    ("serial:///dev/x?ids=1,1,2,3", "lists an id twice"),
    ("serial:///dev/x?ids=a,b", "must be numbers like 1,2,3,4 or 1-4"),
    ("serial:///dev/x?rate=5000", "rate must be in 0.1..2000 Hz, got 5000"),
    ("serial:///dev/x?rate=fast", "parameter 'rate=fast' is not a number"),
    ("serial:///dev/x?baud=12345", "'baud=12345' is not an X-series baud rate"),
    ("canopen://virtual/ch?heartbeat_ms=0", "heartbeat_ms must be in 1..65535 ms, got 0"),
    ("sim://skull?link=usb", "link must be one of direct, serial, canopen, got 'usb'"),
    ("sim://skull?instrument=maybe", "'instrument=maybe' must be true or false"),
])
def test_robot_url_values_are_checked_by_type_and_range(url, message):
    if message is None:
        robot = open_robot(url, DeviceContext())
        assert isinstance(robot, RobotDriver)
        return
    with pytest.raises(ConfigError, match=f"device URL '{re.escape(url)}'.*{re.escape(message)}"):
        open_robot(url, DeviceContext())


@pytest.mark.parametrize("url, message", [
    ("v4l2:///dev/video0?fourcc=MJPEG", "'fourcc=MJPEG' must be 4 characters"),
    ("v4l2:///dev/video0?queue=0", "queue must be in 1..1000 frame, got 0"),
    ("v4l2:///dev/video0?width=1.5", "'width=1.5' is not an integer"),
    ("sim://skull?pace=fast", "pace must be one of afap, realtime, got 'fast'"),
    ("sim://skull?frames=-1", "frames must be at least 0, got -1"),
])
def test_grabber_url_values_are_checked_by_type_and_range(url, message):
    with pytest.raises(ConfigError, match=f"device URL '{re.escape(url)}'.*{re.escape(message)}"):
        open_grabber(url, DeviceContext())


def test_configs_are_frozen_dataclasses():
    import dataclasses

    robot = open_robot("canopen://virtual/ch?nodes=3-6&heartbeat_ms=50&rate=20", DeviceContext())
    assert robot.config.nodes == (3, 4, 5, 6) and robot.config.heartbeat_ms == 50 and robot.config.rate == 20.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        robot.config.rate = 1.0


# --- the contract ------------------------------------------------------------------------------------------------

def _check_robot_contract(robot) -> None:
    assert isinstance(robot, RobotDriver)
    assert robot.url.raw and isinstance(robot.faults, Mapping) and robot.faults["never_seen"] == 0
    assert isinstance(robot.readings_delivered, int) and robot.info.joint_names
    assert robot.health.state is not None and robot.clock_domain in ("host", "simulated", "recorded")


def test_every_robot_back_end_declares_the_contract_and_counts_what_it_delivers(warp_cpu):
    jm = cia402_joint_map("ecm")
    channel = f"contract-{next(_channels)}"
    with DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map(), lambda t: np.zeros(4) + 0.01) as dxl, \
            CANopenDriveChainEmulator(channel, [1, 2, 3, 4], jm, lambda t: np.zeros(4) + 0.01):
        for url in (f"serial://{dxl.port}?rate=100", f"canopen://virtual/{channel}?rate=100",
                    f"sim://apple?{SMALL}&speed=1.0"):
            robot = open_robot(url, DeviceContext(device=warp_cpu))
            _check_robot_contract(robot)
            with robot:
                time.sleep(0.2)
                got = len(robot.read(timeout_s=0.5))
                got += len(robot.read(timeout_s=0.5))
            assert got > 0 and robot.readings_delivered == got, url


def test_the_grabber_contract(warp_cpu):
    grabber = open_grabber(f"sim://apple?{SMALL}&frames=3", DeviceContext(device=warp_cpu))
    assert isinstance(grabber, Grabber) and grabber.nominal_fps == 10.0 and grabber.camera is not None
    assert isinstance(grabber.faults, Mapping) and not isinstance(grabber, FiniteSource)
    v4l2 = open_grabber("v4l2:///dev/video0?fps=30", DeviceContext())
    assert v4l2.nominal_fps == 30.0 and v4l2.camera is None and v4l2.ground_truth is None
    assert v4l2.faults["dropped_by_driver"] == 0 and "frames" not in v4l2.faults


# --- discovery -------------------------------------------------------------------------------------------------------

def test_discovery_asks_every_back_end_and_says_why_nothing_was_found(monkeypatch, tmp_path):
    from lapreco_hil.drivers.discovery import discover, format_devices
    from lapreco_hil.drivers.grabber import v4l2
    from lapreco_hil.drivers.robot import canopen402

    monkeypatch.setattr(canopen402, "SYS_NET", tmp_path / "no-sys-class-net")  # a machine without SocketCAN
    monkeypatch.setattr(v4l2, "video_devices", lambda: [])
    found = discover()
    titles = [d.title for d in found]
    assert all(isinstance(d, Discovery) for d in found)
    assert any("Dynamixel" in t for t in titles) and any("V4L2" in t for t in titles)
    assert len([t for t in titles if t.startswith("simulated")]) == 1  # robot and grabber: one entry
    can = next(d for d in found if "CANopen" in d.title)
    assert can.found == () and "cannot look" in can.note and "no-sys-class-net" in can.note
    text = format_devices(found)
    assert "none: no /dev/video* devices" in text and "sim://skull" in text and "replay://" in text


def test_socketcan_interfaces_are_found_by_type(monkeypatch, tmp_path):
    from lapreco_hil.drivers.robot import canopen402

    for name, kind in (("can0", "280"), ("eth0", "1"), ("vcan1", "280")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "type").write_text(kind + "\n")
    monkeypatch.setattr(canopen402, "SYS_NET", tmp_path)
    d = canopen402.CANopenRobot.discover()
    assert [f.address for f in d.found] == ["can0", "vcan1"]
    assert d.found[0].url == "canopen://socketcan/can0?nodes=1-4"
    open_robot(d.found[0].url, DeviceContext())  # the example URL is one the back-end accepts


# --- one clock per run -------------------------------------------------------------------------------------------------

def test_a_sim_grabber_with_a_real_robot_stamps_on_the_host_clock_and_the_recording_replays(tmp_path, warp_cpu):
    from lapreco_hil.sessions.recorder import record
    from lapreco_hil.sessions.session import Session
    from lapreco_hil.types import RobotDescription

    with DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map(), lambda t: np.full(4, 0.02)) as emu:
        context = DeviceContext(device=warp_cpu)
        robot = open_robot(f"serial://{emu.port}?rate=100", context)
        grabber = open_grabber(f"sim://apple?{SMALL}", context)
        world = grabber.world
        description = RobotDescription(world.robot_model, world.tip_frame, world.T_tip_camera)
        with robot, grabber:
            stats = record(grabber, robot, str(tmp_path / "s"), seconds=1.0, description=description,
                           progress=False, with_truth=False)
            frame = grabber.read()
            truth = grabber.ground_truth.camera_pose(frame.t_ns)
    assert abs(frame.t_ns - time.monotonic_ns()) < 1e9  # the host's monotonic clock, not simulated time
    # the truth at a host stamp is the simulated pose at the matching simulated time
    np.testing.assert_allclose(truth, world.true_camera_pose(grabber._timeline.to_sim(frame.t_ns)))
    session = Session(str(tmp_path / "s"))
    t_frames = np.asarray(session.frame_t_ns)
    t_joints = np.array([s.t_ns for s in session.joint_samples])
    assert stats.frames >= 8 and stats.joint_samples >= 50
    # every frame (after the first) lies among joint readings: a pose can be interpolated at it
    inner = t_frames[1:]
    assert np.all(inner >= t_joints[0]) and np.all(inner <= t_joints[-1] + 50_000_000)
    gaps = np.array([np.min(np.abs(t_joints - t)) for t in inner])
    assert np.all(gaps < 50_000_000), gaps
    # and it replays: the replayed robot hands out the readings up to each replayed frame
    context = DeviceContext(device=warp_cpu)
    url = f"replay://{tmp_path / 's'}"
    replay_grabber, replay_robot = open_grabber(url, context), open_robot(url, context)
    assert isinstance(replay_grabber, FiniteSource) and isinstance(replay_grabber, RecordedSource)
    assert len(replay_grabber) == stats.frames and not isinstance(robot, RecordedSource)
    with replay_grabber, replay_robot:
        while replay_grabber.read() is not None:
            replay_robot.read()
    assert replay_robot.readings_delivered == stats.joint_samples


def test_all_simulated_devices_stay_on_simulated_time(warp_cpu):
    from lapreco_hil.simulators.world.world import T0_NS

    context = DeviceContext(device=warp_cpu)
    robot, grabber = open_robot(f"sim://apple?{SMALL}", context), open_grabber(f"sim://apple?{SMALL}", context)
    with robot, grabber:
        frames = [grabber.read() for _ in range(3)]
        samples = robot.read()
    assert [f.t_ns for f in frames] == [T0_NS, T0_NS + 100_000_000, T0_NS + 200_000_000]
    assert samples and samples[-1].t_ns <= frames[-1].t_ns + 100_000_000


def test_clock_mixes_that_cannot_work_are_clear_errors(warp_cpu, tmp_path):
    context = DeviceContext(device=warp_cpu)
    robot = open_robot("serial:///dev/ttyNOPE", context)
    grabber = open_grabber(f"sim://apple?{SMALL}&pace=afap", context)
    with pytest.raises(ConfigError, match="pace=afap runs ahead of real time"):
        grabber.open()
    del robot

    context = DeviceContext(device=warp_cpu)
    grabber = open_grabber(f"sim://apple?{SMALL}", context)
    grabber.open()  # every device so far simulated: the run's clock is fixed to simulated time
    with pytest.raises(ConfigError, match="joins a run whose clock was fixed when 'sim://apple.*' opened"):
        open_robot("serial:///dev/ttyNOPE", context)

    context = DeviceContext()
    open_robot("serial:///dev/ttyNOPE", context)
    with pytest.raises((ConfigError, DeviceError), match="cannot run with the replay"):
        from lapreco_hil.registry import _make, parse_url
        from lapreco_hil.sessions.replay import ReplayGrabber

        class NoSession(ReplayGrabber):  # the clock check, without a session folder
            def __init__(self, url, context):
                self.url = url

        _make(NoSession, parse_url(f"replay://{tmp_path}"), context)


def test_a_back_end_that_cannot_be_imported_is_said_not_raised(monkeypatch):
    from types import MappingProxyType

    from lapreco_hil import registry
    from lapreco_hil.drivers.discovery import discover

    monkeypatch.setattr(registry, "ROBOT_BACKENDS", MappingProxyType({**registry.ROBOT_BACKENDS,
                                                                      "bogus": "lapreco_hil.no_such_module:Bogus"}))
    found = discover()
    bogus = next(d for d in found if d.title == "Bogus")
    assert bogus.found == () and "cannot look (No module named 'lapreco_hil.no_such_module')" in bogus.note
    assert found.index(bogus) < next(i for i, d in enumerate(found) if d.title.startswith("simulated"))


@pytest.mark.parametrize("link", ["direct", "serial"])
def test_a_sim_robot_in_a_run_with_a_real_grabber_stamps_on_the_host_clock(link, warp_cpu):
    context = DeviceContext(device=warp_cpu)
    open_grabber("v4l2:///dev/video7", context)  # a real device in the run (never opened here)
    robot = open_robot(f"sim://apple?{SMALL}&speed=1.0&link={link}", context)
    with robot:
        robot.read(timeout_s=0.5)
        time.sleep(0.3)
        samples = robot.read(timeout_s=0.5)
        now = time.monotonic_ns()
    timeline = robot._timeline
    assert len(samples) >= 10 and abs(samples[-1].t_ns - now) < 200_000_000  # host time, not simulated
    world = robot.world
    # the pose at a host stamp is the simulated arm's at the matching simulated time; through the serial link the
    # stamp and the device's reading lie the link's latency apart (a few ms on a pty, more on a loaded machine)
    lag_s = np.linspace(-0.03, 0.03, 61) if link == "serial" else np.zeros(1)
    for s in samples:
        t_sim = world.seconds(timeline.to_sim(s.t_ns))
        gap = min(np.abs(s.q - world.arm.motor_joints(t_sim - lag)).max() for lag in lag_s)
        assert gap < 2e-3, (s.q, world.arm.motor_joints(t_sim))
