"""``lapreco bench robot``: the real robot drivers against their emulators over the real transports
(Dynamixel on a pseudo-terminal, CANopen on python-can's virtual bus): achieved sample rate, period
jitter, and latency from a sample's capture stamp to the moment the consumer has it."""

from __future__ import annotations

import platform
import time

import numpy as np


def _joints_at(t_ns: int) -> np.ndarray:
    return np.array([0.1, -0.2, 0.12, 0.3]) + np.array([0.2, 0.1, 0.02, 0.3]) * np.sin(0.7 * t_ns * 1e-9)


def _measure(robot, seconds: float) -> dict:
    latency, samples = [], []
    robot.read()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        got = robot.read(timeout_s=0.1)
        now = time.monotonic_ns()
        if got:
            latency.append(now - got[-1].t_ns)
            samples.extend(got)
    t = np.array([s.t_ns for s in samples], dtype=np.int64)
    period_ms = np.diff(t) * 1e-6
    lat_ms = np.array(latency) * 1e-6
    return {"samples": len(samples), "rate_hz": len(samples) / seconds,
            "period_ms": {"mean": float(period_ms.mean()), "std": float(period_ms.std()),
                          "max": float(period_ms.max())},
            "latency_ms": {p: float(np.percentile(lat_ms, q)) for p, q in (("p50", 50), ("p95", 95), ("p99", 99))},
            "faults": dict(robot.faults)}


def run(links=("serial", "canopen"), rates=(100.0, 500.0), seconds: float = 5.0) -> dict:
    from lapreco_hil.drivers.robot.joint_map import cia402_joint_map, dynamixel_joint_map
    from lapreco_hil.registry import DeviceContext, open_robot
    from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator
    from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

    rows = []
    for link in links:
        for rate in rates:
            if link == "serial":
                emu = DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map("ecm"), _joints_at)
                url = f"serial://{emu.port}?baud=1000000&ids=1,2,3,4&rate={rate}"
            else:
                emu = CANopenDriveChainEmulator(f"bench-{rate}", [1, 2, 3, 4],
                                                cia402_joint_map("ecm"), _joints_at)
                url = f"canopen://virtual/bench-{rate}?nodes=1-4&rate={rate}"
            try:
                with open_robot(url, DeviceContext()) as robot:
                    rows.append({"link": link, "requested_hz": rate, **_measure(robot, seconds)})
            finally:
                emu.close()
    return {"machine": platform.processor() or platform.machine(), "seconds": seconds, "rows": rows}


def format_table(result: dict) -> str:
    lines = [f"robot drivers on their emulators ({result['machine']}, {result['seconds']} s each)",
             "| link | requested Hz | achieved Hz | period mean / std / max (ms) | latency p50 / p95 / p99 (ms) |",
             "|---|---|---|---|---|"]
    for r in result["rows"]:
        p, lat = r["period_ms"], r["latency_ms"]
        lines.append(f"| {r['link']} | {r['requested_hz']:.0f} | {r['rate_hz']:.1f} | {p['mean']:.2f} / {p['std']:.2f} / "
                     f"{p['max']:.2f} | {lat['p50']:.2f} / {lat['p95']:.2f} / {lat['p99']:.2f} |")
    return "\n".join(lines)
