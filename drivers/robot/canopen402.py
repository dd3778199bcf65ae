"""A robot of CiA 402 drives (e.g. maxon EPOS4) on a CAN bus, through the ``canopen`` package on python-can.

``canopen://<interface>/<channel>?nodes=1-4&rate=100&heartbeat_ms=100&model=ecm&bitrate=1000000``
(``canopen://socketcan/can0?...`` on real hardware, ``canopen://virtual/ch0?...`` in tests; parameters:
:class:`CANopenConfig`; node ids 1..127.) Position actual value increments become joint positions with the
CiA 402 convention, 0 increments = 0 (see ``joint_map``).

On connect the master checks every node answers SDO (device type), reads its TPDO1 set-up (0x1800, 0x1A00) and
writes only what is missing: a mapping that already holds statusword (0x6041) and position actual value (0x6064),
in any order and beside other objects, is used as it is (a drive's static mapping may be read-only); else
TPDO1 is mapped to statusword + position. TPDO1 goes on every SYNC (transmission type 1) at 0x180 + node, keeping
the device's own "no RTR" bit (bit 30: some devices refuse to clear it). Then each node's producer heartbeat time
(0x1017) and NMT start. Each poll sends one SYNC, stamped on the injected clock (the drives latch their position
on SYNC), and waits ``sync_timeout_ms`` for every node's TPDO1.

A reading only ever combines the TPDOs that answer one SYNC (CiA 301: a synchronous TPDO carries what the drive
sampled at the SYNC that triggered it): a TPDO that comes after its SYNC's wait is discarded and counted
(``stale_tpdos``; the link shows degraded). After a wait times out, the master waits once more as long for the
missing nodes' late frames before the next SYNC; if one is still owed (lost, or later still) it sends no SYNC for
``late_limit_s`` (max(100 ms, 5 x the wait)), discarding any frame meanwhile: a frame could pass for the answer
to a later SYNC only if it came more than 2 x the wait + ``late_limit_s`` after its own.

Heartbeats are supervised (a node silent for 1.5 x its producer time is lost); a node that restarts (boot-up
message, or a heartbeat saying pre-operational while it should be operational) is configured again and started
(``node_restarts``; degraded until its readings resume); from its restart on it owes no TPDO, so a restart during a
SYNC's wait costs no wait for its late frame nor a SYNC pause. While configuring it again fails, it is tried again
every ``reconnect_interval_s`` with no SYNC in between: one counted timeout per attempt. EMCY messages (described
by their CiA 301 error class) and the statusword's fault bit mark the robot faulted until an error-reset EMCY or a
clean statusword clears them.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.robot.cia402 import (POSITION_ACTUAL, PRODUCER_HEARTBEAT, RTR_NOT_ALLOWED, STATUS_FAULT_BIT,
                                              STATUSWORD, TPDO1_COMMUNICATION, TPDO1_MAPPING, TPDO_NOT_VALID,
                                              cia402_object_dictionary, emcy_description)
from lapreco_hil.drivers.robot.joint_map import cia402_joint_map
from lapreco_hil.drivers.robot.polling import PolledRobotConfig, PollingRobotDriver
from lapreco_hil.errors import DeviceDisconnectedError, DeviceError, DeviceNotFoundError, DeviceTimeoutError
from lapreco_hil.registry import id_list_parser, url_param

log = logging.getLogger(__name__)


CANOPEN_NODE_IDS = (1, 127)  # CiA 301: node-ID 0 is reserved for NMT broadcast
SYS_NET = Path("/sys/class/net")


def can_interfaces() -> list[str]:
    """SocketCAN network interfaces this machine has (Linux: type 280 in /sys/class/net)."""
    out = []
    for dev in sorted(SYS_NET.glob("*")):
        try:
            if (dev / "type").read_text().strip() == "280":
                out.append(dev.name)
        except OSError:
            continue
    return out


NMT_BOOT_UP, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x05, 0x7F  # heartbeat states (CiA 301)
NMT_START, NMT_ENTER_PRE_OPERATIONAL = 0x01, 0x80  # NMT commands


def send_nmt(node, command: int) -> None:
    """An NMT command to one node, sent as it is (canopen's ``nmt.state = ...`` logs the state the last heartbeat
    said, and fails on a state it does not know: a heartbeat frame with a broken state byte would then end the
    reader thread)."""
    node.network.send_message(0x000, bytes([command, node.id]))


STATUSWORD_ENTRY = STATUSWORD << 16 | 16  # a TPDO mapping entry: index, sub-index 0, length in bits
POSITION_ENTRY = POSITION_ACTUAL << 16 | 32


def describe_mapping(entries: list[int]) -> str:
    return ", ".join(f"0x{e >> 16:04X}:{(e >> 8) & 0xFF:02X} ({e & 0xFF} bits)" for e in entries) or "nothing"


@dataclass(frozen=True)
class Tpdo1Layout:
    """Where statusword and position actual value sit in a node's TPDO1 (bit offsets, CiA 301 little-endian
    packing in mapping order), read from its mapping entries."""

    entries: tuple[int, ...]
    nbytes: int
    status_bit: int
    position_bit: int

    @classmethod
    def from_entries(cls, entries: list[int]) -> Tpdo1Layout | None:
        """The layout, or None when the mapping lacks statusword (16 bits) or position actual value (32 bits)."""
        offsets, bit = {}, 0
        for e in entries:
            offsets.setdefault(e & 0xFFFFFF00, (bit, e & 0xFF))
            bit += e & 0xFF
        status = offsets.get(STATUSWORD << 16)
        position = offsets.get(POSITION_ACTUAL << 16)
        if bit > 64 or status is None or position is None or status[1] != 16 or position[1] != 32:
            return None
        return cls(tuple(entries), (bit + 7) // 8, status[0], position[0])

    @staticmethod
    def missing(entries: list[int]) -> str:
        have = set(entries)
        lacks = [name for entry, name in ((STATUSWORD_ENTRY, "statusword 0x6041"),
                                          (POSITION_ENTRY, "position actual value 0x6064")) if entry not in have]
        total = sum(e & 0xFF for e in entries)
        return " and ".join(lacks) or f"room for them ({total} bits mapped, 64 at most)"

    def decode(self, data: bytes) -> tuple[int, int]:
        word = int.from_bytes(data, "little")
        status = (word >> self.status_bit) & 0xFFFF
        position = (word >> self.position_bit) & 0xFFFFFFFF
        return status, position - (1 << 32) if position & 0x80000000 else position


@dataclass(frozen=True)
class CANopenConfig(PolledRobotConfig):
    nodes: tuple[int, ...] = url_param((1, 2, 3, 4), parse=id_list_parser(*CANOPEN_NODE_IDS, "CANopen"),
                                       help="node ids in joint order, e.g. 1-4")
    heartbeat_ms: int = url_param(100, low=1, high=65535, unit="ms", help="producer heartbeat time set on each node")
    bitrate: int | None = url_param(None, low=10_000, high=1_000_000, help="CAN bit rate (interfaces that set it)")
    sync_timeout_ms: float = url_param(20.0, low=0.1, high=10_000, unit="ms", help="wait for TPDO1 after SYNC")
    # quadrature: 4 increments per encoder line
    counts_per_rev: float = url_param(4.0 * 4096, low=1.0, help="increments per revolution")


class CANopenRobot(PollingRobotDriver):
    raw_unit = "increments"

    def __init__(self, url, context) -> None:
        config = CANopenConfig.from_url(url)
        self.interface = url.netloc
        self.channel = url.path.lstrip("/")
        if not self.interface or not self.channel:
            raise url.error("give the CAN interface and channel, e.g. canopen://socketcan/can0?nodes=1-4")
        self.node_ids = list(config.nodes)
        self.heartbeat_ms = config.heartbeat_ms
        self.bitrate = config.bitrate
        self.sync_timeout_s = config.sync_timeout_ms / 1e3
        joint_map = cia402_joint_map(config.model, config.map, config.lead_m, config.counts_per_rev)
        if len(self.node_ids) != len(joint_map.names):
            raise DeviceError(f"robot '{url.raw}': {len(self.node_ids)} nodes for {len(joint_map.names)} joints "
                              f"({', '.join(joint_map.names)})")
        super().__init__(url, context, config, joint_map, f"CANopen bus {self.interface}/{self.channel}")
        self._network = None
        self._nodes = {}
        self._layouts: dict[int, Tpdo1Layout] = {}
        self._tpdo_callbacks = {n: functools.partial(self._on_tpdo, n) for n in self.node_ids}
        # what the notifier thread and the reader share, under this lock: the SYNC being waited for, the answers
        # to it, the nodes that still owe one, each node's state
        self._tpdo_lock = threading.Condition()
        self._sync_no = 0  # the number of the last SYNC sent (this connection)
        self._sync_open = False  # its TPDOs are still being waited for
        self._tpdo: dict[int, tuple[int, int]] = {}  # node -> (statusword, position) answering SYNC _sync_no
        # the nodes whose TPDO1 answering SYNC _sync_no is still to come (a node sends one per SYNC, in order). No
        # SYNC goes out while a node may still owe a frame for an earlier one: after a wait times out, the master
        # waits as long again for the late frames, and if one is still owed, pauses late_limit_s (any frame then
        # is discarded) before the next SYNC. So a frame can only pass for a later SYNC's answer if it comes more
        # than 2 x sync_timeout_ms + late_limit_s after its own SYNC
        self._owes: set[int] = set()
        self._sync_wall = 0.0  # when SYNC _sync_no went out (monotonic)
        self.late_limit_s = max(0.1, 5 * self.sync_timeout_s)
        self._node_state: dict[int, str] = {}  # node -> starting | running | restarted (absent: not set up)
        self._started_wall: dict[int, float] = {}
        self._restart_gen: dict[int, int] = {}  # node -> restarts seen (a restart during a reconfiguration)
        self._retry_at: dict[int, float] = {}  # node -> when to try configuring a restarted node again
        self._heartbeat_wall: dict[int, float] = {}

    @classmethod
    def discover(cls) -> Discovery:
        title = "SocketCAN interfaces (CANopen robots)"
        if not SYS_NET.is_dir():
            return Discovery(title, (), f"cannot look: {SYS_NET} is missing (SocketCAN is Linux only)")
        found = can_interfaces()
        return Discovery(title, tuple(FoundDevice(i, f"canopen://socketcan/{i}?nodes=1-4") for i in found),
                         "" if found else "no SocketCAN interfaces (is the CAN adapter plugged in and up? "
                                          "'ip link set can0 up type can bitrate 1000000')")

    # --- connection ------------------------------------------------------------------------------------------
    def _connect(self) -> None:
        import can
        import canopen

        network = canopen.Network()
        kwargs = {"interface": self.interface, "channel": self.channel}
        if self.bitrate:
            kwargs["bitrate"] = self.bitrate
        try:
            network.connect(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            present = can_interfaces()
            raise DeviceNotFoundError(f"CAN interface '{self.interface}' channel '{self.channel}' cannot be opened "
                                      f"({exc}); SocketCAN interfaces here: {', '.join(present) or 'none'}") from None
        try:
            self._setup_nodes(network)
        except BaseException:
            network.disconnect()
            raise
        self._network = network

    def _setup_nodes(self, network) -> None:
        import canopen

        od = cia402_object_dictionary()
        nodes, missing = {}, []
        for node_id in self.node_ids:
            node = canopen.RemoteNode(node_id, od)
            node.sdo.RESPONSE_TIMEOUT = 0.2
            network.add_node(node)
            try:
                node.sdo.upload(0x1000, 0)
            except (canopen.SdoCommunicationError, canopen.SdoAbortedError):
                missing.append(node_id)
                continue
            nodes[node_id] = node
        if missing:
            raise DeviceNotFoundError(f"{self.device_name}: no SDO answer from node(s) {', '.join(map(str, missing))} "
                                      f"(answered: {', '.join(map(str, nodes)) or 'none'}); check node IDs, "
                                      f"bit rate and termination")
        with self._tpdo_lock:
            self._node_state.clear()
            self._sync_no, self._sync_open = 0, False
            self._tpdo.clear()
            self._owes.clear()
        layouts = {}
        for node_id, node in nodes.items():
            try:
                layouts[node_id] = self._configure_node(node)
            except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as exc:
                raise DeviceError(f"{self.device_name}: node {node_id} refused the TPDO1/heartbeat setup ({exc})") \
                    from None
        self._layouts = layouts
        for node_id, node in nodes.items():
            network.subscribe(0x180 + node_id, self._tpdo_callbacks[node_id])
            node.emcy.add_callback(lambda emcy, node_id=node_id: self._on_emcy(node_id, emcy))
            node.nmt.add_heartbeat_callback(lambda state, node_id=node_id: self._on_heartbeat(node_id, state))
            self._heartbeat_wall[node_id] = time.monotonic()
        self._nodes = nodes
        for node_id, node in nodes.items():
            self._start_node(node_id, node)

    def _configure_node(self, node) -> Tpdo1Layout:
        """TPDO1 (statusword + position actual value on every SYNC) and the producer heartbeat time, writing only
        what the node lacks; its TPDO1 layout. Raises canopen's SDO errors, or DeviceError when its TPDO1 mapping
        lacks an object and cannot be changed."""
        import canopen

        node_id = node.id
        sdo = node.sdo

        def read(index: int, sub: int) -> int:
            return int.from_bytes(sdo.upload(index, sub)[:4], "little")

        def write(index: int, sub: int, value: int, size: int) -> None:
            sdo.download(index, sub, value.to_bytes(size, "little"))

        send_nmt(node, NMT_ENTER_PRE_OPERATIONAL)
        cob_raw = read(TPDO1_COMMUNICATION, 1)
        trans_type = read(TPDO1_COMMUNICATION, 2)
        count = read(TPDO1_MAPPING, 0)
        entries = [read(TPDO1_MAPPING, sub) for sub in range(1, min(count, 64) + 1)]
        layout = Tpdo1Layout.from_entries(entries)
        cob_id = 0x180 + node_id
        no_rtr = cob_raw & RTR_NOT_ALLOWED  # the device's own: some refuse to allow RTR (abort 0x06090030)
        if layout is None or trans_type != 1 or cob_raw & ~RTR_NOT_ALLOWED != cob_id:
            write(TPDO1_COMMUNICATION, 1, cob_id | TPDO_NOT_VALID | no_rtr, 4)  # CiA 301: invalid while changed
            if trans_type != 1:
                write(TPDO1_COMMUNICATION, 2, 1, 1)  # synchronous, on every SYNC
            if layout is None:
                wanted = [STATUSWORD_ENTRY, POSITION_ENTRY]
                try:
                    write(TPDO1_MAPPING, 0, 0, 1)
                    for sub, entry in enumerate(wanted, 1):
                        write(TPDO1_MAPPING, sub, entry, 4)
                    write(TPDO1_MAPPING, 0, len(wanted), 1)
                except canopen.SdoAbortedError as exc:
                    raise DeviceError(
                        f"{self.device_name}: node {node_id}'s TPDO1 mapping lacks {Tpdo1Layout.missing(entries)} and "
                        f"cannot be changed ({exc}); it maps {describe_mapping(entries)}. Map statusword (0x6041) "
                        f"and position actual value (0x6064) into the drive's TPDO1 with its own set-up tool") \
                        from None
                layout = Tpdo1Layout.from_entries(wanted)
            write(TPDO1_COMMUNICATION, 1, cob_id | no_rtr, 4)
        write(PRODUCER_HEARTBEAT, 0, self.heartbeat_ms, 2)
        return layout

    def _start_node(self, node_id: int, node) -> None:
        with self._tpdo_lock:
            self._node_state[node_id] = "starting"
            self._started_wall[node_id] = time.monotonic()
            self._restart_gen.setdefault(node_id, 0)
        send_nmt(node, NMT_START)

    def _disconnect(self) -> None:
        with self._tpdo_lock:
            self._node_state.clear()  # their pre-operational heartbeats from here on are no restart
        if self._network is not None:
            network, self._network = self._network, None
            try:
                for node in self._nodes.values():
                    send_nmt(node, NMT_ENTER_PRE_OPERATIONAL)  # stop the drives' PDO traffic; no motion command
            finally:
                network.disconnect()

    # --- callbacks (python-can's notifier thread) -----------------------------------------------------------
    def _on_tpdo(self, node_id: int, can_id: int, data, timestamp) -> None:
        layout = self._layouts.get(node_id)
        if layout is None:
            return
        if len(data) != layout.nbytes:  # anything but the mapped length is a broken frame
            self._note_lost("protocol_errors", f"{self.device_name}: node {node_id} TPDO1 of {len(data)} bytes, "
                                               f"expected {layout.nbytes}")
            return
        status, position = layout.decode(bytes(data))
        with self._tpdo_lock:
            if self._node_state.get(node_id) == "starting":
                self._node_state[node_id] = "running"
            sync_no = self._sync_no
            owed = node_id in self._owes
            self._owes.discard(node_id)
            if owed and self._sync_open:
                self._tpdo[node_id] = (status, position)
                self._tpdo_lock.notify_all()
                return
            self._tpdo_lock.notify_all()  # the wait for late frames before the next SYNC
            late_ms = (time.monotonic() - self._sync_wall) * 1e3
        if sync_no == 0:
            return  # before the first SYNC: nothing it can answer
        if owed:
            what = (f"TPDO1 for SYNC {sync_no} came {late_ms:.1f} ms after it, after the wait for it (sync_timeout_ms "
                    f"{self.sync_timeout_s * 1e3:g})")
        else:
            what = (f"TPDO1 answering no SYNC waited for ({late_ms:.1f} ms after SYNC {sync_no}, which it had already "
                    f"answered or was not expected to: a very late one, or a second one)")
        self._note_lost("stale_tpdos", f"{self.device_name}: node {node_id}'s {what}: discarded, never combined with "
                                       f"another SYNC's")

    def _on_emcy(self, node_id: int, emcy) -> None:
        if emcy.code == 0:
            self.set_device_fault(f"node {node_id} EMCY", None)
            log.info("%s: node %d error reset", self.device_name, node_id)
        else:
            self.count_fault("emcy")
            what = emcy_description(emcy.code)
            self.set_device_fault(f"node {node_id} EMCY", f"0x{emcy.code:04X} {what} "
                                                          f"(error register 0x{emcy.register:02X})")
            log.warning("%s: node %d EMCY 0x%04X %s", self.device_name, node_id, emcy.code, what)

    def _on_heartbeat(self, node_id: int, state: int) -> None:
        now = time.monotonic()
        self._heartbeat_wall[node_id] = now
        restarted = ""
        with self._tpdo_lock:
            was = self._node_state.get(node_id)
            if was is None:
                return  # not set up (connecting, closing)
            grace = max(0.5, 3 * self.heartbeat_ms / 1e3)  # a pre-operational heartbeat sent before the NMT start
            if state == NMT_BOOT_UP:
                restarted = "restarted (boot-up message)"
            elif state == NMT_PRE_OPERATIONAL and (
                    was == "running" or (was == "starting" and now - self._started_wall.get(node_id, now) > grace)):
                restarted = "is pre-operational (restarted, or stopped by another master)"
            elif state == NMT_OPERATIONAL and was == "starting":
                self._node_state[node_id] = "running"
            if restarted:
                self._restart_gen[node_id] = self._restart_gen.get(node_id, 0) + 1
                self._node_state[node_id] = "restarted"
                self._retry_at.pop(node_id, None)
                # pre-operational from its restart on: it sends no TPDO1, so it owes no answer to the SYNC being
                # waited for (nor its late one): the wait, and the drain after it, stop expecting it
                self._owes.discard(node_id)
                self._tpdo_lock.notify_all()
        if restarted and (state == NMT_BOOT_UP or was != "restarted"):
            message = (f"{self.device_name}: node {node_id} {restarted}: configuring its TPDO1 and heartbeat again "
                       f"and starting it")
            self._note_lost("node_restarts", message)
            log.warning("%s", message)

    # --- one poll -----------------------------------------------------------------------------------------------
    def _supervise_heartbeats(self) -> None:
        limit = 1.5 * self.heartbeat_ms / 1e3
        now = time.monotonic()
        for node_id in self.node_ids:
            silent = now - self._heartbeat_wall.get(node_id, now)
            if silent > limit:
                if f"node {node_id} heartbeat" not in self._device_faults:
                    self.count_fault("heartbeat_lost")
                self.set_device_fault(f"node {node_id} heartbeat", f"no heartbeat for {silent * 1e3:.0f} ms "
                                                                   f"(producer time {self.heartbeat_ms} ms)")
            else:
                self.set_device_fault(f"node {node_id} heartbeat", None)

    def _recover_restarted_nodes(self) -> None:
        """Configure and start again every node that restarted (reader thread: SDO needs the notifier free)."""
        import can
        import canopen

        with self._tpdo_lock:
            todo = [(n, self._restart_gen.get(n, 0)) for n, st in self._node_state.items() if st == "restarted"]
        if todo:
            # after a failed attempt, no poll until the next one is due (every node is needed for a reading, and
            # a restarted one sends none): one counted timeout per attempt, not one per poll of the back-off
            due = min(self._retry_at.get(n, 0.0) for n, _ in todo)
            while (left := due - time.monotonic()) > 0 and not self._stop.wait(min(left, 0.01)):
                self._supervise_heartbeats()  # a lost heartbeat is still reported within 100 ms
                with self._tpdo_lock:
                    if any(self._retry_at.get(n, 0.0) <= time.monotonic() for n, _ in todo):
                        break  # restarted again (boot-up): due at once
        failed = []
        for node_id, gen in todo:
            now = time.monotonic()
            if now < self._retry_at.get(node_id, 0.0) or self._stop.is_set():
                failed.append(node_id)
                continue
            node = self._nodes[node_id]
            try:
                layout = self._configure_node(node)
            except (canopen.SdoCommunicationError, canopen.SdoAbortedError, DeviceError, can.CanError, OSError) as exc:
                self._retry_at[node_id] = now + self.reconnect_interval_s
                self._last_fault = f"{self.device_name}: node {node_id} restarted; configuring it again failed ({exc})"
                log.warning("%s; retrying every %.1f s", self._last_fault, self.reconnect_interval_s)
                failed.append(node_id)
                continue
            with self._tpdo_lock:
                self._layouts[node_id] = layout
                self._owes.discard(node_id)  # pre-operational since its boot: it owes no frame
                if self._restart_gen.get(node_id, 0) != gen:
                    failed.append(node_id)  # it restarted again meanwhile: configured again at the next poll
                    continue
            self._start_node(node_id, node)
            log.warning("%s: node %d configured again and started after its restart", self.device_name, node_id)
        if failed:
            raise DeviceTimeoutError(f"{self.device_name}: node(s) {', '.join(map(str, failed))} restarted and "
                                     f"are being configured again ({self._last_fault})")

    def _poll(self) -> tuple[np.ndarray, int]:
        import can

        self._supervise_heartbeats()
        self._recover_restarted_nodes()
        with self._tpdo_lock:
            self._tpdo.clear()
            self._sync_no += 1
            sync_no = self._sync_no
            self._sync_open = True
            # every node answers but one that restarted (pre-operational until configured again)
            self._owes = {n for n in self.node_ids if self._node_state.get(n) in ("starting", "running")}
            self._sync_wall = time.monotonic()
        t_ns = self._clock()
        try:
            self._network.sync.transmit()
        except (can.CanError, OSError) as exc:
            raise DeviceDisconnectedError(f"{self.device_name}: cannot send SYNC ({exc}); reconnecting") from None
        deadline = time.monotonic() + self.sync_timeout_s
        with self._tpdo_lock:
            while len(self._tpdo) < len(self.node_ids):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._tpdo_lock.wait(left)
            self._sync_open = False  # from here on, a TPDO answering this SYNC is stale
            got = dict(self._tpdo)
            missing = [n for n in self.node_ids if n not in got]
            if missing:
                self._last_fault = (f"{self.device_name}: no TPDO1 from node(s) {', '.join(map(str, missing))} within "
                                    f"{self.sync_timeout_s * 1e3:g} ms of SYNC")
                # wait as long again for the missing nodes' late answers, so that they come (and are discarded)
                # before the next SYNC, not after it, where they could pass for its answers
                expected = [n for n in missing if n in self._owes]  # not a node restarted meanwhile (no longer owes)
                drain_end = time.monotonic() + self.sync_timeout_s
                while self._owes.intersection(expected):
                    left = drain_end - time.monotonic()
                    if left <= 0:
                        break
                    self._tpdo_lock.wait(left)
                late = [n for n in expected if n not in self._owes]
                still_owed = sorted(self._owes.intersection(expected))
        if missing:
            why = (f"; node(s) {', '.join(map(str, late))} answered later (discarded: raise sync_timeout_ms if the "
                   f"drives need longer)" if late else "")
            if still_owed:
                # a frame lost, or later than twice the timeout: no SYNC until it can no longer come (a node's
                # frame that came after it would pass for its answer to the next SYNC)
                pause_end = time.monotonic() + self.late_limit_s
                while (left := pause_end - time.monotonic()) > 0 and not self._stop.wait(min(left, 0.01)):
                    self._supervise_heartbeats()  # a lost heartbeat is still reported within 100 ms
                with self._tpdo_lock:
                    self._owes.clear()
                why += (f"; no SYNC for {self.late_limit_s * 1e3:g} ms so that node(s) "
                        f"{', '.join(map(str, still_owed))} could answer no later SYNC with a late frame")
            raise DeviceTimeoutError(f"{self.device_name}: no TPDO1 from node(s) {', '.join(map(str, missing))} "
                                     f"within {self.sync_timeout_s * 1e3:g} ms of SYNC{why}")
        counts = np.empty(len(self.node_ids), np.int64)
        for j, node_id in enumerate(self.node_ids):
            status, position = got[node_id]
            counts[j] = position
            self.set_device_fault(f"node {node_id} statusword",
                                  f"fault bit set (0x{status:04X})" if status & STATUS_FAULT_BIT else None)
        return counts, t_ns
