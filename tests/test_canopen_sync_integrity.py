"""The CANopen driver against drives that behave as CiA 301 allows but our own set-up does not assume: TPDOs that
come after the driver's SYNC wait, a "no RTR" bit the drive will not clear, a static TPDO1 mapping (in another
order), a drive that restarts, EMCY codes canopen has no text for. python-can's in-process virtual bus only.

Every drive of the emulator reports 1000 + the SYNC's number as its position (``count_syncs_from``), so a reading
shows which SYNC each joint answers: all its joints must answer one SYNC, and it must be stamped at that SYNC."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.drivers.robot.cia402 import emcy_description
from lapreco_hil.drivers.robot.joint_map import cia402_joint_map
from lapreco_hil.errors import DeviceError
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator

from test_robot_drivers import wait_for

BASE = 1000  # position = BASE + SYNC number: inside every ECM joint's limits for the few hundred SYNCs of a test
_channels = itertools.count()


def still(t_ns: int) -> np.ndarray:
    return np.array([0.1, -0.2, 0.12, 0.3])



def open_chain(query: str = "", **emulator_options):
    channel = f"sync-{next(_channels)}"
    emu = CANopenDriveChainEmulator(channel, [1, 2, 3, 4], cia402_joint_map("ecm"), still, **emulator_options)
    robot = open_robot(f"canopen://virtual/{channel}?nodes=1-4&rate=100&heartbeat_ms=40{query}", DeviceContext())
    try:
        robot.open()
    except BaseException:
        emu.close()
        raise
    return emu, robot


def read_for(robot, seconds: float, healths: list | None = None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        robot.read(timeout_s=0.01)
        if healths is not None:
            healths.append(robot.health.state)


def check_each_reading_answers_one_sync(emu, readings) -> int:
    """Every delivered reading: all joints from one SYNC, stamped at that SYNC (after the SYNC before it went out,
    no later than this one arrived). The number of readings checked."""
    delivered = [r for r in readings if r.delivered]
    for r in delivered:
        syncs = {int(c) - BASE for c in r.counts}
        assert len(syncs) == 1, f"one reading combines the answers to SYNCs {sorted(syncs)}"
        k = syncs.pop()
        assert r.t_ns <= emu.sync_times[k], f"stamped {(r.t_ns - emu.sync_times[k]) * 1e-6:.2f} ms after SYNC {k}"
        if k - 1 in emu.sync_times:
            assert r.t_ns > emu.sync_times[k - 1], f"reading of SYNC {k} stamped before SYNC {k - 1}"
    return len(delivered)


# --- 1. a TPDO after the wait never joins another SYNC's reading -------------------------------------------------

@pytest.mark.parametrize("times", [1, 2], ids=["once", "twice in a row"])
def test_a_late_tpdo_is_discarded_not_taken_for_the_next_syncs(times):
    emu, robot = open_chain(count_syncs_from=BASE)
    try:
        robot.read(timeout_s=1.0)
        late_sync = emu.stats["syncs"] + 10
        # node 4 answers that SYNC (and the next) 30 ms late (the wait is 20 ms), every other at once
        emu.faults.tpdo_delay = lambda node, k: 0.030 if node == 4 and late_sync <= k < late_sync + times else None
        healths: list[HealthState] = []
        read_for(robot, 0.6, healths)
        assert emu.stats["syncs"] > late_sync + 20
        readings = robot.take_raw_readings()
        assert check_each_reading_answers_one_sync(emu, readings) > 20
        faults = robot.faults
        assert faults["timeouts"] >= 1 and faults["stale_tpdos"] >= 1, faults
        assert HealthState.DEGRADED in healths  # the late frame showed
        wait_for(lambda: robot.health.state is HealthState.OK)  # and it recovers by itself
    finally:
        robot.close()
        emu.close()


@pytest.mark.parametrize("late_nodes", [(4,), (1, 2, 3, 4)], ids=["one node always late", "every node late"])
def test_drives_always_later_than_the_wait_give_no_mixed_or_misdated_reading(late_nodes):
    emu, robot = open_chain(count_syncs_from=BASE)
    try:
        robot.read(timeout_s=1.0)
        emu.faults.tpdo_delay = lambda node, k: 0.025 if node in late_nodes else None
        read_for(robot, 0.6)
        readings = robot.take_raw_readings()
        check_each_reading_answers_one_sync(emu, readings)  # (every reading after the switch is lost)
        faults = robot.faults
        assert faults["stale_tpdos"] >= 5 and faults["timeouts"] >= 5, faults
        health = robot.health
        assert health.state is HealthState.STALE, health
        assert "within 20 ms of SYNC" in health.detail or "discarded" in health.detail, health
        emu.faults.tpdo_delay = None  # the drives are quick again: readings resume, all of one SYNC each
        wait_for(lambda: robot.health.state is HealthState.OK)
        read_for(robot, 0.2)
        assert check_each_reading_answers_one_sync(emu, robot.take_raw_readings()) > 5
    finally:
        robot.close()
        emu.close()


def test_a_late_tpdo_within_the_wait_is_no_fault():
    emu, robot = open_chain(count_syncs_from=BASE)
    try:
        robot.read(timeout_s=1.0)
        robot.take_raw_readings()
        emu.faults.tpdo_delay = lambda node, k: 0.004 if node == 2 else None
        read_for(robot, 0.4)
        assert check_each_reading_answers_one_sync(emu, robot.take_raw_readings()) > 20
        faults = robot.faults  # none, unless a stall of this machine made a wait time out (then counted with it)
        assert faults["stale_tpdos"] <= 4 * faults["timeouts"], faults
    finally:
        robot.close()
        emu.close()


def test_a_frame_lost_once_costs_readings_never_their_integrity():
    emu, robot = open_chain(count_syncs_from=BASE)
    try:
        robot.read(timeout_s=1.0)
        emu.set_silent(3)  # one or two SYNCs unanswered (no frame at all), then node 3 answers on time again
        time.sleep(0.015)
        emu.set_silent(3, False)
        wait_for(lambda: robot.faults["timeouts"] >= 1)
        wait_for(lambda: robot.health.state is HealthState.OK)
        read_for(robot, 0.2)
        assert check_each_reading_answers_one_sync(emu, robot.take_raw_readings()) > 10
    finally:
        robot.close()
        emu.close()


# --- 2. a drive whose TPDOs take no RTR ----------------------------------------------------------------------------

def test_a_drive_that_refuses_rtr_keeps_its_no_rtr_bit():
    emu, robot = open_chain(no_rtr_nodes={1, 2, 3, 4})
    try:
        assert robot.read(timeout_s=1.0)
        for node_id, node in emu.nodes.items():
            assert node.sdo[0x1800][1].raw == 0x40000180 + node_id  # valid, bit 30 kept
            assert node.sdo[0x1800][2].raw == 1
    finally:
        robot.close()
        emu.close()


# --- 3. a static TPDO1 mapping -------------------------------------------------------------------------------------

def test_a_static_mapping_that_holds_statusword_and_position_is_used_as_it_is():
    # position first, then the mode display (8 bits), then statusword: 7 bytes, read-only
    static = [0x60640020, 0x60610008, 0x60410010]
    emu, robot = open_chain(count_syncs_from=BASE, static_tpdo1={n: static for n in (1, 2, 3, 4)})
    try:
        robot.read(timeout_s=1.0)
        read_for(robot, 0.2)
        assert check_each_reading_answers_one_sync(emu, robot.take_raw_readings()) > 10
        assert all(0x1A00 not in emu.written.get(n, set()) for n in emu.nodes)  # the mapping was not touched
        emu.faults.fault_bit_nodes = {2}  # the statusword is decoded from where this mapping puts it
        wait_for(lambda: "node 2 statusword: fault bit set (0x023F)" in robot.health.detail)
        emu.faults.fault_bit_nodes = set()
        wait_for(lambda: robot.health.state is HealthState.OK)
    finally:
        robot.close()
        emu.close()


def test_a_static_mapping_without_position_is_one_clear_error():
    channel = f"sync-{next(_channels)}"
    with CANopenDriveChainEmulator(channel, [1, 2, 3, 4], cia402_joint_map("ecm"), still,
                                   static_tpdo1={3: [0x60410010, 0x606C0020]}):
        robot = open_robot(f"canopen://virtual/{channel}?nodes=1-4", DeviceContext())
        with pytest.raises(DeviceError, match=r"node 3's TPDO1 mapping lacks position actual value 0x6064 and cannot "
                                              r"be changed \(Code 0x06010002.*it maps 0x6041:00 \(16 bits\), "
                                              r"0x606C:00 \(32 bits\)"):
            robot.open()


# --- 4. a drive that restarts ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("boot_up", [True, False], ids=["boot-up message", "boot-up lost, pre-operational heartbeat"])
def test_a_drive_that_restarts_is_configured_again_and_delivers(boot_up):
    emu, robot = open_chain(count_syncs_from=BASE, boot_heartbeat_ms=0 if boot_up else 30)
    try:
        robot.read(timeout_s=1.0)
        restarted_at = emu.stats["syncs"]
        emu.restart(3, boot_up=boot_up)
        healths: list[HealthState] = []
        read_for(robot, 0.8, healths)
        readings = robot.take_raw_readings()
        assert check_each_reading_answers_one_sync(emu, readings) > 20
        assert any(int(r.counts[2]) - BASE > restarted_at + 2 for r in readings if r.delivered)  # node 3 delivers
        assert robot.faults["node_restarts"] == 1, robot.faults
        assert HealthState.DEGRADED in healths
        wait_for(lambda: robot.health.state is HealthState.OK)
        node = emu.nodes[3]
        assert node.sdo[0x1017].raw == 40 and node.sdo[0x1800][2].raw == 1 and node.nmt.state == "OPERATIONAL"
    finally:
        robot.close()
        emu.close()


def test_a_drive_that_restarts_during_a_sync_s_wait_is_no_longer_waited_for(caplog):
    """Node 3 restarts (boot-up) while the master waits for its answer to a SYNC: from then on it owes none, so
    that SYNC costs one timeout, with no wait for a late frame and no SYNC pause after it."""
    import logging
    import threading

    emu, robot = open_chain("&sync_timeout_ms=150", count_syncs_from=BASE)
    restarted_at: list[int] = []

    def restart_while_waited_for(node_id: int, sync_no: int):
        if node_id != 3 or restarted_at:
            return None
        restarted_at.append(sync_no)
        threading.Timer(0.02, emu.restart, (3,)).start()
        return 5.0  # its answer to this SYNC never comes in time (the drive restarts before sending it)

    try:
        robot.read(timeout_s=1.0)
        with caplog.at_level(logging.DEBUG, logger="lapreco_hil.drivers.robot.polling"):
            emu.faults.tpdo_delay = restart_while_waited_for
            wait_for(lambda: robot.faults["node_restarts"] == 1 and robot.faults["timeouts"] >= 1, 3.0)
            k = restarted_at[0]
            wait_for(lambda: k + 1 in emu.sync_times, 2.0)
        first = next(r.getMessage() for r in caplog.records if "no TPDO1 from node(s)" in r.getMessage())
        assert "node(s) 3 within 150 ms" in first, first
        assert "no SYNC for" not in first and "answered later" not in first, first
        gap_s = (emu.sync_times[k + 1] - emu.sync_times[k]) * 1e-9
        assert gap_s < 0.4, gap_s  # the wait (150 ms) and the node's configuration, no drain nor 750 ms pause
    finally:
        robot.close()
        emu.close()


def test_a_restarted_drive_whose_configuration_fails_counts_one_timeout_per_attempt():
    """Configuring a restarted node again fails for about a second (it does not answer SDO yet): it is retried
    every reconnect_interval_s, each failed attempt one timeout, none for the polls of the back-off between."""
    import canopen

    emu, robot = open_chain(count_syncs_from=BASE)
    configure, fail_until = robot._configure_node, [0.0]

    def flaky_configure(node):
        if node.id == 3 and time.monotonic() < fail_until[0]:
            raise canopen.SdoCommunicationError("no SDO response (test)")
        return configure(node)

    robot._configure_node = flaky_configure
    try:
        robot.read(timeout_s=1.0)
        wait_for(lambda: robot.health.state is HealthState.OK)
        before = robot.faults["timeouts"]
        fail_until[0] = time.monotonic() + 1.2
        emu.restart(3)
        wait_for(lambda: robot.faults["node_restarts"] == 1, 1.0)
        wait_for(lambda: time.monotonic() > fail_until[0] and robot.health.state is HealthState.OK, 4.0)
        timeouts = robot.faults["timeouts"] - before
        # attempts at about 0, 0.5 and 1.0 s fail, the next succeeds (plus one SYNC the restart may have cut)
        assert 2 <= timeouts <= 6, robot.faults
        robot.read()
        assert robot.read(timeout_s=1.0)
    finally:
        robot.close()
        emu.close()


# --- 5. EMCY descriptions -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("code, text", [(0x7305, "additional modules"), (0x8130, "monitoring: communication"),
                                        (0x8210, "monitoring: protocol error"), (0x5530, "device hardware"),
                                        (0x4210, "device temperature"), (0xFF01, "device specific"),
                                        (0x0000, "error reset or no error"), (0xA100, "reserved error class 0xA1")])
def test_emcy_codes_are_described_by_their_cia301_class(code, text):
    assert emcy_description(code) == text


def test_an_emcy_canopen_has_no_text_for_says_its_class():
    emu, robot = open_chain()
    try:
        robot.read(timeout_s=1.0)
        emu.send_emcy(2, 0x7305, 0x81)
        wait_for(lambda: "node 2 EMCY: 0x7305 additional modules (error register 0x81)" in robot.health.detail)
    finally:
        robot.close()
        emu.close()


# --- the emulator's CiA 301 rules ------------------------------------------------------------------------------------

def test_the_emulator_refuses_to_remap_a_valid_tpdo():
    import canopen

    from lapreco_hil.drivers.robot.cia402 import cia402_object_dictionary

    channel = f"sync-{next(_channels)}"
    with CANopenDriveChainEmulator(channel, [1], cia402_joint_map("ecm"), still):
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = network.add_node(1, cia402_object_dictionary())
            node.sdo[0x1800][1].raw = 0x181  # valid
            with pytest.raises(canopen.SdoAbortedError, match="0x06010000"):
                node.sdo[0x1A00][0].raw = 0
            with pytest.raises(canopen.SdoAbortedError, match="0x06090030"):
                node.sdo[0x1800][1].raw = 0x182  # a valid PDO's COB-ID changed
            node.sdo[0x1800][1].raw = 0x80000181  # invalid first: then both may change
            node.sdo[0x1A00][0].raw = 0
        finally:
            network.disconnect()
