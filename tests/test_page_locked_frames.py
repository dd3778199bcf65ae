"""Frames staged in page-locked memory by the capture thread: the pool's buffers are reused only once nothing
holds the frame, and the Warp front-end's device path (one upload, the grey conversion on the device) gives the
host path's grey levels and tracks bit for bit (Warp's CPU device here; CUDA with LAPRECO_TEST_DEVICE=cuda:0)."""

import os

import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.types import Frame

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")


@pytest.fixture(scope="module")
def wp(warp_cpu):
    import warp

    return warp


def test_the_device_grey_conversion_is_opencvs_bit_for_bit(wp, rng):
    from lapreco_hil.frontend.warp.page_locked import bgr_to_grey

    image = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    image[0, :3] = [[255, 255, 255], [0, 0, 0], [1, 2, 3]]
    grey = wp.zeros((37, 53), dtype=wp.uint8, device=DEVICE)
    bgr_to_grey(wp.array(image, dtype=wp.uint8, device=DEVICE), grey, DEVICE)
    np.testing.assert_array_equal(grey.numpy(), cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))


def test_a_buffer_is_reused_only_once_nothing_holds_its_frame(wp, rng):
    from lapreco_hil.frontend.warp.page_locked import PageLockedFrames, page_locked_source

    pool = PageLockedFrames((8, 6, 3), 2, DEVICE)
    images = [rng.integers(0, 256, (8, 6, 3), dtype=np.uint8) for _ in range(4)]
    a = pool.stage(Frame(images[0], 1, 1))
    b = pool.stage(Frame(images[1], 2, 2))
    assert page_locked_source(a.image) is not None and page_locked_source(b.image) is not None
    band = a.image[2:5]  # a slice still holds a's buffer after a is gone
    del a
    c = pool.stage(Frame(images[2], 3, 3))  # both buffers held: passed on as it came
    assert c.image is images[2] and page_locked_source(c.image) is None
    np.testing.assert_array_equal(band, images[0][2:5])
    np.testing.assert_array_equal(b.image, images[1])
    del band
    d = pool.stage(Frame(images[3], 4, 4))  # a's buffer is free again
    np.testing.assert_array_equal(d.image, images[3])
    np.testing.assert_array_equal(b.image, images[1])
    assert (pool.staged, pool.passed_on) == (3, 1)
    # a part of a staged frame, or a frame of another shape, is not a page-locked frame
    assert page_locked_source(d.image[1:]) is None and page_locked_source(d.image.copy()) is None
    other = pool.stage(Frame(np.zeros((4, 6, 3), np.uint8), 5, 5))
    assert page_locked_source(other.image) is None and pool.passed_on == 2


def test_the_front_end_tracks_a_page_locked_frame_as_a_host_one(wp, rng):
    from lapreco_hil.frontend.warp import WarpFrontEnd
    from lapreco_hil.frontend.warp.page_locked import PageLockedFrames

    cam = CameraModel.from_paper_model(320, 240, 230.0, 230.0, 161.0, 118.0, k=(-0.2, 0.05, 0.0))
    base = cv2.GaussianBlur(rng.random((280, 380, 3)).astype(np.float32), (0, 0), 2.0)
    base = (30 + 200 * (base - base.min()) / (base.max() - base.min())).astype(np.uint8)
    images = [np.ascontiguousarray(base[3 * k:3 * k + 240, 2 * k:2 * k + 320]) for k in range(4)]
    cfg = TrackerConfig(max_features=300)
    host, staged = WarpFrontEnd(cam, cfg, DEVICE), WarpFrontEnd(cam, cfg, DEVICE)
    pool = PageLockedFrames((240, 320, 3), 3, DEVICE)
    for k, image in enumerate(images):
        a = host.process(Frame(image, k, k))
        b = staged.process(pool.stage(Frame(image, k, k)))
        assert len(a) > 100
        # the image the trackers start from: the same grey levels, bit for bit
        np.testing.assert_array_equal(host._frame.numpy(), staged._frame.numpy())
        if DEVICE == "cpu":
            # (on CUDA two front-ends given the same frames may order their corners differently)
            np.testing.assert_array_equal(a.track_ids, b.track_ids)
            np.testing.assert_array_equal(a.uv, b.uv)
            np.testing.assert_array_equal(a.colors, b.colors)
        else:
            assert abs(len(a) - len(b)) <= 0.05 * len(a)
    assert (host.frames_page_locked, staged.frames_page_locked) == (0, len(images))


class ListGrabber:
    def __init__(self, frames):
        self.frames = list(frames)

    def read(self, timeout_s=None):
        return self.frames.pop(0) if self.frames else None


def test_the_capture_thread_stages_frames_and_counts_those_it_could_not(wp, rng):
    from lapreco_hil.frontend.warp.page_locked import PageLockedFrames, page_locked_source
    from lapreco_hil.runtime.metrics import LiveMetrics
    from lapreco_hil.runtime.stages import Capture, StageLinks

    images = [rng.integers(0, 256, (6, 8, 3), dtype=np.uint8) for _ in range(5)]
    links, metrics = StageLinks(), LiveMetrics()
    pool = PageLockedFrames((6, 8, 3), 3, DEVICE)  # fewer buffers than the queue holds: the last two pass as came
    Capture(ListGrabber(Frame(im, k + 1, k) for k, im in enumerate(images)), links, metrics, capture_queue=8,
            record_queue=8, recording=False, page_locked=pool).run()
    queued = [frame for frame, _ in links.capture_q]
    assert [page_locked_source(f.image) is not None for f in queued] == [True, True, True, False, False]
    for frame, image in zip(queued, images):
        np.testing.assert_array_equal(frame.image, image)
    assert (metrics.get("frames_page_locked"), metrics.get("frames_not_page_locked")) == (3, 2)
