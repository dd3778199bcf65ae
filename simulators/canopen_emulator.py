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
interface is taken (some of them reach beyond this machine).

Faults on demand: a node that goes silent (no TPDO, no heartbeat), a node whose heartbeat stops, an EMCY (and its
reset), the statusword's fault bit, a position out of the joint's limits, a node whose
TPDO1 comes late after its SYNC (``faults.tpdo_delay``: per node and SYNC, each node's frames still in order, as
from a real drive's transmit queue), a node that restarts (``restart``: boot-up message, pre-operational, its
defaults back). Drive variants (constructor): TPDO COB-IDs that refuse RTR (``no_rtr_nodes``: bit 30 set by
default, a write clearing it is aborted with 0x06090030, as some devices do) and a static, read-only TPDO1 mapping
(``static_tpdo1``). ``count_syncs_from``: every node reports that number plus the SYNC's number as its position,
so a test can tell which SYNC a value answers (``sync_times`` keeps when each SYNC arrived).

Like a CiA 301 device, a node refuses to change the COB-ID or the mapping of a valid (enabled) TPDO
(abort 0x06090030 / 0x06010000): a master invalidates it first.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import canopen

from lapreco_hil.drivers.robot.cia402 import (POSITION_ACTUAL, PRODUCER_HEARTBEAT, RTR_NOT_ALLOWED,
                                              STATUS_FAULT_BIT, STATUS_OPERATION_ENABLED, STATUSWORD,
                                              TPDO_NOT_VALID, cia402_object_dictionary)
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
    late_tpdo_s: float = 0.0  # TPDOs sent this late after SYNC (every node; the emulator's notifier sleeps)
    # (node id, SYNC number) -> seconds after that SYNC the node's TPDO1 goes out (None: at once). A node's frames
    # stay in order (a later SYNC's frame never overtakes a late one), as from a real drive's transmit queue
    tpdo_delay: Callable[[int, int], float] | None = None


