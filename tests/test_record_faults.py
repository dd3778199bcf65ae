"""`record` never fails silently: device faults and health changes reach the console as they happen (rate
limited) and are kept in the session (events.csv, session.json's health); a robot whose readings are all
refused ends the recording with a clear error, and the frames already written stay."""

from __future__ import annotations

import csv
import json
import logging

import numpy as np
import pytest

from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map
from lapreco_hil.errors import DeviceError
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.sessions import Session
from lapreco_hil.sessions.recorder import record
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator
from lapreco_hil.types import RobotDescription


N_FRAMES = 15
GOOD_Q = np.array([0.1, -0.2, 0.12, 0.3])
BEYOND_Q = np.array([0.1, 2.5, 0.12, 0.3])  # pitch far beyond its limits ([-44, 44] degrees)


@pytest.fixture(scope="module")
def source_session(warp_cpu):
    """Frames to record from: the simulated grabber, which beside a live robot runs in real time on the host's
    clock (a replayed session would play recorded time, which a live robot cannot share)."""
    return f"sim://skull?width=160&height=120&fps=10&frames={N_FRAMES}&device={warp_cpu}"


def _record_through_chain(joints_at, source, out):
    with DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map("ecm"), joints_at) as emu:
        context = DeviceContext(device="cpu")
        robot = open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=200", context)
        grabber = open_grabber(source, context)
        with robot, grabber:
            return robot, record(grabber, robot, str(out), camera=grabber.camera,
                                 description=RobotDescription("ecm", "ecm_tip", np.eye(4)), progress=False,
                                 with_truth=False)


def recording_started(folder) -> bool:
    return (folder / "frames.csv").exists()


def _events(folder):
    with open(folder / "events.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_chain_whose_readings_are_all_refused_ends_with_a_clear_error(source_session, tmp_path, caplog):
    out = tmp_path / "rec"
    with caplog.at_level(logging.WARNING), pytest.raises(DeviceError) as err:
        _record_through_chain(lambda t_ns: BEYOND_Q, source_session, out)
    msg = str(err.value)
    assert "\n" not in msg
    assert "none was usable (0 joint samples kept" in msg and "out_of_limits" in msg
    assert "joint 'pitch' = 2.5 rad outside" in msg  # the cause: the joint and its value
    assert f"the {N_FRAMES} frames are saved in {out}" in msg and "lapreco devices --probe serial://" in msg
    # nothing is lost: the frames are on disk and the session is closed
    meta = json.loads((out / "session.json").read_text())
    assert meta["complete"] and meta["counts"]["frames"] == N_FRAMES
    assert (out / "frames.csv").read_text().count("\n") == N_FRAMES + 1
    assert meta["health"]["robot_faults"]["out_of_limits"] > 10
    assert "joint 'pitch' = 2.5" in meta["health"]["last_robot_problem"]
    # the fault is in events.csv and reached the console as it happened, once (rate limited), not per reading
    events = _events(out)
    faults = [e for e in events if e["event"] == "fault:out_of_limits"]
    assert faults and faults[0]["device"].startswith("robot serial://") and "pitch" in faults[0]["detail"]
    assert any(e["event"] == "health:faulted" for e in events)
    live = [m for m in caplog.messages if "fault:out_of_limits" in m]
    assert 1 <= len(live) <= 2 and len(live) < len(faults), caplog.messages
    summary = [m for m in caplog.messages if "faults during the recording" in m]
    assert len(summary) == 1 and "readings refused" in summary[0] and "joint 'pitch' = 2.5" in summary[0]


def test_faults_during_a_recording_are_kept_and_reported(source_session, tmp_path, caplog):
    """Readings refused for the first 0.6 s of the recording, then good: the recording succeeds, and the session
    keeps when the fault came and went."""
    start = []  # when the recording's first frame was taken (the simulated grabber's first frame)

    def joints_at(t_ns):
        if not start and recording_started(out):
            start.append(t_ns)
        return BEYOND_Q if not start or t_ns - start[0] < 600_000_000 else GOOD_Q

    out = tmp_path / "rec"
    with caplog.at_level(logging.WARNING):
        robot, stats = _record_through_chain(joints_at, source_session, out)
    assert stats.frames == N_FRAMES and stats.joint_samples > 20
    assert stats.robot_faults["out_of_limits"] > 5 and stats.events >= 2
    s = Session(out)
    assert s.meta.health["robot_faults"]["out_of_limits"] == stats.robot_faults["out_of_limits"]
    assert s.meta.counts["events"] == stats.events
    states = [e["event"] for e in _events(out) if e["event"].startswith("health:")]
    # it came and went: a later state is not faulted (on a loaded machine a late reply may show the link
    # stale or degraded for a while, each one an event too)
    assert "health:faulted" in states and states[-1] != "health:faulted", states
    summary = [m for m in caplog.messages if "faults during the recording" in m]
    assert len(summary) == 1 and "out_of_limits" in summary[0] and "last: limits: joint 'pitch' = 2.5" in summary[0]


def test_good_readings_are_all_kept_and_no_refusal_is_reported(source_session, tmp_path, caplog):
    """(A loaded machine may lose a reply on the pty now and then: those are timeouts, not refusals.)"""
    out = tmp_path / "rec"
    with caplog.at_level(logging.WARNING):
        _, stats = _record_through_chain(lambda t_ns: GOOD_Q, source_session, out)
    assert stats.frames == N_FRAMES and stats.joint_samples > 20 and stats.skipped_joint_samples == 0
    assert "out_of_limits" not in stats.robot_faults
    events = _events(out) if (out / "events.csv").exists() else []
    assert [e for e in events if e["event"] in ("fault:out_of_limits", "health:faulted")] == []
    assert not [m for m in caplog.messages if "fault:out_of_limits" in m or "none was usable" in m]
    assert len(Session(out).joint_samples) == stats.joint_samples


def test_a_grabber_that_delivers_no_frame_ends_the_recording_with_a_clear_error(tmp_path, warp_cpu):
    """A grabber that gives nothing (here the simulated one asked for 0 frames) must not end in an empty
    session and exit 0: the error names the grabber and what to check; the robot's readings are kept."""
    out = tmp_path / "rec"
    empty = f"sim://skull?width=160&height=120&fps=10&frames=0&device={warp_cpu}"
    with pytest.raises(DeviceError) as err:
        _record_through_chain(lambda t_ns: GOOD_Q, empty, out)
    msg = str(err.value)
    assert "\n" not in msg
    assert f"grabber '{empty}' delivered no frame" in msg and f"the session {out} holds 0 frames" in msg
    assert "lapreco devices --probe sim://" in msg
    assert json.loads((out / "session.json").read_text())["complete"]  # closed, nothing half-written
