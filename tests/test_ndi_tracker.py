"""The NDI tracker driver (``ndi://``): the Combined API's CRC and its TX / BX replies decoded from bytes built
here from the documented layout (not by the emulator's encoder), then the driver against the NDI emulator on
a pseudo-terminal: poses in metres equal to the served ones (scalar-first quaternions), MISSING and
out-of-volume tools counted and shown in health, corrupted replies counted and never delivered, the
RESET-less bring-up, and random bytes in a BX reply (hypothesis)."""

from __future__ import annotations

import re
import struct
import time
from collections.abc import Mapping

import numpy as np
import pytest
from fuzz_settings import FUZZ, mutated
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.drivers.tracker.base import TrackerDriver
from lapreco_hil.drivers.tracker.ndi_protocol import (HANDLE_DISABLED, HANDLE_MISSING, HANDLE_VALID, NDIReplyError,
                                                      ReplyCRCError, check_text_reply, command_bytes, crc16_arc,
                                                      parse_bx, parse_tx, pose_matrix)
from lapreco_hil.errors import ConfigError, DeviceError, DeviceNotFoundError, ProtocolError
from lapreco_hil.registry import DeviceContext, open_tracker
from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

FAST = "reset_wait_ms=100&timeout_ms=300"


def crc_arc_bitwise(data: bytes) -> int:
    """CRC-16/ARC bit by bit (poly 0x8005 reflected = 0xA001, init 0), independent of the driver's table."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def wait_for(predicate, timeout_s: float = 3.0) -> None:
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError("condition not reached in time")
        time.sleep(0.005)


# --- the wire format -----------------------------------------------------------------------------------------

def test_crc16_arc_check_values_and_framing():
    assert crc16_arc(b"123456789") == 0xBB3D == crc_arc_bitwise(b"123456789")
    assert crc16_arc(b"RESET") == 0xBE6F
    assert check_text_reply(b"RESETBE6F\r", "t") == "RESET"
    assert command_bytes("INIT:") == b"INIT:" + f"{crc_arc_bitwise(b'INIT:'):04X}".encode() + b"\r"
    assert command_bytes("TSTART") == b"TSTART\r"  # no colon: no CRC
    with pytest.raises(ReplyCRCError, match="CRC BE6E"):
        check_text_reply(b"RESETBE6E\r", "t")
    err = b"ERROR0C"
    with pytest.raises(NDIReplyError, match="ERROR0C \\(not tracking\\)") as exc:
        check_text_reply(err + f"{crc_arc_bitwise(err):04X}".encode() + b"\r", "t")
    assert exc.value.code == 0x0C


def bx_reply(records: list[tuple], system_status: int = 0) -> bytes:
    """A BX reply written from the layout: C4 A5, u16 length, u16 header CRC; u8 count, per handle u8 handle,
    u8 status, [8 float32 if valid], [u32 port status, u32 frame unless disabled]; u16 system status; u16 CRC."""
    body = bytes([len(records)])
    for handle, status, values, port_status, frame in records:
        body += bytes([handle, status])
        if status == 0x01:
            body += b"".join(struct.pack("<f", v) for v in values)
        if status != 0x04:
            body += port_status.to_bytes(4, "little") + frame.to_bytes(4, "little")
    body += system_status.to_bytes(2, "little")
    head = b"\xc4\xa5" + len(body).to_bytes(2, "little")
    return head + crc_arc_bitwise(head).to_bytes(2, "little") + body + crc_arc_bitwise(body).to_bytes(2, "little")


def test_bx_decoding_follows_the_layout():
    q = (0.5, 0.5, -0.5, 0.5)
    raw = bx_reply([(0x01, 0x01, (*q, 12.5, -20.25, -1500.0, 0.125), 0x31, 1234),
                    (0x02, 0x02, None, 0x31, 1234),
                    (0x03, 0x04, None, 0, 0),
                    (0x0A, 0x01, (1.0, 0, 0, 0, 1.0, 2.0, 3.0, 0.5), 0x71, 1235)], system_status=0x0102)
    reply = parse_bx(raw)
    assert reply.system_status == 0x0102 and [r.handle for r in reply.records] == [1, 2, 3, 10]
    a, missing, disabled, outside = reply.records
    assert a.status == HANDLE_VALID and a.q == q and a.t_mm == (12.5, -20.25, -1500.0) and a.rms_mm == 0.125
    assert a.port_status == 0x31 and a.frame == 1234 and a.in_volume
    assert missing.status == HANDLE_MISSING and missing.q is None and missing.frame == 1234
    assert disabled.status == HANDLE_DISABLED
    assert outside.port_status & 0x40 and not outside.in_volume  # out of the characterised volume: flagged
    broken = bytearray(raw)
    broken[10] ^= 0x01  # a byte of the body
    with pytest.raises(ReplyCRCError, match="body CRC"):
        parse_bx(bytes(broken))
    broken = bytearray(raw)
    broken[2] ^= 0x01  # the length
    with pytest.raises(ReplyCRCError, match="header CRC"):
        parse_bx(bytes(broken))


def test_tx_decoding_follows_the_layout_and_the_quaternion_is_scalar_first():
    # q0 qx qy qz: sign + 5 digits x 1e-4; tx ty tz: sign + 6 digits x 0.01 mm; rms sign + 5 digits x 1e-4 mm
    text = ("02"
            "0A" "+07071+00000+00000+07071" "+001234-002345-150000" "+01230" "00000031" "0000002A" "\n"
            "0BMISSING" "00000031" "0000002A" "\n"
            "0000")
    reply = parse_tx(text)
    a, b = reply.records
    assert a.handle == 0x0A and a.q == pytest.approx((0.7071, 0, 0, 0.7071)) and a.frame == 42
    assert a.t_mm == pytest.approx((12.34, -23.45, -1500.0)) and a.rms_mm == pytest.approx(0.123)
    assert b.handle == 0x0B and b.status == HANDLE_MISSING
    T = pose_matrix(a.q, a.t_mm)
    # scalar first: (cos 45, 0, 0, sin 45) is 90 degrees about z (read scalar-last it would be about x)
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.01234, -0.02345, -1.5])  # millimetres -> metres
    np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0, atol=1e-12)  # normalised (0.7071^2 * 2 != 1)
    with pytest.raises(ProtocolError, match="not a sign and digits"):
        parse_tx(text.replace("+001234", "+0012x4"))
    with pytest.raises(ProtocolError):
        parse_tx(text[:-2])


# --- the driver on the emulator -------------------------------------------------------------------------------

def moving_pose(offset_mm: np.ndarray, in_volume=lambda t: True):
    """A tool turning about z and sliding, fast enough that two frames never share a pose (mm)."""
    def pose_at(t_ns: int):
        s = t_ns * 1e-9
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("zyx", [0.7 * s, 0.3 * np.sin(s), 0.1]).as_matrix()
        T[:3, 3] = offset_mm + [30.0 * np.sin(s), 20.0 * np.cos(s), -1200.0 + 40.0 * np.sin(0.5 * s)]
        return T, in_volume(t_ns)
    return pose_at


def served_error(emu: NDITrackerEmulator, handle: int, T_m: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation rad) between a delivered pose and the nearest pose served for that handle."""
    best = (np.inf, np.inf)
    for h, _frame, T_mm, _iv in list(emu.served):
        if h != handle:
            continue
        dt = float(np.linalg.norm(T_mm[:3, 3] * 1e-3 - T_m[:3, 3]))
        dr = float(Rotation.from_matrix(T_mm[:3, :3].T @ T_m[:3, :3]).magnitude())
        if dt + dr < sum(best):
            best = (dt, dr)
    return best


