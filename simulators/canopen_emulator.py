"""CiA 402 drives as canopen LocalNodes on a python-can bus: the device side of the CANopen robot.

Each node has the same object dictionary as the driver's RemoteNodes (drivers/robot/cia402.py), answers
SDO, follows NMT, produces its heartbeat at the period the master writes to 0x1017, and on every SYNC
latches its position actual value (from ``joints_at(t_ns)`` through the shared JointMap,
``cia402_joint_map``: increments, 0 = the joint's zero)
and sends TPDO1 with the mapping the master configured.

Tests use python-can's in-process ``virtual`` interface (``canopen://virtual/<channel>``); nothing leaves
the process, and nothing outside it can reach the nodes. ``lapreco emulate canopen`` puts them on a SocketCAN
interface instead (``interface="socketcan"``: a virtual ``vcan0`` on this machine, for other programs to reach);
an interface that does not exist is a DeviceNotFoundError that says how to create one. No other python-can
interface is taken (some of them, udp_multicast for one, leave the machine). Faults on demand: a node that goes silent (no TPDO, no heartbeat), a node whose heartbeat
stops, an EMCY (and its reset), the statusword's fault bit, a position out of the joint's limits.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import canopen

from lapreco_hil.drivers.robot.cia402 import (POSITION_ACTUAL, STATUS_FAULT_BIT, STATUS_OPERATION_ENABLED,
                                              STATUSWORD, cia402_object_dictionary)
from lapreco_hil.drivers.robot.joint_map import JointMap

log = logging.getLogger(__name__)

EMULATOR_INTERFACES = ("virtual", "socketcan")


def check_socketcan(channel: str) -> None:
    """Raise DeviceNotFoundError, one line with the remedy, unless this machine has the SocketCAN ``channel``."""
    from lapreco_hil.drivers.robot.canopen402 import SYS_NET, can_interfaces
    from lapreco_hil.errors import DeviceNotFoundError

    if not SYS_NET.is_dir():
        raise DeviceNotFoundError(f"SocketCAN interface '{channel}': this machine has no SocketCAN ({SYS_NET} is "
                                  f"missing; SocketCAN is Linux only)")
    present = can_interfaces()
    if channel not in present:
        raise DeviceNotFoundError(
            f"SocketCAN interface '{channel}' does not exist on this machine (SocketCAN interfaces here: "
            f"{', '.join(present) or 'none'}); create a virtual one: sudo modprobe vcan && sudo ip link add dev "
            f"{channel} type vcan && sudo ip link set up {channel}")


@dataclass
class CANopenFaults:
    silent_nodes: set[int] = field(default_factory=set)  # no TPDO and no heartbeat (node off the bus)
    fault_bit_nodes: set[int] = field(default_factory=set)  # statusword fault bit set
    position_override: dict[int, int] = field(default_factory=dict)  # node -> raw increments
    late_tpdo_s: float = 0.0  # TPDOs sent this late after SYNC


class CANopenDriveChainEmulator:
    def __init__(self, channel: str, node_ids: list[int], joint_map: JointMap, joints_at,
                 clock_ns=time.monotonic_ns, interface: str = "virtual") -> None:
        if interface not in EMULATOR_INTERFACES:
            # emulated traffic stays inside this process (virtual) or this machine's CAN interfaces (socketcan)
            raise ValueError(f"the CANopen emulator runs on python-can's {' or '.join(EMULATOR_INTERFACES)} "
                             f"interface, not '{interface}'")
        if interface == "socketcan":
            check_socketcan(channel)
        self.node_ids = list(node_ids)
        self.joint_map = joint_map
        self.joints_at = joints_at
        self.clock_ns = clock_ns
        self.faults = CANopenFaults()
        self.stats = {"syncs": 0, "tpdos": 0}
        self.written: dict[int, set[int]] = {}  # node -> object indices the master wrote (safety tests read it)
        self._updating = False
        self._lock = threading.Lock()
        self.network = canopen.Network()
        self.interface, self.channel = interface, channel
        self.network.connect(interface=interface, channel=channel)
        self.nodes: dict[int, canopen.LocalNode] = {}
        self._mapping_loaded: dict[int, bool] = {}
        for node_id in self.node_ids:
            node = canopen.LocalNode(node_id, cia402_object_dictionary())
            self.network.add_node(node)
            node.add_write_callback(lambda index, node_id=node_id, **kw: self._on_write(node_id, index))
            self.nodes[node_id] = node
            self._mapping_loaded[node_id] = False
            node.nmt.state = "PRE-OPERATIONAL"
        self.network.subscribe(0x80, self._on_sync)

    def _on_write(self, node_id: int, index: int) -> None:
        if not self._updating:  # a write from the bus (SDO), not the drive updating its own values
            self.written.setdefault(node_id, set()).add(index)
        if 0x1800 <= index <= 0x1A03:
            self._mapping_loaded[node_id] = False  # the master changed the PDO set-up: reload before sending

    def _on_sync(self, can_id, data, timestamp) -> None:
        t_ns = self.clock_ns()
        self.stats["syncs"] += 1
        counts = self.joint_map.to_counts(self.joints_at(t_ns))
        with self._lock:
            faults = (set(self.faults.silent_nodes), set(self.faults.fault_bit_nodes),
                      dict(self.faults.position_override), self.faults.late_tpdo_s)
        silent, fault_bit, override, late = faults
        if late:
            time.sleep(late)
        for j, node_id in enumerate(self.node_ids):
            node = self.nodes[node_id]
            if node_id in silent or node.nmt.state != "OPERATIONAL":
                continue
            status = STATUS_OPERATION_ENABLED | (STATUS_FAULT_BIT if node_id in fault_bit else 0)
            position = int(override.get(node_id, counts[j]))
            self._updating = True
            try:
                node.set_data(STATUSWORD, 0, status.to_bytes(2, "little"))
                node.set_data(POSITION_ACTUAL, 0, position.to_bytes(4, "little", signed=True))
            finally:
                self._updating = False
            tpdo = node.tpdo[1]
            if not self._mapping_loaded[node_id]:
                tpdo.read()
                self._mapping_loaded[node_id] = True
            if not tpdo.enabled or tpdo.trans_type != 1:
                continue
            for var in tpdo.map:
                var.raw = {STATUSWORD: status, POSITION_ACTUAL: position}.get(var.index, 0)
            tpdo.transmit()
            self.stats["tpdos"] += 1

    # --- faults ---------------------------------------------------------------------------------------------
    def set_silent(self, node_id: int, silent: bool = True) -> None:
        """The node drops off the bus: no TPDO and no heartbeat (or comes back)."""
        with self._lock:
            (self.faults.silent_nodes.add if silent else self.faults.silent_nodes.discard)(node_id)
        node = self.nodes[node_id]
        if silent:
            node.nmt.stop_heartbeat()
        else:
            node.nmt.start_heartbeat(node.sdo[0x1017].raw)

    def stop_heartbeat(self, node_id: int) -> None:
        self.nodes[node_id].nmt.stop_heartbeat()

    def resume_heartbeat(self, node_id: int) -> None:
        node = self.nodes[node_id]
        node.nmt.start_heartbeat(node.sdo[0x1017].raw)

    def send_emcy(self, node_id: int, code: int = 0x4210, register: int = 0x08) -> None:
        """An emergency (default: 0x4210, excess temperature in the device)."""
        self.nodes[node_id].emcy.send(code, register)

    def reset_emcy(self, node_id: int) -> None:
        self.nodes[node_id].emcy.reset()

    def close(self) -> None:
        for node in self.nodes.values():
            node.nmt.stop_heartbeat()
        self.network.disconnect()

    def __enter__(self) -> "CANopenDriveChainEmulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
