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

import numpy as np

from ..health import Health, HealthState
from .base import RobotDriver
from .joint_map import JointMap
from ...errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError, ProtocolError
from ...types import JointLimits, JointSample, RobotInfo

log = logging.getLogger(__name__)


class PollingRobotDriver(RobotDriver):
    reconnect_interval_s = 0.5
    stale_after_periods = 3.0
    # readings lost to corrupt, late or missing replies mark the link degraded for this long after the last
    # one (at least ``degraded_min_s``), so a burst of errors is visible even while good readings interleave
    degraded_after_periods = 10.0
    degraded_min_s = 0.25
    buffer_len = 4096

    def __init__(self, url, context, joint_map: JointMap, device_name: str) -> None:
        self.url = url
        self.device_name = device_name
        self.joint_map = joint_map
        self.rate_hz = url.get("rate", 100.0, float)
        if not 0.1 <= self.rate_hz <= 2000:
            raise DeviceError(f"robot '{url.raw}': rate={self.rate_hz} Hz out of range (0.1..2000)")
        self.info = RobotInfo(url.get("model", "ecm"), joint_map.names, JointLimits(joint_map.lower, joint_map.upper))
        # the clock is injected (a simulated world's clock in the demo); staleness is judged on the wall clock
        self._clock = context.options.get("clock_ns", time.monotonic_ns)
        self._cond = threading.Condition()
        self._new: collections.deque[JointSample] = collections.deque(maxlen=self.buffer_len)
        self._history: collections.deque[JointSample] = collections.deque(maxlen=self.buffer_len)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._connected = False
        self._device_faults: dict[str, str] = {}  # source -> message, while a device reports a fault
        self._last_fault = ""
        self._last_sample_wall = 0.0
        self._last_error_wall = 0.0
        self._last_error = ""
        self._last_t_ns = 0
        self._seq = 0
        self.faults: collections.Counter[str] = collections.Counter()

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
        self._connect()
        self._connected = True
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"robot {self.device_name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._connected:
            self._connected = False
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

    def _note(self, kind: str, message: str) -> None:
        self.faults[kind] += 1
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

    def _reconnect(self) -> None:
        if self._stop.wait(self.reconnect_interval_s):
            return
        try:
            self._connect()
        except DeviceError as exc:
            self._last_fault = str(exc)
            return
        self._connected = True
        self.faults["reconnects"] += 1
        log.warning("%s reconnected", self.device_name)

    def _accept(self, counts: np.ndarray, t_ns: int) -> None:
        q = self.joint_map.to_si(counts)
        bad = self.joint_map.out_of_limits(q)
        if bad:
            # a reading beyond the joint limits is a broken reading, not a pose: it is counted, not delivered
            self._note("out_of_limits", f"{self.device_name}: {'; '.join(bad)}")
            self.set_device_fault("limits", f"{'; '.join(bad)}")
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

    def read(self, timeout_s: float | None = None) -> list[JointSample]:
        self._raise_if_failed()
        with self._cond:
            if not self._new and timeout_s:
                self._cond.wait(timeout_s)
            out = list(self._new)
            self._new.clear()
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
            lost = self.faults["timeouts"] + self.faults["protocol_errors"]
            return Health(HealthState.DEGRADED, f"{lost} readings lost so far; last: {self._last_error}", self._clock())
        return Health(HealthState.OK, "", self._clock())
