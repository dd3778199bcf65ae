"""``probe_robot``: live readings raw and in SI, the limits, and which readings are beyond them, against the
Dynamixel emulator on a pty and the CiA 402 emulator on python-can's virtual bus."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest

from lapreco_hil.drivers.probe import probe_robot
from lapreco_hil.drivers.robot.joint_map import cia402_joint_map
from lapreco_hil.errors import DeviceNotFoundError
from lapreco_hil.registry import DeviceContext
from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

_channels = itertools.count()


def _row(text: str, joint: str) -> str:
    return next(line for line in text.splitlines() if re.match(rf"\s+{joint}\s", line))


def test_probe_of_a_dynamixel_chain_shows_ticks_si_limits_and_what_is_beyond():
    ticks = (3200, 2048, 2748, 2100)  # yaw 1.767 rad: beyond its limit; the others within theirs
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: ticks) as emu:
        text = probe_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext(), 0.5)
    head = text.splitlines()[0]
    n = int(re.search(r": (\d+) readings", head).group(1))
    assert n >= 20 and "0 delivered" in head and f"{n} refused" in head
    yaw, roll = _row(text, "yaw"), _row(text, "roll")
    assert "3200" in yaw and f"{(3200 - 2048) * 2 * math.pi / 4096:.4g}" in yaw and "[-1.571, 1.571]" in yaw
    assert f"{n} of {n}" in yaw and "BEYOND" in yaw
    assert "2100" in roll and f"{52 * 2 * math.pi / 4096:.4g}" in roll and f"0 of {n}" in roll
    assert "BEYOND" not in roll and "2048" in roll  # the zero of the X-series convention is shown
    assert "check the joint map" in text and "out_of_limits" in text


def test_probe_of_cia402_drives_shows_increments_and_si():
    jm = cia402_joint_map("ecm")
    q = np.array([0.1, -0.2, 0.12, 0.3])
    channel = f"probe-{next(_channels)}"
    with CANopenDriveChainEmulator(channel, [1, 2, 3, 4], jm, lambda t_ns: q):
        text = probe_robot(f"canopen://virtual/{channel}?nodes=1-4&rate=100", DeviceContext(), 0.5)
    counts = jm.to_counts(q)
    head = text.splitlines()[0]
    n = int(re.search(r": (\d+) readings", head).group(1))
    assert n >= 20 and f"{n} delivered, 0 refused" in head
    for name, c, v in zip(jm.names, counts, jm.to_si(counts)):
        row = _row(text, name)
        assert str(c) in row and f"{v:.4g}" in row and f"0 of {n}" in row
    # (a loaded machine may miss a SYNC's replies now and then: a timeout, counted, is not a wrong reading; the
    # replies that came after the wait are discarded and counted as stale_tpdos)
    assert "increments" in text and re.search(r"^faults: (none|(stale_tpdos \d+, )?timeouts \d+)$", text, re.M), text


def test_probe_of_a_missing_port_is_the_driver_s_clear_error():
    with pytest.raises(DeviceNotFoundError, match="serial port '/dev/ttyNOPE' cannot be opened"):
        probe_robot("serial:///dev/ttyNOPE?ids=1,2,3,4", DeviceContext(), 0.1)


def test_probing_absent_canopen_nodes_prints_the_one_line_error_only(caplog, capsys):
    """The canopen library logs each aborted SDO transfer at ERROR: a probe of nodes that do not answer printed
    four of its lines before the driver's own one-line error. They are kept off the console (shown with -v)."""
    import logging

    from lapreco_hil.cli.main import main

    jm = cia402_joint_map("ecm")
    channel = f"probe-{next(_channels)}"
    with CANopenDriveChainEmulator(channel, [1, 2, 3, 4], jm, lambda t_ns: np.zeros(4)):
        with caplog.at_level(logging.WARNING):  # the console's level without -v
            rc = main(["devices", "--probe", f"canopen://virtual/{channel}?nodes=2-5&rate=100"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("lapreco: error:") and "node" in err, err
    assert not [r for r in caplog.records if r.name.startswith("canopen") and r.levelno >= logging.ERROR]


def test_probe_of_a_servo_flagging_an_encoder_error_says_why_its_readings_were_refused():
    """Readings the driver refuses because a servo's Hardware Error Status flags its motor encoder are shown (not
    "0 readings ... no readings"), counted by their cause, with the servo to check rather than the joint map."""
    from lapreco_hil.simulators.dynamixel_emulator import HW_MOTOR_ENCODER

    emu = DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: np.array([2148, 2100, 1900, 2000]))
    emu.faults.hardware_error_status = {2: HW_MOTOR_ENCODER}
    emu.faults.hardware_alert = {2}
    try:
        text = probe_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=100", DeviceContext(), 0.5)
    finally:
        emu.close()
    head = text.splitlines()[0]
    n = int(re.search(r": (\d+) readings", head).group(1))
    assert n >= 20 and "0 delivered" in head and f"{n} refused ({n} for an encoder error the device flags)" in head
    assert "no readings" not in text and "2148" in _row(text, "yaw")
    assert "Hardware Error Status" in text and "not the joint map" in text, text
    assert "check the joint map (zero_count" not in text  # the limits hint: none beyond them
    assert re.search(r"^faults: .*refused_encoder_error \d+", text, re.M), text
