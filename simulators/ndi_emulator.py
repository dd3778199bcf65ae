"""An NDI tracker (Polaris / Aurora) behind a pseudo-terminal: the device side of the Combined API.

The real driver opens ``emulator.port`` (a stable symlink to the pty's slave, like /dev/ttyUSB0) with pyserial
and cannot tell it from the tracker's USB serial cable. It answers ``RESET``, ``INIT``, ``COMM``, ``VER``,
``APIREV``, ``PHRQ``, ``PVWR`` (the uploaded .rom is kept: ``emulator.roms``), ``PHF``, ``PHSR``, ``PINIT``,
``PENA``, ``TSTART``, ``TSTOP``, ``TX`` and ``BX`` (reply options 0001 and 0800), with CRC-16/ARC on every reply; a
command whose CRC is wrong gets ``ERROR04``, an unknown one ``ERROR01``, tracking replies outside tracking mode
``ERROR0C``, a handle it does not hold ``ERROR2B``. ``command_log`` keeps the commands' names in order.

Tools: passive tools (``passive``: one ``pose_at`` each, given to the handles PHRQ hands out, in order) and
wired tools (``wired``: handles 0A, 0B, ... present after INIT, as an Aurora's sensors). A wired tool's handle
that a client freed (``PHF``) is not assigned again, by INIT or RESET, until its sensor is plugged in again
(``replug()``) or the device is power-cycled (``power_blip()``), as a real Aurora may behave.

Port handles live as on the device: ``PHRQ`` hands out the lowest free handle (01, 02, ...) to the first passive
tool that holds none, ``PHF`` frees one, and ``INIT`` or ``RESET`` start a fresh handle table, as a device just
brought up has (no passive handles; the wired tools present again but for those freed, neither initialised nor
enabled). A client that ended without freeing its handles (crashed, or killed) therefore leaves nothing in the way
of the next bring-up, and the emulator serves any number of clients one after another on the same pty (each opens
``emulator.port``, brings the device up, and closes it). ``pose_at(t_ns)``
returns ``(T_tracker_tool 4x4 in MILLIMETRES, in_volume)`` or None (the tool is out of view: MISSING). The device
measures at ``frame_rate_hz``: a reply carries the latest frame (number and pose at that frame's time);
``served`` logs what went out. ``in_volume`` may also be ``PARTIAL`` ("partial"): the tool is partially out of the
characterised volume (port status bit 7, 0x80); its pose is reported whatever the reply option, as one inside.

A serial break cannot pass through a Linux pty (the driver's tcsendbreak does nothing here), so the emulator
never answers a break with ``RESET``: the driver's RESET-less path is what runs against it. With
``start_baud`` / ``start_tracking`` it stands for a device a previous session left at a high rate, tracking.
The emulator reads the pty's line speed (set by the driver through termios) and ignores bytes sent at a rate
other than its own, as a UART would see them: garbage.

Faults on demand (``emulator.faults``): replies corrupted after their CRC was computed, every tool MISSING, a
silent line, ``disconnect()`` / ``reconnect()`` (the cable pulled and plugged back in), and ``power_blip()``:
the device resets by itself in the middle of a session, as after a power blip (back at 9600 baud, neither
initialised nor tracking, a fresh handle table, ``RESET`` sent unasked, or nothing with ``announce=False``: a
RESET sent at 9600 that a host at its session's rate reads as garbage).
"""

from __future__ import annotations

import collections
import logging
import os
import select
import struct
import termios
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from lapreco_hil.drivers.tracker.ndi_protocol import crc16_arc
from lapreco_hil.simulators.pty_emulator import TERMIOS_RATES, PtyEmulator  # noqa: F401 (TERMIOS_RATES: once here)

log = logging.getLogger(__name__)

