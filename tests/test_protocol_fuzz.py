"""Protocol parsing under random and mutated frames (hypothesis): the drivers' decoding of Dynamixel status
packets and CANopen PDO/EMCY frames, and the emulator's instruction parser. No crash, no hang: a typed,
counted error, or a reading the test proves came from a valid frame (a CRC-checked status packet found in
the bytes by an oracle written here from the protocol, independent of the SDK)."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from dynamixel_sdk import PacketHandler
from fuzz_settings import EXAMPLES, FUZZ
from hypothesis import given
from hypothesis import strategies as st

from lapreco_hil.drivers.robot.joint_map import cia402_joint_map
from lapreco_hil.errors import DeviceTimeoutError, ProtocolError
from lapreco_hil.registry import DeviceContext, open_robot
from lapreco_hil.drivers.robot.dynamixel import BLOCK_LEN
from lapreco_hil.simulators.dynamixel_emulator import status_packet

SDK = PacketHandler(2.0)
IDS = [1, 2, 3, 4]


class ScriptedPort:
    """Stands in for dynamixel-sdk's PortHandler: the reply bytes are scripted, then the line goes quiet."""

    class _Serial:
        def reset_input_buffer(self):
            pass

    def __init__(self, reply: bytes):
        self.ser = self._Serial()
        self.is_using = False
        self._reply = bytearray(reply)
        self._quiet_reads = 0

    def clearPort(self):
        pass

    def writePort(self, packet):
        return len(packet)

    def readPort(self, n):
        chunk = bytes(self._reply[:n])
        del self._reply[:n]
        if not chunk:
            self._quiet_reads += 1
        return chunk

    def setPacketTimeout(self, n):
        self._quiet_reads = 0

    def setPacketTimeoutMillis(self, ms):
        self._quiet_reads = 0

    def isPacketTimeout(self):
        return self._quiet_reads > 2  # quiet line: the SDK's timeout, without waiting for it


def crc16_buypass(data: bytes) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, not reflected), the Dynamixel Protocol 2.0 CRC, bit by bit."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005 if crc & 0x8000 else crc << 1) & 0xFFFF
    return crc


def valid_status_packets(data: bytes) -> dict[int, list[tuple[int, bytes]]]:
    """Every CRC-valid Protocol 2.0 status packet anywhere in ``data``: servo ID -> [(error, unstuffed params)]."""
    found: dict[int, list[tuple[int, bytes]]] = {}
    start = data.find(b"\xff\xff\xfd\x00")
    while start >= 0:
        if start + 7 <= len(data):
            length = data[start + 5] | (data[start + 6] << 8)
            end = start + 7 + length
            if length >= 4 and end <= len(data) and data[start + 7] == 0x55:
                packet = data[start:end]
                if crc16_buypass(packet[:-2]) == packet[-2] | (packet[-1] << 8):
                    params = packet[9:-2].replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")
                    found.setdefault(packet[4], []).append((packet[8], params))
        start = data.find(b"\xff\xff\xfd\x00", start + 1)
    return found


def assert_decoded_from_valid_packets(got, data: bytes) -> None:
    """Each servo's decoded position is the Present Position of a CRC-valid status packet from that servo."""
    packets = valid_status_packets(data)
    for dxl_id, counts in zip(IDS, got.tolist()):
        candidates = [int.from_bytes(p[12:16], "little", signed=True) for err, p in packets.get(dxl_id, [])
                      if len(p) == BLOCK_LEN and not err & 0x7F]
        assert counts in candidates, (dxl_id, counts, candidates)


def test_the_oracle_knows_the_protocol():
    assert crc16_buypass(b"123456789") == 0xFEE8  # the catalogued check value of CRC-16/BUYPASS
    reply = _valid_reply([5, -6, 2**31 - 1, 0xFDFFFF])  # the last one holds FF FF FD: stuffed on the wire
    assert b"\xff\xff\xfd\xfd" in reply
    assert_decoded_from_valid_packets(np.array([5, -6, 2**31 - 1, 0xFDFFFF]), b"junk" + reply)
    with pytest.raises(AssertionError):
        assert_decoded_from_valid_packets(np.array([5, -6, 7, 0xFDFFFF]), reply)


def _driver():
    robot = open_robot("serial:///dev/null-fuzz?ids=1,2,3,4", DeviceContext())
    robot._packets = SDK
    return robot


def _valid_reply(counts) -> bytes:
    out = bytearray()
    for dxl_id, c in zip(IDS, counts):
        block = bytearray(BLOCK_LEN)
        block[12:16] = int(c).to_bytes(4, "little", signed=True)
        out += status_packet(SDK, dxl_id, 0, bytes(block))
    return bytes(out)


def _poll(robot, reply: bytes):
    robot._port = ScriptedPort(reply)
    t0 = time.monotonic()
    try:
        return robot._poll()
    finally:
        assert time.monotonic() - t0 < 2.0  # never hangs


