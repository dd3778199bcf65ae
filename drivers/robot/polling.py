"""The shared body of the real robot drivers: a reader thread that polls the device at a fixed rate, a
bounded buffer of samples, health from what the thread sees, reconnection, and counted faults.

A back-end implements ``_connect`` / ``_disconnect`` / ``_poll``; ``_poll`` returns one reading (raw
counts and the capture time) or raises DeviceTimeoutError, ProtocolError (the reading is lost, counted, the
thread goes on) or DeviceDisconnectedError (the thread reconnects). Any other exception stops the thread and
is raised to the consumer by the next ``read``: nothing dies silently.
"""

from __future__ import annotations

import abc
import bisect
import collections
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from lapreco_hil.drivers.device import ReaderHandover
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.drivers.robot.joint_map import JointMap
from lapreco_hil.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError, ProtocolError
from lapreco_hil.registry import URLConfig, url_param
from lapreco_hil.types import JointLimits, JointSample, RobotInfo

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PolledRobotConfig(URLConfig):
    """URL parameters every polled robot takes (a back-end adds its own)."""

    rate: float = url_param(100.0, low=0.1, high=2000.0, unit="Hz", help="readings per second")
    model: str = url_param("ecm", help="robot model: a packaged name or a URDF path")
    map: str | None = url_param(None, help="joint map TOML (sign, zero_count, offset, counts_per_rev per joint)")
    counts_per_rev: float = url_param(4096.0, low=1.0, help="encoder counts per revolution")
    lead_m: float = url_param(0.002, low=1e-6, high=1.0, unit="m", help="prismatic joints: metres per revolution")


# why a raw reading was refused (RawReading.refused)
REFUSED_LIMITS = "limits"  # beyond the joint limits (a wrong joint map, or a broken reading)
REFUSED_ENCODER_ERROR = "encoder_error"  # the device flags its encoder (a Dynamixel's Hardware Error Status)


@dataclass(frozen=True)
class RawReading:
    """One reading as the device gave it (before the joint map), whether it was delivered, and if not why
    (``refused``: REFUSED_LIMITS, REFUSED_ENCODER_ERROR; "" when delivered)."""

    counts: np.ndarray
    t_ns: int
    delivered: bool
    refused: str = ""


class _RateLimitedWarning:
    """The first warning at once, then at most one per ``interval_s`` with the count of those held back."""

    def __init__(self, interval_s: float = 5.0) -> None:
        self.interval_s = interval_s
        self._last = -float("inf")
        self._held = 0

    def __call__(self, message: str) -> None:
        now = time.monotonic()
        if now - self._last < self.interval_s:
            self._held += 1
            return
        more = f" ({self._held} more since the last warning)" if self._held else ""
        log.warning("%s%s", message, more)
        self._last, self._held = now, 0


