"""The V4L2 grabber with a stereo scope: two devices paired by capture time, or one device carrying both views
(side-by-side, top-bottom), with the rig from a stereo calibration file; against scripted stand-ins for
cv2.VideoCapture (no /dev/video exists on CI machines)."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from lapreco_hil.calib.files import write_camera_yaml, write_stereo_yaml
from lapreco_hil.camera import CameraModel
from lapreco_hil.drivers.health import HealthState
from lapreco_hil.errors import CalibrationError, ConfigError, DeviceError, DeviceNotFoundError, LaprecoError
from lapreco_hil.registry import DeviceContext, open_grabber

FPS = 30.0
PERIOD_NS = int(1e9 / FPS)


class ScriptedCapture:
    """A device that captures frame k at t0 + k * period + jitter[k] (its V4L2 buffer stamp) and delivers it
    then, unless k is in ``skipped`` (the driver lost it). Frame k's image is filled with k; channel 1 says which
    device (0 left, 1 right). After the script it delivers nothing."""

    def __init__(self, t0_ns: int, jitter_ns, skipped=(), side: int = 0, size=(64, 48), image_fn=None):
        self.t0_ns, self.jitter_ns, self.skipped = t0_ns, list(jitter_ns), set(skipped)
        self.side, self.size, self.image_fn = side, size, image_fn
        self.k = 0
        self.stamp_ms = 0.0

    def isOpened(self):
        return True

    def release(self):
        pass

    def set(self, prop, value):
        return True

    def get(self, prop):
        return {cv2.CAP_PROP_FRAME_WIDTH: self.size[0], cv2.CAP_PROP_FRAME_HEIGHT: self.size[1],
                cv2.CAP_PROP_FPS: FPS, cv2.CAP_PROP_FOURCC: float(cv2.VideoWriter_fourcc(*"YUYV")),
                cv2.CAP_PROP_POS_MSEC: self.stamp_ms}[prop]

    def read(self):
        while self.k in self.skipped:
            self.k += 1
        if self.k >= len(self.jitter_ns):
            time.sleep(0.005)
            return False, None
        t_ns = self.t0_ns + self.k * PERIOD_NS + self.jitter_ns[self.k]
        delay = (t_ns - time.monotonic_ns()) * 1e-9
        if delay > 0:
            time.sleep(delay)
        self.stamp_ms = t_ns / 1e6
        if self.image_fn is not None:
            image = self.image_fn(self.k)
        else:
            image = np.full((self.size[1], self.size[0], 3), self.k, np.uint8)
            image[..., 1] = self.side
        self.k += 1
        return True, image


def _context(captures: dict) -> DeviceContext:
    def factory(device):
        return captures.get(device)

    return DeviceContext(v4l2_capture=factory)


def _one_line(exc: LaprecoError) -> str:
    text = str(exc)
    assert "\n" not in text
    return text


def test_a_pair_is_matched_by_capture_time_and_a_frame_without_partner_is_dropped_and_counted():
    n = 24
    rng = np.random.default_rng(3)
    t0 = time.monotonic_ns() + 50_000_000
    # both devices' stamps jitter by up to +-5 ms (a sixth of a period) about the shared instant; the right device
    # lost frame 5, the left lost frame 12
    left = ScriptedCapture(t0, rng.integers(-5_000_000, 5_000_000, n), skipped={12}, side=0)
    right = ScriptedCapture(t0 + 1_000_000, rng.integers(-5_000_000, 5_000_000, n), skipped={5}, side=1)
    g = open_grabber(f"v4l2:///dev/video0?pair=/dev/video1&fps={FPS:g}",
                     _context({"/dev/video0": left, "/dev/video1": right}))
    with g:
        frames = [g.read(timeout_s=2.0) for _ in range(n - 2)]
    ks = [int(f.image[0, 0, 0]) for f in frames]
    assert ks == [k for k in range(n) if k not in (5, 12)]
    for f in frames:  # never a mismatched pair: the right view is of the same instant, from the right device
        assert len(f.views) == 1 and f.views[0][0, 0, 0] == f.image[0, 0, 0]
        assert f.image[0, 0, 1] == 0 and f.views[0][0, 0, 1] == 1
    assert g.stats["unpaired_left"] == 1 and g.stats["unpaired_right"] == 1
    assert g.faults["unpaired_left"] == 1 and g.faults["unpaired_right"] == 1
    assert g.device_stats["/dev/video0"]["dropped_by_driver"] == 1
    assert g.device_stats["/dev/video1"]["dropped_by_driver"] == 1
    # the frame carries the left camera's time and sequence numbers (a gap where its pair was lost)
    seqs = [f.seq for f in frames]
    assert seqs == ks
    assert all(abs(f.t_ns - (t0 + k * PERIOD_NS)) <= 5_000_000 for f, k in zip(frames, ks))
    assert g.max_pair_skew_ns < PERIOD_NS / 2


def test_a_pair_whose_right_device_goes_silent_counts_every_left_frame_and_says_which_device():
    n = 30
    t0 = time.monotonic_ns() + 50_000_000
    left = ScriptedCapture(t0, [0] * n, side=0)
    right = ScriptedCapture(t0, [0] * 3, side=1)  # delivers 3 frames, then nothing (unplugged)
    g = open_grabber(f"v4l2:///dev/video0?pair=/dev/video1&fps={FPS:g}",
                     _context({"/dev/video0": left, "/dev/video1": right}))
    g.reconnect_interval_s = 60.0  # (never comes back in this test)
    with g:
        frames = [g.read(timeout_s=2.0) for _ in range(3)]
        deadline = time.monotonic() + 3
        while left.k < n - 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        health = g.health  # (the left device still delivers)
        while left.k < n and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.05)
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 1, 2]
    # the left frames after the right went silent are all given up (those within pair_wait_ns may still wait)
    waiting = g.pair_wait_ns // PERIOD_NS + 1
    assert n - 3 - waiting <= g.stats["unpaired_left"] <= n - 3
    assert health.state is HealthState.DISCONNECTED and "/dev/video1" in health.detail


@pytest.mark.parametrize("layout", ["side-by-side", "side-by-side-half", "top-bottom"])
def test_one_device_with_both_views_is_split_exactly_without_copies(layout):
    rng = np.random.default_rng(7)
    w, h = (64, 24) if layout != "top-bottom" else (32, 48)
    images = [rng.integers(0, 256, (h, w, 3), np.uint8) for _ in range(3)]
    cap = ScriptedCapture(time.monotonic_ns(), [0] * 3, size=(w, h), image_fn=lambda k: images[k])
    g = open_grabber(f"v4l2:///dev/video0?layout={layout}&width={w}&height={h}", _context({"/dev/video0": cap}))
    with g:
        frames = [g.read(timeout_s=2.0) for _ in range(3)]
    for f, whole in zip(frames, images):
        if layout == "top-bottom":
            np.testing.assert_array_equal(f.image, whole[:24])
            np.testing.assert_array_equal(f.views[0], whole[24:])
        else:
            np.testing.assert_array_equal(f.image, whole[:, :32])
            np.testing.assert_array_equal(f.views[0], whole[:, 32:])
        assert f.image.shape == f.views[0].shape == ((h, w // 2, 3) if layout != "top-bottom" else (h // 2, w, 3))
        # views of the delivered frame: nothing copied
        assert f.image.base is not None and f.views[0].base is f.image.base
    assert "unpaired_left" not in g.faults


def _rig_file(path, width, height, baseline_m=0.005):
    cam0 = CameraModel(width, height, 500.0, 500.0, width / 2, height / 2, (-0.1, 0.01))
    cam1 = CameraModel(width, height, 505.0, 503.0, width / 2 + 1, height / 2 - 1, (-0.11, 0.012))
    R = cv2.Rodrigues(np.array([0.0, 0.01, 0.0]))[0]
    T = np.array([-baseline_m, 0.0, 0.0])
    write_stereo_yaml(path, cam0, cam1, R, T, np.eye(3), np.eye(3))
    return cam0, cam1, R, T


def test_the_rig_comes_from_the_stereo_calibration_file(tmp_path):
    cam0, cam1, R, T = _rig_file(tmp_path / "rig.yaml", 32, 24)
    cap = ScriptedCapture(time.monotonic_ns(), [0] * 2, size=(64, 24))
    g = open_grabber(f"v4l2:///dev/video0?layout=side-by-side&calib={tmp_path / 'rig.yaml'}",
                     _context({"/dev/video0": cap}))
    rig = g.rig
    assert rig.is_stereo and rig.cameras[0] == cam0 and rig.cameras[1] == cam1 and g.camera == cam0
    T_cam1_cam0 = np.eye(4)
    T_cam1_cam0[:3, :3], T_cam1_cam0[:3, 3] = R, T
    np.testing.assert_allclose(rig.T_cam0_cam[1], np.linalg.inv(T_cam1_cam0), atol=1e-12)
    assert rig.baseline_m() == pytest.approx(0.005)
    with g:
        f = g.read(timeout_s=2.0)
    assert f.n_cameras == len(rig)


def test_a_calibration_of_another_size_is_refused_at_open(tmp_path):
    _rig_file(tmp_path / "rig.yaml", 64, 24)  # calibrated on full-width images, but the views are half width
    cap = ScriptedCapture(time.monotonic_ns(), [0] * 2, size=(64, 24))
    g = open_grabber(f"v4l2:///dev/video0?layout=side-by-side-half&calib={tmp_path / 'rig.yaml'}",
                     _context({"/dev/video0": cap}))
    with pytest.raises(CalibrationError, match=r"camera 0 is calibrated at 64x24 but .* delivers 32x24 views"):
        g.open()


def test_url_errors_are_one_line(tmp_path):
    write_camera_yaml(tmp_path / "camera.yaml", CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0))
    ctx = _context({})
    cases = [
        ("v4l2:///dev/video0?pair=/dev/video1&layout=side-by-side", ConfigError, "exclude each other"),
        ("v4l2:///dev/video0?pair=/dev/video0", ConfigError, "the URL's own device"),
        ("v4l2:///dev/video0?pair=video1", ConfigError, "must be a device path"),
        ("v4l2:///dev/video0?layout=sbs", ConfigError, "layout must be one of mono, side-by-side"),
        (f"v4l2:///dev/video0?layout=top-bottom&calib={tmp_path / 'nope.yaml'}", CalibrationError,
         "no such calibration file"),
        (f"v4l2:///dev/video0?pair=/dev/video1&calib={tmp_path / 'camera.yaml'}", CalibrationError,
         "needs a stereo rig file"),
    ]
    for url, kind, words in cases:
        with pytest.raises(kind) as info:
            open_grabber(url, ctx)
        assert words in _one_line(info.value), url


def test_a_missing_device_of_a_pair_is_named_and_the_other_is_released():
    t0 = time.monotonic_ns()
    released = []
    left = ScriptedCapture(t0, [0] * 2)
    left.release = lambda: released.append(True)
    g = open_grabber("v4l2:///dev/video0?pair=/dev/video9&fps=30", _context({"/dev/video0": left}))
    with pytest.raises(DeviceNotFoundError) as info:
        g.open()
    assert "V4L2 device '/dev/video9' cannot be opened" in _one_line(info.value) and released == [True]


def test_a_pair_in_two_modes_is_refused():
    t0 = time.monotonic_ns()
    g = open_grabber("v4l2:///dev/video0?pair=/dev/video1",
                     _context({"/dev/video0": ScriptedCapture(t0, [0], size=(64, 48)),
                               "/dev/video1": ScriptedCapture(t0, [0], size=(32, 24))}))
    with pytest.raises(DeviceError, match="run in different modes"):
        g.open()


def test_a_mono_grabber_takes_its_camera_from_a_camera_file(tmp_path):
    camera = CameraModel(64, 48, 50.0, 51.0, 32.0, 24.0, (-0.2, 0.05))
    write_camera_yaml(tmp_path / "camera.yaml", camera)
    cap = ScriptedCapture(time.monotonic_ns(), [0] * 2, size=(64, 48))
    g = open_grabber(f"v4l2:///dev/video0?calib={tmp_path / 'camera.yaml'}", _context({"/dev/video0": cap}))
    assert g.camera == camera and len(g.rig) == 1
    with g:
        f = g.read(timeout_s=2.0)
    assert f.views == () and f.image.shape == (48, 64, 3)
    small = ScriptedCapture(time.monotonic_ns(), [0] * 2, size=(32, 24))
    g = open_grabber(f"v4l2:///dev/video0?calib={tmp_path / 'camera.yaml'}", _context({"/dev/video0": small}))
    with pytest.raises(CalibrationError, match="calibrated at 64x48 but .* delivers 32x24"):
        g.open()
