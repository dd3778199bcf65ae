"""A chain of Dynamixel X-series servos behind a pseudo-terminal: the device side of Protocol 2.0.

The real driver opens ``emulator.port`` (a stable symlink to the pty's slave, like /dev/ttyUSB0) with
pyserial through dynamixel-sdk and cannot tell it from a USB-RS485 adapter. Each servo has an X-series
control table; Present Position comes from ``joints_at(t_ns)`` (the simulated robot's encoder-side joints)
through the shared JointMap (``dynamixel_joint_map``: 2048 ticks = 0 rad, the X-series convention), which
quantises to ticks; or, in raw mode (``ticks_at``), straight from ticks the caller chooses, with no JointMap
at all (a chain whose servos rest where they rest). Framing, byte stuffing and the CRC are the SDK's own
routines (the SDK is written for the master side; the device side here parses and answers).

The chain runs at ``baud`` (default 1 000 000, the driver's default; the X-series factory setting is 57600). It
reads the rate the driver set on the pty (termios, on the slave side) and ignores every byte sent at another rate,
as a servo's UART would (framing errors, never a packet): a host at the wrong baud rate gets no answer at all
(``stats["wrong_baud_bytes"]`` counts what it sent).

Faults on demand (``emulator.faults``): corrupted replies (bad CRC), garbage bytes on the line, dropped
replies, late replies, one servo's reply to one chosen Sync Read held back until a later time or until the next
Sync Read (so it lands among that one's replies: a status packet carries no sequence number), a silent bus, a servo's hardware-error alert (the error byte's alert bit, and Hardware
Error Status, address 70, with the bits ``hardware_error_status`` gives: overheating unless told), a joint
reading out of its limits, and ``disconnect()`` / ``reconnect()`` (the adapter unplugged and plugged back in).

Every Sync Read is counted (``sync_reads``, from 1) and the time it was answered kept (``sync_read_times``), so
a test can make the positions a function of the Sync Read's number (``ticks_at`` reads ``sync_reads``) and tell
which one a reading answers.

``reply_order``: the servos answer a Sync Read in the order of the instruction's ID list (``"request"``, as the
e-manual has it) or, as some chains do, by ascending or descending ID (``"ascending"``, ``"descending"``).
"""

from __future__ import annotations

import logging
import os
import select
import termios
import threading
import time
from dataclasses import dataclass, field

import numpy as np

# Hardware Error Status (address 70) and its bits (X-series): the driver's, one definition for both sides
from lapreco_hil.drivers.robot.dynamixel import (HARDWARE_ERROR_STATUS, HW_ELECTRICAL_SHOCK,  # noqa: F401
                                                 HW_INPUT_VOLTAGE, HW_MOTOR_ENCODER, HW_OVERHEATING, HW_OVERLOAD)
from lapreco_hil.drivers.robot.joint_map import JointMap
from lapreco_hil.simulators.pty_emulator import PtyEmulator

log = logging.getLogger(__name__)

HEADER = bytes([0xFF, 0xFF, 0xFD, 0x00])
INST_PING, INST_READ, INST_WRITE, INST_SYNC_READ, INST_STATUS = 0x01, 0x02, 0x03, 0x82, 0x55
BROADCAST = 0xFE
ERR_INSTRUCTION, ERR_DATA_RANGE, ERR_ALERT = 0x02, 0x04, 0x80
REPLY_ORDERS = ("request", "ascending", "descending")
MODEL_XM430_W350 = 1020
TABLE_SIZE = 147


def status_packet(sdk, dxl_id: int, error: int, params: bytes) -> bytearray:
    """A Protocol 2.0 status packet, stuffed and with its CRC (``sdk``: a Protocol2PacketHandler)."""
    length = len(params) + 4  # instruction + error + params + CRC
    packet = list(HEADER) + [dxl_id, length & 0xFF, length >> 8, INST_STATUS, error] + list(params) + [0, 0]
    packet = sdk.addStuffing(packet)  # a new list when it stuffed (and the length field updated)
    total = 7 + (packet[5] | (packet[6] << 8))
    crc = sdk.updateCRC(0, packet, total - 2)
    packet[total - 2], packet[total - 1] = crc & 0xFF, crc >> 8
    return bytearray(packet[:total])


