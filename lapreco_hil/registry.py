"""Devices chosen by URL, python-can style: a scheme names a back-end class, imported only when used.

    open_robot("sim://skull?fps=25", context)     open_grabber("sim://skull", context)

A back-end class takes ``(url: DeviceURL, context: DeviceContext)`` and parses the URL's query into its own
frozen :class:`URLConfig` dataclass (``Config.from_url(url)``): unknown parameters, values of the wrong type
and values out of range are refused with one line naming the URL and the parameter. The context is made once
per run and holds what devices opened in that run share (a simulated world, a CAN bus, the run's clock),
keyed by name, so two devices with the same name meet in the same object, and nothing is shared between runs.

One clock per run: every back-end class says which clock it stamps on (``clock_domain``: ``"host"`` for real
devices, ``"simulated"`` for a simulator, ``"recorded"`` for a session replay). The simulated clock is the
run's clock only when every device of the run is simulated; a simulator in a run with a real device stamps on
the host's monotonic clock (``DeviceContext.clock_ns``), and a replay cannot be mixed with live devices.
"""

from __future__ import annotations

import dataclasses
import importlib
import threading
import time
import typing
from dataclasses import dataclass
from types import MappingProxyType, UnionType
from typing import Any, Callable
from urllib.parse import parse_qs, urlsplit

from lapreco_hil.errors import ConfigError

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

TRACKER_BACKENDS = MappingProxyType({
    "ndi": "lapreco_hil.drivers.tracker.ndi:NDITracker",
    "replay": "lapreco_hil.sessions.replay_tracker:ReplayTracker",
})

HOST, SIMULATED, RECORDED = "host", "simulated", "recorded"


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

    def error(self, message: str) -> ConfigError:
        return ConfigError(f"device URL '{self.raw}': {message}")


def parse_url(url: str) -> DeviceURL:
    parts = urlsplit(url)
    if not parts.scheme:
        raise ConfigError(f"device URL '{url}' has no scheme (expected e.g. sim://skull or serial:///dev/ttyUSB0)")
    query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    return DeviceURL(url, parts.scheme, parts.netloc, parts.path, query)


# --- typed URL configs -------------------------------------------------------------------------------------------

def url_param(default: Any, *, parse: Callable[[str], Any] | None = None, low: float | None = None,
              high: float | None = None, choices: tuple[str, ...] | None = None, unit: str = "",
              help: str = "") -> Any:
    """A field of a :class:`URLConfig`: its default, and how its text is checked.

    ``parse`` turns the text into the value (default: from the field's type: int, float, str, bool); it may
    raise ValueError with a message. ``low``/``high`` bound a number (inclusive), ``choices`` a word."""
    return dataclasses.field(default=default, metadata={"parse": parse, "low": low, "high": high,
                                                        "choices": choices, "unit": unit, "help": help})


def parse_bool(text: str) -> bool:
    word = text.strip().lower()
    if word in ("1", "true", "yes", "on"):
        return True
    if word in ("0", "false", "no", "off"):
        return False
    raise ValueError("must be true or false")


_TYPE_PARSERS: dict[Any, tuple[Callable[[str], Any], str]] = {
    int: (int, "an integer"), float: (float, "a number"), str: (str, "text"), bool: (parse_bool, "true or false"),
}


