"""``lapreco devices``: what this machine sees, and a short probe of one robot or tracker."""

from __future__ import annotations

from lapreco_hil.registry import TRACKER_BACKENDS, DeviceContext, parse_url
from lapreco_hil.warp_device import resolve_device


def list_devices() -> str:
    """The serial ports, CAN interfaces and video devices found, as a table."""
    from lapreco_hil.drivers.discovery import discover, format_devices

    return format_devices(discover())


def probe(url: str, seconds: float, device: str = "auto") -> str:
    """Open the robot (or tracker) at ``url``, read it for ``seconds`` and say what it answered."""
    from lapreco_hil.drivers.probe import probe_robot, probe_tracker

    context = DeviceContext(device=resolve_device(device))
    if _is_tracker(url):
        return probe_tracker(url, context, seconds)
    return probe_robot(url, context, seconds)


def _is_tracker(url: str) -> bool:
    """A tracker's URL scheme; a recorded session (``replay://``, robot and tracker alike) by its pose source."""
    parsed = parse_url(url)
    if parsed.scheme == "replay":
        from lapreco_hil.sessions import Session

        return Session(parsed.name).meta.pose_source == "marker_poses"
    return parsed.scheme in TRACKER_BACKENDS
