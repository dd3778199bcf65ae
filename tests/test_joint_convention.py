"""The Dynamixel driver's joint positions follow the X-series convention (2048 ticks = 0 rad, 2*pi/4096 rad per
tick), checked without the project's JointMap on the device side: the emulator serves raw Present Position
ticks the test chooses, and the expected SI values are computed here from the ticks."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest

from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

TICKS = (1648, 2048, 2748, 2100)  # a chain resting near its centre: yaw, pitch, insertion, roll
LEAD_M = 0.002  # the driver's default lead of the prismatic joint (metres per revolution)
SYNC_READ = 0x82


def expected_si(ticks) -> np.ndarray:
    """What the documented convention gives, from first principles: 2048 ticks is zero, 4096 ticks a turn."""
    per_tick = [2 * math.pi / 4096, 2 * math.pi / 4096, LEAD_M / 4096, 2 * math.pi / 4096]
    return np.array([(t - 2048) * k for t, k in zip(ticks, per_tick)])


def test_raw_ticks_near_the_centre_become_the_documented_si_values_and_every_reading_is_delivered():
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS) as emu:
        robot = open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext())
        with robot:
            time.sleep(1.0)
            samples = robot.read()
            polls = emu.instructions.get(SYNC_READ, 0)
            faults = robot.faults
    assert len(samples) >= 50  # ~100 at 100 Hz; a loaded 2-core machine still makes half
    want = expected_si(TICKS)
    for s in samples:
        np.testing.assert_allclose(s.q, want, rtol=0, atol=1e-12)
    assert want[0] == pytest.approx(-0.6136, abs=1e-4) and want[3] == pytest.approx(0.0798, abs=1e-4)
    assert faults["out_of_limits"] == 0
    # every Sync Read the chain answered became a sample: none refused, none lost except on the link
    lost_on_link = faults["timeouts"] + faults["protocol_errors"]
    assert robot.readings_delivered == len(samples)
    assert polls - lost_on_link - 1 <= len(samples) <= polls  # (-1: a poll in flight when the robot closed)


def test_a_map_file_moves_the_zero_per_joint(tmp_path):
    (tmp_path / "map.toml").write_text('[[joint]]\nname = "yaw"\nzero_count = 1648\nsign = -1\n')
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: (1548, 2048, 2748, 2100)) as emu:
        robot = open_robot(f"serial://{emu.port}?ids=1,2,3,4&map={tmp_path / 'map.toml'}", DeviceContext())
        with robot:
            s = robot.read(timeout_s=1.0)[-1]
    assert s.q[0] == pytest.approx(-(1548 - 1648) * 2 * math.pi / 4096, abs=1e-12)
    np.testing.assert_allclose(s.q[1:], expected_si((1548, 2048, 2748, 2100))[1:], atol=1e-12)


def test_readings_beyond_the_limits_are_refused_with_a_rate_limited_warning(caplog):
    ticks = [3200, 2048, 2048, 2048]  # yaw (3200 - 2048) ticks = 1.77 rad: past its 1.571 rad limit
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: ticks) as emu:
        robot = open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=200", DeviceContext())
        with caplog.at_level(logging.WARNING, logger="lapreco_hil.drivers.robot.polling"), robot:
            time.sleep(0.5)
            assert robot.read() == []
            refused = robot.faults["out_of_limits"]
    warnings = [r.getMessage() for r in caplog.records if "reading refused" in r.getMessage()]
    assert refused >= 20 and robot.readings_delivered == 0
    assert len(warnings) == 1, warnings  # the first at once, the next not before a few seconds
    assert f"Dynamixel bus '{emu.port}'" in warnings[0] and "joint 'yaw' = 1.767 rad (3200 ticks)" in warnings[0]
    assert "[-1.571, 1.571] rad" in warnings[0]
