"""``lapreco emulate``: one device emulator on its own, for an integrator to point their own tools (or this app's
drivers, in another process) at: a Dynamixel chain or an NDI tracker on a pseudo-terminal, CiA 402 drives on a
CAN interface. Each ``start_*`` returns a :class:`RunningEmulator` whose ``lines`` say where to connect and
with which driver URL; :func:`serve` keeps it up until Ctrl-C (or SIGTERM).

The joints move on their own (``motion="scan"``: each joint a slow sine about the middle of its limits, periods
of a few seconds; ``"still"``: at the middle) through the same joint maps the drivers use, so a driver reads
SI joints within the model's limits. NDI tools move a few centimetres about a point 1.2 m in front of the
tracker, 100 mm apart.

Transports: a pty is reachable from any process on this machine. python-can's ``virtual`` bus connects buses
inside ONE process only, so a CANopen emulator meant for another program needs a SocketCAN interface (a virtual
``vcan0``); ``start_canopen`` takes ``virtual`` for an emulator used in the caller's own process."""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from lapreco_hil.errors import ConfigError

log = logging.getLogger(__name__)

MOTIONS = ("scan", "still")
SCAN_PERIOD_S = 8.0
VIRTUAL_BUS_NOTE = ("python-can's virtual bus connects buses inside one process only: no other program could reach "
                    "an emulator on it")


@dataclass
class RunningEmulator:
    """An emulator and what to tell whoever will connect to it."""

    kind: str
    emulator: object
    url: str  # the driver URL that opens it
    lines: list[str] = field(default_factory=list)

    def close(self) -> None:
        self.emulator.close()


def _joints_at(joint_map, motion: str) -> Callable[[int], np.ndarray]:
    """SI joints over time for ``joint_map``'s joints: a sine per joint about the middle of its limits."""
    if motion not in MOTIONS:
        raise ConfigError(f"motion '{motion}' is not one of {', '.join(MOTIONS)}")
    lower, upper = np.asarray(joint_map.lower, float), np.asarray(joint_map.upper, float)
    finite = np.isfinite(lower) & np.isfinite(upper)
    middle = np.where(finite, (lower + upper) / 2, 0.0)
    amplitude = np.where(finite, 0.25 * (upper - lower) / 2, 0.5)
    if motion == "still":
        amplitude = np.zeros_like(amplitude)
    n = len(middle)
    w = 2 * math.pi / SCAN_PERIOD_S * (1.0 + 0.25 * np.arange(n))
    phase = 0.7 * np.arange(n)
    t0 = time.monotonic_ns()

    def joints_at(t_ns: int) -> np.ndarray:
        return middle + amplitude * np.sin(w * (t_ns - t0) * 1e-9 + phase)

    return joints_at


def start_dynamixel(ids=(1, 2, 3, 4), baud: int = 1_000_000, model: str = "ecm", motion: str = "scan",
                    link_dir: str | None = None, alert_ids=(), reply_delay_ms: float = 0.0) -> RunningEmulator:
    """A chain of X-series servos (XM430-W350) on a pty, one per joint of ``model``, at ``baud``."""
    from lapreco_hil.drivers.robot.dynamixel import BAUD_RATES
    from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map
    from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

    if baud not in BAUD_RATES:
        raise ConfigError(f"baud {baud} is not an X-series baud rate ({', '.join(map(str, BAUD_RATES))})")
    joint_map = dynamixel_joint_map(model)
    ids = list(ids)
    if len(ids) != len(joint_map.names):
        raise ConfigError(f"{len(ids)} servo IDs for the {len(joint_map.names)} joints of model '{model}' "
                          f"({', '.join(joint_map.names)}); give one ID per joint")
    unknown = [i for i in alert_ids if i not in ids]
    if unknown:
        raise ConfigError(f"--alert {unknown[0]}: not one of the chain's IDs ({', '.join(map(str, ids))})")
    emu = DynamixelChainEmulator(ids, joint_map, _joints_at(joint_map, motion), link_dir=link_dir, baud=baud)
    emu.faults.hardware_alert = set(alert_ids)
    emu.faults.reply_delay_s = reply_delay_ms / 1e3
    id_text = ",".join(map(str, ids))
    url = f"serial://{emu.port}?baud={baud}&ids={id_text}&model={model}"
    lines = [f"Dynamixel chain: {len(ids)} XM430-W350 servos (IDs {id_text}) at {baud} baud, joints of model "
             f"'{model}' ({', '.join(joint_map.names)}), {motion}",
             f"port: {emu.port}",
             f"url: {url}"]
    if alert_ids:
        lines.append(f"faults: hardware error alert on ID(s) {', '.join(map(str, sorted(alert_ids)))}")
    if reply_delay_ms:
        lines.append(f"faults: every reply {reply_delay_ms:g} ms late")
    return RunningEmulator("dynamixel", emu, url, lines)


