"""Dynamixel hardware-error alert, driver against its emulator on a pseudo-terminal: at each servo's alert onset
its Hardware Error Status (address 70) is read once and its bits named in health; the readings go on while the
positions are good, and with the motor-encoder bit set they are refused (counted), not delivered, until the
alert clears."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.dynamixel_emulator import (HARDWARE_ERROR_STATUS, HW_MOTOR_ENCODER, HW_OVERHEATING,
                                                       HW_OVERLOAD, DynamixelChainEmulator)

from test_robot_drivers import wait_for



def test_the_hardware_error_status_bits_in_words():
    from lapreco_hil.drivers.robot.dynamixel import hardware_error_text

    assert hardware_error_text(0x01) == "hardware error alert: Hardware Error Status (address 70) 0x01: input voltage"
    assert hardware_error_text(0x3D).endswith("0x3D: input voltage, overheating, motor encoder, electrical shock, "
                                              "overload; its positions are not trustworthy: readings refused")
    assert hardware_error_text(0x42).endswith("0x42: bits 0x42")
    assert "could not be read" in hardware_error_text(None)


@pytest.fixture
def chain():
    emu = DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: np.array([2148, 2100, 1900, 2000]))
    robot = open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext())
    robot.open()
    robot.read(timeout_s=1.0)
    yield emu, robot
    robot.close()
    emu.close()


def test_a_hardware_alert_reads_address_70_once_per_onset_and_names_its_bits(chain):
    emu, robot = chain
    emu.faults.hardware_error_status = {3: HW_OVERHEATING | HW_OVERLOAD}
    emu.faults.hardware_alert = {3}
    wait_for(lambda: robot.health.state is HealthState.FAULTED)
    time.sleep(0.3)  # some 30 polls, each with the alert bit
    health = robot.health
    assert emu.reads.get((3, HARDWARE_ERROR_STATUS)) == 1 and len(emu.reads) == 1, emu.reads
    assert "servo 3" in health.detail and "0x24: overheating, overload" in health.detail, health
    assert "refused" not in health.detail
    robot.read()
    assert robot.read(timeout_s=0.5)  # the positions are still good: delivered
    assert robot.faults["refused_encoder_error"] == 0
    emu.faults.hardware_alert = set()
    wait_for(lambda: robot.health.state is HealthState.OK)
    emu.faults.hardware_error_status = {3: HW_OVERHEATING}
    emu.faults.hardware_alert = {3}  # a second onset: read again
    wait_for(lambda: "0x04: overheating" in robot.health.detail)
    assert emu.reads[(3, HARDWARE_ERROR_STATUS)] == 2


def test_a_motor_encoder_error_refuses_the_readings_until_it_clears(chain):
    emu, robot = chain
    emu.faults.hardware_error_status = {2: HW_MOTOR_ENCODER}
    emu.faults.hardware_alert = {2}
    wait_for(lambda: robot.faults["refused_encoder_error"] >= 5)
    health = robot.health
    robot.read()
    time.sleep(0.15)
    during = robot.read()
    assert during == [], during  # untrustworthy positions are not poses
    assert health.state is HealthState.FAULTED, health
    assert "servo 2" in health.detail and "motor encoder" in health.detail and "refused" in health.detail
    assert robot.faults["protocol_errors"] == 0 and emu.reads[(2, HARDWARE_ERROR_STATUS)] == 1
    emu.faults.hardware_alert = set()
    wait_for(lambda: robot.health.state is HealthState.OK)
    refused = robot.faults["refused_encoder_error"]
    robot.read()
    assert robot.read(timeout_s=0.5)
    assert robot.faults["refused_encoder_error"] == refused


def test_readings_refused_for_an_encoder_error_are_in_the_raw_log_with_their_cause(chain):
    from lapreco_hil.drivers.robot.polling import REFUSED_ENCODER_ERROR

    emu, robot = chain
    robot.take_raw_readings()
    emu.faults.hardware_error_status = {2: HW_MOTOR_ENCODER}
    emu.faults.hardware_alert = {2}
    wait_for(lambda: robot.faults["refused_encoder_error"] >= 5)
    time.sleep(0.1)
    refused = [r for r in robot.take_raw_readings() if not r.delivered]
    assert len(refused) >= 5 and {r.refused for r in refused} == {REFUSED_ENCODER_ERROR}
    assert [int(c) for c in refused[-1].counts] == [2148, 2100, 1900, 2000]


def test_the_emulator_uses_the_driver_s_hardware_error_constants():
    """One definition of address 70 and its bits, the driver's: the emulator imports them."""
    import inspect

    from lapreco_hil.drivers.robot import dynamixel as driver
    from lapreco_hil.simulators import dynamixel_emulator as emulator

    source = inspect.getsource(emulator)
    for name in ("HARDWARE_ERROR_STATUS", "HW_INPUT_VOLTAGE", "HW_OVERHEATING", "HW_MOTOR_ENCODER",
                 "HW_ELECTRICAL_SHOCK", "HW_OVERLOAD"):
        assert getattr(emulator, name) == getattr(driver, name)
    # no definition of its own (a module-level assignment of any of them)
    assert not [line for line in source.splitlines() if line.startswith(("HW_", "HARDWARE_ERROR"))]


def test_a_run_and_a_recording_whose_readings_an_encoder_error_refused_name_the_servo_not_the_joint_map():
    from types import SimpleNamespace

    from lapreco_hil.runtime.live import LiveRun
    from lapreco_hil.runtime.metrics import LiveMetrics
    from lapreco_hil.sessions.recorder import RecordStats, _no_joints_message

    last = "servo 2: hardware error alert: Hardware Error Status (address 70) 0x08: motor encoder"
    run = LiveRun.__new__(LiveRun)
    run.metrics = LiveMetrics()
    run.metrics.counts.update(frames_in=20, frames_without_pose=20)
    robot = SimpleNamespace(faults={"refused_encoder_error": 50}, last_fault=last)
    run.poses = SimpleNamespace(rejected=0, rejected_by_cause={}, last_refusal="", robot=robot, source="robot")
    hint = run.why_few_frames()
    assert "refused 50 readings" in hint and "encoder error" in hint and "Hardware Error Status" in hint, hint
    assert "check the servo" in hint and "joint map and units" not in hint, hint
    robot.faults = {"out_of_limits": 50}  # the limits: the joint map is still what to check
    assert "joint map and units" in run.why_few_frames()

    stats = RecordStats(frames=30, joint_samples=0, skipped_joint_samples=0, capture_span_s=1.0, wall_s=1.0,
                        stopped_by="seconds", robot_faults={"refused_encoder_error": 50})
    message = _no_joints_message("serial:///dev/ttyUSB0", "out", stats, 0, 50, last)
    assert "hardware fault" in message and "Hardware Error Status" in message and "check the servo" in message
    assert "(joint map, limits, units)" not in message, message
    stats.robot_faults = {"out_of_limits": 50}
    assert "(joint map, limits, units)" in _no_joints_message("serial:///dev/ttyUSB0", "out", stats, 0, 50, "")
