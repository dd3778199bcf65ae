"""The V4L2 grabber's logic (format negotiation, driver timestamps, drop counting, unplug and re-plug, a
missing device) against a scripted stand-in for cv2.VideoCapture: no /dev/video exists on CI machines."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.errors import DeviceError, DeviceNotFoundError, DeviceTimeoutError
from lapreco_hil.registry import DeviceContext, open_grabber


class FakeCamera:
    """A capture device: real frame period, driver buffer stamps on the monotonic clock (ms, as
    CAP_PROP_POS_MSEC gives them), a mode table, and switches for unplugging and skipped frames."""

    def __init__(self, modes=((640, 480, 30.0, "YUYV"),), period_s: float = 1 / 200):
        self.modes = modes
        self.period_s = period_s
        self.present = True
        self.skip_next = 0  # frames the "driver" drops (their stamps advance, nothing is delivered)
        self.opened = 0

    def factory(self, device: str):
        return FakeCapture(self) if self.present else FakeCapture(None)


class FakeCapture:
    def __init__(self, cam: FakeCamera | None):
        self.cam = cam
        if cam is not None:
            cam.opened += 1
        self.mode = list(cam.modes[0]) if cam else None
        self.asked = {}
        self.t_next = time.monotonic_ns()
        self.stamp_ms = 0.0
        self.n = 0

    def isOpened(self):
        return self.cam is not None

    def release(self):
        pass

    def set(self, prop, value):
        self.asked[prop] = value
        for m in self.cam.modes:  # a driver takes a mode only if it has it
            w = self.asked.get(cv2.CAP_PROP_FRAME_WIDTH, m[0])
            h = self.asked.get(cv2.CAP_PROP_FRAME_HEIGHT, m[1])
            if (m[0], m[1]) == (w, h):
                self.mode = list(m)
        return True

    def get(self, prop):
        w, h, fps, cc = self.mode
        return {cv2.CAP_PROP_FRAME_WIDTH: w, cv2.CAP_PROP_FRAME_HEIGHT: h, cv2.CAP_PROP_FPS: fps,
                cv2.CAP_PROP_FOURCC: float(cv2.VideoWriter_fourcc(*cc)), cv2.CAP_PROP_POS_MSEC: self.stamp_ms}[prop]

    def read(self):
        if not self.cam.present:
            time.sleep(0.001)
            return False, None
        delay = (self.t_next - time.monotonic_ns()) * 1e-9
        if delay > 0:
            time.sleep(delay)
        period_ns = int(1e9 / self.mode[2])
        while self.cam.skip_next > 0:
            self.t_next += period_ns
            self.cam.skip_next -= 1
        self.stamp_ms = self.t_next / 1e6  # the buffer's capture time, not the time read() returns
        self.t_next += int(self.cam.period_s * 1e9)
        self.n += 1
        image = np.full((self.mode[1], self.mode[0], 3), self.n % 256, np.uint8)
        return True, image


def _grabber(cam: FakeCamera, query: str = "width=640&height=480&fps=30"):
    return open_grabber(f"v4l2:///dev/video7?{query}", DeviceContext(v4l2_capture=cam.factory))


def test_frames_carry_the_driver_stamp_and_increasing_sequence():
    cam = FakeCamera(period_s=1 / 30)
    g = _grabber(cam)
    with g:
        frames = [g.read(timeout_s=1.0) for _ in range(5)]
        assert g.health.state is HealthState.OK
    t = np.array([f.t_ns for f in frames])
    assert np.all(np.diff(t) > 0) and [f.seq for f in frames] == list(range(5))
    # the stamp is the capture time (driver), within a frame period of the monotonic clock
    assert abs(t[-1] - time.monotonic_ns()) < 1e9
    np.testing.assert_allclose(np.diff(t), 1e9 / 30, rtol=0.05)
    assert g.stats["stamped_on_arrival"] == 0


def test_unsupported_mode_is_a_clear_error():
    cam = FakeCamera(modes=((1280, 720, 60.0, "MJPG"),))
    with pytest.raises(DeviceError, match=r"'/dev/video7' does not support the requested mode: it gives size "
                                          r"1280x720 \(asked 1920x1080\).*v4l2-ctl"):
        _grabber(cam, "width=1920&height=1080&fps=60").open()
    with pytest.raises(DeviceError, match=r"format MJPG \(asked YUYV\)"):
        _grabber(cam, "width=1280&height=720&fourcc=YUYV").open()


def test_missing_device_names_it_and_lists_what_exists():
    cam = FakeCamera()
    cam.present = False
    with pytest.raises(DeviceNotFoundError, match=r"V4L2 device '/dev/video7' cannot be opened \(video devices "
                                                  r"here: "):
        _grabber(cam).open()


def test_real_opencv_back_end_without_a_device_is_a_clear_error():
    # no factory injected: the real cv2.VideoCapture(..., CAP_V4L2) on a path that does not exist
    g = open_grabber("v4l2:///dev/video-does-not-exist", DeviceContext())
    with pytest.raises(DeviceNotFoundError, match="'/dev/video-does-not-exist' cannot be opened"):
        g.open()


def test_driver_drops_are_counted_from_stamp_gaps_and_seq_skips():
    cam = FakeCamera(period_s=1 / 30)
    g = _grabber(cam)
    with g:
        a = g.read(timeout_s=1.0)
        cam.skip_next = 3
        frames = [g.read(timeout_s=1.0) for _ in range(3)]
    seqs = [a.seq] + [f.seq for f in frames]
    assert g.stats["dropped_by_driver"] == 3
    assert max(np.diff(seqs)) == 4  # the sequence number keeps one step per frame period


def test_a_slow_consumer_loses_the_oldest_frames_and_they_are_counted():
    cam = FakeCamera(period_s=1 / 500)
    g = _grabber(cam, "width=640&height=480&fps=30&queue=2")
    with g:
        time.sleep(0.2)  # the consumer does nothing while ~100 frames arrive
        newest = g.read(timeout_s=1.0)
        later = g.read(timeout_s=1.0)
    assert g.stats["dropped_by_consumer"] > 50
    assert later.seq > newest.seq


def test_unplug_is_reported_and_the_grabber_reconnects_by_itself():
    cam = FakeCamera(modes=((640, 480, 200.0, "YUYV"),), period_s=1 / 200)
    g = _grabber(cam, "width=640&height=480&fps=200")
    g.reconnect_interval_s = 0.05
    with g:
        g.read(timeout_s=1.0)
        cam.present = False
        t0 = time.monotonic()
        while g.health.state is not HealthState.DISCONNECTED and time.monotonic() - t0 < 1:
            time.sleep(0.002)
        assert g.health.state is HealthState.DISCONNECTED and "unplugged" in g.health.detail
        assert time.monotonic() - t0 < 0.1  # reported within 100 ms
        while True:  # empty what was queued before the unplug
            try:
                g.read(timeout_s=0.01)
            except DeviceTimeoutError as exc:
                assert "disconnected" in str(exc)
                break
        cam.present = True
        f = g.read(timeout_s=2.0)
        assert f is not None and g.health.state is HealthState.OK
    assert g.stats["unplugs"] == 1 and g.stats["reconnects"] == 1 and cam.opened == 2


def test_stamps_on_another_clock_fall_back_to_arrival_time():
    cam = FakeCamera(period_s=1 / 100)
    clock_offset = 3_600_000_000_000  # the app's clock is an hour ahead of the driver's

    ctx = DeviceContext(v4l2_capture=cam.factory, clock_ns=lambda: time.monotonic_ns() + clock_offset)
    g = open_grabber("v4l2:///dev/video7?width=640&height=480&fps=30", ctx)
    with g:
        f = g.read(timeout_s=1.0)
    assert g.stats["stamped_on_arrival"] >= 1
    assert abs(f.t_ns - (time.monotonic_ns() + clock_offset)) < 1e9


def test_a_failing_reader_thread_is_surfaced_on_read():
    cam = FakeCamera()
    g = _grabber(cam)

    def broken_read():
        raise RuntimeError("driver exploded")

    with g:
        # swap in a capture whose read() raises, as a buggy back-end might
        cam_capture = FakeCapture(cam)
        cam_capture.read = broken_read
        g.close()
        g._factory = lambda device: cam_capture
        g.open()
        deadline = time.monotonic() + 1
        while g.health.state is not HealthState.FAULTED and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(DeviceError, match="reader failed: driver exploded"):
            g.read(timeout_s=0.1)