def start_canopen(nodes=(1, 2, 3, 4), model: str = "ecm", motion: str = "scan", interface: str = "socketcan",
                  channel: str = "vcan0", fault_bit_nodes=()) -> RunningEmulator:
    """CiA 402 drives (one node per joint of ``model``) on a SocketCAN interface (or, for use in this process
    only, python-can's virtual bus)."""
    from lapreco_hil.drivers.robot.joint_map import cia402_joint_map
    from lapreco_hil.simulators.canopen_emulator import EMULATOR_INTERFACES, CANopenDriveChainEmulator

    if interface not in EMULATOR_INTERFACES:
        raise ConfigError(f"interface '{interface}' is not one the CANopen emulator runs on "
                          f"({', '.join(EMULATOR_INTERFACES)})")
    joint_map = cia402_joint_map(model)
    nodes = list(nodes)
    if len(nodes) != len(joint_map.names):
        raise ConfigError(f"{len(nodes)} node ids for the {len(joint_map.names)} joints of model '{model}' "
                          f"({', '.join(joint_map.names)}); give one node per joint")
    unknown = [n for n in fault_bit_nodes if n not in nodes]
    if unknown:
        raise ConfigError(f"--fault-bit {unknown[0]}: not one of the nodes ({', '.join(map(str, nodes))})")
    emu = CANopenDriveChainEmulator(channel, nodes, joint_map, _joints_at(joint_map, motion), interface=interface)
    emu.faults.fault_bit_nodes = set(fault_bit_nodes)
    node_text = ",".join(map(str, nodes))
    url = f"canopen://{interface}/{channel}?nodes={node_text}&model={model}"
    lines = [f"CANopen CiA 402 drives: nodes {node_text} on {interface} channel {channel}, joints of model "
             f"'{model}' ({', '.join(joint_map.names)}), {motion}",
             f"interface: {interface}",
             f"channel: {channel}",
             f"url: {url}"]
    if interface == "virtual":
        lines.append(f"note: {VIRTUAL_BUS_NOTE}; only this process can use it")
    if fault_bit_nodes:
        lines.append(f"faults: statusword fault bit on node(s) {', '.join(map(str, sorted(fault_bit_nodes)))}")
    return RunningEmulator("canopen", emu, url, lines)


def _tool_pose(offset_mm: float, motion: str):
    still = motion == "still"

    def pose_at(t_ns: int):
        s = 0.0 if still else t_ns * 1e-9
        c, d = math.cos(0.2 * math.sin(0.5 * s)), math.sin(0.2 * math.sin(0.5 * s))
        T = np.eye(4)
        T[:3, :3] = [[c, -d, 0.0], [d, c, 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [offset_mm + 30.0 * math.sin(0.4 * s), 20.0 * math.cos(0.3 * s), -1200.0 + 40.0 * math.sin(0.2 * s)]
        return T, True

    return pose_at


def start_ndi(wired: int = 1, passive: int = 0, frame_rate_hz: float = 60.0, motion: str = "scan",
              link_dir: str | None = None, start_baud: int = 9600, start_tracking: bool = False,
              baud: int = 921600) -> RunningEmulator:
    """An NDI tracker on a pty: ``wired`` tools (an Aurora's sensors, handles 0A, 0B, ...) and ``passive`` tools
    (a Polaris': each needs a .rom in the driver's ``tools=``; any .rom file does, the emulator keeps what is
    uploaded). ``baud`` only goes into the URL printed (the rate the driver asks for with COMM)."""
    from lapreco_hil.drivers.tracker.ndi import COMM_BAUD_CODES
    from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

    if motion not in MOTIONS:
        raise ConfigError(f"motion '{motion}' is not one of {', '.join(MOTIONS)}")
    for name, rate in (("start baud", start_baud), ("baud", baud)):
        if rate not in COMM_BAUD_CODES:
            raise ConfigError(f"{name} {rate} is not an NDI rate ({', '.join(map(str, sorted(COMM_BAUD_CODES)))})")
    if wired + passive == 0:
        raise ConfigError("an NDI tracker with no tool: give --wired N or --passive N (at least one tool)")
    poses = [_tool_pose(100.0 * i, motion) for i in range(wired + passive)]
    emu = NDITrackerEmulator(passive=poses[wired:], wired=poses[:wired], frame_rate_hz=frame_rate_hz,
                             link_dir=link_dir, start_baud=start_baud, start_tracking=start_tracking)
    url = f"ndi://{emu.port}?baud={baud}&rate={frame_rate_hz:g}"
    if passive:
        url += "&tools=" + ",".join(f"TOOL{i + 1}.rom" for i in range(passive))
    lines = [f"NDI tracker: {wired} wired tool(s) (handles {', '.join(f'{0x0A + i:02X}' for i in range(wired)) or '-'})"
             f", {passive} passive tool(s), {frame_rate_hz:g} Hz, {motion}; at {start_baud} baud"
             + (", tracking" if start_tracking else "") + " until a driver's COMM",
             f"port: {emu.port}",
             f"url: {url}"]
    if passive:
        lines.append(f"note: replace TOOL1.rom ... with {passive} .rom file(s) of your own (any content: the "
                     f"emulator keeps what is uploaded)")
    return RunningEmulator("ndi", emu, url, lines)


def serve(running: RunningEmulator, stop: threading.Event | None = None) -> None:
    """Keep ``running`` up until Ctrl-C, SIGTERM (or ``stop`` is set), then close it. Signals are set here
    explicitly: a process started in the background by a non-interactive shell inherits SIGINT ignored."""
    stop = stop or threading.Event()

    def on_signal(signum, frame):
        stop.set()

    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        running.close()