@pytest.mark.parametrize("reply, tol_m, tol_rad", [("bx", 1e-6, 1e-6), ("tx", 9e-6, 3e-4)])
def test_poses_in_metres_equal_the_served_ones(reply, tol_m, tol_rad, tmp_path):
    roms = [tmp_path / "8700339.rom", tmp_path / "8700340.rom"]
    rng = np.random.default_rng(1)
    contents = [rng.integers(0, 256, 150, dtype=np.uint8).tobytes(), rng.integers(0, 256, 64, dtype=np.uint8).tobytes()]
    for path, data in zip(roms, contents):
        path.write_bytes(data)
    with NDITrackerEmulator(passive=[moving_pose(np.zeros(3)), moving_pose(np.array([100.0, 0, 0]))]) as emu:
        url = f"ndi://{emu.port}?rate=60&reply={reply}&tools={roms[0]},{roms[1]}&{FAST}"
        tracker = open_tracker(url, DeviceContext())
        assert isinstance(tracker, TrackerDriver) and isinstance(tracker.faults, Mapping)
        assert tracker.faults["never_seen"] == 0 and tracker.clock_domain == "host"
        with tracker:
            assert tracker.tools == ("8700339", "8700340") and emu.baud == 921600  # COMM took it to the URL's rate
            tracker.read(timeout_s=1.0)
            time.sleep(0.6)
            samples = tracker.read(timeout_s=1.0)
            health = tracker.health
            now = time.monotonic_ns()
        assert emu.commands["TSTOP"] >= 1 and not emu.tracking  # TSTOP on close
    # the .rom files went up in 64-byte chunks, the last padded with zeros
    assert emu.roms[1] == contents[0] + bytes(42) and emu.roms[2] == contents[1]
    assert health.state is HealthState.OK, health
    assert len(samples) >= 20 and {s.tool for s in samples} == {"8700339", "8700340"}
    t = np.array([s.t_ns for s in samples])
    assert np.all(np.diff(t) >= 0) and abs(int(t[-1]) - now) < 0.2e9  # host clock, stamped at receipt
    assert [s.seq for s in samples] == list(range(samples[0].seq, samples[0].seq + len(samples)))
    for s in samples:
        dt, dr = served_error(emu, 1 if s.tool == "8700339" else 2, s.T_tracker_marker)
        assert dt < tol_m and dr < tol_rad, (s.tool, dt, dr)
        assert s.in_volume and s.rms_mm > 0
    assert tracker.readings_delivered >= len(samples) and tracker.faults["crc_errors"] == 0


