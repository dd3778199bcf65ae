"""The drift check on a lightly smoothed tracker image (``[tracker] drift_smoothing_px``, ``drift.drift_image``):
on low-contrast texture the sensor noise the corner detector picked up with a corner does not come back in the
next frame, and the residual test, relative to the patch's contrast, refuses tracks that are right."""

import os

import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend import drift, make_frontend
from lapreco_hil.types import Frame

import textures

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
W, H = 640, 480
SHIFT = np.array([3.3, -2.1])


def low_contrast_frame(shift, noise_seed, contrast=6.0, noise=3.0):
    return textures.low_contrast_frame(shift, noise_seed, W, H, 20, contrast, noise)


def first_step(tracker, smoothing_px):
    """(share of the first frame's tracks kept in the second, their errors in px)."""
    fe = make_frontend(tracker, CameraModel(W, H, 400.0, 400.0, W / 2, H / 2),
                       TrackerConfig(drift_smoothing_px=smoothing_px), DEVICE)
    obs0 = fe.process(Frame(low_contrast_frame((0, 0), 0), 0, 0))
    obs1 = fe.process(Frame(low_contrast_frame(SHIFT, 1), 1, 1))
    kept = np.isin(obs1.track_ids, obs0.track_ids)
    pos = np.searchsorted(obs0.track_ids, obs1.track_ids[kept])
    err = np.linalg.norm(obs1.uv[kept] - (obs0.uv[pos] + SHIFT), axis=1)
    return kept.sum() / len(obs0), err


@pytest.mark.parametrize("tracker", ["opencv", "warp"])
def test_the_smoothed_drift_check_keeps_right_tracks_on_low_contrast_noisy_texture(warp_cpu, tracker):
    kept, err = first_step(tracker, 0.8)
    assert kept > 0.95, kept
    assert np.median(err) < 0.25 and np.percentile(err, 90) < 0.5, (np.median(err), np.percentile(err, 90))
    # registered on the unsmoothed image (the default), a fifth of the same tracks fail the residual test, and
    # the kept ones are no closer to the truth
    kept_raw, err_raw = first_step(tracker, TrackerConfig().drift_smoothing_px)
    assert kept_raw < 0.9, kept_raw
    assert np.median(err_raw) > np.median(err), (np.median(err_raw), np.median(err))


def test_drift_image_is_the_separable_gaussian_the_warp_kernels_apply():
    taps = drift.drift_smoothing_weights(0.8)
    assert len(taps) == 7 and abs(taps.sum() - 1) < 1e-6
    image = np.random.default_rng(0).normal(0, 1, (40, 50)).astype(np.float32)
    assert drift.drift_image(image, 0.0) is image
    out = drift.drift_image(image, 0.8)
    assert out.dtype == np.float32 and out.shape == image.shape
    # at an inner pixel: the taps along rows, then along columns
    r = len(taps) // 2
    window = image[20 - r:20 + r + 1, 25 - r:25 + r + 1].astype(np.float64)
    assert abs(out[20, 25] - taps @ window @ taps) < 1e-5
