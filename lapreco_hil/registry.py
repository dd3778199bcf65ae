"""Devices chosen by URL, python-can style: a scheme names a back-end class, imported only when used.

    open_robot("sim://skull?fps=25", context)     open_grabber("sim://skull", context)

A back-end class takes ``(url: DeviceURL, context: DeviceContext)``. The context is made once per run and
holds what devices opened in that run share (a simulated world, a CAN bus), keyed by name, so two devices
with the same name meet in the same object, and nothing is shared between runs.
"""

from __future__ import annotations

import importlib
import threading
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Callable
from urllib.parse import parse_qs, urlsplit

from .errors import ConfigError

ROBOT_BACKENDS = MappingProxyType({
    "sim": "lapreco_hil.simulators.devices:SimRobot",
    "replay": "lapreco_hil.sessions.replay:ReplayRobot",
    "serial": "lapreco_hil.drivers.robot.dynamixel:DynamixelRobot",
    "canopen": "lapreco_hil.drivers.robot.canopen402:CANopenRobot",
})

GRABBER_BACKENDS = MappingProxyType({
    "sim": "lapreco_hil.simulators.devices:SimGrabber",
    "replay": "lapreco_hil.sessions.replay:ReplayGrabber",
    "v4l2": "lapreco_hil.drivers.grabber.v4l2:V4L2Grabber",
})


@dataclass(frozen=True)
class DeviceURL:
    raw: str
    scheme: str
    netloc: str
    path: str
    query: dict[str, str]

    @property
    def name(self) -> str:
        """``sim://skull`` -> 'skull'; ``serial:///dev/ttyUSB0`` -> '/dev/ttyUSB0'."""
        return self.netloc + self.path if self.netloc else self.path

    def get(self, key: str, default: Any = None, cast: Callable = str) -> Any:
        if key not in self.query:
            return default
        try:
            return cast(self.query[key])
        except ValueError:
            raise ConfigError(f"device URL '{self.raw}': parameter '{key}={self.query[key]}' is not a valid "
                              f"{getattr(cast, '__name__', 'value')}") from None


def parse_url(url: str) -> DeviceURL:
    parts = urlsplit(url)
    if not parts.scheme:
        raise ConfigError(f"device URL '{url}' has no scheme (expected e.g. sim://skull or serial:///dev/ttyUSB0)")
    query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    return DeviceURL(url, parts.scheme, parts.netloc, parts.path, query)


class DeviceContext:
    """Objects shared by the devices of one run, created on first use (thread-safe)."""

    def __init__(self, **options: Any) -> None:
        self.options = options
        self._shared: dict[tuple[str, str], Any] = {}
        self._lock = threading.Lock()

    def shared(self, kind: str, name: str, factory: Callable[[], Any]) -> Any:
        with self._lock:
            key = (kind, name)
            if key not in self._shared:
                self._shared[key] = factory()
            return self._shared[key]


def _load(backends, kind: str, url: str):
    parsed = parse_url(url)
    try:
        target = backends[parsed.scheme]
    except KeyError:
        raise ConfigError(f"{kind} URL '{url}': unknown scheme '{parsed.scheme}' "
                          f"(known: {', '.join(sorted(backends))})") from None
    module_name, cls_name = target.split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls, parsed


def open_robot(url: str, context: DeviceContext):
    """An (unopened) RobotDriver for the URL."""
    cls, parsed = _load(ROBOT_BACKENDS, "robot", url)
    return cls(parsed, context)


def open_grabber(url: str, context: DeviceContext):
    """An (unopened) Grabber for the URL."""
    cls, parsed = _load(GRABBER_BACKENDS, "grabber", url)
    return cls(parsed, context)
