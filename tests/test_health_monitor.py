"""The health monitor: every change of a source's state is an event and one console line (a warning when it
leaves OK, "ok again" when it is back), a flapping source is shown at most once per interval, and the run's
degraded flag follows its sources."""

from __future__ import annotations

import logging
import threading
import time

from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.runtime.health import Condition, HealthMonitor


class Source:
    def __init__(self, reading):
        self.reading = reading

    def __call__(self):
        return self.reading


def _lines(caplog):
    return [(r.levelno, r.getMessage()) for r in caplog.records if r.name == "lapreco_hil.runtime.health"]


def test_each_change_is_an_event_and_one_line(caplog):
    caplog.set_level(logging.INFO, logger="lapreco_hil.runtime.health")
    now = [100.0]
    grabber, robot = Source(Health(HealthState.OK)), Source(Health(HealthState.OK))
    monitor = HealthMonitor({"grabber": grabber, "robot": robot}, log_interval_s=1.0, clock=lambda: now[0])
    monitor.poll()
    assert not monitor.degraded and _lines(caplog) == []  # OK at the start is no news
    assert [(e.source, e.state) for e in monitor.events] == [("grabber", "ok"), ("robot", "ok")]
    now[0] += 0.5
    grabber.reading = Health(HealthState.DEGRADED, "3 frames dropped")
    monitor.poll()
    monitor.poll()  # no change: no new event, no new line
    assert monitor.degraded
    now[0] += 2.0
    grabber.reading = Health(HealthState.OK)
    robot.reading = Health(HealthState.FAULTED, "hardware alert on joint 2")
    monitor.poll()
    assert _lines(caplog) == [(logging.WARNING, "grabber: degraded: 3 frames dropped"),
                              (logging.INFO, "grabber: ok again"),
                              (logging.WARNING, "robot: faulted: hardware alert on joint 2")]
    events = monitor.event_dicts()
    assert events[2] == {"t_s": 0.5, "t_monotonic": 100.5, "device": "grabber", "state": "degraded",
                         "detail": "3 frames dropped"}
    assert monitor.event_count == 5 and monitor.counts == {"grabber_degraded": 1, "robot_faulted": 1}
    assert monitor.degraded


def test_a_flapping_source_is_shown_once_per_interval_and_every_change_is_kept(caplog):
    caplog.set_level(logging.INFO, logger="lapreco_hil.runtime.health")
    now = [0.0]
    robot = Source(Health(HealthState.OK))
    monitor = HealthMonitor({"robot": robot}, log_interval_s=1.0, clock=lambda: now[0])
    monitor.poll()
    for i in range(10):  # stale / ok every 50 ms
        now[0] += 0.05
        robot.reading = Health(HealthState.STALE, "no reading for 30 ms") if i % 2 == 0 else Health(HealthState.OK)
        monitor.poll()
    assert monitor.event_count == 11 and monitor.counts["robot_stale"] == 5
    assert _lines(caplog) == [(logging.WARNING, "robot: stale: no reading for 30 ms")]
    now[0] += 1.0  # the interval has passed: where it ended up is shown, with how much was not
    monitor.poll()
    assert _lines(caplog)[1:] == [(logging.INFO, "robot: ok again (9 changes in between not shown)")]
    assert not monitor.degraded


def test_conditions_name_their_counters_and_the_monitor_runs_in_a_thread():
    tracks = Source(Condition("tracking", True))
    monitor = HealthMonitor({"front-end": tracks}, period_s=0.005)
    finished = threading.Event()
    thread = threading.Thread(target=monitor.run_until, args=(finished,))
    thread.start()
    try:
        time.sleep(0.05)
        tracks.reading = Condition("no tracks", False, count_as="tracks_lost")
        deadline = time.monotonic() + 2.0
        while not monitor.degraded and time.monotonic() < deadline:
            time.sleep(0.005)
        assert monitor.degraded
    finally:
        finished.set()
        thread.join(timeout=2.0)
    assert not thread.is_alive()
    assert [(e["device"], e["state"]) for e in monitor.event_dicts()] == [("front-end", "tracking"),
                                                                         ("front-end", "no tracks")]
    assert monitor.counts == {"tracks_lost": 1}


def test_ok_after_a_state_that_was_ok_too_is_not_ok_again(caplog):
    """The time-offset watch goes from "watching" (OK, nothing measured yet) to "ok": that is news, but nothing was
    wrong before, so the line is "time offset: ok", not "ok again"."""
    caplog.set_level(logging.INFO, logger="lapreco_hil.runtime.health")
    now = [0.0]
    watch = Source(Condition("watching", True))
    monitor = HealthMonitor({"time offset": watch}, log_interval_s=0.0, clock=lambda: now[0])
    monitor.poll()
    now[0] += 2.0
    watch.reading = Condition("ok", True, "+12 ms")
    monitor.poll()
    now[0] += 2.0
    watch.reading = Condition("drifted", False, "the video and the poses line up at +90 ms")
    monitor.poll()
    now[0] += 2.0
    watch.reading = Condition("ok", True, "+3 ms")
    monitor.poll()
    assert [line for _, line in _lines(caplog)] == ["time offset: ok", "time offset: drifted: the video and the "
                                                    "poses line up at +90 ms", "time offset: ok again"]
