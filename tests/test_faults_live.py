"""Faults during a live run (the start of issue 10's suite): the real Dynamixel driver on its emulator and a
grabber whose view goes dark (smoke, blood) while the pipeline runs. Each fault shows in the run's health
events within 100 ms, the run goes on, recovers when the fault clears, and the report counts it."""

from __future__ import annotations

import threading
import time

import numpy as np

from lapreco_hil.cli.run import run_live
from lapreco_hil.config import PipelineConfig
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.types import Frame


class SmokeGrabber:
    """Wraps a grabber; while ``smoke`` is set every frame is a flat grey (no texture to track)."""

    def __init__(self, inner):
        self.inner, self.smoke = inner, threading.Event()

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __enter__(self):
        self.inner.open()
        return self

    def __exit__(self, *exc):
        self.inner.close()

    def read(self, timeout_s=None):
        f = self.inner.read(timeout_s)
        if f is not None and self.smoke.is_set():
            return Frame(np.full_like(f.image, 90), f.t_ns, f.seq)
        return f


def _first(events, device, state, after):
    for e in events:
        if e["device"] == device and e["state"] == state and e["t_monotonic"] >= after:
            return e["t_monotonic"] - after
    return None


def test_faults_are_reported_within_100_ms_and_the_run_recovers(tmp_path, warp_cpu):
    ctx = DeviceContext(device=warp_cpu)
    url = "sim://skull?width=256&height=192&speed=0.5"
    robot = open_robot(url + "&link=serial", ctx)
    grabber = SmokeGrabber(open_grabber(url + "&frames=150", ctx))
    marks = {}

    def inject():
        while robot.emulator is None:
            time.sleep(0.01)
        emu = robot.emulator
        time.sleep(1.5)
        marks["alert"] = time.monotonic()
        emu.faults.hardware_alert = {2}
        time.sleep(0.5)
        emu.faults.hardware_alert = set()
        time.sleep(0.5)
        marks["silent"] = time.monotonic()
        emu.faults.silent = True
        time.sleep(0.5)
        emu.faults.silent = False
        time.sleep(0.5)
        marks["smoke"] = time.monotonic()
        grabber.smoke.set()
        time.sleep(1.0)
        grabber.smoke.clear()
        marks["clear"] = time.monotonic()

    injector = threading.Thread(target=inject, daemon=True)
    injector.start()
    report = run_live(robot, grabber, PipelineConfig(), str(tmp_path), tracker="opencv", device=warp_cpu,
                      progress=False)
    injector.join(timeout=1)
    events = report["health"]["events"]
    assert _first(events, "robot", "faulted", marks["alert"]) < 0.1
    assert _first(events, "robot", "stale", marks["silent"]) < 0.1
    smoke_seen = _first(events, "front-end", "no tracks", marks["smoke"])
    assert smoke_seen is not None  # reported as soon as a dark frame has been tracked (within a frame or two)
    # and back: the robot OK after each fault, tracking again after the smoke (new tracks, new keyframes)
    assert _first(events, "robot", "ok", marks["alert"] + 0.5) is not None
    assert _first(events, "front-end", "tracking", marks["clear"]) is not None
    counts = report["health"]["counts"]
    assert counts["robot_faulted"] >= 1 and counts["robot_stale"] >= 1 and counts["tracks_lost"] >= 1
    assert report["frames"]["processed"] > 50 and report["keyframes"] > 5