PoseAt = Callable[[int], "tuple[np.ndarray, bool] | None"]
PORT_OCCUPIED, PORT_INITIALISED, PORT_ENABLED, PORT_OUT_OF_VOLUME = 0x01, 0x10, 0x20, 0x40
PORT_PARTIALLY_OUT_OF_VOLUME = 0x80
PARTIAL = "partial"  # pose_at's in_volume for a tool partially out of the characterised volume


def _port_status(in_volume: bool | str) -> int:
    status = PORT_OCCUPIED | PORT_INITIALISED | PORT_ENABLED
    if in_volume == PARTIAL:
        return status | PORT_PARTIALLY_OUT_OF_VOLUME
    return status | (0 if in_volume else PORT_OUT_OF_VOLUME)
COMM_RATES = {"0": 9600, "1": 14400, "2": 19200, "3": 38400, "4": 57600, "5": 115200, "6": 921600,
              "7": 1228739, "A": 230400}


@dataclass
class NDIFaults:
    """Switches the tests turn on; counts are consumed as replies go out."""

    corrupt_replies: int = 0  # the next N tracking replies get a changed byte after their CRC was computed
    missing: bool = False  # every tool reads MISSING
    silent: bool = False  # no replies at all


@dataclass
class _Handle:
    pose_at: PoseAt
    wired: bool
    tool: int = -1  # a passive handle's tool: its index in ``passive``
    rom: bytearray = field(default_factory=bytearray)
    initialised: bool = False
    enabled: bool = False


def _signed(value: float, scale: float, digits: int) -> str:
    n = int(round(value / scale))
    n = max(-(10 ** digits - 1), min(10 ** digits - 1, n))
    return f"{'-' if n < 0 else '+'}{abs(n):0{digits}d}"


