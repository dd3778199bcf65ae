"""Health of whatever a run depends on, polled from one place: devices (a grabber, a robot, the pose source's
refusals) and states that are not a device's (the front-end's tracks, the frames' time stamps).

A ``HealthMonitor`` is generic over named sources, each a callable returning a ``Health`` (drivers/health.py) or
a ``Condition``. Each change of a source's state becomes a timestamped event (for report.json) and one console
line: a WARNING when the source leaves OK (``grabber: degraded: 3 frames dropped``), an INFO line when it comes
back (``robot: ok again``). A source that flaps faster than ``log_interval_s`` gets one line per interval (the
events keep every change). The live runtime polls it from a thread of its own (``start``/``stop``); a recorder
can do the same, or call ``poll`` from its own loop."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable, Mapping, Union

from lapreco_hil.drivers.health import Health, HealthState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Condition:
    """A state of something that is not a device (e.g. the front-end: "tracking", "no tracks", "partial view").
    ``count_as`` names the report's counter for entering it (default: ``<source>_<state>``)."""

    state: str
    ok: bool
    detail: str = ""
    count_as: str | None = None


HealthSource = Callable[[], Union[Health, Condition]]


@dataclass(frozen=True)
class HealthEvent:
    t_s: float  # since the monitor started
    t_monotonic: float
    source: str
    state: str
    detail: str
    ok: bool
    recovered: bool = False  # OK after a state that was not (what "again" says)

    def as_dict(self) -> dict:
        # "device" is the report's key for the source (report.json's contract)
        return {"t_s": round(self.t_s, 3), "t_monotonic": self.t_monotonic, "device": self.source,
                "state": self.state, "detail": self.detail}

    @property
    def line(self) -> str:
        if self.ok:
            return f"{self.source}: {self.state} again" if self.recovered else f"{self.source}: {self.state}"
        return f"{self.source}: {self.state}: {self.detail}" if self.detail else f"{self.source}: {self.state}"


def _normalise(name: str, reading: Health | Condition) -> tuple[str, bool, str, str]:
    """(state, ok, detail, counter key) of a source's reading."""
    if isinstance(reading, Health):
        state = reading.state.value
        return state, reading.state is HealthState.OK, reading.detail, f"{name}_{state}".replace(" ", "_")
    return reading.state, reading.ok, reading.detail, \
        reading.count_as or f"{name}_{reading.state}".replace(" ", "_").replace("-", "_")


class HealthMonitor:
    def __init__(self, sources: Mapping[str, HealthSource] | None = None, *, period_s: float = 0.02,
                 log_interval_s: float = 1.0, max_events: int = 10_000, logger: logging.Logger | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s, self.log_interval_s, self.max_events = period_s, log_interval_s, max_events
        self.logger = logger or log
        self.clock = clock
        self._sources: dict[str, HealthSource] = dict(sources or {})
        self._lock = threading.Lock()
        self._t0: float | None = None
        self._state: dict[str, tuple[str, bool]] = {}  # source -> (state, ok) last seen
        self._logged: dict[str, tuple[float, str]] = {}  # source -> (when, state) of its last console line
        self._unlogged: dict[str, HealthEvent] = {}  # the newest change not shown because of the rate limit
        self._suppressed: dict[str, int] = {}
        self.events: list[HealthEvent] = []  # the first max_events changes
        self.event_count = 0
        self.counts: dict[str, int] = {}  # entries into each non-OK state, by counter key
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def add(self, name: str, source: HealthSource) -> None:
        with self._lock:
            self._sources[name] = source

    @property
    def degraded(self) -> bool:
        """Whether any source is not OK as last polled."""
        with self._lock:
            return any(not ok for _, ok in self._state.values())

    def poll(self) -> None:
        """Read every source once; record (and show) what changed."""
        now = self.clock()
        with self._lock:
            if self._t0 is None:
                self._t0 = now
            for name, source in self._sources.items():
                state, ok, detail, key = _normalise(name, source())
                if self._state.get(name) == (state, ok):
                    continue
                first = name not in self._state
                was_ok = self._state.get(name, (None, True))[1]
                self._state[name] = (state, ok)
                event = HealthEvent(now - self._t0, now, name, state, detail, ok, recovered=ok and not was_ok)
                self.event_count += 1
                if len(self.events) < self.max_events:
                    self.events.append(event)
                if not ok:
                    self.counts[key] = self.counts.get(key, 0) + 1
                if not (first and ok):  # "robot: ok" at the start is no news
                    self._show(event)
            for name in list(self._unlogged):  # a flapping source's state once its interval has passed
                if now - self._logged[name][0] >= self.log_interval_s:
                    event = self._unlogged.pop(name)
                    if self._state[name][0] != self._logged[name][1]:
                        self._show(event, note=f" ({self._suppressed[name]} changes in between not shown)")
                    self._suppressed[name] = 0

    def _show(self, event: HealthEvent, note: str = "") -> None:
        last = self._logged.get(event.source)
        if not note and last is not None and event.t_monotonic - last[0] < self.log_interval_s:
            self._unlogged[event.source] = event
            self._suppressed[event.source] = self._suppressed.get(event.source, 0) + 1
            return
        self._logged[event.source] = (event.t_monotonic, event.state)
        self._unlogged.pop(event.source, None)
        self.logger.log(logging.INFO if event.ok else logging.WARNING, "%s%s", event.line, note)

    def event_dicts(self, limit: int | None = None) -> list[dict]:
        with self._lock:
            return [e.as_dict() for e in self.events[:limit]]

    # --- polling from a thread of its own ----------------------------------------------------------------------
    def start(self, name: str = "health") -> "HealthMonitor":
        self._stop.clear()
        self._thread = threading.Thread(target=self.run_until, args=(self._stop,), name=name, daemon=True)
        self._thread.start()
        return self

    def run_until(self, stop: threading.Event) -> None:
        """Poll every ``period_s`` until ``stop`` is set (a thread body)."""
        while not stop.wait(self.period_s):
            self.poll()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
