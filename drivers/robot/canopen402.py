"""A robot of CiA 402 drives (e.g. maxon EPOS4) on a CAN bus, through the ``canopen`` package on python-can.

``canopen://<interface>/<channel>?nodes=1-4&rate=100&heartbeat_ms=100&model=ecm&bitrate=1000000``
(``canopen://socketcan/can0?...`` on real hardware, ``canopen://virtual/ch0?...`` in tests; parameters:
:class:`CANopenConfig`; node ids 1..127.) Position actual value increments become joint positions with the
CiA 402 convention, 0 increments = 0 (see ``joint_map``).

On connect the master checks every node answers SDO (device type), maps statusword (0x6041) and position
actual value (0x6064) into TPDO1 sent on every SYNC, sets each node's producer heartbeat time (0x1017) and
starts the nodes (NMT operational). Each poll sends one SYNC, stamped on the injected clock (the drives
latch their position on SYNC), and waits for every node's TPDO1. Heartbeats are supervised (a node silent
for 1.5 x its producer time is lost); EMCY messages and the statusword's fault bit mark the robot faulted
until an error-reset EMCY or a clean statusword clears them.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.robot.cia402 import (POSITION_ACTUAL, PRODUCER_HEARTBEAT, STATUS_FAULT_BIT, STATUSWORD,
                                              cia402_object_dictionary)
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
        self._tpdo_lock = threading.Condition()
        self._tpdo: dict[int, tuple[int, int]] = {}  # node -> (statusword, position) since the last SYNC
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
        for node_id, node in nodes.items():
            try:
                node.nmt.state = "PRE-OPERATIONAL"
                tpdo = node.tpdo[1]
                tpdo.clear()
                tpdo.add_variable(STATUSWORD)
                tpdo.add_variable(POSITION_ACTUAL)
                tpdo.cob_id = 0x180 + node_id
                tpdo.trans_type = 1  # on every SYNC
                tpdo.enabled = True
                tpdo.save()
                node.sdo[PRODUCER_HEARTBEAT].raw = self.heartbeat_ms
            except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as exc:
                raise DeviceError(f"{self.device_name}: node {node_id} refused the TPDO1/heartbeat setup ({exc})") \
                    from None
            tpdo.add_callback(self._on_tpdo)
            node.emcy.add_callback(lambda emcy, node_id=node_id: self._on_emcy(node_id, emcy))
            node.nmt.add_heartbeat_callback(lambda state, node_id=node_id: self._on_heartbeat(node_id, state))
            self._heartbeat_wall[node_id] = time.monotonic()
        for node in nodes.values():
            node.nmt.state = "OPERATIONAL"
        self._nodes = nodes

    def _disconnect(self) -> None:
        if self._network is not None:
            network, self._network = self._network, None
            try:
                for node in self._nodes.values():
                    node.nmt.state = "PRE-OPERATIONAL"  # stop the drives' PDO traffic; never a motion command
            finally:
                network.disconnect()

    # --- callbacks (python-can's notifier thread) -----------------------------------------------------------
    def _on_tpdo(self, pdo_map) -> None:
        node_id = pdo_map.pdo_node.node.id
        if len(pdo_map.data) != 6:  # statusword (2) + position (4); anything else is a broken frame
            self._note_lost("protocol_errors", f"{self.device_name}: node {node_id} TPDO1 of {len(pdo_map.data)} bytes, "
                                          f"expected 6")
            return
        values = {v.index: v.raw for v in pdo_map.map}
        with self._tpdo_lock:
            self._tpdo[node_id] = (int(values.get(STATUSWORD, 0)), int(values.get(POSITION_ACTUAL, 0)))
            self._tpdo_lock.notify_all()

    def _on_emcy(self, node_id: int, emcy) -> None:
        if emcy.code == 0:
            self.set_device_fault(f"node {node_id} EMCY", None)
            log.info("%s: node %d error reset", self.device_name, node_id)
        else:
            self.count_fault("emcy")
            self.set_device_fault(f"node {node_id} EMCY", f"0x{emcy.code:04X} {emcy.get_desc()} "
                                                          f"(error register 0x{emcy.register:02X})")
            log.warning("%s: node %d EMCY 0x%04X %s", self.device_name, node_id, emcy.code, emcy.get_desc())

    def _on_heartbeat(self, node_id: int, state: int) -> None:
        self._heartbeat_wall[node_id] = time.monotonic()

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

    def _poll(self) -> tuple[np.ndarray, int]:
        import can

        self._supervise_heartbeats()
        with self._tpdo_lock:
            self._tpdo.clear()
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
                    missing = [n for n in self.node_ids if n not in self._tpdo]
                    raise DeviceTimeoutError(f"{self.device_name}: no TPDO1 from node(s) "
                                             f"{', '.join(map(str, missing))} after SYNC")
                self._tpdo_lock.wait(left)
            got = dict(self._tpdo)
        counts = np.empty(len(self.node_ids), np.int64)
        for j, node_id in enumerate(self.node_ids):
            status, position = got[node_id]
            counts[j] = position
            self.set_device_fault(f"node {node_id} statusword",
                                  f"fault bit set (0x{status:04X})" if status & STATUS_FAULT_BIT else None)
        return counts, t_ns
