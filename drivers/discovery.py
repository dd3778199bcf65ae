"""What devices this machine can see: every registered back-end looks for its own (serial ports, SocketCAN
interfaces, V4L2 video devices, simulated scenes); see ``Device.discover``."""

from __future__ import annotations

from .device import Discovery


def discover() -> list[Discovery]:
    from ..registry import discover_all

    return discover_all()


def format_devices(found: list[Discovery]) -> str:
    lines = []
    for d in found:
        lines.append(f"{d.title}:")
        if not d.found:
            lines.append(f"  none{f': {d.note}' if d.note else ''}")
        elif d.note:
            lines.append(f"  ({d.note})")
        for dev in d.found:
            lines.append(f"  {dev.address:<20} {dev.url}")
    lines.append("recorded: replay://SESSION (a session folder written by 'lapreco record')")
    return "\n".join(lines)