@pytest.fixture
def wired():
    """An Aurora-like emulator: two wired tools (handles 0A, 0B), the second out of the volume when asked."""
    state = {"outside": False}
    emu = NDITrackerEmulator(wired=[moving_pose(np.zeros(3)),
                                    moving_pose(np.array([50.0, 0, 0]), lambda t: not state["outside"])])
    yield emu, state
    emu.close()


def test_missing_tools_are_counted_and_degrade_health(wired):
    emu, _ = wired
    with open_tracker(f"ndi://{emu.port}?rate=40&{FAST}", DeviceContext()) as tracker:
        assert tracker.tools == ("handle 0A", "handle 0B")  # wired tools need no .rom
        tracker.read(timeout_s=1.0)
        wait_for(lambda: tracker.health.state is HealthState.OK)
        emu.faults.missing = True
        wait_for(lambda: tracker.faults["missing"] >= 10)
        health = tracker.health
        tracker.read()
        time.sleep(0.2)
        during = tracker.read()
        emu.faults.missing = False
        wait_for(lambda: tracker.health.state is HealthState.OK)
        after = tracker.read(timeout_s=1.0)
    assert health.state is HealthState.DEGRADED and "handle 0A: MISSING" in health.detail, health
    assert during == [] and after  # nothing delivered while missing; poses again after


def test_out_of_volume_poses_are_flagged_counted_and_degrade_health(wired):
    emu, state = wired
    with open_tracker(f"ndi://{emu.port}?rate=40&reply=tx&{FAST}", DeviceContext()) as tracker:
        tracker.read(timeout_s=1.0)
        state["outside"] = True
        wait_for(lambda: tracker.faults["out_of_volume"] >= 5)
        health = tracker.health
        time.sleep(0.1)
        samples = tracker.read()
    outside = [s for s in samples if s.tool == "handle 0B"]
    assert outside and not any(s.in_volume for s in outside)  # still poses, flagged untrusted
    assert all(s.in_volume for s in samples if s.tool == "handle 0A")
    assert health.state is HealthState.DEGRADED and "handle 0B: out of volume" in health.detail


