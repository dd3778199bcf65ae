"""The NDI Combined API's wire format (Polaris, Aurora), host side: command framing, reply CRCs, and the
decoding of ``TX`` (text) and ``BX`` (binary) tracking replies. Pure functions over bytes; no I/O.

- A command is ASCII ending in CR. ``CMD:params`` carries a CRC-16/ARC of everything before it, as 4 uppercase
  hex digits; ``CMD params`` and ``CMD`` carry none.
- Every text reply ends with the CRC-16/ARC of its text (4 uppercase hex digits), then CR; errors read
  ``ERRORxx`` (hex code).
- ``BX``: little-endian; C4 A5, u16 body length, u16 CRC of those 4 bytes; the body: u8 handle count, per
  handle u8 handle, u8 status (01 valid, 02 missing, 04 disabled), for a valid handle 8 float32 (q0 qx qy qz
  tx ty tz rms), for a valid or missing one u32 port status and u32 frame number; then u16 system status; then
  the body's u16 CRC. (The handle count is not in docs/device-facts' summary; ndicapi's BX parser and NDI's
  API guide have it.)
- ``TX``: 2 hex digits handle count, per handle 2 hex digits handle, then 51 characters of transform (q0 qx qy
  qz: sign + 5 digits x 1e-4; tx ty tz: sign + 6 digits x 0.01 mm; rms: sign + 5 digits x 1e-4 mm) or
  ``MISSING`` / ``DISABLED``, 8 hex digits port status, 8 hex digits frame number, LF; then 4 hex digits system
  status.

Quaternions are scalar FIRST (q0 qx qy qz), translations in millimetres, in the tracker's frame.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lapreco_hil.errors import ProtocolError

CR = b"\r"
BX_START = b"\xc4\xa5"  # 0xA5C4, little-endian
HANDLE_VALID, HANDLE_MISSING, HANDLE_DISABLED = 0x01, 0x02, 0x04
# port status bits (NDI Combined API): bit 6 out of volume: the tool is outside the characterised volume (its pose
# reported only with reply option 0800); bit 7 partially out of volume: some of its markers are (ndicapi names the
# bit NDI_PARTIALLY_IN_VOLUME; NDI's guide "partially out of volume"). A pose with either is less trusted.
PORT_OUT_OF_VOLUME = 0x40
PORT_PARTIALLY_OUT_OF_VOLUME = 0x80
REPLY_TRANSFORMS, REPLY_OUT_OF_VOLUME = 0x0001, 0x0800
MAX_BX_BODY = 8192
ERROR_CODES = {0x01: "unknown command", 0x04: "bad CRC in the command", 0x0C: "not tracking",
               0x2B: "bad port handle"}
ERROR_NOT_TRACKING = 0x0C


class ReplyCRCError(ProtocolError):
    """A reply whose CRC does not match its bytes: the reply is lost, never parsed."""


class NDIReplyError(ProtocolError):
    """The device answered ``ERRORxx``."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class TrackerResetError(ProtocolError):
    """The device said ``RESET`` unasked (a power blip, a watchdog): it is back at 9600 baud, neither initialised
    nor tracking, with a fresh handle table; only a full bring-up gets it going again."""


def _crc16_arc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1  # 0xA001: 0x8005 reflected
        table.append(crc)
    return tuple(table)


_TABLE = _crc16_arc_table()


def crc16_arc(data: bytes) -> int:
    """CRC-16/ARC (poly 0x8005 reflected, init 0, no final xor): "123456789" -> 0xBB3D, b"RESET" -> 0xBE6F."""
    crc = 0
    for byte in data:
        crc = (crc >> 8) ^ _TABLE[(crc ^ byte) & 0xFF]
    return crc


# what a device sends when it comes out of a reset (a break, a power blip): RESET, its CRC, CR
RESET_REPLY = b"RESET" + f"{crc16_arc(b'RESET'):04X}".encode("ascii") + CR


def command_bytes(command: str) -> bytes:
    """The bytes to send: ``CMD:params`` gets its CRC appended, ``CMD params`` / ``CMD`` none; then CR."""
    text = command.encode("ascii")
    if b":" in text:
        text += f"{crc16_arc(text):04X}".encode("ascii")
    return text + CR


