"""Dynamixel driver against its emulator on a pseudo-terminal: a status packet that comes after its Sync Read gave
up is never taken as the next Sync Read's reply (status packets carry no sequence number).

The emulator's positions are a function of the Sync Read's number (each servo at its base + that number), so every
delivered reading tells which Sync Read each of its joints answered: all must answer the same one, and the
reading must be stamped within that one's exchange."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

from test_robot_drivers import wait_for

IDS = [1, 2, 3, 4]
BASE = np.array([2148, 2100, 1900, 2000])  # near the centre (2048 = 0 rad), within every joint's limits
WRAP = 1000  # the Sync Read number modulo this: a few hundred ticks at most, and consecutive ones differ


def counting_chain() -> DynamixelChainEmulator:
    """A chain whose Present Position is base + the number of the Sync Read being answered (mod WRAP)."""
    box: list[DynamixelChainEmulator] = []
    emu = DynamixelChainEmulator(IDS, ticks_at=lambda t_ns: BASE + box[0].sync_reads % WRAP)
    box.append(emu)
    return emu


def check_readings(emu: DynamixelChainEmulator, raw) -> int:
    """Every delivered reading answers one Sync Read on all its joints and is stamped within that exchange
    (after the Sync Read before it was answered, before the next one was); the number of readings checked."""
    times = emu.sync_read_times
    checked = 0
    for r in raw:
        if not r.delivered:
            continue
        cycles = np.asarray(r.counts) - BASE
        assert np.all(cycles == cycles[0]), f"a reading mixes Sync Reads {cycles.tolist()} (counts {r.counts})"
        # the Sync Read it answers: the one with that number mod WRAP answered nearest the stamp
        candidates = [n for n in range(1, len(times) + 1) if n % WRAP == cycles[0]]
        n = min(candidates, key=lambda k: abs(times[k - 1] - r.t_ns))
        if n > 1:
            assert r.t_ns > times[n - 2], (n, r.t_ns, times[n - 2])
        if n < len(times):
            assert r.t_ns < times[n], (n, r.t_ns, times[n])
        assert abs(r.t_ns - times[n - 1]) < 40e6, (n, (r.t_ns - times[n - 1]) / 1e6)
        checked += 1
    return checked


def run_with_late_reply(servo: int, late_s: float | None):
    with counting_chain() as emu:
        with open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext()) as robot:
            robot.read(timeout_s=1.0)
            time.sleep(0.1)
            emu.faults.late_reply_s = late_s
            emu.faults.late_reply = (emu.sync_reads + 3, servo)
            wait_for(lambda: emu.late_sent, timeout_s=2.0)
            late_at = emu.late_sent[0][2]
            wait_for(lambda: robot.latest() is not None and robot.latest().t_ns > late_at + 100e6, timeout_s=2.0)
            faults = robot.faults
            raw = robot.take_raw_readings()
    assert any(r.delivered and r.t_ns > late_at for r in raw)  # readings go on after it
    return emu, raw, faults


@pytest.mark.parametrize("servo", [4, 1])
def test_a_reply_landing_in_the_next_sync_read_never_joins_its_reading(servo):
    """The held-back packet comes ahead of the next Sync Read's replies. Servo 4's (the last asked) fills the
    set before the fresh packet of servo 4 comes; servo 1's comes just before its fresh one: both are found."""
    emu, raw, faults = run_with_late_reply(servo, None)
    assert emu.late_sent[0][1] == servo
    assert faults["timeouts"] >= 1  # the Sync Read it belonged to gave up on it
    assert faults["stale_replies"] >= 1, faults
    assert check_readings(emu, raw) >= 10


def test_a_reply_coming_while_the_line_settles_is_dropped_and_counted():
    """45 ms late: past the SDK's Sync Read timeout (about 35 ms), within the quiet wait that follows."""
    emu, raw, faults = run_with_late_reply(3, 0.045)
    assert faults["timeouts"] >= 1
    assert faults["stale_replies"] >= 1, faults
    assert check_readings(emu, raw) >= 10


def test_readings_without_faults_each_answer_their_own_sync_read():
    with counting_chain() as emu:
        with open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext()) as robot:
            robot.read(timeout_s=1.0)
            time.sleep(0.3)
            faults = robot.faults
            raw = robot.take_raw_readings()
    assert check_readings(emu, raw) >= 15
    assert faults["stale_replies"] == 0 and faults["timeouts"] == 0, faults
    assert not emu.late_sent