@FUZZ
@given(st.lists(st.integers(-2**31, 2**31 - 1), min_size=4, max_size=4))
def test_valid_replies_decode_exactly(counts):
    got, _ = _poll(_driver(), _valid_reply(counts))
    assert got.tolist() == counts


@FUZZ
@given(st.binary(max_size=200))
def test_random_bytes_give_a_typed_error(data):
    robot = _driver()
    try:
        got, _ = _poll(robot, data)
    except (DeviceTimeoutError, ProtocolError):
        return  # the only ways a garbled line may fail
    assert_decoded_from_valid_packets(got, data)  # a reading: only what valid packets in the bytes say


@FUZZ
@given(st.binary(max_size=60), st.lists(st.integers(-2**31, 2**31 - 1), min_size=4, max_size=4),
       st.binary(max_size=60))
def test_valid_replies_among_noise_decode_exactly_or_fail_cleanly(before, counts, after):
    data = before + _valid_reply(counts) + after
    try:
        got, _ = _poll(_driver(), data)
    except (DeviceTimeoutError, ProtocolError):
        return
    assert_decoded_from_valid_packets(got, data)


@FUZZ
@given(st.lists(st.integers(-2**20, 2**20), min_size=4, max_size=4), st.data())
def test_mutated_replies_decode_or_fail_cleanly(counts, data):
    reply = bytearray(_valid_reply(counts))
    op = data.draw(st.sampled_from(["flip", "insert", "delete", "truncate", "error_byte"]))
    i = data.draw(st.integers(0, len(reply) - 1))
    if op == "flip":
        reply[i] ^= data.draw(st.integers(1, 255))
    elif op == "insert":
        reply[i:i] = data.draw(st.binary(min_size=1, max_size=8))
    elif op == "delete":
        del reply[i]
    elif op == "truncate":
        del reply[i:]
    else:
        reply[8] = data.draw(st.integers(1, 255))  # the first servo's error byte
    robot = _driver()
    try:
        got, _ = _poll(robot, bytes(reply))
    except (DeviceTimeoutError, ProtocolError):
        return
    # a reply that decodes must be the true one: the CRC lets no corruption through
    assert got.tolist() == counts


@FUZZ
@given(st.binary(max_size=300), st.binary(max_size=40))
def test_emulator_parser_skips_garbage_and_finds_valid_instructions(noise, tail):
    from lapreco_hil.simulators import dynamixel_emulator as de

    emu = de.DynamixelChainEmulator.__new__(de.DynamixelChainEmulator)  # the parser alone, no pty
    emu._sdk, emu.stats = SDK, {"packets": 0, "bad_crc": 0, "replies": 0}
    ping = [0xFF, 0xFF, 0xFD, 0x00, 3, 3, 0, de.INST_PING, 0, 0]
    crc = SDK.updateCRC(0, ping, 8)
    ping[8:10] = [crc & 0xFF, crc >> 8]
    buf = bytearray(noise.replace(b"\xff\xff\xfd", b"") + bytes(ping) + tail)
    found = list(emu._packets(buf))
    assert bytes(ping) in found  # the noise holds no header (removed above), so the ping is always recovered


_channels = itertools.count()


def test_random_can_frames_on_pdo_and_emcy_ids_are_survived():
    import can

    from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator

    jm = cia402_joint_map("ecm")
    channel = f"fuzz-{next(_channels)}"
    rng = np.random.default_rng(7)
    q_true = np.array([0.1, -0.2, 0.12, 0.3])
    # positions a reading may carry: the drive's own, or one from a well-formed (6-byte) TPDO1 sent as noise
    # (CANopen has no application-level check beyond CAN's own CRC: such a frame is a valid TPDO)
    allowed = {node: {int(c)} for node, c in zip(IDS, jm.to_counts(q_true))}
    with CANopenDriveChainEmulator(channel, IDS, jm, lambda t: q_true):
        robot = open_robot(f"canopen://virtual/{channel}?nodes=1-4&rate=100&heartbeat_ms=100", DeviceContext())
        samples = []
        with robot, can.Bus(interface="virtual", channel=channel) as noise:
            for _ in range(max(400, EXAMPLES)):
                cob = int(rng.choice([0x181, 0x182, 0x81, 0x82, 0x701, 0x80]))
                data = rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8).tobytes()
                if cob in (0x181, 0x182) and len(data) == 6:
                    allowed[cob - 0x180].add(int.from_bytes(data[2:6], "little", signed=True))
                noise.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
                samples += robot.read()
            time.sleep(0.2)
            samples += robot.read(timeout_s=0.5)
            assert samples  # still reading
            assert robot.faults["protocol_errors"] >= 1  # wrong-length TPDOs were seen and counted
    for s in samples:
        for node, c in zip(IDS, jm.to_counts(s.q)):
            assert int(c) in allowed[node], (node, c)
