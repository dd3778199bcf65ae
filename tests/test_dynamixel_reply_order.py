"""Dynamixel driver against its emulator on a pseudo-terminal: Sync Read status packets taken in whatever order
the chain sends them (each by its ID, the values exact)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

from test_robot_drivers import wait_for

# Present Position of servo ID 1..4: distinct, near the centre (2048 = 0 rad), insertion (joint 3) >= 0
TICKS = {1: 2148, 2: 2100, 3: 1900, 4: 2000}



def still_chain(reply_order: str = "request") -> DynamixelChainEmulator:
    ids = [1, 2, 3, 4]
    return DynamixelChainEmulator(ids, ticks_at=lambda t_ns: np.array([TICKS[i] for i in ids]),
                                  reply_order=reply_order)


@pytest.mark.parametrize("url_ids, order", [("4,3,2,1", "ascending"), ("1,2,3,4", "descending"),
                                            ("2,4,1,3", "ascending"), ("4,3,2,1", "request")])
def test_sync_read_replies_in_any_order_give_exact_readings(url_ids, order):
    ids = [int(i) for i in url_ids.split(",")]
    with still_chain(order) as emu:
        with open_robot(f"serial://{emu.port}?ids={url_ids}&rate=100", DeviceContext()) as robot:
            robot.read(timeout_s=1.0)
            time.sleep(0.3)
            samples = robot.read(timeout_s=1.0)
            health, faults = robot.health, robot.faults
    expected = dynamixel_joint_map("ecm").to_si(np.array([TICKS[i] for i in ids]))
    assert len(samples) >= 15, (len(samples), faults)
    for s in samples:  # each joint from its own servo, to the tick
        np.testing.assert_array_equal(s.q, expected)
    assert health.state is HealthState.OK, health
    assert faults["timeouts"] == 0 and faults["protocol_errors"] == 0, faults


def test_the_emulator_orders_its_status_packets_as_asked():
    with pytest.raises(ValueError, match="reply_order must be one of request, ascending, descending"):
        still_chain("random")