def quaternion_scalar_first(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    return q if q[0] >= 0 else -q


class NDITrackerEmulator(PtyEmulator):
    def __init__(self, passive: list[PoseAt] = (), wired: list[PoseAt] = (), frame_rate_hz: float = 60.0,
                 clock_ns=time.monotonic_ns, link_dir: str | None = None, start_baud: int = 9600,
                 start_tracking: bool = False) -> None:
        self.passive = list(passive)
        self.frame_rate_hz = frame_rate_hz
        self.clock_ns = clock_ns
        self.faults = NDIFaults()
        self.commands: collections.Counter[str] = collections.Counter()  # command name -> count received
        self.command_log: collections.deque[str] = collections.deque(maxlen=100_000)  # names, in order
        self.stats = {"bad_crc": 0, "wrong_baud_bytes": 0, "replies": 0}
        self.served: collections.deque[tuple[int, int, np.ndarray, bool]] = collections.deque(maxlen=100_000)
        self._lock = threading.Lock()
        self._t0 = clock_ns()
        self.baud = start_baud
        self.tracking = start_tracking
        self.initialised = start_tracking
        self.wired = list(wired)
        self._uploads: dict[int, bytearray] = {}
        self._unassigned: set[int] = set()  # wired tools (index) whose handle was freed: gone until replugged
        self._blip: bool | None = None  # a power blip to apply in the serving thread (True: announce it)
        self.blips = 0  # power blips applied
        self.handles: dict[int, _Handle] = {}
        self._fresh_handles()
        for tool in self.handles.values():  # a previous session left them enabled, tracking
            tool.initialised = tool.enabled = start_tracking
        super().__init__(link_dir, "lapreco-ndi-", "ttyNDI0", "ndi emulator")
        self._open_pty()

    @property
    def roms(self) -> dict[int, bytes]:
        """What PVWR uploaded, per passive handle number: the latest tool given that number, still readable after
        the handle was freed (PHF, INIT)."""
        return {h: bytes(rom) for h, rom in self._uploads.items()}

    def _fresh_handles(self) -> None:
        """The handle table of a device just brought up: the wired tools' handles (but those freed since their
        sensor was plugged in), no passive ones."""
        self.handles = {0x0A + i: _Handle(pose_at, True) for i, pose_at in enumerate(self.wired)
                        if i not in self._unassigned}

    def replug(self) -> None:
        """Every wired sensor unplugged and plugged in again: a freed wired handle is assigned at the next INIT."""
        self._unassigned.clear()

    def power_blip(self, announce: bool = True, wait_s: float = 1.0) -> None:
        """The device resets by itself, between two commands (applied by the serving thread, within ``wait_s``):
        back at 9600 baud, not initialised, not tracking, a fresh handle table (uploaded .roms gone); it sends
        ``RESET`` unasked when ``announce`` (the bytes reach the host whatever its rate: a pty carries no line
        speed), else says nothing."""
        blips = self.blips
        self._blip = announce
        deadline = time.monotonic() + wait_s
        while self.blips == blips and time.monotonic() < deadline:
            time.sleep(0.002)

    def _apply_blip(self, master: int) -> None:
        announce, self._blip = self._blip, None
        self.tracking = False
        self.initialised = False
        self._unassigned.clear()  # powered up again: every plugged-in sensor is found
        self._fresh_handles()
        self.baud = 9600
        self.command_log.append("(power blip)")
        self.blips += 1
        if announce:
            self._text(master, "RESET")

    # --- serving ----------------------------------------------------------------------------------------------
    def _serve(self, master: int) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            if self._blip is not None:
                self._apply_blip(master)
                buf.clear()  # a command half received is lost with the reset
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(master, 4096)
                line_baud = self._line_baud()
            except (OSError, termios.error):
                return  # the pty was closed under us (disconnect)
            if line_baud is not None and line_baud != self.baud:
                self.stats["wrong_baud_bytes"] += len(chunk)  # a UART at another rate reads garbage
                continue
            buf.extend(chunk)
            while (end := buf.find(b"\r")) >= 0:
                line = bytes(buf[:end])
                del buf[:end + 1]
                self._handle(master, line)

    def _handle(self, master: int, line: bytes) -> None:
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            self._text(master, "ERROR01")
            return
        if ":" in text:
            name, rest = text.split(":", 1)
            params, crc_text = rest[:-4], rest[-4:]
            try:
                crc_ok = len(crc_text) == 4 and int(crc_text, 16) == crc16_arc(line[:-4])
            except ValueError:
                crc_ok = False
            if not crc_ok:
                self.stats["bad_crc"] += 1
                self._text(master, "ERROR04")
                return
        else:
            name, _, params = text.partition(" ")
        name = name.upper()
        self.commands[name] += 1
        self.command_log.append(name)
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            self._text(master, "ERROR01")
            return
        handler(master, params)

    def _text(self, master: int, reply: str) -> None:
        data = reply.encode("ascii")
        self._send(master, bytearray(data + f"{crc16_arc(data):04X}".encode("ascii") + b"\r"), corrupt_at=None)

    def _send(self, master: int, data: bytearray, corrupt_at: int | None) -> None:
        with self._lock:
            if self.faults.silent:
                return
            corrupt = corrupt_at is not None and self.faults.corrupt_replies > 0
            self.faults.corrupt_replies -= corrupt
        if corrupt:  # the pose's x changes on the line by metres (the CRC was computed before): a driver that
            # skipped the CRC check would deliver a pose far from any served one
            c = data[corrupt_at]
            data[corrupt_at] = ord(str((int(chr(c)) + 5) % 10)) if chr(c).isdigit() else c ^ 0x40
        try:
            os.write(master, bytes(data))
            self.stats["replies"] += 1
        except OSError:
            pass

    # --- commands -----------------------------------------------------------------------------------------
    def _cmd_reset(self, master: int, params: str) -> None:
        """A software reset, as after a serial break: a fresh device at 9600 baud, not yet initialised."""
        self.tracking = False
        self.initialised = False
        self._fresh_handles()
        self._text(master, "RESET")
        time.sleep(0.02)  # the reply leaves at the old rate
        self.baud = 9600

    def _cmd_init(self, master: int, params: str) -> None:
        self.tracking = False
        self.initialised = True
        self._fresh_handles()  # what an earlier client requested, initialised or enabled is gone
        self._text(master, "OKAY")

    def _cmd_comm(self, master: int, params: str) -> None:
        rate = COMM_RATES.get(params[:1].upper())
        if rate is None or len(params) != 5:
            self._text(master, "ERROR01")
            return
        self._text(master, "OKAY")
        time.sleep(0.02)  # the OKAY leaves at the old rate
        self.baud = rate

    def _cmd_ver(self, master: int, params: str) -> None:
        self._text(master, "NDI Polaris (lapreco-hil emulator)\nCombined Firmware Revision 000\n")

    def _cmd_apirev(self, master: int, params: str) -> None:
        self._text(master, "G.001.004")

    def _cmd_phrq(self, master: int, params: str) -> None:
        held = {t.tool for t in self.handles.values() if not t.wired}
        free_tools = [i for i in range(len(self.passive)) if i not in held]
        if not free_tools:
            self._text(master, "ERROR2B")  # no tool left to hand a handle to
            return
        handle = next(h for h in range(1, 0xFF) if h not in self.handles)
        self.handles[handle] = _Handle(self.passive[free_tools[0]], False, tool=free_tools[0])
        self._uploads[handle] = self.handles[handle].rom
        self._text(master, f"{handle:02X}")

    def _cmd_phf(self, master: int, params: str) -> None:
        """Port handle free: the handle (and what was uploaded to it) is gone; PHRQ may hand it out again. A wired
        tool's handle stays gone until its sensor is plugged in again (``replug``) or a power-up."""
        try:
            handle = int(params[:2], 16)
        except ValueError:
            handle = -1
        tool = self.handles.pop(handle, None)
        if tool is None:
            self._text(master, "ERROR2B")
            return
        if tool.wired:
            self._unassigned.add(handle - 0x0A)
        self._text(master, "OKAY")

    def _cmd_pvwr(self, master: int, params: str) -> None:
        try:
            handle, address, data = int(params[:2], 16), int(params[2:6], 16), bytes.fromhex(params[6:])
        except ValueError:
            self._text(master, "ERROR01")
            return
        tool = self.handles.get(handle)
        if tool is None or tool.wired or len(data) != 64:
            self._text(master, "ERROR2B")
            return
        if len(tool.rom) < address + 64:
            tool.rom.extend(bytes(address + 64 - len(tool.rom)))
        tool.rom[address:address + 64] = data
        self._text(master, "OKAY")

    def _cmd_phsr(self, master: int, params: str) -> None:
        which = params[:2] or "00"
        pick = {"00": lambda t: True, "01": lambda t: False, "02": lambda t: not t.initialised,
                "03": lambda t: t.initialised and not t.enabled, "04": lambda t: t.enabled}.get(which)
        if pick is None or not self.initialised:
            self._text(master, "ERROR01")
            return
        handles = [h for h, t in sorted(self.handles.items()) if pick(t)]
        self._text(master, f"{len(handles):02X}" + "".join(f"{h:02X}001" for h in handles))

    def _tool(self, master: int, params: str) -> _Handle | None:
        try:
            tool = self.handles.get(int(params[:2], 16))
        except ValueError:
            tool = None
        if tool is None:
            self._text(master, "ERROR2B")
        return tool

    def _cmd_pinit(self, master: int, params: str) -> None:
        if (tool := self._tool(master, params)) is not None:
            tool.initialised = True
            self._text(master, "OKAY")

    def _cmd_pena(self, master: int, params: str) -> None:
        if (tool := self._tool(master, params)) is not None:
            if not tool.initialised or params[2:3].upper() not in ("D", "S", "B"):
                self._text(master, "ERROR2B")
                return
            tool.enabled = True
            self._text(master, "OKAY")

    def _cmd_tstart(self, master: int, params: str) -> None:
        self.tracking = True
        self._text(master, "OKAY")

    def _cmd_tstop(self, master: int, params: str) -> None:
        if not self.tracking:
            self._text(master, "ERROR0C")
            return
        self.tracking = False
        self._text(master, "OKAY")

    def _frame(self) -> list[tuple[int, int, np.ndarray | None, bool]]:
        """The latest measured frame: (handle, frame number, T in mm or None when MISSING, in_volume) per
        enabled handle."""
        frame = int((self.clock_ns() - self._t0) * self.frame_rate_hz // 1_000_000_000)
        t_frame = self._t0 + int(frame * 1e9 / self.frame_rate_hz)
        out = []
        for handle, tool in sorted(self.handles.items()):
            if not tool.enabled:
                continue
            got = None if self.faults.missing else tool.pose_at(t_frame)
            T, in_volume = (None, False) if got is None else (np.asarray(got[0], np.float64),
                                                              PARTIAL if isinstance(got[1], str) else bool(got[1]))
            out.append((handle, frame, T, in_volume))
        return out

    def _option(self, master: int, params: str) -> int | None:
        try:
            option = int(params[:4], 16) if params else 0x0001
        except ValueError:
            self._text(master, "ERROR01")
            return None
        if not self.tracking:
            self._text(master, "ERROR0C")
            return None
        return option

    def _cmd_tx(self, master: int, params: str) -> None:
        if (option := self._option(master, params)) is None:
            return
        parts, corrupt_at = [], None
        for handle, frame, T, in_volume in self._frame():
            status = _port_status(in_volume)
            head = f"{handle:02X}"
            if T is None or (not in_volume and not option & 0x0800):
                parts.append(f"{head}MISSING{status:08X}{frame:08X}\n")
                continue
            q = quaternion_scalar_first(T[:3, :3])
            rms = 0.1 + 0.01 * handle
            transform = ("".join(_signed(v, 1e-4, 5) for v in q) + "".join(_signed(v, 1e-2, 6) for v in T[:3, 3])
                         + _signed(rms, 1e-4, 5))
            if corrupt_at is None:  # the leading digit of tx (metres)
                corrupt_at = 2 + sum(len(p) for p in parts) + 2 + 24 + 1
            parts.append(f"{head}{transform}{status:08X}{frame:08X}\n")
            self.served.append((handle, frame, T, in_volume))
        text = f"{len(parts):02X}" + "".join(parts) + "0000"
        data = text.encode("ascii")
        reply = bytearray(data + f"{crc16_arc(data):04X}".encode("ascii") + b"\r")
        self._send(master, reply, corrupt_at)

    def _cmd_bx(self, master: int, params: str) -> None:
        if (option := self._option(master, params)) is None:
            return
        body = bytearray([0])
        corrupt_at = None
        for handle, frame, T, in_volume in self._frame():
            body[0] += 1
            status = _port_status(in_volume)
            if T is None or (not in_volume and not option & 0x0800):
                body += struct.pack("<BB", handle, 0x02) + struct.pack("<II", status, frame)
                continue
            q = quaternion_scalar_first(T[:3, :3])
            body += struct.pack("<BB", handle, 0x01)
            if corrupt_at is None:  # the sign/exponent byte of tx
                corrupt_at = 6 + len(body) + 4 * 4 + 3
            body += struct.pack("<8f", *q, *T[:3, 3], 0.1 + 0.01 * handle)
            body += struct.pack("<II", status, frame)
            self.served.append((handle, frame, T, in_volume))
        body += struct.pack("<H", 0)
        header = b"\xc4\xa5" + struct.pack("<H", len(body))
        header += struct.pack("<H", crc16_arc(header))
        self._send(master, bytearray(header + body + struct.pack("<H", crc16_arc(bytes(body)))), corrupt_at)
