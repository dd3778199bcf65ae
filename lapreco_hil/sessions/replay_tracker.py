"""A recorded tracked scope as a tracker: ``replay://<session folder>[?pace=afap|realtime&queue=N]``.

It serves a marker-pose session's marker_poses.csv as the NDI driver delivers a live tracker's poses: every
row of every tool (the scope's, a calibration board's), as ``MarkerSample`` with T_tracker_marker in metres,
the marker-fit RMS in mm and the volume flag, stamped on the tracker's clock as recorded (``time_offset_ns``
is the pose source's to apply, as for a live tracker). Nothing is judged here: an out-of-volume or high-RMS
row is delivered as the device reported it, and the pose source refuses it.

Paced as the replay robot (``lapreco_hil.sessions.replay``): a tracker and a grabber opened on the same session
in one DeviceContext share one replay clock, and each frame the grabber hands on releases the rows captured up
to one frame period after it (on the tracker's clock: frame time + the session's ``time_offset_ns``). So
``lapreco run --marker replay://S --grabber replay://S?pace=realtime`` plays at the recorded rate and
``pace=afap`` is deterministic; the tracker takes the grabber's parameters, so one URL opens both, and the
grabber's pace rules.

Opened with no grabber of its session (``lapreco devices --probe replay://S``) it plays by itself from its first
read: ``afap`` hands every row on at once, ``realtime`` at the recorded rate.

Faults: ``out_of_volume`` (rows delivered flagged outside the characterised volume, counted as the NDI driver
counts them); health is degraded while a tool's latest pose is outside the volume.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.tracker.base import TrackerDriver
from lapreco_hil.errors import ConfigError, DeviceError, SessionError
from lapreco_hil.registry import RECORDED, DeviceContext, DeviceURL, URLConfig, parse_url, url_param
from lapreco_hil.sessions.replay import _shared
from lapreco_hil.types import MarkerSample

_POSE_SOURCE_WORDS = {"joints": "joint readings", "camera_poses": "given camera poses"}


@dataclass(frozen=True)
class ReplayTrackerConfig(URLConfig):
    # the tracker follows the grabber's pace; it takes the grabber's parameters so one URL opens both (alone,
    # it plays by itself at this pace)
    pace: str = url_param("afap", choices=("afap", "realtime"), help="as fast as possible, or the recorded rate")
    queue: int = url_param(4, low=1, unit="frame")


class ReplayTracker(TrackerDriver):
    clock_domain = RECORDED
    wait_step_s = 0.005  # how often a waiting read looks at the replay clock

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        config = ReplayTrackerConfig.from_url(url)
        self.url, self._context = url, context
        self.realtime = config.pace == "realtime"
        self.session, self.clock = _shared(url, context)
        self.device_name = f"tracker {url.raw}"
        pose_source = self.session.meta.pose_source
        if pose_source != "marker_poses" or self.session.markers is None:
            hint = (f"open it as a robot (--robot replay://{url.name})" if pose_source == "joints"
                    else f"replay it with 'lapreco replay {url.name}'")
            raise SessionError(f"session '{url.name}' has no marker poses to replay as a tracker: its pose source is "
                               f"{_POSE_SOURCE_WORDS.get(pose_source, pose_source)} (pose_source "
                               f"'{pose_source}'); {hint}")
        table = self.session.markers
        # each tool's rows increase in time; across tools the file order need not: released in time order
        order = np.argsort(table.t_ns, kind="stable")
        self._t_ns = np.asarray(table.t_ns)[order]
        self._poses = np.asarray(table.poses)[order]
        self._tools = [table.tools[k] for k in order]
        self._rms = np.asarray(table.rms_mm, float)[order]
        self._inside = np.asarray(table.in_volume, bool)[order]
        self.tools = tuple(dict.fromkeys(table.tools))  # in the order the session first names them
        self._lock = threading.Lock()
        self._i = 0  # the next row to hand on
        self._faults: Counter = Counter()
        self._outside: dict[str, bool] = {}  # tool -> whether its latest pose was outside the volume
        self._open = False
        self._alone = False  # no grabber of the session in the run: plays by itself
        self._wall0: float | None = None

    # --- lifecycle -------------------------------------------------------------------------------------------------
    def open(self) -> None:
        if self._open:
            return
        self._alone = not self._paired()
        self._wall0 = None  # (alone and real-time: it starts playing at the first read, as the grabber does)
        self._open = True

    def close(self) -> None:
        self._open = False

    def _paired(self) -> bool:
        """Whether another device of this run replays the same session (its grabber: a marker session opens no
        robot); a run whose other replays are of another session is refused, as its clock would never move."""
        with self._context._lock:  # (the run's devices: the registry's record, read only)
            urls = [u for u, domain in self._context._devices if domain == RECORDED]
        mine = sum(parse_url(u).name == self.url.name for u in urls)
        others = [u for u in urls if parse_url(u).name != self.url.name]
        if mine <= 1 and others:
            raise ConfigError(f"device URL '{self.url.raw}': the tracker replay plays with the grabber of its own "
                              f"session, and this run replays another ('{others[0]}'); give both the same session "
                              f"folder, spelt the same")
        return mine > 1

    # --- reading ---------------------------------------------------------------------------------------------------
    def _now_ns(self) -> float:
        """The newest time (tracker clock) whose rows are due."""
        if not self._alone:
            return self.clock.now_ns
        if not self.realtime:
            return float("inf")
        if self._wall0 is None:
            self._wall0 = time.monotonic()
        return float(self._t_ns[0]) + (time.monotonic() - self._wall0) * 1e9 if len(self._t_ns) else 0.0

    def _due(self) -> int:
        """The index after the last row due now."""
        now = self._now_ns()
        return len(self._t_ns) if now == float("inf") else int(np.searchsorted(self._t_ns, now, side="right"))

    def _read(self, timeout_s: float | None) -> list[MarkerSample]:
        if not self._open:
            raise DeviceError(f"{self.device_name} is not open")
        end = self._due()
        if end <= self._i and timeout_s:
            # like a live tracker, wait up to the timeout for a pose (at the end of the session: the whole wait)
            deadline = time.monotonic() + timeout_s
            while (end := self._due()) <= self._i and (left := deadline - time.monotonic()) > 0:
                time.sleep(min(self.wait_step_s, left))
        with self._lock:
            start, self._i = self._i, max(self._i, end)
            out = []
            for k in range(start, self._i):
                tool, inside = self._tools[k], bool(self._inside[k])
                if not inside:
                    self._faults["out_of_volume"] += 1
                self._outside[tool] = not inside
                out.append(MarkerSample(self._poses[k].copy(), int(self._t_ns[k]), k, tool, float(self._rms[k]),
                                        inside))
        return out

    # --- state -----------------------------------------------------------------------------------------------------
    @property
    def faults(self) -> Mapping[str, int]:
        with self._lock:
            return Counter(self._faults)

    @property
    def health(self) -> Health:
        if not self._open:
            return Health(HealthState.DISCONNECTED, "not open")
        with self._lock:
            outside = [tool for tool, out in self._outside.items() if out]
        if outside:
            return Health(HealthState.DEGRADED, "; ".join(f"{tool}: out of volume" for tool in outside))
        return Health(HealthState.OK)