@dataclass
class DynamixelFaults:
    """Switches the tests (and the fault-injection suite) turn on; counts are consumed as replies go out."""

    corrupt_replies: int = 0  # the next N replies get a flipped byte (CRC fails at the master)
    garbage_before_reply: int = 0  # N random bytes on the line before the next reply
    drop_replies: int = 0  # the next N replies are never sent
    reply_delay_s: float = 0.0  # every reply is late by this much
    silent: bool = False  # no replies at all (cable cut on the data line)
    hardware_alert: set[int] = field(default_factory=set)  # servo IDs reporting a hardware error
    # a servo's Hardware Error Status (address 70) while it reports the alert (absent: HW_OVERHEATING)
    hardware_error_status: dict[int, int] = field(default_factory=dict)
    position_override: dict[int, int] = field(default_factory=dict)  # servo ID -> raw counts (e.g. off limits)
    # (Sync Read number, counted from 1 as ``sync_reads``; servo ID): that servo's status packet to that Sync Read
    # is held back, and sent ``late_reply_s`` later (from a timer; the chain goes on answering meanwhile) or, with
    # ``late_reply_s`` None, at the next Sync Read, ahead of that one's replies (a late packet landing in the next
    # cycle)
    late_reply: tuple[int, int] | None = None
    late_reply_s: float | None = None


