"""Port handles across sessions, NDI tracker and its emulator on one pseudo-terminal: a probe then a record (two
sessions of the driver, one after the other) both bring the device up; the driver frees its handles (PHF, after
TSTOP) when it closes; a client that died holding handles is no obstacle to the next, whose INIT starts a fresh
handle table; and the emulator's handle table follows the device's (PHRQ, PHF, INIT, RESET)."""

from __future__ import annotations

import numpy as np
import pytest
import serial

from lapreco_hil.drivers.tracker.ndi_protocol import NDIReplyError, check_text_reply, command_bytes
from lapreco_hil.registry import DeviceContext, open_tracker
from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

FAST = "reset_wait_ms=100&timeout_ms=300"


def still_pose(x_mm: float):
    def pose_at(t_ns: int):
        T = np.eye(4)
        T[:3, 3] = [x_mm + 10.0 * np.sin(t_ns * 1e-9), 0.0, -1200.0]
        return T, True
    return pose_at


@pytest.fixture
def rom(tmp_path):
    path = tmp_path / "8700339.rom"
    path.write_bytes(bytes(range(100)))
    return path


def passive_handles(emu: NDITrackerEmulator) -> list[int]:
    return sorted(h for h, t in emu.handles.items() if not t.wired)


def test_a_probe_then_a_record_on_one_emulator(rom):
    from lapreco_hil.app.devices import probe

    with NDITrackerEmulator(passive=[still_pose(0.0)]) as emu:
        url = f"ndi://{emu.port}?rate=60&tools={rom}&{FAST}"
        text = probe(url, 0.5, device="cpu")
        assert "8700339" in text and "no pose" not in text, text
        # the probe's session ended cleanly: tracking stopped, then its handle freed
        log = list(emu.command_log)
        assert log[-2:] == ["TSTOP", "PHF"], log[-6:]
        assert passive_handles(emu) == [] and not emu.tracking
        # the record's session: a second bring-up on the same pty
        with open_tracker(url, DeviceContext()) as tracker:
            assert tracker.tools == ("8700339",)
            samples = tracker.read(timeout_s=1.0)
        assert emu.commands["PHRQ"] == 2 and emu.commands["INIT"] == 2
        assert passive_handles(emu) == []
    assert samples and {s.tool for s in samples} == {"8700339"}


def test_sessions_of_an_aurora_keep_its_wired_handles():
    """A wired sensor's handle is the device's: the driver does not free it on close (a real Aurora may not assign
    a freed one again until the sensor is plugged in again; the emulator behaves so), and the next session's INIT
    initialises it afresh."""
    with NDITrackerEmulator(wired=[still_pose(0.0), still_pose(50.0)]) as emu:
        for session in (1, 2, 3):
            with open_tracker(f"ndi://{emu.port}?rate=40&{FAST}", DeviceContext()) as tracker:
                assert tracker.tools == ("handle 0A", "handle 0B")
                assert tracker.read(timeout_s=1.0)
            assert sorted(emu.handles) == [0x0A, 0x0B] and not emu.tracking
        assert emu.commands["PHF"] == 0 and emu.commands["INIT"] == 3


def test_close_frees_only_the_handles_requested_with_phrq(rom):
    with NDITrackerEmulator(passive=[still_pose(0.0)], wired=[still_pose(50.0)]) as emu:
        for _session in (1, 2):
            with open_tracker(f"ndi://{emu.port}?rate=40&tools={rom}&{FAST}", DeviceContext()) as tracker:
                assert tracker.tools == ("8700339", "handle 0A")
                assert tracker.read(timeout_s=1.0)
            assert list(emu.command_log)[-2:] == ["TSTOP", "PHF"]  # one PHF: the passive tool's handle 01
            assert sorted(emu.handles) == [0x0A]
        assert emu.commands["PHF"] == 2


def test_the_emulator_assigns_a_freed_wired_handle_again_only_once_its_sensor_is_replugged():
    with NDITrackerEmulator(wired=[still_pose(0.0), still_pose(50.0)]) as emu:
        line = Line(emu.port)
        try:
            assert line("INIT:") == "OKAY" and line("PHSR:00") == "020A0010B001"
            assert line("PHF:0A") == "OKAY"
            assert line("INIT:") == "OKAY" and line("PHSR:00") == "010B001"  # not assigned again by INIT
            emu.replug()
            assert line("INIT:") == "OKAY" and line("PHSR:00") == "020A0010B001"
            assert line("PHF:0B") == "OKAY"
            emu.power_blip()  # a power-up finds every plugged-in sensor
            assert sorted(emu.handles) == [0x0A, 0x0B]
        finally:
            line.close()


def test_a_client_that_died_holding_its_handles_is_no_obstacle(rom):
    with NDITrackerEmulator(passive=[still_pose(0.0)]) as emu:
        url = f"ndi://{emu.port}?rate=60&tools={rom}&{FAST}"
        crashed = open_tracker(url, DeviceContext())
        crashed.open()
        assert crashed.read(timeout_s=1.0)
        # the process dies: its reader stops and the port closes, with no TSTOP and no PHF
        crashed._stop.set()
        crashed._thread.join(timeout=2.0)
        crashed._close_port()
        assert emu.tracking and passive_handles(emu) == [1]  # the device still holds the handle, tracking
        with open_tracker(url, DeviceContext()) as tracker:
            assert tracker.tools == ("8700339",) and list(tracker.tool_handles) == [1]
            samples = tracker.read(timeout_s=1.0)
    assert samples


class Line:
    """The host side of the pty by hand: one command, its reply's text (CRC checked)."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, 9600, timeout=0.5)

    def __call__(self, command: str) -> str:
        self.ser.reset_input_buffer()
        self.ser.write(command_bytes(command))
        return check_text_reply(self.ser.read_until(b"\r"), command)

    def close(self) -> None:
        self.ser.close()


def test_the_emulator_s_handle_table_follows_phrq_phf_init_and_reset():
    with NDITrackerEmulator(passive=[still_pose(0.0), still_pose(100.0)], wired=[still_pose(0.0)]) as emu:
        line = Line(emu.port)
        try:
            assert line("INIT:") == "OKAY"
            assert line("PHSR:00") == "010A001"  # a fresh device: the wired tool only
            assert line("PHRQ:*********1****") == "01" and line("PHRQ:*********1****") == "02"
            with pytest.raises(NDIReplyError, match="ERROR2B"):  # both passive tools hold a handle
                line("PHRQ:*********1****")
            assert line("PHF:01") == "OKAY"
            with pytest.raises(NDIReplyError, match="ERROR2B"):  # freed: not a handle any more
                line("PENA:01D")
            with pytest.raises(NDIReplyError, match="ERROR2B"):
                line("PHF:01")
            assert line("PHRQ:*********1****") == "01"  # the freed handle, to the tool that has none
            assert emu.handles[1].pose_at is emu.passive[0]
            assert line("PINIT:0A") == "OKAY" and line("PENA:0AD") == "OKAY"
            assert line("INIT:") == "OKAY"  # a fresh table: no passive handle, the wired one not initialised
            assert line("PHSR:00") == "010A001" and line("PHSR:02") == "010A001" and line("PHSR:04") == "00"
            assert line("PHRQ:*********1****") == "01"
            assert line("RESET:0") == "RESET"  # back to 9600 and a fresh table, not initialised
            assert emu.baud == 9600 and not emu.initialised and passive_handles(emu) == []
        finally:
            line.close()