class PollingRobotDriver(ReaderHandover, RobotDriver):
    reconnect_interval_s = 0.5
    stale_after_periods = 3.0
    # readings lost to corrupt, late or missing replies mark the link degraded for this long after the last
    # one (at least ``degraded_min_s``), so a burst of errors is visible even while good readings interleave
    degraded_after_periods = 10.0
    degraded_min_s = 0.25
    buffer_len = 4096
    raw_unit = "counts"  # what the device's raw positions are called (ticks, increments)
    # how long close() waits for the reader thread; one still busy past it (inside a reconnect's _connect, or a
    # poll) disconnects what it holds itself when it ends
    close_join_s = 5.0

    def __init__(self, url, context, config: PolledRobotConfig, joint_map: JointMap, device_name: str) -> None:
        self.url = url
        self.config = config
        self.device_name = device_name
        self.joint_map = joint_map
        self.rate_hz = config.rate
        self.info = RobotInfo(config.model, joint_map.names, JointLimits(joint_map.lower, joint_map.upper))
        # the run's clock comes through the context (a simulated world's clock when the driver sits on a device
        # emulator inside a simulation); staleness is judged on the wall clock
        self._clock = context.clock_ns
        self._raw: collections.deque[RawReading] = collections.deque(maxlen=self.buffer_len)
        self._warn_limits = _RateLimitedWarning()
        self._cond = threading.Condition()
        self._new: collections.deque[JointSample] = collections.deque(maxlen=self.buffer_len)
        self._history: collections.deque[JointSample] = collections.deque(maxlen=self.buffer_len)
        self._error: BaseException | None = None
        self._init_handover()  # (the reader disconnects itself when close() gave up waiting for it)
        self._device_faults: dict[str, str] = {}  # source -> message, while a device reports a fault
        self._last_fault = ""
        self._last_sample_wall = 0.0
        self._last_error_wall = 0.0
        self._last_error = ""
        self._last_t_ns = 0
        self._seq = 0
        self._faults: collections.Counter[str] = collections.Counter()
        self._faults_lock = threading.Lock()  # counted from the reader thread and python-can's notifier

    @property
    def faults(self) -> collections.Counter[str]:
        """Counts per fault kind: timeouts, protocol_errors, disconnects, reconnects, out_of_limits,
        non_increasing_stamps, and the back-end's own (emcy, heartbeat_lost)."""
        with self._faults_lock:
            return collections.Counter(self._faults)

    def count_fault(self, kind: str) -> None:
        with self._faults_lock:
            self._faults[kind] += 1

    # --- what a back-end implements -------------------------------------------------------------------------
    @abc.abstractmethod
    def _connect(self) -> None:
        """Open the transport and check the device answers; raise DeviceError (naming it) when it cannot."""

    @abc.abstractmethod
    def _disconnect(self) -> None:
        ...

    @abc.abstractmethod
    def _poll(self) -> tuple[np.ndarray, int]:
        """One reading: (raw counts per joint, capture time in ns of the injected clock)."""

    # --- lifecycle ---------------------------------------------------------------------------------------
    def open(self) -> None:
        if self._thread is not None:
            return
        self._wait_for_leftover("connecting?")
        self._stop.clear()
        self._connect()
        self._reader_started(threading.Thread(target=self._run, name=f"robot {self.device_name}", daemon=True))

    def close(self) -> None:
        """Stop the reader and disconnect. A reader busy past ``close_join_s`` (a reconnect's _connect on a slow
        device, a blocked poll) is left to end by itself: it disconnects whatever it holds by then, so the
        transport is never left open with nobody to close it."""
        if self._stop_reader("disconnects"):
            self._disconnect_quietly()

    def _disconnect_quietly(self) -> None:
        try:
            self._disconnect()
        except Exception:  # closing a dead transport may fail; nothing is left to do about it
            log.debug("closing %s", self.device_name, exc_info=True)

    # --- the reader thread -------------------------------------------------------------------------------
    def set_device_fault(self, source: str, message: str | None) -> None:
        """A back-end reports (or clears, with None) a fault the device itself signals (EMCY, error bit)."""
        with self._cond:
            if message is None:
                self._device_faults.pop(source, None)
            else:
                self._device_faults[source] = message
                self._last_fault = message

    @property
    def last_fault(self) -> str:
        """The newest fault's one-line description ("" before any)."""
        return self._last_fault

    def _note(self, kind: str, message: str) -> None:
        self.count_fault(kind)
        self._last_fault = message
        log.debug("%s: %s", self.device_name, message)

    def _note_lost(self, kind: str, message: str) -> None:
        """A reading lost on the link (counted, and the link shows as degraded for a while)."""
        self._note(kind, message)
        self._last_error = message
        self._last_error_wall = time.monotonic()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                if not self._connected:
                    self._reconnect()
                    next_t = time.monotonic()
                    continue
                try:
                    counts, t_ns = self._poll()
                    self._accept(counts, t_ns)
                except DeviceTimeoutError as exc:
                    self._note_lost("timeouts", str(exc))
                except ProtocolError as exc:
                    self._note_lost("protocol_errors", str(exc))
                except DeviceDisconnectedError as exc:
                    self._note("disconnects", str(exc))
                    log.warning("%s", exc)
                    self._connected = False
                    try:
                        self._disconnect()
                    except Exception:
                        log.debug("closing %s after a disconnect", self.device_name, exc_info=True)
                    continue
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()  # behind: do not try to catch up with a burst
        except BaseException as exc:  # stored and raised by read(): never lost with the thread
            self._error = exc
            log.error("%s: reader thread failed: %s", self.device_name, exc)
        finally:
            with self._life:
                self._reader_running = False
                disconnect = self._abandoned and self._connected  # close() gave up waiting: nobody else will
                if disconnect:
                    self._connected = False
            if disconnect:
                self._disconnect_quietly()

    def _reconnect(self) -> None:
        if self._stop.wait(self.reconnect_interval_s):
            return
        try:
            self._connect()
        except DeviceError as exc:
            self._last_fault = str(exc)
            return
        with self._life:
            closing = self._stop.is_set()
            if not closing:
                self._connected = True
        if closing:  # close() came while connecting (and may have stopped waiting): what was opened is closed here
            self._disconnect_quietly()
            return
        self.count_fault("reconnects")
        log.warning("%s reconnected", self.device_name)

    def _accept(self, counts: np.ndarray, t_ns: int) -> None:
        jm = self.joint_map
        q = jm.to_si(counts)
        beyond = jm.beyond_limits(q)
        self._raw.append(RawReading(np.array(counts, np.int64), t_ns, not beyond.any(),
                                    REFUSED_LIMITS if beyond.any() else ""))
        if beyond.any():
            # a reading beyond the joint limits is a broken reading (or a wrong joint map), not a pose: it is
            # counted and reported, not delivered
            bad = jm.out_of_limits(q)
            self._note("out_of_limits", f"{self.device_name}: {'; '.join(bad)}")
            self.set_device_fault("limits", f"{'; '.join(bad)}")
            i = int(np.flatnonzero(beyond)[0])
            self._warn_limits(f"{self.device_name}: reading refused: joint '{jm.names[i]}' = {q[i]:.4g} {jm.unit(i)} "
                              f"({int(counts[i])} {self.raw_unit}) is beyond its limits [{jm.lower[i]:.4g}, "
                              f"{jm.upper[i]:.4g}] {jm.unit(i)}"
                              + (f" ({len(bad) - 1} more joint(s) too)" if len(bad) > 1 else "")
                              + "; check the joint map (map=FILE) with 'lapreco devices --probe URL'")
            return
        self.set_device_fault("limits", None)
        if t_ns <= self._last_t_ns:
            self._note("non_increasing_stamps", f"{self.device_name}: timestamp did not increase")
            t_ns = self._last_t_ns + 1
        self._last_t_ns = t_ns
        sample = JointSample(q, t_ns, self._seq)
        self._seq += 1
        with self._cond:
            self._new.append(sample)
            self._history.append(sample)
            self._last_sample_wall = time.monotonic()
            self._cond.notify_all()

    # --- the consumer's side -----------------------------------------------------------------------------
    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise DeviceError(f"{self.device_name}: reader failed: {self._error}") from self._error
        if self._thread is None:
            raise DeviceError(f"{self.device_name} is not open")

    def _read(self, timeout_s: float | None) -> list[JointSample]:
        self._raise_if_failed()
        with self._cond:
            if not self._new and timeout_s:
                self._cond.wait(timeout_s)
            out = list(self._new)
            self._new.clear()
        return out

    def take_raw_readings(self) -> list[RawReading]:
        """Every reading polled since the last call (up to ``buffer_len``), delivered or refused, raw counts."""
        out = []
        while self._raw:
            out.append(self._raw.popleft())
        return out

    def latest(self) -> JointSample | None:
        with self._cond:
            return self._history[-1] if self._history else None

    def at(self, t_ns: int) -> JointSample | None:
        """Joint positions at ``t_ns``, interpolated between the two samples around it (None outside)."""
        with self._cond:
            hist = list(self._history)
        times = [s.t_ns for s in hist]
        i = bisect.bisect_left(times, t_ns)
        if i < len(hist) and times[i] == t_ns:
            return hist[i]
        if i == 0 or i >= len(hist):
            return None
        a, b = hist[i - 1], hist[i]
        s = (t_ns - a.t_ns) / (b.t_ns - a.t_ns)
        return JointSample(a.q + s * (b.q - a.q), t_ns, a.seq)

    @property
    def health(self) -> Health:
        now = time.monotonic()
        if self._error is not None:
            return Health(HealthState.FAULTED, f"reader thread failed: {self._error}", self._clock())
        if self._thread is None:
            return Health(HealthState.DISCONNECTED, "not open", self._clock())
        if not self._connected:
            return Health(HealthState.DISCONNECTED, self._last_fault or "reconnecting", self._clock())
        with self._cond:
            faults = dict(self._device_faults)
            last = self._last_sample_wall
        if faults:
            return Health(HealthState.FAULTED, "; ".join(f"{k}: {v}" for k, v in faults.items()), self._clock())
        if last == 0.0 or now - last > self.stale_after_periods / self.rate_hz:
            silent = "no reading yet" if last == 0.0 else f"no reading for {(now - last) * 1e3:.0f} ms"
            return Health(HealthState.STALE, f"{silent} ({self._last_fault or 'no fault seen'})", self._clock())
        if now - self._last_error_wall < max(self.degraded_min_s, self.degraded_after_periods / self.rate_hz):
            counts = self.faults
            lost = counts["timeouts"] + counts["protocol_errors"]
            return Health(HealthState.DEGRADED, f"{lost} readings lost so far; last: {self._last_error}", self._clock())
        return Health(HealthState.OK, "", self._clock())
