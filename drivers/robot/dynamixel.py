"""A robot of ROBOTIS Dynamixel X-series servos on one serial bus, Protocol 2.0, through the official
``dynamixel-sdk`` (PortHandler, Protocol2PacketHandler: framing, byte stuffing, CRC-16).

``serial:///dev/ttyUSB0?baud=1000000&ids=1,2,3,4&rate=100&model=ecm&map=joints.toml``
(parameters: :class:`DynamixelConfig`; servo IDs 0..252, in joint order). Present Position ticks become
joint positions with the X-series convention, 2048 ticks = 0 rad (see ``joint_map``).

Each poll is one Sync Read of the block 120..135 of every servo (Realtime Tick, current, velocity, Present
Position), servo IDs in joint order. The status packets are taken in whatever order they come, each by its ID
(the e-manual has servos answer in the instruction's order, but a chain that answers otherwise loses nothing).
A reading is stamped at the middle of the request/reply exchange on the injected clock (the servos sample their
encoders when they build the reply).

Status packets carry no sequence number, so a packet that comes after its Sync Read gave up (timed out, or cut
short by a corrupt or duplicate packet) would pass for the next Sync Read's reply from that servo, and a reading
would join positions of two cycles under one stamp. After any exchange that did not end clean, and whenever
bytes wait on the line before a Sync Read, the driver lets the line go quiet first: it reads and drops what
comes until nothing has come for ``settle_quiet_s`` (the servos' longest Return Delay, 508 us, plus a USB
adapter's latency timer, 16 ms, plus a few byte-times), at most ``settle_limit_s`` (past that the cycle is lost
and the next one tries again). The status packets dropped so are counted as ``stale_replies``. The first Sync
Read after such an exchange is on probation: after its last reply the driver listens for another
``settle_quiet_s``, and any status packet then (a late one may have come ahead of the fresh reply of the same
servo and filled the set), or a second packet from one servo within an exchange, discards the whole reading
(``stale_replies`` and a protocol error): a reading is never made of packets of two cycles. What is left: a
packet later than the timeout, the quiet wait and a whole clean cycle that comes just before its servo's fresh
reply; the servos' Realtime Tick could tell it, but it follows the emulator's clock in a simulation, so it is
not used.

A status packet with the error byte's alert bit set marks the robot faulted until replies come back clean; at
each servo's alert onset its Hardware Error Status (address 70) is read once and its bits named (input voltage,
overheating, motor encoder, electrical shock, overload). With the motor-encoder bit set the positions are not
trustworthy: the readings are refused (counted as ``refused_encoder_error``) until the alert clears.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.robot.joint_map import DYNAMIXEL_TICKS_PER_REV, dynamixel_joint_map
from lapreco_hil.drivers.robot.polling import REFUSED_ENCODER_ERROR, PolledRobotConfig, PollingRobotDriver, RawReading
from lapreco_hil.errors import (DeviceDisconnectedError, DeviceError, DeviceNotFoundError, DeviceTimeoutError,
                       ProtocolError)
from lapreco_hil.registry import id_list_parser, url_param

log = logging.getLogger(__name__)

BLOCK_START = 120  # Realtime Tick (2), Moving (1), Moving Status (1), PWM (2), Current (2), Velocity (4), Position (4)
BLOCK_LEN = 16
POSITION_OFFSET = 132 - BLOCK_START
ALERT_BIT = 0x80
HARDWARE_ERROR_STATUS = 70  # 1 byte
# Hardware Error Status bits (X-series): 0 input voltage, 2 overheating, 3 motor encoder, 4 electrical shock, 5 overload
HW_INPUT_VOLTAGE, HW_OVERHEATING, HW_MOTOR_ENCODER, HW_ELECTRICAL_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20
HARDWARE_ERROR_BITS = {HW_INPUT_VOLTAGE: "input voltage", HW_OVERHEATING: "overheating",
                       HW_MOTOR_ENCODER: "motor encoder", HW_ELECTRICAL_SHOCK: "electrical shock",
                       HW_OVERLOAD: "overload"}
HW_STATUS_READ_TRIES = 3  # reads of address 70 per alert onset before its bits are given up as unknown
STATUS_HEADER = b"\xff\xff\xfd\x00"  # starts every packet; byte stuffing keeps it out of any payload
RETURN_DELAY_MAX_S = 254 * 2e-6  # Return Delay Time (address 9) at its largest: 254 x 2 us
USB_LATENCY_S = 0.016  # a USB-serial adapter's latency timer (FTDI's default; dynamixel-sdk's LATENCY_TIMER)
X_SERIES_MODELS = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 1120: "XM540-W270", 1000: "XH430-W350"}


def hardware_error_text(status: int | None) -> str:
    """A Hardware Error Status byte (address 70) in words; None: it could not be read."""
    if status is None:
        return "hardware error alert (Hardware Error Status, address 70, could not be read)"
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if status & bit]
    other = status & ~sum(HARDWARE_ERROR_BITS)
    if other:
        names.append(f"bits 0x{other:02X}")
    text = (f"hardware error alert: Hardware Error Status (address 70) 0x{status:02X}: "
            f"{', '.join(names) or 'no bit set'}")
    if status & HW_MOTOR_ENCODER:
        text += "; its positions are not trustworthy: readings refused"
    return text


def serial_ports() -> list[str]:
    from serial.tools import list_ports

    return sorted(p.device for p in list_ports.comports())


DYNAMIXEL_IDS = (0, 252)  # Protocol 2.0: 253..255 are reserved (0xFE broadcast)
BAUD_RATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 4_500_000)  # X-series settings


def _baud(text: str) -> int:
    baud = int(text)
    if baud not in BAUD_RATES:
        raise ValueError(f"is not an X-series baud rate ({', '.join(map(str, BAUD_RATES))})")
    return baud


@dataclass(frozen=True)
class DynamixelConfig(PolledRobotConfig):
    baud: int = url_param(1_000_000, parse=_baud, help="bus baud rate")
    ids: tuple[int, ...] = url_param((1, 2, 3, 4), parse=id_list_parser(*DYNAMIXEL_IDS, "Dynamixel Protocol 2.0"),
                                     help="servo IDs in joint order, e.g. 1,2,3,4 or 1-4")
    counts_per_rev: float = url_param(float(DYNAMIXEL_TICKS_PER_REV), low=1.0, help="ticks per revolution")


class DynamixelRobot(PollingRobotDriver):
    raw_unit = "ticks"

    def __init__(self, url, context) -> None:
        config = DynamixelConfig.from_url(url)
        if not url.name:
            raise url.error("give the serial port, e.g. serial:///dev/ttyUSB0?ids=1,2,3,4")
        self.port_path = url.name
        self.baud = config.baud
        self.ids = list(config.ids)
        joint_map = dynamixel_joint_map(config.model, config.map, config.lead_m, config.counts_per_rev)
        if len(self.ids) != len(joint_map.names):
            raise DeviceError(f"robot '{url.raw}': {len(self.ids)} servo IDs for {len(joint_map.names)} joints "
                              f"({', '.join(joint_map.names)})")
        super().__init__(url, context, config, joint_map, f"Dynamixel bus '{self.port_path}'")
        self._port = None
        self._packets = None
        self.models: dict[int, int] = {}
        # per servo reporting the alert bit: its Hardware Error Status (None: unread after every try), and the
        # reads tried; both forgotten when the alert clears, so the next onset is read again
        self._hw_status: dict[int, int | None] = {}
        self._hw_tries: dict[int, int] = {}
        self._refuse = ""  # why the reading _poll just returned must not be delivered ("" : it may)
        # set until an exchange ends clean: late packets of it may still come, so the line is let go quiet first
        self._unsettled = False
        # the line is quiet once nothing came for this long (see the module's doc); at most settle_limit_s of it
        self.settle_quiet_s = RETURN_DELAY_MAX_S + USB_LATENCY_S + 20 * 10 / self.baud
        self.settle_limit_s = 0.2

    @classmethod
    def discover(cls) -> Discovery:
        ports = serial_ports()
        return Discovery("serial ports (Dynamixel robots)",
                         tuple(FoundDevice(p, f"serial://{p}?baud=1000000&ids=1,2,3,4") for p in ports),
                         "" if ports else "no serial ports (is the USB-RS485/TTL adapter plugged in?)")

    def _connect(self) -> None:
        import serial
        from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

        port = PortHandler(self.port_path)
        try:
            opened = port.openPort()
        except (serial.SerialException, OSError) as exc:
            ports = serial_ports()
            raise DeviceNotFoundError(f"serial port '{self.port_path}' cannot be opened ({exc}); serial ports "
                                      f"here: {', '.join(ports) if ports else 'none'}") from None
        if not opened:
            raise DeviceNotFoundError(f"serial port '{self.port_path}' cannot be opened")
        if not port.setBaudRate(self.baud):
            port.closePort()
            raise DeviceError(f"serial port '{self.port_path}': baud rate {self.baud} is not supported")
        packets = PacketHandler(2.0)
        missing, models = [], {}
        for dxl_id in self.ids:
            for _ in range(3):  # a ping can be lost on a noisy line; a missing servo misses all three
                port.ser.reset_input_buffer()
                model, result, _ = packets.ping(port, dxl_id)
                port.is_using = False
                if result == COMM_SUCCESS:
                    models[dxl_id] = model
                    break
            else:
                missing.append(dxl_id)
        if missing:
            port.closePort()
            asked = ", ".join(map(str, missing))
            if not models:  # a whole chain silent: most often a baud rate the servos are not set to
                raise DeviceNotFoundError(
                    f"Dynamixel bus '{self.port_path}' at {self.baud} baud: no servo answered (ID(s) {asked} "
                    f"pinged); check the baud rate first (baud= in the URL must equal the servos' Baud Rate "
                    f"setting, address 8; X-series leave the factory at 57600), then the servos' power and IDs")
            found = ", ".join(str(i) for i in models)
            raise DeviceNotFoundError(f"Dynamixel bus '{self.port_path}' at {self.baud} baud: no answer from "
                                      f"ID(s) {asked} (answered: {found}); check the IDs, the baud rate and the "
                                      f"servos' power")
        for dxl_id, model in models.items():
            if model not in X_SERIES_MODELS:
                log.warning("Dynamixel ID %d reports model %d, not a known X-series servo; assuming the X-series "
                            "control table", dxl_id, model)
        self._port, self._packets, self.models = port, packets, models

    def _disconnect(self) -> None:
        if self._port is not None:
            port, self._port = self._port, None
            port.closePort()

    def _poll(self) -> tuple[np.ndarray, int]:
        import termios

        import serial
        from dynamixel_sdk import COMM_SUCCESS

        port, packets = self._port, self._packets
        counts = np.empty(len(self.ids), np.int64)
        self._refuse = ""
        try:
            # bytes waiting before the request are late packets (or noise): the line may not be quiet yet
            probation = self._unsettled or getattr(port.ser, "in_waiting", 0) > 0  # (a scripted test port has none)
            self._unsettled = True  # until this exchange ends clean
            if probation:
                self._settle(port)
            port.is_using = False
            t0 = self._clock()
            result = packets.syncReadTx(port, BLOCK_START, BLOCK_LEN, self.ids, len(self.ids), False)
            if result != COMM_SUCCESS:
                raise ProtocolError(f"{self.device_name}: Sync Read not sent ({packets.getTxRxResult(result)})")
            replies = self._sync_read_replies(port, packets)
            t1 = self._clock()
            if probation:
                late = self._drain_until_quiet(port)
                if late:
                    raise ProtocolError(f"{self.device_name}: reading discarded: {self._stale_text(late)} came "
                                        f"after the Sync Read's replies (a late packet may have stood in for a "
                                        f"fresh one)")
            self._unsettled = False
            refused = []
            for j, dxl_id in enumerate(self.ids):
                error, data = replies[dxl_id]
                if error & ALERT_BIT:
                    status = self._hardware_error_status(port, packets, dxl_id)
                    self.set_device_fault(f"servo {dxl_id}", hardware_error_text(status))
                    if status is not None and status & HW_MOTOR_ENCODER:
                        refused.append(f"servo {dxl_id}: motor encoder error (Hardware Error Status 0x{status:02X})")
                else:
                    self._hw_status.pop(dxl_id, None)
                    self._hw_tries.pop(dxl_id, None)
                    self.set_device_fault(f"servo {dxl_id}", None)
                if error & ~ALERT_BIT:
                    raise ProtocolError(f"{self.device_name}: servo ID {dxl_id}: {packets.getRxPacketError(error)}")
                if len(data) != BLOCK_LEN:
                    raise ProtocolError(f"{self.device_name}: servo ID {dxl_id}: {len(data)} data bytes, "
                                        f"expected {BLOCK_LEN}")
                counts[j] = int.from_bytes(bytes(data[POSITION_OFFSET:POSITION_OFFSET + 4]), "little", signed=True)
            self._refuse = "; ".join(refused)
        except (serial.SerialException, OSError, termios.error) as exc:
            raise DeviceDisconnectedError(f"{self.device_name}: lost ({exc}); reconnecting") from None
        finally:
            port.is_using = False
        return counts, (t0 + t1) // 2

    def _drain_until_quiet(self, port) -> list[int]:
        """Read and drop what comes until nothing has come for ``settle_quiet_s``; the IDs of the status packets
        dropped (each counted as ``stale_replies``). ProtocolError when the line is not quiet within
        ``settle_limit_s`` (the exchange stays unsettled: the next poll waits again)."""
        start = last = time.monotonic()
        dropped = bytearray()
        while True:
            chunk = port.readPort(4096)  # the SDK's port reads without blocking (timeout 0)
            now = time.monotonic()
            if chunk:
                dropped += chunk
                last = now
            elif now - last >= self.settle_quiet_s:
                break
            if now - start > self.settle_limit_s:
                ids = self._count_stale(dropped)
                raise ProtocolError(f"{self.device_name}: the bus did not go quiet within "
                                    f"{self.settle_limit_s * 1e3:.0f} ms ({len(dropped)} bytes dropped"
                                    + (f", {self._stale_text(ids)}" if ids else "") + ")")
            time.sleep(min(0.001, self.settle_quiet_s / 4))
        return self._count_stale(dropped)

    def _count_stale(self, dropped: bytes) -> list[int]:
        """The servo IDs of the status packets (whole or cut) in ``dropped``, each counted as ``stale_replies``."""
        ids, at = [], dropped.find(STATUS_HEADER)
        while at >= 0:
            ids.append(dropped[at + 4] if at + 4 < len(dropped) else -1)
            self.count_fault("stale_replies")
            at = dropped.find(STATUS_HEADER, at + 4)
        return ids

    @staticmethod
    def _stale_text(ids: list[int]) -> str:
        return (f"{len(ids)} late status packet(s) (servo ID(s) "
                f"{', '.join('?' if i < 0 else str(i) for i in ids)})")

    def _settle(self, port) -> None:
        """Let the line go quiet before a Sync Read, dropping (and counting) what comes meanwhile."""
        ids = self._drain_until_quiet(port)
        if ids:
            log.debug("%s: %s dropped before the Sync Read", self.device_name, self._stale_text(ids))

    def _sync_read_replies(self, port, packets) -> dict[int, tuple[int, list[int]]]:
        """Every servo's status packet to the Sync Read just sent, in whatever order they come: servo ID ->
        (error byte, data). The SDK's readRx(ID) would drop every packet before the one it waits for, so a
        chain answering in another order than the instruction's list would lose them; here each is kept by its
        ID (packets of IDs not asked for are skipped, counted as ``stale_replies``). A second packet from one
        servo means one of the two answers an earlier request: the reading is discarded (ProtocolError). Within
        the Sync Read's packet timeout, as readRx."""
        from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS
        from dynamixel_sdk.protocol2_packet_handler import PKT_ERROR, PKT_ID, PKT_PARAMETER0

        replies: dict[int, tuple[int, list[int]]] = {}
        while len(replies) < len(self.ids):
            packet, result = packets.rxPacket(port, False)
            if result != COMM_SUCCESS:
                waiting = ", ".join(str(i) for i in self.ids if i not in replies)
                if result == COMM_RX_TIMEOUT:
                    raise DeviceTimeoutError(f"{self.device_name}: servo ID(s) {waiting} did not answer the Sync Read")
                raise ProtocolError(f"{self.device_name}: servo ID(s) {waiting}: {packets.getTxRxResult(result)}")
            dxl_id = packet[PKT_ID]
            if dxl_id in replies:
                self.count_fault("stale_replies")
                raise ProtocolError(f"{self.device_name}: reading discarded: two status packets from servo ID "
                                    f"{dxl_id} to one Sync Read (one of them late, from an earlier request)")
            if dxl_id in self.ids:
                replies[dxl_id] = (packet[PKT_ERROR],
                                   packet[PKT_PARAMETER0 + 1:PKT_PARAMETER0 + 1 + BLOCK_LEN])
            else:
                self.count_fault("stale_replies")
        return replies

    def _hardware_error_status(self, port, packets, dxl_id: int) -> int | None:
        """A servo's Hardware Error Status (address 70), read once per alert onset (up to HW_STATUS_READ_TRIES
        reads while it cannot be read; None after them)."""
        from dynamixel_sdk import COMM_SUCCESS

        if dxl_id in self._hw_status:
            return self._hw_status[dxl_id]
        tries = self._hw_tries[dxl_id] = self._hw_tries.get(dxl_id, 0) + 1
        port.ser.reset_input_buffer()
        port.is_using = False
        value, result, _error = packets.read1ByteTxRx(port, dxl_id, HARDWARE_ERROR_STATUS)
        port.is_using = False
        if result == COMM_SUCCESS:
            self._hw_status[dxl_id] = value
            log.warning("%s: servo %d: %s", self.device_name, dxl_id, hardware_error_text(value))
            return value
        self._unsettled = True  # its reply may still come, during the next Sync Read
        log.debug("%s: servo %d: Hardware Error Status not read (%s)", self.device_name, dxl_id,
                  packets.getTxRxResult(result))
        if tries >= HW_STATUS_READ_TRIES:
            self._hw_status[dxl_id] = None
            log.warning("%s: servo %d: %s", self.device_name, dxl_id, hardware_error_text(None))
        return None

    def _accept(self, counts: np.ndarray, t_ns: int) -> None:
        """A reading from a servo whose encoder reports an error is refused (counted, with the reason in the
        fault) instead of delivered; any other goes on to the joint map and its limits."""
        if self._refuse:
            self.count_fault("refused_encoder_error")
            # in the raw log as a refused reading, as one beyond the limits is: a probe shows what came and why
            # none was delivered
            self._raw.append(RawReading(np.array(counts, np.int64), t_ns, False, REFUSED_ENCODER_ERROR))
            log.debug("%s: reading refused: %s", self.device_name, self._refuse)
            return
        super()._accept(counts, t_ns)
