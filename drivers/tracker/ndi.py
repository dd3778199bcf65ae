"""NDI optical / electromagnetic trackers (Polaris, Aurora) over serial, speaking the Combined API itself
through pyserial (``serial.serial_for_url``: a device node, a pty, or any pyserial URL).

``ndi:///dev/ttyUSB0?baud=921600&rate=60&tools=8700339.rom,8700340.rom&reply=bx``
(parameters: :class:`NDIConfig`). ``tools`` lists passive tools' .rom files (Polaris); Aurora's wired tools, and
handles already enabled, need none.

Bring-up, as ndicapi does it: a serial break at 9600 baud and the device's ``RESET`` reply; when no ``RESET``
comes (a pty cannot carry a break; some adapters drop it) the RESET-less path: the device is asked at 9600 baud,
then at the target rate (a previous session may have left it there), and taken on from where it is (``TSTOP``
in case it was tracking). Then ``INIT``, ``COMM`` to ``baud``, ``VER 4``, ``APIREV``, per .rom tool ``PHRQ`` +
``PVWR`` (64-byte chunks, hex; after ``PHSR 01`` -> ``PHF`` for handles waiting to be freed), then ``PHSR 02`` ->
``PINIT``, ``PHSR 03`` -> ``PENA hh D``, ``PHSR 04`` (the enabled handles), ``TSTART``. A reader thread polls
``BX 0801`` (or ``TX 0801``) at ``rate``: transforms, and tools outside the characterised volume still reported
with their out-of-volume flag. On close ``TSTOP``, then ``PHF`` for each handle the session requested with
``PHRQ`` (its passive tools): the next session (a record after a probe) finds the device as a new one. Wired
tools' handles (an Aurora's sensors) are not freed: the device assigned them, a freed one may not come back until
the sensor is plugged in again, and the next session's ``INIT`` initialises them afresh. Every new session starts
with ``INIT``, so handles a crashed client left behind are no obstacle either; only a reconnect of the same
session (the cable pulled and plugged back in, the device still tracking at the session's rate with its handles)
skips the bring-up and goes on with the tools it had.

Each pose is stamped on the host clock (the run's ``clock_ns``) when its reply has arrived, minus nothing: the
device's latency and the transfer are left in, for a time-offset fit to absorb.

A reply with a bad CRC is a counted fault (``crc_errors``), never a pose; ``MISSING`` tools and out-of-volume
poses are counted (``missing``, ``out_of_volume``) and mark the tracker degraded while they last; a repeated
frame number (polled faster than the device measures) is not delivered twice. A pose *partially* out of the
volume (port status bit 7) is out of it for the app: delivered with ``in_volume`` False (recorded as
``in_volume`` 0, refused as a camera pose), counted in ``out_of_volume`` and on its own in
``partially_out_of_volume``, and shown as "partially out of volume".

A tracker that resets in the middle of a session (a power blip: it is back at 9600 baud, not initialised, not
tracking, its handles gone) is brought up again: a ``RESET`` seen on the line (``device_resets``; the same for
``ERROR0C``, not tracking, in answer to a poll) goes straight to the full bring-up at 9600, and replies lost in a
row for ``lost_for_s`` (``unanswered``: a RESET sent at 9600 reads as garbage at the session's rate, or is lost)
reconnect as a new session does (the break, then the RESET-less path). Passive tools' .rom files are uploaded
again; the port stays open meanwhile, so health reads stale (not disconnected) until poses come again.

``close()`` during such a bring-up stops it at its next step (the wait for ``RESET`` included) and closes the
port; a bring-up that completes as ``close()`` comes is ended as a session is (``TSTOP``, ``PHF``), by the reader
thread itself when ``close()`` could not wait for it: the port is never left open, nor the device tracking.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from lapreco_hil.drivers.device import Discovery, FoundDevice, ReaderHandover
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.tracker.base import TrackerDriver
from lapreco_hil.drivers.tracker.ndi_protocol import (BX_START, ERROR_NOT_TRACKING, HANDLE_MISSING, HANDLE_VALID,
                                                      REPLY_OUT_OF_VOLUME, REPLY_TRANSFORMS, RESET_REPLY,
                                                      NDIReplyError, ReplyCRCError, TrackerResetError,
                                                      TrackingReply, bx_header, check_text_reply, command_bytes,
                                                      parse_bx, parse_tx, pose_matrix)
from lapreco_hil.errors import (DeviceDisconnectedError, DeviceError, DeviceNotFoundError, DeviceTimeoutError,
                                ProtocolError)
from lapreco_hil.registry import URLConfig, url_param
from lapreco_hil.types import MarkerSample

log = logging.getLogger(__name__)

# COMM's baud-rate digit per rate (ndicapi's NDI_9600 .. NDI_1228739, NDI_230400 = A)
COMM_BAUD_CODES = {9600: "0", 14400: "1", 19200: "2", 38400: "3", 57600: "4", 115200: "5", 921600: "6",
                   1228739: "7", 230400: "A"}
RESET_BAUD = 9600  # every NDI device comes out of a reset (break, power-up) at 9600 baud, 8N1
PVWR_CHUNK = 64
INIT_TIMEOUT_S = 5.0  # INIT and PINIT take seconds on a Polaris


def _baud(text: str) -> int:
    baud = int(text)
    if baud not in COMM_BAUD_CODES:
        raise ValueError(f"is not an NDI COMM rate ({', '.join(map(str, sorted(COMM_BAUD_CODES)))})")
    return baud


def _tools(text: str) -> tuple[str, ...]:
    paths = tuple(p.strip() for p in text.split(",") if p.strip())
    if not paths:
        raise ValueError("lists no .rom files")
    return paths


@dataclass(frozen=True)
class NDIConfig(URLConfig):
    baud: int = url_param(921600, parse=_baud, help="serial rate after COMM (the bring-up starts at 9600)")
    rate: float = url_param(60.0, low=1.0, high=1000.0, unit="Hz", help="polls per second (Polaris ~60, Aurora 40)")
    tools: tuple[str, ...] = url_param((), parse=_tools, help="passive tools' .rom files, comma-separated")
    reply: str = url_param("bx", choices=("bx", "tx"), help="poll with BX (binary) or TX (text)")
    reset_wait_ms: int = url_param(3000, low=0, high=60000, unit="ms",
                                   help="how long to wait for RESET after the serial break (0: send no break)")
    timeout_ms: int = url_param(500, low=10, high=60000, unit="ms", help="reply timeout of one command")


class BringUpStopped(DeviceError):
    """close() came during a bring-up: it stopped at its next step."""


def serial_ports() -> list[str]:
    from serial.tools import list_ports

    return sorted(p.device for p in list_ports.comports())


class NDITracker(ReaderHandover, TrackerDriver):
    reconnect_interval_s = 0.5
    # replies lost in a row (timeouts, CRC errors, garbled replies) for this long, and at least lost_replies_min
    # of them, mean the device is not the one this session set up (reset, power blip): it is brought up again
    lost_for_s = 1.0
    lost_replies_min = 2
    stale_after_periods = 3.0
    degraded_after_periods = 10.0
    degraded_min_s = 0.25
    buffer_len = 4096
    # how long close() waits for the reader thread (its longest step: INIT, PINIT or TSTART, INIT_TIMEOUT_S); one
    # still busy past it ends the session itself (TSTOP, PHF, the port closed) when it is done
    close_join_s = INIT_TIMEOUT_S + 1.0

    def __init__(self, url, context) -> None:
        self.config = NDIConfig.from_url(url)
        if not url.name:
            raise url.error("give the serial port, e.g. ndi:///dev/ttyUSB0?tools=8700339.rom")
        self._roms: list[tuple[str, bytes]] = []  # (tool name: the file's stem, contents), read once here
        for rom in self.config.tools:
            try:
                self._roms.append((Path(rom).stem, Path(rom).read_bytes()))
            except OSError as exc:
                reason = "does not exist" if not Path(rom).exists() else f"cannot be read ({exc.strerror})"
                raise url.error(f"tool file '{rom}' {reason} (give .rom files that exist, or no tools=)") from None
            if not self._roms[-1][1]:
                raise url.error(f"tool file '{rom}' is empty (a tool definition .rom from NDI's tool software)")
        self.url = url
        self.port_path = url.name
        self.rate_hz = self.config.rate
        self.device_name = f"NDI tracker '{self.port_path}'"
        self._clock = context.clock_ns
        self._ser = None
        self.tool_handles: dict[int, str] = {}  # port handle -> tool name (the .rom's stem, or 'handle 0A')
        self._requested: set[int] = set()  # the handles this session asked for with PHRQ (freed with PHF on close)
        self.tools = ()
        self.version = ""
        self.reset_seen = False  # whether the last bring-up got RESET after its break
        self._cond = threading.Condition()
        self._new: collections.deque[MarkerSample] = collections.deque(maxlen=self.buffer_len)
        self._error: BaseException | None = None
        self._init_handover()  # (the reader ends the session itself when close() gave up waiting for it)
        self._recovering = False  # not connected, the port fine: the device is being brought up again
        self._after_reset = False  # the next bring-up follows a RESET the device sent: no break, straight to INIT
        self._faults: collections.Counter[str] = collections.Counter()
        self._faults_lock = threading.Lock()
        self._last_frame: dict[int, int] = {}
        self._tool_trouble: dict[str, str] = {}  # tool -> 'MISSING' / 'out of volume', while it lasts
        self._last_fault = ""
        self._last_pose_wall = 0.0
        self._last_reply_wall = 0.0
        self._last_error_wall = 0.0
        self._last_error = ""
        self._last_t_ns = 0
        self._seq = 0

    @classmethod
    def discover(cls) -> Discovery:
        ports = serial_ports()
        return Discovery("serial ports (NDI Polaris / Aurora trackers)",
                         tuple(FoundDevice(p, f"ndi://{p}?baud=921600&rate=60") for p in ports),
                         "" if ports else "no serial ports (is the tracker's USB serial cable plugged in?)")

    @property
    def faults(self) -> collections.Counter[str]:
        """Counts per fault kind: missing, out_of_volume (wholly or partially), partially_out_of_volume (those of
        them only partially out), crc_errors, timeouts, errors, disconnects, reconnects, non_increasing_stamps, device_resets (RESET or ERROR0C: the device lost its set-up),
        unanswered (replies lost in a row for ``lost_for_s``: brought up again)."""
        with self._faults_lock:
            return collections.Counter(self._faults)

    def _count(self, kind: str, n: int = 1) -> None:
        with self._faults_lock:
            self._faults[kind] += n

    # --- the serial line --------------------------------------------------------------------------------------
    def _command(self, command: str, timeout_s: float | None = None) -> str:
        """Send one command, return its reply's text (CRC checked; ERRORxx raised as NDIReplyError)."""
        ser = self._ser
        ser.reset_input_buffer()  # a late reply to an earlier command must not pass for this one's
        ser.write(command_bytes(command))
        return check_text_reply(self._read_line(timeout_s), f"{self.device_name}: {command.split(':')[0]}")

    def _read_line(self, timeout_s: float | None, prefix: bytes = b"") -> bytes:
        ser = self._ser
        ser.timeout = timeout_s if timeout_s is not None else self.config.timeout_ms / 1e3
        raw = prefix + ser.read_until(b"\r")
        if not raw.endswith(b"\r"):
            raise DeviceTimeoutError(f"{self.device_name}: no complete reply within {ser.timeout:.2g} s "
                                     f"(got {len(raw)} bytes)")
        return raw

    def _poll_reply(self) -> tuple[TrackingReply, int]:
        """One TX/BX exchange: the parsed reply and the host time it arrived.

        The stamp is the injected clock when the reply's last byte was read, minus nothing: the device's own
        latency (exposure to reply, a few ms) and the transfer time are not subtracted; a time-offset fit
        (calib) absorbs them."""
        ser = self._ser
        option = REPLY_TRANSFORMS | REPLY_OUT_OF_VOLUME
        ser.reset_input_buffer()
        ser.timeout = self.config.timeout_ms / 1e3
        if self.config.reply == "tx":
            ser.write(command_bytes(f"TX:{option:04X}"))
            raw = self._read_line(None)
            t_ns = self._clock()
            text = check_text_reply(raw, f"{self.device_name}: TX")
            if text == "RESET":
                raise TrackerResetError(f"{self.device_name}: the tracker sent RESET instead of a TX reply")
            return parse_tx(text), t_ns
        ser.write(command_bytes(f"BX:{option:04X}"))
        start = ser.read(2)
        if len(start) < 2:
            raise DeviceTimeoutError(f"{self.device_name}: no BX reply within {ser.timeout:.2g} s")
        if start != BX_START:  # a text reply (ERRORxx, RESET) or garbage
            raw = self._read_line(None, start)
            if check_text_reply(raw, f"{self.device_name}: BX") == "RESET":
                raise TrackerResetError(f"{self.device_name}: the tracker sent RESET instead of a BX reply")
            raise ProtocolError(f"{self.device_name}: BX answered with text {raw[:40]!r}")
        header = start + ser.read(4)
        if len(header) < 6:
            raise DeviceTimeoutError(f"{self.device_name}: BX reply cut short in its header")
        try:
            length = bx_header(header)
        except ProtocolError:
            self._drain()
            raise
        rest = ser.read(length + 2)
        t_ns = self._clock()
        if len(rest) < length + 2:
            raise DeviceTimeoutError(f"{self.device_name}: BX reply cut short ({len(rest)} of {length + 2} bytes)")
        return parse_bx(header + rest), t_ns

    def _check_unasked(self) -> None:
        """Bytes the device sent since the last reply, unasked, are read before the next poll drops them: a
        RESET among them (a device that reset between two polls) raises TrackerResetError."""
        ser = self._ser
        waiting = ser.in_waiting
        if waiting and RESET_REPLY[:-1] in ser.read(waiting):
            raise TrackerResetError(f"{self.device_name}: the tracker sent RESET between two polls")

    def _drain(self) -> None:
        """After a broken header: let the rest of the reply arrive and drop it."""
        ser = self._ser
        ser.timeout = 0.02
        while ser.read(4096):
            pass

    # --- bring-up ----------------------------------------------------------------------------------------------
    def _open_port(self):
        import serial

        try:
            return serial.serial_for_url(self.port_path, baudrate=RESET_BAUD, timeout=self.config.timeout_ms / 1e3)
        except (serial.SerialException, OSError, ValueError) as exc:
            ports = serial_ports()
            raise DeviceNotFoundError(f"serial port '{self.port_path}' cannot be opened ({exc}); serial ports here: "
                                      f"{', '.join(ports) if ports else 'none'}") from None

    def _wait_for_reset(self) -> bool:
        """Serial break, then the device's RESET reply at 9600 baud (False when none comes)."""
        ser = self._ser
        if self.config.reset_wait_ms == 0:
            return False
        try:
            ser.send_break(0.25)
        except Exception as exc:  # a transport without breaks (some URLs, adapters): the RESET-less path
            log.debug("%s: no serial break (%s)", self.device_name, exc)
        deadline = time.monotonic() + self.config.reset_wait_ms / 1e3
        got = b""
        while time.monotonic() < deadline:
            self._check_stop()  # close() need not wait out a long reset_wait_ms
            ser.timeout = min(0.1, max(0.01, deadline - time.monotonic()))
            got += ser.read_until(b"\r")
            if got.endswith(b"\r"):
                try:
                    if check_text_reply(got, f"{self.device_name}: after a break").endswith("RESET"):
                        return True
                except ProtocolError:
                    pass
                got = b""
        return False

    def _find_device(self) -> None:
        """The RESET-less path: whom does the device answer, at 9600 or at the target rate?"""
        tried = []
        for baud in dict.fromkeys((RESET_BAUD, self.config.baud)):
            self._ser.baudrate = baud
            tried.append(str(baud))
            try:
                self._command("TSTOP:")  # leaves tracking mode if a previous session left it there
                return
            except NDIReplyError:
                return  # it answers (not tracking): alive at this rate
            except (DeviceTimeoutError, ProtocolError):
                continue
        raise DeviceNotFoundError(f"{self.device_name}: no NDI tracker answers at {' or '.join(tried)} baud and no "
                                  f"RESET came after the serial break; check the tracker's power and cable, and the "
                                  f"port")

    def _connect(self, after_reset: bool = False) -> None:
        """Open the port and bring the device up. ``after_reset``: it has just sent RESET by itself (it is at
        9600, fresh): no break and no search, straight to the full bring-up."""
        import termios

        import serial

        try:
            self._ser = self._open_port()
        except DeviceNotFoundError:
            self._recovering = False  # the port itself is gone: disconnected, not a device being brought up
            raise
        try:
            self._check_stop()
            self.reset_seen = after_reset or self._wait_for_reset()
            if not self.reset_seen:
                log.info("%s: no RESET after the serial break; taking the device on where it is", self.device_name)
                self._find_device()
            # a device taken on where it is (no RESET) after this driver lost its cable still tracks the tools it
            # set up: go on with them. Anything else (a new session, a device reset, another client's handles,
            # one that crashed without freeing its own) gets the full bring-up, whose INIT starts afresh.
            self._check_stop()
            if not (not self.reset_seen and self.tool_handles and self._resume()):
                self._bring_up()
            self._check_stop()
            self._command("TSTART:", INIT_TIMEOUT_S)
            self._last_frame.clear()
        except (serial.SerialException, OSError, termios.error) as exc:
            self._close_port()
            raise DeviceDisconnectedError(f"{self.device_name}: lost during bring-up ({exc})") from None
        except DeviceTimeoutError as exc:
            self._close_port()
            raise DeviceNotFoundError(f"{self.device_name}: bring-up stopped: {exc}") from None
        except DeviceError:
            self._close_port()
            raise
        log.info("%s: %s; tracking %s", self.device_name, self.version.splitlines()[0] if self.version else "?",
                 ", ".join(self.tools))

    def _check_stop(self) -> None:
        """Between bring-up steps: close() asked the reader to stop (the port is closed by _connect's caller; what
        this bring-up requested is freed by the next session's INIT)."""
        if self._stop.is_set():
            raise BringUpStopped(f"{self.device_name}: bring-up stopped: the tracker is being closed")

    def _resume(self) -> bool:
        """Whether the device, found at this session's rate, still has every handle this driver enabled."""
        if self._ser.baudrate != self.config.baud:
            return False  # back at 9600: it was reset or power-cycled, its handles are gone
        try:
            enabled = set(self._handles("04"))
        except NDIReplyError:
            return False  # not initialised (reset)
        if not set(self.tool_handles) <= enabled:
            return False
        log.info("%s: the device kept this session's handles (%s); tracking again", self.device_name,
                 ", ".join(f"{h:02X}" for h in sorted(self.tool_handles)))
        return True

    def _bring_up(self) -> None:
        """INIT (a fresh handle table), COMM to the session's rate, VER, APIREV, the .rom tools' handles, PINIT,
        PENA: every tool enabled, ready for TSTART."""
        self._command("INIT:", INIT_TIMEOUT_S)
        self._requested = set()  # INIT's fresh handle table holds none of ours
        self._check_stop()
        if self._ser.baudrate != self.config.baud:
            self._command(f"COMM:{COMM_BAUD_CODES[self.config.baud]}0000")
            time.sleep(0.1)  # the device switches after its OKAY
            self._ser.baudrate = self.config.baud
        self.version = self._command("VER:4").strip()
        try:
            self.version += f" (API {self._command('APIREV:').strip()})"
        except NDIReplyError:
            pass  # older firmware: no APIREV
        # handles the device says are waiting to be freed (a tool unplugged, an earlier client's), as ndicapi's
        # users do before they request their own
        for handle in self._handles("01"):
            self._command(f"PHF:{handle:02X}")
        handles: dict[int, str] = {}
        for name, rom in self._roms:
            self._check_stop()
            reply = self._command("PHRQ:*********1****")
            try:
                handle = int(reply[:2], 16)
            except ValueError:
                raise ProtocolError(f"{self.device_name}: PHRQ: malformed reply {reply[:40]!r}") from None
            self._requested.add(handle)
            self._upload_rom(handle, rom)
            handles[handle] = name
        for handle in self._handles("02"):
            self._check_stop()
            self._command(f"PINIT:{handle:02X}", INIT_TIMEOUT_S)
        for handle in self._handles("03"):
            self._check_stop()
            self._command(f"PENA:{handle:02X}D")
        enabled = self._handles("04")
        if not enabled:
            raise DeviceError(f"{self.device_name}: no tool is enabled; give passive tools' .rom files "
                              f"(tools=a.rom,b.rom) or plug in the Aurora's sensors")
        self.tool_handles = {h: handles.get(h, f"handle {h:02X}") for h in enabled}
        self.tools = tuple(self.tool_handles.values())

    def _release(self) -> None:
        """A clean end: TSTOP, then PHF for every handle this session requested with PHRQ (its passive tools), so
        the device is left as a next client (or NDI's own tools) expect to find it. Wired tools' handles are the
        device's own: kept (a freed one may not be assigned again until its sensor is plugged in again; the next
        INIT initialises them). Stops at the first sign the device is gone."""
        try:
            self._command("TSTOP:")
        except NDIReplyError:
            pass  # not tracking (ERROR0C): the handles are still to be freed
        for handle in sorted(self._requested):
            try:
                self._command(f"PHF:{handle:02X}")
            except NDIReplyError as exc:  # already gone (a device reset under us): nothing to free
                log.debug("%s", exc)

    def _upload_rom(self, handle: int, rom: bytes) -> None:
        """PVWR: the .rom in 64-byte chunks (hex), the last padded with zeros, as ndicapi does."""
        for address in range(0, len(rom), PVWR_CHUNK):
            chunk = rom[address:address + PVWR_CHUNK].ljust(PVWR_CHUNK, b"\0")
            self._command(f"PVWR:{handle:02X}{address:04X}{chunk.hex().upper()}")

    def _handles(self, which: str) -> list[int]:
        """PHSR's handles: 00 all, 02 to initialise, 03 to enable, 04 enabled."""
        text = self._command(f"PHSR:{which}")
        try:
            n = int(text[:2], 16)
            return [int(text[2 + 5 * i:4 + 5 * i], 16) for i in range(n)]
        except ValueError:
            raise ProtocolError(f"{self.device_name}: PHSR {which}: malformed reply {text[:40]!r}") from None

    def _close_port(self) -> None:
        if self._ser is not None:
            ser, self._ser = self._ser, None
            try:
                ser.close()
            except Exception:
                log.debug("closing %s", self.device_name, exc_info=True)

    # --- lifecycle ---------------------------------------------------------------------------------------------
    def open(self) -> None:
        if self._thread is not None:
            return
        self._wait_for_leftover("bringing the tracker up")
        self._stop.clear()  # before the bring-up, which stops at its next step once it is set
        self._connect()
        self._reader_started(threading.Thread(target=self._run, name=f"tracker {self.port_path}", daemon=True))

    def close(self) -> None:
        """Stop the reader, end the session (TSTOP, PHF) and close the port. A reader still busy past
        ``close_join_s`` (a bring-up step that waits for the device) is left to end by itself: it stops the
        bring-up at its next step, or ends the session it completed, and closes the port either way."""
        if self._stop_reader("closes the port"):
            self._release_quietly()
        if not self._abandoned:
            self._close_port()

    def _release_quietly(self) -> None:
        try:
            self._release()
        except Exception:  # the device may be gone; nothing is left to do about it
            log.debug("%s: TSTOP / PHF on close", self.device_name, exc_info=True)

    # --- the reader thread -------------------------------------------------------------------------------------
    def _note_lost(self, kind: str, message: str) -> None:
        self._count(kind)
        self._last_fault = self._last_error = message
        self._last_error_wall = time.monotonic()
        log.debug("%s", message)

    def _run(self) -> None:
        import termios

        import serial

        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        lost, last_reply = 0, next_t  # replies lost in a row; when the last one came
        try:
            while not self._stop.is_set():
                if not self._connected:
                    self._reconnect()
                    next_t = last_reply = time.monotonic()
                    lost = 0
                    continue
                try:
                    self._check_unasked()
                    reply, t_ns = self._poll_reply()
                    self._accept(reply, t_ns)
                    lost, last_reply = 0, time.monotonic()
                except TrackerResetError as exc:
                    self._bring_up_again("device_resets", f"{exc}: it reset (a power blip?); bringing it up "
                                                          f"again", after_reset=True)
                    continue
                except DeviceTimeoutError as exc:
                    self._note_lost("timeouts", str(exc))
                    lost += 1
                except ReplyCRCError as exc:
                    self._note_lost("crc_errors", str(exc))
                    lost += 1
                except NDIReplyError as exc:
                    if exc.code == ERROR_NOT_TRACKING:  # the device left tracking by itself: a reset
                        self._bring_up_again("device_resets", f"{exc}: it is not tracking any more (reset?); "
                                                              f"bringing it up again")
                        continue
                    self._note_lost("errors", str(exc))
                    lost += 1
                except ProtocolError as exc:
                    self._note_lost("errors", str(exc))
                    lost += 1
                except (serial.SerialException, OSError, termios.error) as exc:
                    self._count("disconnects")
                    self._last_fault = f"{self.device_name}: lost ({exc}); reconnecting"
                    log.warning("%s", self._last_fault)
                    self._connected = False
                    self._recovering = False
                    self._close_port()
                    continue
                silent_s = time.monotonic() - last_reply
                if lost >= self.lost_replies_min and silent_s >= self.lost_for_s:
                    self._bring_up_again("unanswered", f"{self.device_name}: {lost} replies lost in a row over "
                                                       f"{silent_s:.1f} s (last: {self._last_error}); bringing "
                                                       f"the tracker up again (a reset puts it back at 9600 baud)")
                    continue
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()  # behind: no burst to catch up
        except BaseException as exc:  # stored and raised by read(): never lost with the thread
            self._error = exc
            log.error("%s: reader thread failed: %s", self.device_name, exc)
        finally:
            with self._life:
                self._reader_running = False
                abandoned = self._abandoned  # close() gave up waiting: nobody else will end the session
                release = abandoned and self._connected
                if abandoned:
                    self._connected = False
            if release:
                self._release_quietly()
            if abandoned:
                self._close_port()

    def _bring_up_again(self, kind: str, message: str, after_reset: bool = False) -> None:
        """The device no longer tracks for this session (it reset, or stopped answering): counted, then the
        reader thread reconnects through the full bring-up; the port itself is fine, so health reads stale."""
        self._count(kind)
        self._last_fault = self._last_error = message
        self._last_error_wall = time.monotonic()
        log.warning("%s", message)
        self._connected = False
        self._recovering = True
        self._after_reset = after_reset
        self._close_port()

    def _reconnect(self) -> None:
        if self._stop.wait(self.reconnect_interval_s):
            return
        after_reset, self._after_reset = self._after_reset, False  # a second try takes the usual path
        try:
            self._connect(after_reset)
        except BringUpStopped:
            return  # close() came: _connect closed the port
        except DeviceError as exc:
            self._last_fault = str(exc)
            return
        with self._life:
            closing = self._stop.is_set()
            if not closing:
                self._connected = True
                self._recovering = False
        if closing:  # close() came as the bring-up completed (and may have stopped waiting): end it here
            self._release_quietly()
            self._close_port()
            return
        self._count("reconnects")
        log.warning("%s reconnected", self.device_name)

    def _accept(self, reply: TrackingReply, t_ns: int) -> None:
        samples, trouble = [], {}
        for rec in reply.records:
            tool = self.tool_handles.get(rec.handle, f"handle {rec.handle:02X}")
            if rec.status == HANDLE_MISSING:
                self._count("missing")
                trouble[tool] = "MISSING"
                continue
            if rec.status != HANDLE_VALID:
                continue
            if not rec.in_volume:
                self._count("out_of_volume")
                trouble[tool] = "out of volume"
                if rec.partially_out_of_volume:
                    self._count("partially_out_of_volume")
                    trouble[tool] = "partially out of volume"
            if self._last_frame.get(rec.handle) == rec.frame:
                continue  # polled faster than the device measures: the same measurement again
            self._last_frame[rec.handle] = rec.frame
            try:
                T = pose_matrix(rec.q, rec.t_mm)
            except ProtocolError as exc:
                self._note_lost("errors", f"{self.device_name}: {tool}: {exc}")
                continue
            samples.append((T, tool, rec))
        if samples and t_ns <= self._last_t_ns:
            self._count("non_increasing_stamps")
            t_ns = self._last_t_ns + 1
        with self._cond:
            self._tool_trouble = trouble
            for T, tool, rec in samples:
                self._new.append(MarkerSample(T, t_ns, self._seq, tool, float(rec.rms_mm), rec.in_volume))
                self._seq += 1
            if samples:
                self._last_t_ns = t_ns
                self._last_pose_wall = time.monotonic()
            # a reply that arrived is a live device even while every tool is missing
            self._last_reply_wall = time.monotonic()
            self._cond.notify_all()

    # --- the consumer's side -------------------------------------------------------------------------------------
    def _read(self, timeout_s: float | None) -> list[MarkerSample]:
        if self._error is not None:
            raise DeviceError(f"{self.device_name}: reader failed: {self._error}") from self._error
        if self._thread is None:
            raise DeviceError(f"{self.device_name} is not open")
        with self._cond:
            if not self._new and timeout_s:
                self._cond.wait(timeout_s)
            out = list(self._new)
            self._new.clear()
        return out

    @property
    def health(self) -> Health:
        now = time.monotonic()
        if self._error is not None:
            return Health(HealthState.FAULTED, f"reader thread failed: {self._error}", self._clock())
        if self._thread is None:
            return Health(HealthState.DISCONNECTED, "not open", self._clock())
        with self._cond:
            last, trouble, last_reply = self._last_pose_wall, dict(self._tool_trouble), self._last_reply_wall
        if not self._connected:
            if self._recovering:  # the port is there; the device is being brought up again
                silent = "no pose yet" if last == 0.0 else f"no pose for {(now - last) * 1e3:.0f} ms"
                return Health(HealthState.STALE, f"{silent} ({self._last_fault})", self._clock())
            return Health(HealthState.DISCONNECTED, self._last_fault or "reconnecting", self._clock())
        fresh = self.stale_after_periods / self.rate_hz
        if trouble and now - last_reply <= fresh:  # the device answers; a tool is not seen (well)
            silent = "" if now - last <= fresh else f" (no pose for {(now - last) * 1e3:.0f} ms)"
            return Health(HealthState.DEGRADED, "; ".join(f"{k}: {v}" for k, v in trouble.items()) + silent,
                          self._clock())
        if last == 0.0 or now - last > fresh:
            silent = "no pose yet" if last == 0.0 else f"no pose for {(now - last) * 1e3:.0f} ms"
            why = "; ".join(f"{k}: {v}" for k, v in trouble.items()) or self._last_fault or "no fault seen"
            return Health(HealthState.STALE, f"{silent} ({why})", self._clock())
        if now - self._last_error_wall < max(self.degraded_min_s, self.degraded_after_periods / self.rate_hz):
            counts = self.faults
            lost = counts["timeouts"] + counts["crc_errors"] + counts["errors"]
            return Health(HealthState.DEGRADED, f"{lost} replies lost so far; last: {self._last_error}",
                          self._clock())
        return Health(HealthState.OK, "", self._clock())
