"""The Dynamixel emulator runs at a baud rate, as a real chain does: it reads the rate the driver set on the pty
(termios on the slave side) and does not understand a host at any other rate. The driver then fails with a
message that names the bus and says to check the baud rate first; at the matching rate it reads as before."""

from __future__ import annotations

import re

import pytest

from lapreco_hil.errors import DeviceNotFoundError
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator
from lapreco_hil.simulators.pty_emulator import line_baud

TICKS = (2048, 2100, 2148, 1990)


def test_a_host_at_the_wrong_baud_rate_gets_no_answer_and_a_message_about_the_baud_rate():
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS, baud=57600) as emu:
        robot = open_robot(f"serial://{emu.port}?baud=1000000&ids=1,2,3,4&rate=50", DeviceContext())
        with pytest.raises(DeviceNotFoundError) as exc:
            robot.open()
        assert emu.stats["replies"] == 0 and emu.stats["packets"] == 0  # not one packet understood
        assert emu.stats["wrong_baud_bytes"] > 0  # the pings reached the line, at the wrong rate
    message = str(exc.value)
    assert f"Dynamixel bus '{emu.port}' at 1000000 baud" in message  # names the device and the rate tried
    assert re.search(r"no servo answered .*check the baud rate first", message), message
    assert "57600" in message  # the factory setting, the likeliest other rate


def test_the_matching_baud_rate_reads_the_chain():
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS, baud=57600) as emu:
        with open_robot(f"serial://{emu.port}?baud=57600&ids=1,2,3,4&rate=50", DeviceContext()) as robot:
            assert line_baud(emu._slave) == 57600  # what the emulator compares: the rate the driver set
            samples = robot.read(timeout_s=2.0)
            raw = robot.take_raw_readings()
    assert samples or raw
    assert [int(c) for c in raw[-1].counts] == list(TICKS)
    assert emu.stats["wrong_baud_bytes"] == 0


def test_the_default_emulator_rate_is_the_driver_default():  # every existing test opens it without baud=
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS) as emu:
        assert emu.baud == 1_000_000
        with open_robot(f"serial://{emu.port}?ids=1,2,3,4&rate=50", DeviceContext()) as robot:
            robot.read(timeout_s=2.0)
            assert robot.take_raw_readings()
