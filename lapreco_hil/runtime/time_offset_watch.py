"""The video-kinematics time offset, watched during a live run: every frame, the image motion the tracker
measured (the tracks' median displacement since the previous frame) and the image motion the pose source
predicts for the same tracks (their depths moved by the relative pose) go to a sliding-window monitor
(lapreco_hil.calib.time_offset.TimeOffsetMonitor). When the two line up best at an offset other than the one in
use, the health line says so: a recording whose clocks slipped is common (a public surgical dataset found 64 of
68 recordings offset, by up to 2.4 s)."""

from __future__ import annotations

import time

import numpy as np

from lapreco_hil.calib.time_offset import OffsetReading, TimeOffsetMonitor
from lapreco_hil.runtime.health import Condition
from lapreco_hil.types import FrameMotion, Observations

# how often the window is searched (a search over +-0.5 s takes milliseconds: never per frame)
READING_PERIOD_S = 2.0
# a drift beyond this is reported: geared joints' backlash alone reads as ~20 ms of delay in the image motion
# (docs/calibration-handeye.md), and the slips worth a warning are tens to thousands of milliseconds
DRIFT_THRESHOLD_NS = 50_000_000
# readings in a row that must disagree with the watch's state (drifted or not) before it changes: one window's
# estimate can stray, and a warning that comes and goes every reading tells the user nothing
READINGS_TO_SWITCH = 2


class TimeOffsetWatch:
    def __init__(self, K: np.ndarray, applied_offset_ns: int, monitor: TimeOffsetMonitor | None = None,
                 clock=time.monotonic) -> None:
        self.K = np.asarray(K, float)
        self.applied_offset_ns = int(applied_offset_ns)
        self.monitor = monitor if monitor is not None else TimeOffsetMonitor(
            applied_offset_ns=applied_offset_ns, drift_threshold_ns=DRIFT_THRESHOLD_NS)
        self.clock = clock
        self._reading = OffsetReading(None, None, False, 0, 0.0)
        self._next_reading = 0.0
        self._drifted = False  # the state reported: changed by READINGS_TO_SWITCH readings in a row
        self._against = 0  # readings in a row that disagree with it
        self._drifted_reading = self._reading  # the newest reading that said drifted while the state is drifted

    def observe(self, prev: Observations, obs: Observations, motion: FrameMotion) -> None:
        """One frame's measured and predicted image motion (tracks seen in both frames, those with a depth)."""
        dt_s = (obs.t_ns - prev.t_ns) * 1e-9
        if dt_s <= 0 or not len(motion.track_ids):
            return
        common, ia, ib = np.intersect1d(prev.track_ids, obs.track_ids, assume_unique=True, return_indices=True)
        _, ic, idep = np.intersect1d(common, motion.track_ids, assume_unique=True, return_indices=True)
        if len(ic) < 10:
            return
        uv0, uv1 = prev.uv[ia[ic]], obs.uv[ib[ic]]
        z = np.asarray(motion.depth_m, float)[idep]
        rays = np.column_stack([uv0, np.ones(len(uv0))]) @ np.linalg.inv(self.K).T
        X = rays * z[:, None] @ motion.T_cur_prev[:3, :3].T + motion.T_cur_prev[:3, 3]
        ok = X[:, 2] > 0
        if ok.sum() < 10:
            return
        proj = (X[ok] @ self.K.T)[:, :2] / X[ok, 2:3]
        t_mid = (prev.t_ns + obs.t_ns) // 2
        self.monitor.add_measured(t_mid, np.median(uv1[ok] - uv0[ok], axis=0) / dt_s)
        self.monitor.add_predicted(t_mid + self.applied_offset_ns, np.median(proj - uv0[ok], axis=0) / dt_s)

    def reading(self) -> OffsetReading:
        """The monitor's newest reading (searched again at most every READING_PERIOD_S)."""
        now = self.clock()
        if now >= self._next_reading:
            self._next_reading = now + READING_PERIOD_S
            self._reading = self.monitor.reading()
            r = self._reading
            # a window with no reading (a still camera) neither confirms nor clears the state
            if r.offset_ns is not None:
                self._against = self._against + 1 if r.drifted != self._drifted else 0
                if self._against >= READINGS_TO_SWITCH:
                    self._drifted, self._against = r.drifted, 0
                if self._drifted and r.drifted:
                    self._drifted_reading = r
        return self._reading

    @property
    def drifted(self) -> bool:
        """Whether the offset in use has drifted: READINGS_TO_SWITCH readings in a row said so, and not as many
        have said otherwise since."""
        return self._drifted

    def health(self) -> Condition:
        r = self.reading()
        if self._drifted:  # (its figures: the newest reading that found the drift)
            r = self._drifted_reading
            return Condition("drifted", False, f"the video and the poses line up at {r.offset_ns / 1e6:+.0f} ms, "
                             f"{r.drift_ns / 1e6:+.0f} ms from the {self.applied_offset_ns / 1e6:+.0f} ms in use; "
                             "estimate it again (lapreco calibrate time-offset SESSION) and pass it on",
                             count_as="time_offset_drifted")
        if r.offset_ns is None:
            return Condition("watching", True)
        return Condition("ok", True, f"{r.offset_ns / 1e6:+.0f} ms")

    def summary(self) -> dict:
        """The offset in use, and the newest reading's figures, or while drifted those of the newest reading that
        found the drift."""
        r = self._drifted_reading if self._drifted else self._reading
        return {"applied_ms": self.applied_offset_ns / 1e6,
                "estimated_ms": None if r.offset_ns is None else r.offset_ns / 1e6,
                "drift_ms": None if r.drift_ns is None else r.drift_ns / 1e6,
                "uncertainty_ms": None if r.uncertainty_ns is None else r.uncertainty_ns / 1e6,
                "drifted": self._drifted, "window_samples": r.samples,
                "drift_threshold_ms": getattr(self.monitor, "drift_threshold_ns", DRIFT_THRESHOLD_NS) / 1e6,
                # a drift beyond the threshold that the reading does not call one, and why
                "not_called_because": r.not_called_because}


class RecordingTimeOffsetWatch(TimeOffsetWatch):
    """The watch over a recording (``lapreco replay``, ``demo --sequential``), for every pose source alike (joint
    readings, a tracker's marker poses, given camera poses: each has a clock of its own). It reads on the video's
    clock, not the wall's: searched every READING_PERIOD_S of video as the frames come (a replay runs as fast as
    it can, and a wall clock would make its readings depend on the machine), and once more at the end
    (``finish``) over the last window, so the report's figures are the same on every replay."""

    def __init__(self, K: np.ndarray, applied_offset_ns: int, monitor: TimeOffsetMonitor | None = None) -> None:
        self._video_s = 0.0
        self._read_at: float | None = None  # the video time of the last reading
        super().__init__(K, applied_offset_ns, monitor, clock=lambda: self._video_s)

    def observe(self, prev: Observations, obs: Observations, motion: FrameMotion) -> None:
        super().observe(prev, obs, motion)
        self._video_s = obs.t_ns * 1e-9
        self.reading()

    def reading(self) -> OffsetReading:
        before = self._next_reading
        r = super().reading()
        if self._next_reading != before:
            self._read_at = self._video_s
        return r

    def finish(self) -> dict:
        """The summary after a last reading over the window at the end (unless the newest reading was of it)."""
        if self._read_at != self._video_s:
            self._next_reading = -float("inf")
            self.reading()
        return self.summary()