def check_text_reply(raw: bytes, what: str) -> str:
    """The text of a reply (``raw`` without its CR or with it) after its CRC is checked; ``ERRORxx`` raised.

    Raises ReplyCRCError (bad or absent CRC), NDIReplyError (the device's ERRORxx)."""
    raw = raw[:-1] if raw.endswith(CR) else raw
    if len(raw) < 4:
        raise ReplyCRCError(f"{what}: reply {raw!r} is too short to carry a CRC")
    body, crc_text = raw[:-4], raw[-4:]
    try:
        crc = int(crc_text.decode("ascii"), 16)
    except (UnicodeDecodeError, ValueError):
        raise ReplyCRCError(f"{what}: reply {raw[:40]!r} does not end in 4 hex digits of CRC") from None
    if crc != crc16_arc(body):
        raise ReplyCRCError(f"{what}: reply CRC {crc:04X} != {crc16_arc(body):04X} computed over {len(body)} bytes")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(f"{what}: reply is not ASCII") from None
    if text.startswith("ERROR"):
        try:
            code = int(text[5:7], 16)
        except ValueError:
            raise ProtocolError(f"{what}: malformed error reply {text!r}") from None
        raise NDIReplyError(f"{what}: device answered ERROR{code:02X} ({ERROR_CODES.get(code, 'see the API guide')})",
                            code)
    return text


@dataclass(frozen=True)
class HandleRecord:
    """One port handle's part of a TX/BX reply. ``q`` scalar first (q0 qx qy qz, as sent: not normalised),
    ``t_mm`` millimetres; both None unless the handle is valid."""

    handle: int
    status: int  # HANDLE_VALID, HANDLE_MISSING, HANDLE_DISABLED
    q: tuple[float, float, float, float] | None
    t_mm: tuple[float, float, float] | None
    rms_mm: float
    port_status: int
    frame: int

    @property
    def in_volume(self) -> bool:
        """Wholly inside the characterised volume: neither out of it (bit 6) nor partially out (bit 7). A pose
        partially out is not trusted either: the device's accuracy holds inside the volume only."""
        return not self.port_status & (PORT_OUT_OF_VOLUME | PORT_PARTIALLY_OUT_OF_VOLUME)

    @property
    def partially_out_of_volume(self) -> bool:
        """Partially out of the characterised volume (bit 7) and not wholly out (bit 6)."""
        return bool(self.port_status & PORT_PARTIALLY_OUT_OF_VOLUME) and not self.port_status & PORT_OUT_OF_VOLUME


@dataclass(frozen=True)
class TrackingReply:
    records: tuple[HandleRecord, ...]
    system_status: int


def bx_header(header: bytes) -> int:
    """The body length a 6-byte BX header announces (raises ReplyCRCError / ProtocolError)."""
    if len(header) != 6 or header[:2] != BX_START:
        raise ProtocolError(f"BX: reply does not start with C4 A5 ({header[:6].hex(' ')})")
    length, crc = struct.unpack_from("<HH", header, 2)
    if crc != crc16_arc(header[:4]):
        raise ReplyCRCError(f"BX: header CRC {crc:04X} != {crc16_arc(header[:4]):04X}")
    if length > MAX_BX_BODY:
        raise ProtocolError(f"BX: body length {length} is beyond any BX reply ({MAX_BX_BODY})")
    return length