@pytest.mark.parametrize("reply", ["bx", "tx"])
def test_a_corrupted_reply_is_counted_and_no_pose_comes_from_it(reply, wired):
    emu, _ = wired
    with open_tracker(f"ndi://{emu.port}?rate=60&reply={reply}&{FAST}", DeviceContext()) as tracker:
        tracker.read(timeout_s=1.0)
        emu.faults.corrupt_replies = 5
        wait_for(lambda: tracker.faults["crc_errors"] >= 5)
        health = tracker.health
        wait_for(lambda: tracker.health.state is HealthState.OK)  # clean replies again
        samples = tracker.read()
    assert tracker.faults["crc_errors"] == 5 and emu.faults.corrupt_replies == 0
    # five lost replies in a row at 60 Hz: no pose for more than three periods (stale), else degraded
    assert health.state in (HealthState.DEGRADED, HealthState.STALE) and "CRC" in health.detail, health
    # a corrupted reply moves a pose by metres: every delivered pose is one the emulator served
    for s in samples:
        dt, dr = served_error(emu, 0x0A if s.tool == "handle 0A" else 0x0B, s.T_tracker_marker)
        assert dt < 9e-6 and dr < 3e-4, (s.tool, dt)


def test_a_silent_tracker_goes_stale_with_counted_timeouts_and_recovers(wired):
    emu, _ = wired
    with open_tracker(f"ndi://{emu.port}?rate=40&{FAST}", DeviceContext()) as tracker:
        tracker.read(timeout_s=1.0)
        emu.faults.silent = True
        wait_for(lambda: tracker.faults["timeouts"] >= 2)
        health = tracker.health
        emu.faults.silent = False
        wait_for(lambda: tracker.health.state is HealthState.OK)
        tracker.read()
        assert tracker.read(timeout_s=1.0)
    assert health.state is HealthState.STALE and "no BX reply within 0.3 s" in health.detail, health


def test_the_reset_less_bring_up_finds_a_device_left_tracking_at_a_high_rate():
    # a previous session left the tracker at 921600 baud, tracking; the break cannot pass the pty, so no RESET
    pose = moving_pose(np.zeros(3))
    with NDITrackerEmulator(wired=[pose], start_baud=921600, start_tracking=True) as emu:
        with open_tracker(f"ndi://{emu.port}?baud=921600&{FAST}", DeviceContext()) as tracker:
            assert not tracker.reset_seen
            samples = tracker.read(timeout_s=1.0)
        assert emu.stats["wrong_baud_bytes"] > 0  # it was asked at 9600 first and heard nothing
        assert emu.commands["TSTOP"] >= 2 and emu.commands["INIT"] == 1 and emu.commands["COMM"] == 0
    assert samples and samples[0].tool == "handle 0A"


def test_the_bring_up_from_9600_switches_the_rate_with_comm():
    with NDITrackerEmulator(wired=[moving_pose(np.zeros(3))]) as emu:
        with open_tracker(f"ndi://{emu.port}?baud=230400&{FAST}", DeviceContext()) as tracker:
            samples = tracker.read(timeout_s=1.0)
        assert emu.baud == 230400 and emu.commands["COMM"] == 1 and emu.stats["wrong_baud_bytes"] == 0
    assert samples


def test_a_missing_or_silent_device_is_a_clear_error():
    with pytest.raises(DeviceNotFoundError, match="serial port '/dev/ttyNDI-nope' cannot be opened"):
        open_tracker("ndi:///dev/ttyNDI-nope", DeviceContext()).open()
    with NDITrackerEmulator(wired=[moving_pose(np.zeros(3))]) as emu:
        emu.faults.silent = True
        with pytest.raises(DeviceNotFoundError, match=rf"NDI tracker '{re.escape(emu.port)}': no NDI tracker "
                                                      r"answers at 9600 or 921600 baud"):
            open_tracker(f"ndi://{emu.port}?{FAST}", DeviceContext()).open()


