"""A look at a device before recording with it. A robot: what each joint reads, raw (ticks, increments) and in
SI with the joint map applied, against the joint limits; a wrong joint map (a zero in the wrong place, a flipped
sign) shows as readings beyond the limits, which the driver refuses; readings it refuses because the device flags
its encoder (a Dynamixel's Hardware Error Status) are counted apart, with the servo to check. A tracker: each tool's poses, how often it
was missing or outside the measured volume. ``lapreco devices --probe URL`` prints either."""

from __future__ import annotations

import time

import numpy as np

from lapreco_hil.drivers.robot.polling import (REFUSED_ENCODER_ERROR, REFUSED_LIMITS, PollingRobotDriver,
                                              RawReading)
from lapreco_hil.registry import DeviceContext, open_robot, open_tracker
from lapreco_hil.types import JointSample, MarkerSample


def probe_robot(url: str, context: DeviceContext, seconds: float) -> str:
    """Open the robot at ``url``, read for ``seconds``, and describe what it read (several lines of text)."""
    robot = open_robot(url, context)
    raw: list[RawReading] = []
    samples: list[JointSample] = []
    with robot:
        polled = isinstance(robot, PollingRobotDriver)
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            samples += robot.read(timeout_s=max(0.0, min(0.1, left)))
            if polled:
                raw += robot.take_raw_readings()  # drained as it goes: the driver keeps a bounded buffer
            if left <= 0:
                break
        health, faults = robot.health, dict(robot.faults)
    names, limits = robot.info.joint_names, robot.info.limits
    lines = []
    if polled:
        jm = robot.joint_map
        refused = sum(not r.delivered for r in raw)
        by_limits = sum(r.refused == REFUSED_LIMITS for r in raw)
        by_encoder = sum(r.refused == REFUSED_ENCODER_ERROR for r in raw)
        causes = [text for n, text in ((by_limits, f"{by_limits} beyond the joint limits"),
                                       (by_encoder, f"{by_encoder} for an encoder error the device flags"),
                                       (refused - by_limits - by_encoder,
                                        f"{refused - by_limits - by_encoder} for another reason")) if n]
        lines.append(f"robot {url} ({robot.device_name}): {len(raw)} readings in {seconds:g} s, {len(samples)} "
                     f"delivered, {refused} refused" + (f" ({', '.join(causes)})" if causes else ""))
        lines.append(f"joint map: model '{robot.config.model}', file {robot.config.map or 'none (the device convention)'}; "
                     f"SI = sign * ({robot.raw_unit} - zero) * scale + offset")
        counts = np.array([r.counts for r in raw], np.int64).reshape(len(raw), len(names))
        q = jm.to_si(counts) if len(raw) else np.zeros((0, len(names)))
        beyond = jm.beyond_limits(q) if len(raw) else np.zeros((0, len(names)), bool)
        header = (f"  {'joint':<10} {'zero':>6} {'scale':>10} {'sign':>4} {'offset':>8}  {'raw last':>9} "
                  f"{'raw min..max':>21}  {'SI last':>10} {'SI min..max':>21} {'limits':>22}  beyond")
        lines.append(header)
        for i, name in enumerate(names):
            unit = jm.unit(i)
            row = (f"  {name:<10} {jm.zero_count[i]:>6.0f} {jm.si_per_count[i]:>10.4g} {jm.sign[i]:>+4.0f} "
                   f"{jm.offset[i]:>8.4g}  ")
            if len(raw):
                c, v = counts[:, i], q[:, i]
                row += (f"{c[-1]:>9d} {f'{c.min()}..{c.max()}':>21}  {v[-1]:>10.4g} "
                        f"{f'{v.min():.4g}..{v.max():.4g}':>21} ")
            else:
                row += f"{'-':>9} {'-':>21}  {'-':>10} {'-':>21} "
            row += f"{f'[{limits.lower[i]:.4g}, {limits.upper[i]:.4g}]':>22} {unit:<3}"
            n_beyond = int(beyond[:, i].sum())
            row += f" {n_beyond} of {len(raw)}" + ("  <-- BEYOND THE LIMITS" if n_beyond else "")
            lines.append(row)
        if by_encoder:
            lines.append("readings the device flags with an encoder error are refused by the driver (their positions "
                         "are not trustworthy): a hardware fault, not the joint map; check the servo named in health "
                         "(its Hardware Error Status, address 70: motor encoder; its cable and power), then "
                         "power-cycle or reboot it to clear the alert")
        if by_limits:
            lines.append("readings beyond the limits are refused by the driver: check the joint map (zero_count, "
                         "sign, offset, counts_per_rev per joint in a map=FILE TOML) and the servo IDs' order")
    else:
        lines.append(f"robot {url}: {len(samples)} readings in {seconds:g} s, SI units (this back-end has no raw "
                     f"encoder units)")
        q = np.array([s.q for s in samples]).reshape(len(samples), len(names))
        lines.append(f"  {'joint':<10} {'SI last':>10} {'SI min..max':>21} {'limits':>22}")
        for i, name in enumerate(names):
            if len(samples):
                v = q[:, i]
                row = f"  {name:<10} {v[-1]:>10.4g} {f'{v.min():.4g}..{v.max():.4g}':>21} "
            else:
                row = f"  {name:<10} {'-':>10} {'-':>21} "
            lines.append(row + f"{f'[{limits.lower[i]:.4g}, {limits.upper[i]:.4g}]':>22}")
    if not samples and not raw:
        lines.append(f"no readings in {seconds:g} s")
    lines.append(f"health: {health.state.value}{f' ({health.detail})' if health.detail else ''}")
    counted = {k: v for k, v in faults.items() if v}
    lines.append("faults: " + (", ".join(f"{k} {v}" for k, v in sorted(counted.items())) or "none"))
    return "\n".join(lines)


def probe_tracker(url: str, context: DeviceContext, seconds: float) -> str:
    """Open the tracker at ``url``, read for ``seconds``, and describe each tool's poses (several lines of text)."""
    tracker = open_tracker(url, context)
    samples: list[MarkerSample] = []
    with tracker:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            samples += tracker.read(timeout_s=min(0.1, left))
        health, faults = tracker.health, dict(tracker.faults)
    lines = [f"tracker {url}: {len(samples)} poses in {seconds:g} s"]
    tools = sorted({s.tool for s in samples})
    if tools:
        lines.append(f"  {'tool':<16} {'poses':>6} {'rate Hz':>8} {'last position (mm)':>28} {'rms mm':>7} "
                     f"{'outside volume':>14}")
    for tool in tools:
        mine = [s for s in samples if s.tool == tool]
        span_s = (mine[-1].t_ns - mine[0].t_ns) * 1e-9
        rate = (len(mine) - 1) / span_s if span_s > 0 else float("nan")
        x, y, z = mine[-1].T_tracker_marker[:3, 3] * 1e3
        outside = sum(not s.in_volume for s in mine)
        lines.append(f"  {tool:<16} {len(mine):>6} {rate:>8.1f} {f'{x:.1f} {y:.1f} {z:.1f}':>28} "
                     f"{mine[-1].rms_mm:>7.3f} {outside:>14}")
    if not samples:
        lines.append(f"no pose in {seconds:g} s: is a tool in view (or plugged in), and enabled?")
    lines.append(f"health: {health.state.value}{f' ({health.detail})' if health.detail else ''}")
    counted = {k: v for k, v in faults.items() if v}
    lines.append("faults: " + (", ".join(f"{k} {v}" for k, v in sorted(counted.items())) or "none"))
    return "\n".join(lines)