def _base_type(hint):
    """``int | None`` -> int; ``int`` -> int."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if typing.get_origin(hint) in (typing.Union, UnionType) and len(args) == 1 else hint


@dataclass(frozen=True)
class URLConfig:
    """Base of every back-end's URL config: the dataclass fields are the URL's query parameters."""

    @classmethod
    def known_parameters(cls) -> list[str]:
        """The parameter names, the back-end's own first (most derived class first)."""
        names = {f.name for f in dataclasses.fields(cls)}
        ordered = [n for c in cls.__mro__ for n in c.__dict__.get("__annotations__", {}) if n in names]
        return list(dict.fromkeys(ordered))

    @classmethod
    def from_url(cls, url: DeviceURL):
        """The config the URL's query asks for (fields not in the query keep their defaults)."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = [k for k in url.query if k not in fields]
        if unknown:
            raise url.error(f"unknown parameter '{unknown[0]}' (known: {', '.join(cls.known_parameters())})")
        hints = typing.get_type_hints(cls)
        return cls(**{key: _parse_field(url, fields[key], _base_type(hints[key]), text)
                      for key, text in url.query.items()})


def _parse_field(url: DeviceURL, f: dataclasses.Field, kind, text: str) -> Any:
    meta = f.metadata
    parse, what = (meta.get("parse"), "a valid value") if meta.get("parse") else _TYPE_PARSERS.get(kind, (kind, ""))
    try:
        value = parse(text)
    except (ValueError, TypeError) as exc:
        reason = str(exc) if meta.get("parse") and str(exc) else f"is not {what or 'valid'}"
        raise url.error(f"parameter '{f.name}={text}' {reason}") from None
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    if meta.get("choices") and value not in meta["choices"]:
        raise url.error(f"{f.name} must be one of {', '.join(meta['choices'])}, got '{text}'")
    low, high = meta.get("low"), meta.get("high")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if value != value:
            raise url.error(f"parameter '{f.name}={text}' is not a number")
        if low is not None and high is not None and not low <= value <= high:
            raise url.error(f"{f.name} must be in {low:g}..{high:g}{unit}, got {text}")
        if low is not None and value < low:
            raise url.error(f"{f.name} must be at least {low:g}{unit}, got {text}")
        if high is not None and value > high:
            raise url.error(f"{f.name} must be at most {high:g}{unit}, got {text}")
    return value


def id_list_parser(low: int, high: int, protocol: str) -> Callable[[str], tuple[int, ...]]:
    """A parser of device ids ``1,2,3`` or ``1-4`` or ``1-2,5``: distinct, each in low..high (the protocol's
    range, named in the error)."""

    def parse(text: str) -> tuple[int, ...]:
        ids: list[int] = []
        try:
            for part in text.split(","):
                if "-" in part.strip()[1:]:
                    a, b = (int(v) for v in part.split("-", 1))
                    ids.extend(range(a, b + 1))
                elif part.strip():
                    ids.append(int(part))
        except ValueError:
            raise ValueError("must be numbers like 1,2,3,4 or 1-4") from None
        if not ids:
            raise ValueError("lists no ids")
        if len(set(ids)) != len(ids):
            raise ValueError("lists an id twice")
        bad = [i for i in ids if not low <= i <= high]
        if bad:
            raise ValueError(f"has id {bad[0]} outside {protocol}'s range {low}..{high}")
        return tuple(ids)

    return parse


# --- the devices of one run --------------------------------------------------------------------------------------

class DeviceContext:
    """Objects shared by the devices of one run, created on first use (thread-safe), and the run's clock.

    ``clock_ns`` (option, default ``time.monotonic_ns``) is the host clock every real device stamps on."""

    def __init__(self, **options: Any) -> None:
        self.options = options
        self.clock_ns: Callable[[], int] = options.get("clock_ns", time.monotonic_ns)
        self._shared: dict[tuple[str, str], Any] = {}
        self._lock = threading.Lock()
        self._devices: list[tuple[str, str]] = []  # (url, clock domain) of every device made in this context
        self._decided: tuple[str, str] | None = None  # (domain, the device whose opening decided it)

    def shared(self, kind: str, name: str, factory: Callable[[], Any]) -> Any:
        with self._lock:
            key = (kind, name)
            if key not in self._shared:
                self._shared[key] = factory()
            return self._shared[key]

    @staticmethod
    def _domain_of(devices: list[tuple[str, str]]) -> str:
        domains = {d for _, d in devices}
        if RECORDED in domains:
            return RECORDED
        return SIMULATED if domains == {SIMULATED} else HOST

    def join(self, url: str, domain: str) -> None:
        """A device of this run, stamping on ``domain``'s clock; a mix that cannot share one clock is refused."""
        with self._lock:
            others = [(u, d) for u, d in self._devices if (d == RECORDED) != (domain == RECORDED)]
            if others:
                live, replay = (others[0][0], url) if domain == RECORDED else (url, others[0][0])
                raise ConfigError(f"device URL '{live}' cannot run with the replay '{replay}': a replay plays "
                                  f"recorded time, a live device stamps on this host's clock; replay both "
                                  f"devices from the session, or record live ones")
            devices = self._devices + [(url, domain)]
            if self._decided is not None and self._domain_of(devices) != self._decided[0]:
                raise ConfigError(f"device URL '{url}' joins a run whose clock was fixed when '{self._decided[1]}' "
                                  f"opened ({self._decided[0]} time); make every device of a run before opening any")
            self._devices = devices

    def clock_domain(self, opener: str) -> str:
        """The clock the run's devices stamp on (fixed from the first call: a device calls this when it opens)."""
        with self._lock:
            if self._decided is None:
                self._decided = (self._domain_of(self._devices), opener)
            return self._decided[0]


def _load(backends, kind: str, url: str):
    parsed = parse_url(url)
    try:
        target = backends[parsed.scheme]
    except KeyError:
        raise ConfigError(f"{kind} URL '{url}': unknown scheme '{parsed.scheme}' "
                          f"(known: {', '.join(sorted(backends))})") from None
    return import_backend(target), parsed


def import_backend(target: str):
    module_name, cls_name = target.split(":")
    return getattr(importlib.import_module(module_name), cls_name)


def _make(cls, parsed: DeviceURL, context: DeviceContext):
    device = cls(parsed, context)
    context.join(parsed.raw, cls.clock_domain)
    return device


def open_robot(url: str, context: DeviceContext):
    """An (unopened) RobotDriver for the URL."""
    cls, parsed = _load(ROBOT_BACKENDS, "robot", url)
    return _make(cls, parsed, context)


def open_grabber(url: str, context: DeviceContext):
    """An (unopened) Grabber for the URL."""
    cls, parsed = _load(GRABBER_BACKENDS, "grabber", url)
    return _make(cls, parsed, context)


def open_tracker(url: str, context: DeviceContext):
    """An (unopened) TrackerDriver (optical / electromagnetic marker tracker) for the URL."""
    cls, parsed = _load(TRACKER_BACKENDS, "tracker", url)
    return _make(cls, parsed, context)
