"""What devices this machine can see: every registered back-end looks for its own (serial ports, SocketCAN
interfaces, V4L2 video devices, NDI trackers, simulated scenes); see ``Device.discover``."""

from __future__ import annotations

from lapreco_hil import registry
from lapreco_hil.drivers.device import Discovery


def discover() -> list[Discovery]:
    """What every registered back-end finds on this machine (``Discovery`` per back-end that looks), each
    back-end imported only now; a back-end that cannot be imported says so instead of raising."""
    real, simulated = [], []
    for target in dict.fromkeys([*registry.ROBOT_BACKENDS.values(), *registry.GRABBER_BACKENDS.values(),
                                   *registry.TRACKER_BACKENDS.values()]):
        try:
            cls = registry.import_backend(target)
            found, kind = cls.discover(), cls.clock_domain
        except (ImportError, OSError) as exc:  # a missing library or an unreadable OS listing: said, not raised
            found, kind = Discovery(target.split(":")[1], (), f"cannot look ({exc})"), registry.HOST
        out = real if kind == registry.HOST else simulated  # hardware first
        if found is not None and found not in out:
            out.append(found)
    return real + simulated


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