class CANopenDriveChainEmulator:
    def __init__(self, channel: str, node_ids: list[int], joint_map: JointMap, joints_at,
                 clock_ns=time.monotonic_ns, interface: str = "virtual", *, no_rtr_nodes=(),
                 static_tpdo1: dict[int, list[int]] | None = None, boot_heartbeat_ms: int = 0,
                 count_syncs_from: int | None = None) -> None:
        """``no_rtr_nodes``: nodes whose TPDO COB-IDs have bit 30 ("no RTR") set and refuse a write clearing it;
        ``static_tpdo1``: node -> its fixed TPDO1 mapping entries (0xIIIISSLL each), read-only;
        ``boot_heartbeat_ms``: producer heartbeat time after power-on or a restart (CiA 301 default 0: none);
        ``count_syncs_from``: report position = this + the SYNC's number (1, 2, ...) instead of ``joints_at``."""
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
        self.stats = {"syncs": 0, "tpdos": 0, "restarts": 0}
        self.written: dict[int, set[int]] = {}  # node -> object indices the master wrote (safety tests read it)
        self.no_rtr_nodes = set(no_rtr_nodes)
        self.static_tpdo1 = dict(static_tpdo1 or {})
        self.boot_heartbeat_ms = boot_heartbeat_ms
        self.count_syncs_from = count_syncs_from
        self.sync_times: dict[int, int] = {}  # SYNC number -> clock_ns when it arrived (with count_syncs_from)
        self._updating = False
        self._lock = threading.Lock()
        self._outbox: list[tuple[float, int, int, int, bytes]] = []  # (send at, order, node, COB-ID, data)
        self._outbox_cond = threading.Condition()
        self._outbox_order = 0
        self._node_sends_at: dict[int, float] = {}  # node -> when its last queued frame goes out (keeps order)
        self._sender: threading.Thread | None = None
        self._closed = False
        self.network = canopen.Network()
        self.interface, self.channel = interface, channel
        self.network.connect(interface=interface, channel=channel)
        self.nodes: dict[int, canopen.LocalNode] = {}
        self._mapping_loaded: dict[int, bool] = {}
        for node_id in self.node_ids:
            node = canopen.LocalNode(node_id, self._object_dictionary(node_id))
            self.network.add_node(node)
            node.add_write_callback(lambda index, subindex, data, node_id=node_id, **kw:
                                    self._on_write(node_id, index, subindex, data))
            self.nodes[node_id] = node
            self._mapping_loaded[node_id] = False
            node.nmt.state = "PRE-OPERATIONAL"
        self.network.subscribe(0x80, self._on_sync)

    def _object_dictionary(self, node_id: int) -> canopen.ObjectDictionary:
        """The node's dictionary with its defaults (what it holds after power-on or a restart)."""
        od = cia402_object_dictionary()
        od[PRODUCER_HEARTBEAT].default = self.boot_heartbeat_ms
        if node_id in self.no_rtr_nodes:
            for n in range(4):
                od[0x1800 + n][1].default |= RTR_NOT_ALLOWED
        if node_id in self.static_tpdo1:
            entries = self.static_tpdo1[node_id]
            mapping = od[0x1A00]
            mapping[0].default = len(entries)
            for sub in range(9):
                mapping[sub].access_type = "ro"
                if sub:
                    mapping[sub].default = entries[sub - 1] if sub <= len(entries) else 0
        return od

    def _on_write(self, node_id: int, index: int, subindex: int = 0, data: bytes = b"") -> None:
        if self._updating:  # the drive updating its own values, not a write from the bus (SDO)
            return
        self.written.setdefault(node_id, set()).add(index)
        node = self.nodes.get(node_id)
        if node is not None and 0x1800 <= index <= 0x1803 and subindex == 1:
            new = int.from_bytes(data, "little")
            old = int.from_bytes(node.get_data(index, 1), "little")
            if node_id in self.no_rtr_nodes and not new & RTR_NOT_ALLOWED:
                raise canopen.SdoAbortedError(0x06090030)  # value range: this device's PDOs take no RTR
            if not old & TPDO_NOT_VALID and not new & TPDO_NOT_VALID and (old & 0x7FF) != (new & 0x7FF):
                raise canopen.SdoAbortedError(0x06090030)  # CiA 301: COB-ID of a valid PDO changed
        if node is not None and 0x1A00 <= index <= 0x1A03:
            if not int.from_bytes(node.get_data(index - 0x200, 1), "little") & TPDO_NOT_VALID:
                raise canopen.SdoAbortedError(0x06010000)  # CiA 301: the mapping of a valid PDO
        if 0x1800 <= index <= 0x1A03:
            self._mapping_loaded[node_id] = False  # the master changed the PDO set-up: reload before sending

    def _on_sync(self, can_id, data, timestamp) -> None:
        t_ns = self.clock_ns()
        self.stats["syncs"] += 1
        sync_no = self.stats["syncs"]
        if self.count_syncs_from is not None:
            self.sync_times[sync_no] = t_ns
            counts = [self.count_syncs_from + sync_no] * len(self.node_ids)
        else:
            counts = self.joint_map.to_counts(self.joints_at(t_ns))
        received = time.monotonic()
        with self._lock:
            faults = (set(self.faults.silent_nodes), set(self.faults.fault_bit_nodes),
                      dict(self.faults.position_override), self.faults.late_tpdo_s, self.faults.tpdo_delay)
        silent, fault_bit, override, late, delay_of = faults
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
            delay = delay_of(node_id, sync_no) if delay_of is not None else None
            if delay is None and node_id not in self._node_sends_at:
                tpdo.transmit()
            else:
                self._queue(node_id, received + (delay or 0.0), tpdo.cob_id, bytes(tpdo.data))
            self.stats["tpdos"] += 1

    # --- late TPDOs: one sender thread, each node's frames in order ---------------------------------------------
    def _queue(self, node_id: int, send_at: float, cob_id: int, data: bytes) -> None:
        with self._outbox_cond:
            send_at = max(send_at, self._node_sends_at.get(node_id, 0.0))  # never before the node's earlier frame
            self._node_sends_at[node_id] = send_at
            self._outbox_order += 1
            heapq.heappush(self._outbox, (send_at, self._outbox_order, node_id, cob_id, data))
            if self._sender is None:
                self._sender = threading.Thread(target=self._send_late, name="canopen emulator TPDOs", daemon=True)
                self._sender.start()
            self._outbox_cond.notify_all()

    def _send_late(self) -> None:
        with self._outbox_cond:
            while not self._closed:
                if not self._outbox:
                    self._outbox_cond.wait()
                    continue
                send_at, _, node_id, cob_id, data = self._outbox[0]
                wait = send_at - time.monotonic()
                if wait > 0:
                    self._outbox_cond.wait(wait)
                    continue
                heapq.heappop(self._outbox)
                if self._node_sends_at.get(node_id) == send_at and not any(f[2] == node_id for f in self._outbox):
                    del self._node_sends_at[node_id]  # nothing of this node queued: its next frame may go at once
                try:
                    self.network.send_message(cob_id, data)
                except Exception:  # the bus closed under a queued frame
                    log.debug("late TPDO not sent", exc_info=True)

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

    def restart(self, node_id: int, boot_up: bool = True) -> None:
        """The node restarts (a power blip, a watchdog reset): every object back to its default (TPDO1 invalid,
        producer heartbeat ``boot_heartbeat_ms``), the boot-up message (unless ``boot_up`` is False: lost on the
        bus), then pre-operational, where it sends no PDO until a master configures and starts it."""
        node = self.nodes[node_id]
        node.nmt.stop_heartbeat()
        with self._lock:
            node.data_store.clear()  # the defaults of the object dictionary again
            self._mapping_loaded[node_id] = False
        self.stats["restarts"] += 1
        node.nmt._state = 0  # initialising
        if boot_up:
            self.network.send_message(0x700 + node_id, [0x00])
        node.nmt._state = 127  # pre-operational, with the heartbeat it has by default
        if self.boot_heartbeat_ms and node_id not in self.faults.silent_nodes:
            node.nmt.start_heartbeat(self.boot_heartbeat_ms)

    def close(self) -> None:
        for node in self.nodes.values():
            node.nmt.stop_heartbeat()
        with self._outbox_cond:
            self._closed = True
            self._outbox_cond.notify_all()
        if self._sender is not None:
            self._sender.join(timeout=1.0)
        self.network.disconnect()

    def __enter__(self) -> "CANopenDriveChainEmulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