def test_a_tracker_with_no_enabled_tool_says_what_to_give():
    with NDITrackerEmulator() as emu:
        with pytest.raises(DeviceError, match="no tool is enabled; give passive tools' .rom files"):
            open_tracker(f"ndi://{emu.port}?{FAST}", DeviceContext()).open()


def test_unplugged_and_plugged_back_in_it_reconnects(wired):
    emu, _ = wired
    with open_tracker(f"ndi://{emu.port}?rate=60&{FAST}", DeviceContext()) as tracker:
        tracker.read(timeout_s=1.0)
        emu.disconnect()
        wait_for(lambda: tracker.health.state is HealthState.DISCONNECTED)
        emu.reconnect()  # the device kept its rate and is still tracking: the RESET-less path takes it on
        wait_for(lambda: tracker.faults["reconnects"] == 1, timeout_s=5.0)
        tracker.read()
        assert tracker.read(timeout_s=1.0)
    assert tracker.faults["disconnects"] >= 1


def test_a_reconnect_keeps_the_passive_tools_the_device_still_holds(tmp_path):
    rom = tmp_path / "8700339.rom"
    rom.write_bytes(bytes(range(100)))
    with NDITrackerEmulator(passive=[moving_pose(np.zeros(3))]) as emu:
        with open_tracker(f"ndi://{emu.port}?rate=60&tools={rom}&{FAST}", DeviceContext()) as tracker:
            tracker.read(timeout_s=1.0)
            emu.disconnect()
            wait_for(lambda: tracker.health.state is HealthState.DISCONNECTED)
            emu.reconnect()  # the tracker kept its handles: no second PHRQ (it has no second tool to give)
            wait_for(lambda: tracker.faults["reconnects"] == 1, timeout_s=5.0)
            tracker.read()
            samples = tracker.read(timeout_s=1.0)
        assert emu.commands["PHRQ"] == 1 and emu.commands["PVWR"] == 2
    assert samples and {s.tool for s in samples} == {"8700339"}


@pytest.mark.parametrize("url, message", [
    ("ndi:///dev/x?colour=red", "unknown parameter 'colour' (known: baud, rate, tools, reply, "),
    ("ndi:///dev/x?reply=json", "reply must be one of bx, tx, got 'json'"),
    ("ndi:///dev/x?baud=12345", "'baud=12345' is not an NDI COMM rate"),
    ("ndi:///dev/x?rate=0", "rate must be in 1..1000 Hz, got 0"),
    ("ndi:///dev/x?tools=/no/such.rom", "tool file '/no/such.rom' does not exist"),
    ("ndi://?rate=60", "give the serial port"),
])
def test_url_parameters_are_checked(url, message):
    with pytest.raises(ConfigError, match=rf"^device URL '{re.escape(url)}': .*{re.escape(message)}"):
        open_tracker(url, DeviceContext())


def test_discovery_lists_the_tracker_back_end():
    from lapreco_hil.drivers.discovery import discover

    assert any("NDI" in d.title for d in discover())


# --- random bytes in a BX reply --------------------------------------------------------------------------------

class ScriptedSerial:
    """Stands in for pyserial: the reply bytes are scripted, then the line goes quiet (reads return short)."""

    def __init__(self, reply: bytes):
        self._data = bytearray(reply)
        self.timeout = 0.1
        self.written = b""

    def reset_input_buffer(self):
        pass

    def write(self, data):
        self.written += data

    def read(self, n):
        out = bytes(self._data[:n])
        del self._data[:n]
        return out

    def read_until(self, end=b"\r"):
        i = self._data.find(end)
        n = len(self._data) if i < 0 else i + 1
        return self.read(n)


def oracle_bx(data: bytes) -> list[tuple[int, tuple, tuple]] | None:
    """The valid records of a BX reply at the start of ``data`` whose header and body CRCs hold (None: none)."""
    if len(data) < 6 or data[:2] != b"\xc4\xa5" or crc_arc_bitwise(data[:4]) != int.from_bytes(data[4:6], "little"):
        return None
    n = int.from_bytes(data[2:4], "little")
    body = data[6:6 + n]
    if len(data) < 6 + n + 2 or crc_arc_bitwise(body) != int.from_bytes(data[6 + n:8 + n], "little"):
        return None
    out, pos = [], 1
    try:
        for _ in range(body[0]):
            handle, status = body[pos], body[pos + 1]
            pos += 2
            if status == 0x01:
                v = struct.unpack("<8f", body[pos:pos + 32])
                out.append((handle, v[:4], v[4:7]))
                pos += 32
            if status != 0x04:
                pos += 8
    except (IndexError, struct.error):
        return None
    return out