def parse_bx(reply: bytes) -> TrackingReply:
    """A whole BX reply (header, body, body CRC) with reply option 0001 (plus 0800, which adds no bytes)."""
    length = bx_header(reply[:6])
    if len(reply) != 6 + length + 2:
        raise ProtocolError(f"BX: {len(reply)} bytes for a body of {length} (expected {6 + length + 2})")
    body = reply[6:6 + length]
    (crc,) = struct.unpack_from("<H", reply, 6 + length)
    if crc != crc16_arc(body):
        raise ReplyCRCError(f"BX: body CRC {crc:04X} != {crc16_arc(body):04X}")
    try:
        count = body[0]
        pos, records = 1, []
        for _ in range(count):
            handle, status = body[pos], body[pos + 1]
            pos += 2
            if status == HANDLE_DISABLED:
                records.append(HandleRecord(handle, status, None, None, float("nan"), 0, 0))
                continue
            if status not in (HANDLE_VALID, HANDLE_MISSING):
                raise ProtocolError(f"BX: handle {handle:02X} has status {status:02X} (not 01, 02 or 04)")
            q = t = None
            rms = float("nan")
            if status == HANDLE_VALID:
                values = struct.unpack_from("<8f", body, pos)
                pos += 32
                q, t, rms = tuple(values[0:4]), tuple(values[4:7]), values[7]
            port_status, frame = struct.unpack_from("<II", body, pos)
            pos += 8
            records.append(HandleRecord(handle, status, q, t, rms, port_status, frame))
        (system_status,) = struct.unpack_from("<H", body, pos)
        pos += 2
    except (IndexError, struct.error):
        raise ProtocolError(f"BX: body of {length} bytes ends inside a handle record") from None
    if pos != length:
        raise ProtocolError(f"BX: {length - pos} bytes left over after the system status")
    return TrackingReply(tuple(records), system_status)


def _signed(text: str, scale: float, what: str) -> float:
    if text[:1] not in ("+", "-") or not text[1:].isdigit():
        raise ProtocolError(f"TX: {what} field {text!r} is not a sign and digits")
    return int(text) * scale


def _hex(text: str, n: int, what: str) -> int:
    if len(text) != n or any(c not in "0123456789ABCDEFabcdef" for c in text):
        raise ProtocolError(f"TX: {what} {text!r} is not {n} hex digits")
    return int(text, 16)


def parse_tx(text: str) -> TrackingReply:
    """The text of a TX reply (CRC already checked and removed) with reply option 0001 (plus 0800)."""
    count = _hex(text[:2], 2, "handle count")
    pos, records = 2, []
    for _ in range(count):
        handle = _hex(text[pos:pos + 2], 2, "handle")
        pos += 2
        q = t = None
        rms = float("nan")
        if text.startswith("MISSING", pos):
            status, pos = HANDLE_MISSING, pos + 7
        elif text.startswith("DISABLED", pos):
            status, pos = HANDLE_DISABLED, pos + 8
        else:
            f = text[pos:pos + 51]
            if len(f) != 51:
                raise ProtocolError(f"TX: handle {handle:02X}: transform cut short")
            q = tuple(_signed(f[i:i + 6], 1e-4, "quaternion") for i in (0, 6, 12, 18))
            t = tuple(_signed(f[i:i + 7], 1e-2, "translation") for i in (24, 31, 38))
            rms = _signed(f[45:51], 1e-4, "rms")
            status, pos = HANDLE_VALID, pos + 51
        port_status, frame = 0, 0
        if status != HANDLE_DISABLED:
            port_status = _hex(text[pos:pos + 8], 8, "port status")
            frame = _hex(text[pos + 8:pos + 16], 8, "frame number")
            pos += 16
        if text[pos:pos + 1] != "\n":
            raise ProtocolError(f"TX: handle {handle:02X}: record does not end in LF")
        pos += 1
        records.append(HandleRecord(handle, status, q, t, rms, port_status, frame))
    system_status = _hex(text[pos:pos + 4], 4, "system status")
    if pos + 4 != len(text):
        raise ProtocolError(f"TX: {len(text) - pos - 4} characters left over after the system status")
    return TrackingReply(tuple(records), system_status)


def pose_matrix(q: tuple[float, float, float, float], t_mm: tuple[float, float, float]) -> np.ndarray:
    """4x4 T_tracker_marker in METRES from a scalar-first quaternion (normalised here: TX's 4-digit components
    are off unit length by up to ~1e-4) and a translation in millimetres. Raises ProtocolError on a zero or
    non-finite quaternion or translation."""
    qv = np.asarray(q, np.float64)
    tv = np.asarray(t_mm, np.float64)
    norm = float(np.linalg.norm(qv))
    if not (np.all(np.isfinite(qv)) and np.all(np.isfinite(tv))) or norm < 0.5:
        raise ProtocolError(f"pose with quaternion {tuple(qv)} and translation {tuple(tv)} mm is not a pose")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(qv / norm, scalar_first=True).as_matrix()
    T[:3, 3] = tv * 1e-3
    return T