class DynamixelChainEmulator(PtyEmulator):
    def __init__(self, ids: list[int], joint_map: JointMap | None = None, joints_at=None, clock_ns=time.monotonic_ns,
                 link_dir: str | None = None, seed: int = 0, ticks_at=None, baud: int = 1_000_000,
                 reply_order: str = "request") -> None:
        """``joint_map`` + ``joints_at(t_ns) -> SI joints``, or ``ticks_at(t_ns) -> raw Present Position ticks``;
        ``baud``: the servos' Baud Rate setting (a host at another rate is not understood); ``reply_order``: how
        the servos order their status packets after a Sync Read (REPLY_ORDERS)."""
        from dynamixel_sdk import PacketHandler

        if (ticks_at is None) == (joint_map is None or joints_at is None):
            raise ValueError("give joint_map and joints_at, or ticks_at")
        if reply_order not in REPLY_ORDERS:
            raise ValueError(f"reply_order must be one of {', '.join(REPLY_ORDERS)}, got {reply_order!r}")
        self.ids = list(ids)
        self.reply_order = reply_order
        self.joint_map = joint_map
        self.joints_at = joints_at
        self.ticks_at = ticks_at or (lambda t_ns: joint_map.to_counts(joints_at(t_ns)))
        self.clock_ns = clock_ns
        self.faults = DynamixelFaults()
        self.baud = int(baud)
        self.stats = {"packets": 0, "bad_crc": 0, "replies": 0, "wrong_baud_bytes": 0}
        self.instructions: dict[int, int] = {}  # instruction code -> count received (safety tests read it)
        self.reads: dict[tuple[int, int], int] = {}  # (servo ID, address) of a Read instruction -> count
        self.sync_reads = 0  # Sync Read instructions answered so far (the one being answered: its number)
        self.sync_read_times: list[int] = []  # clock_ns() when each was answered (index: its number - 1)
        self.late_sent: list[tuple[int, int, int]] = []  # (Sync Read number, servo ID, clock_ns) of held-back replies
        self._held: list[tuple[int, int, bytes]] = []  # held-back status packets for the next Sync Read
        self._write_lock = threading.Lock()  # the serving thread and a late reply's timer write to the pty
        self._sdk = PacketHandler(2.0)  # its CRC and stuffing routines
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._tick0 = clock_ns()
        super().__init__(link_dir, "lapreco-dxl-", "ttyDXL0", "dynamixel emulator")
        self._open_pty()

    # --- serving ----------------------------------------------------------------------------------------------
    def _serve(self, master: int) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(master, 4096)
                line_baud = self._line_baud()
            except (OSError, termios.error):
                return  # the pty was closed under us (disconnect)
            if line_baud is not None and line_baud != self.baud:
                self.stats["wrong_baud_bytes"] += len(chunk)  # framing errors at the servos' UART: no packet
                buf.clear()
                continue
            buf.extend(chunk)
            for packet in self._packets(buf):
                self._handle(master, packet)

    def _packets(self, buf: bytearray):
        """Complete, CRC-valid instruction packets taken off the front of ``buf`` (garbage skipped)."""
        while True:
            start = buf.find(HEADER)
            if start < 0:
                del buf[: max(0, len(buf) - 3)]
                return
            del buf[:start]
            if len(buf) < 7:
                return
            length = buf[5] | (buf[6] << 8)
            total = 7 + length
            if length < 3 or total > 1024:
                del buf[:1]
                continue
            if len(buf) < total:
                return
            packet = bytes(buf[:total])
            del buf[:total]
            self.stats["packets"] += 1
            crc = self._sdk.updateCRC(0, list(packet), total - 2)
            if crc != (packet[-2] | (packet[-1] << 8)):
                self.stats["bad_crc"] += 1  # a servo ignores a corrupt instruction; the master times out
                continue
            yield packet

    @staticmethod
    def _unstuff(params: bytes) -> bytes:
        return params.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")

    def _handle(self, master: int, packet: bytes) -> None:
        dxl_id, inst = packet[4], packet[7]
        self.instructions[inst] = self.instructions.get(inst, 0) + 1
        params = self._unstuff(packet[8:-2])
        t_ns = self.clock_ns()
        if inst == INST_PING:
            targets = self.ids if dxl_id == BROADCAST else [dxl_id] if dxl_id in self.ids else []
            for i in targets:
                self._reply(master, i, 0, bytes([MODEL_XM430_W350 & 0xFF, MODEL_XM430_W350 >> 8, 52]))
        elif inst == INST_READ and dxl_id in self.ids and len(params) == 4:
            addr, n = params[0] | (params[1] << 8), params[2] | (params[3] << 8)
            self.reads[(dxl_id, addr)] = self.reads.get((dxl_id, addr), 0) + 1
            self._reply_block(master, dxl_id, addr, n, t_ns)
        elif inst == INST_SYNC_READ and dxl_id == BROADCAST and len(params) >= 5:
            addr, n = params[0] | (params[1] << 8), params[2] | (params[3] << 8)
            listed = [i for i in params[4:] if i in self.ids]  # by default in the order the master listed them
            if self.reply_order != "request":
                listed.sort(reverse=self.reply_order == "descending")
            with self._lock:
                self.sync_reads += 1
                self.sync_read_times.append(t_ns)
                held, self._held = self._held, []
                late = self.faults.late_reply
            for cycle, i, data in held:  # the last Sync Read's held-back packet, ahead of this one's
                self._write_late(master, cycle, i, data)
            for i in listed:
                self._reply_block(master, i, addr, n, t_ns, late=late == (self.sync_reads, i))
        elif inst == INST_WRITE and dxl_id in self.ids:
            self._reply(master, dxl_id, 0, b"")  # acknowledged; this robot is read-only and never moves
        elif dxl_id in self.ids:
            self._reply(master, dxl_id, ERR_INSTRUCTION, b"")

    def _table(self, dxl_id: int, t_ns: int) -> bytearray:
        table = bytearray(TABLE_SIZE)
        table[0:2] = MODEL_XM430_W350.to_bytes(2, "little")
        table[6] = 52  # firmware version
        table[7] = dxl_id
        j = self.ids.index(dxl_id)
        counts = int(self.ticks_at(t_ns)[j])
        counts = self.faults.position_override.get(dxl_id, counts)
        alert = dxl_id in self.faults.hardware_alert
        status = self.faults.hardware_error_status.get(dxl_id, HW_OVERHEATING)
        table[HARDWARE_ERROR_STATUS] = status if alert else 0
        table[64] = 1  # Torque Enable
        tick = ((t_ns - self._tick0) // 1_000_000) % 32768
        table[120:122] = int(tick).to_bytes(2, "little")
        table[132:136] = int(counts).to_bytes(4, "little", signed=True)
        table[144:146] = (120).to_bytes(2, "little")  # 12.0 V
        table[146] = 38  # degrees C
        return table

    def _reply_block(self, master: int, dxl_id: int, addr: int, n: int, t_ns: int, late: bool = False) -> None:
        if addr + n > TABLE_SIZE or n == 0:
            self._reply(master, dxl_id, ERR_DATA_RANGE, b"")
            return
        error = ERR_ALERT if dxl_id in self.faults.hardware_alert else 0
        self._reply(master, dxl_id, error, bytes(self._table(dxl_id, t_ns)[addr:addr + n]), late)

    def _write_late(self, master: int, cycle: int, dxl_id: int, data: bytes) -> None:
        self.late_sent.append((cycle, dxl_id, self.clock_ns()))
        self._write(master, data)

    def _write(self, master: int, data: bytes) -> None:
        try:
            with self._write_lock:
                os.write(master, data)
            self.stats["replies"] += 1
        except OSError:
            pass

    def _reply(self, master: int, dxl_id: int, error: int, params: bytes, late: bool = False) -> None:
        """``late``: the packet held back as ``faults.late_reply`` says (built now, with the values of now)."""
        f = self.faults
        with self._lock:
            if f.silent:
                return
            if f.drop_replies > 0:
                f.drop_replies -= 1
                return
            corrupt = f.corrupt_replies > 0
            f.corrupt_replies -= corrupt
            garbage, f.garbage_before_reply = f.garbage_before_reply, 0
            delay = f.reply_delay_s
        data = status_packet(self._sdk, dxl_id, error, params)
        total = len(data)
        if corrupt:
            data[9 + int(self._rng.integers(0, max(1, total - 11)))] ^= 0x5A
        if garbage:
            data = bytearray(self._rng.integers(0, 256, garbage, dtype=np.uint8).tobytes()) + data
        if late:
            cycle, late_s = self.sync_reads, f.late_reply_s
            if late_s is None:
                with self._lock:
                    self._held.append((cycle, dxl_id, bytes(data)))
            else:
                timer = threading.Timer(late_s, self._write_late, (master, cycle, dxl_id, bytes(data)))
                timer.daemon = True
                timer.start()
            return
        if delay:
            time.sleep(delay)
        self._write(master, bytes(data))