VALID = bx_reply([(0x01, 0x01, (0.5, 0.5, -0.5, 0.5, 12.5, -20.25, -1500.0, 0.125), 0x31, 7),
                  (0x02, 0x02, None, 0x31, 7), (0x0A, 0x01, (1.0, 0, 0, 0, 1.0, 2.0, 3.0, 0.5), 0x71, 7)])


def test_the_scripted_line_delivers_the_valid_reply():  # the fuzz harness below can deliver poses at all
    tracker = open_tracker("ndi:///dev/fuzz?reply=bx", DeviceContext())
    tracker._ser = ScriptedSerial(VALID + b"trailing junk")
    reply, _ = tracker._poll_reply()
    tracker._accept(reply, 1)
    assert [s.tool for s in tracker._new] == ["handle 01", "handle 0A"] and tracker.faults["missing"] == 1
    np.testing.assert_allclose(tracker._new[1].T_tracker_marker[:3, 3], [0.001, 0.002, 0.003], rtol=1e-6)


@FUZZ
@given(data=st.one_of(mutated(VALID), st.binary(max_size=200), st.just(VALID)))
def test_random_bytes_in_a_bx_reply_give_a_typed_error_or_only_crc_valid_poses(data):
    tracker = open_tracker("ndi:///dev/fuzz?reply=bx", DeviceContext())
    tracker._ser = ScriptedSerial(data)
    try:
        reply, _ = tracker._poll_reply()
    except DeviceError:  # typed: CRC, framing, timeout, ERRORxx (ProtocolError, DeviceTimeoutError)
        return
    carried = oracle_bx(data)
    assert carried is not None, "a reply was parsed from bytes without a CRC-valid BX reply"
    got = [(r.handle, r.q, r.t_mm) for r in reply.records if r.status == HANDLE_VALID]
    np.testing.assert_equal(got, carried)
    tracker._accept(reply, 1)  # poses from it (or counted errors), never an exception
    for s in tracker._new:
        assert np.all(np.isfinite(s.T_tracker_marker))


def test_probe_of_a_tracker_shows_each_tool_its_rate_position_and_what_was_outside_the_volume():
    from lapreco_hil.app.devices import probe

    outside = moving_pose(np.zeros(3), in_volume=lambda t: False)
    with NDITrackerEmulator(wired=[moving_pose(np.zeros(3)), outside]) as emu:
        text = probe(f"ndi://{emu.port}?rate=60&{FAST}", 1.0, device="cpu")
        served = [(handle, T) for handle, _frame, T, _in_volume in list(emu.served)]
    lines = text.splitlines()
    assert lines[0].startswith(f"tracker ndi://{emu.port}") and "poses in 1 s" in lines[0]
    rows = {line.split()[0] + " " + line.split()[1]: line.split() for line in lines if line.startswith("  handle")}
    assert set(rows) == {"handle 0A", "handle 0B"}
    # poses and rate: about 60 Hz each; the last position shown is one the device served for that tool, in mm
    for name, handle in (("handle 0A", 0x0A), ("handle 0B", 0x0B)):
        n, rate = int(rows[name][2]), float(rows[name][3])
        assert n > 20 and 30 < rate < 70
        shown = np.array([float(v) for v in rows[name][4:7]])
        gap_mm = min(np.abs(T[:3, 3] - shown).max() for h, T in served if h == handle)
        assert gap_mm < 0.06  # printed to 0.1 mm
    assert int(rows["handle 0A"][8]) == 0 and int(rows["handle 0B"][8]) == int(rows["handle 0B"][2])
    assert "out_of_volume" in lines[-1]
