"""The OpenCV baseline front-end and its Zinsser drift check, on images with known motion."""

import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend.drift import AffineDriftCheck
from lapreco_hil.frontend.opencv import OpenCVFrontEnd
from lapreco_hil.types import Frame


def texture(rng, h=240, w=320):
    base = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 2.0)
    return (base - base.mean()) / base.std()


def shifted(image, dx, dy, A=np.eye(2)):
    """image warped so that content at x moves to A x + (dx, dy) (about the image centre)."""
    h, w = image.shape
    c = np.array([w / 2, h / 2])
    M = np.hstack([A, (c + [dx, dy] - A @ c)[:, None]])
    return cv2.warpAffine(image, M, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def gradients(img):
    return (cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8), cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8))


@pytest.mark.parametrize("motion", [(0.37, -0.61, np.eye(2)),
                                    (1.2, 0.4, np.array([[np.cos(0.05), -np.sin(0.05)], [np.sin(0.05), np.cos(0.05)]])),
                                    (-0.8, 0.9, np.eye(2) * 1.06)])
def test_registration_recovers_subpixel_motion_with_gain_and_bias(rng, motion):
    dx, dy, A = motion
    I = texture(rng)
    J = 1.3 * shifted(I, dx, dy, A) + 0.2  # brighter and offset: alpha, beta
    pts = np.array([[100.0, 80.0], [200.0, 150.0], [160.0, 120.0], [220.0, 90.0]])
    check = AffineDriftCheck(patch_px=15, max_iterations=20)
    ref = check.reference_patches(I, pts)
    c = np.array([160.0, 120.0])
    truth = (A @ (pts - c).T).T + c + [dx, dy]
    start = np.round(truth)  # what the tracker hands over: within a pixel
    res = check.register(J, *gradients(J), ref, np.repeat(np.eye(2)[None], len(pts), 0), start)
    assert res.keep.all()
    np.testing.assert_allclose(res.positions, truth, atol=0.05)


def test_registration_drops_a_track_that_slid_onto_other_content(rng):
    I = texture(rng)
    J = shifted(I, 0.0, 0.0)
    pts = np.array([[100.0, 80.0], [200.0, 150.0]])
    check = AffineDriftCheck(patch_px=15)
    ref = check.reference_patches(I, pts)
    wrong = pts + [[9.0, -7.0], [0.0, 0.0]]  # first track drifted onto unrelated texture
    res = check.register(J, *gradients(J), ref, np.repeat(np.eye(2)[None], 2, 0), wrong)
    assert list(res.keep) == [False, True]


def make_frame(img, seq):
    u8 = np.clip(img * 40 + 128, 0, 255).astype(np.uint8)
    return Frame(cv2.cvtColor(u8, cv2.COLOR_GRAY2BGR), seq * 40_000_000, seq)


def test_frontend_tracks_known_translation_and_keeps_ids(rng):
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    I = texture(rng)
    cfg = TrackerConfig(max_features=150, shading_sigma_px=0.0, min_brightness=0.0)
    fe = OpenCVFrontEnd(cam, cfg)
    first = fe.process(make_frame(I, 0))
    assert len(first) > 100 and first.n_new == len(first)
    second = fe.process(make_frame(shifted(I, 2.3, -1.4), 1))
    common, ia, ib = np.intersect1d(first.track_ids, second.track_ids, return_indices=True)
    inner = np.all((first.uv[ia] > 30) & (first.uv[ia] < [290, 210]), axis=1)
    err = second.uv[ib][inner] - first.uv[ia][inner] - [2.3, -1.4]
    assert len(common) > 0.8 * len(first)
    assert np.median(np.linalg.norm(err, axis=1)) < 0.1


def test_new_features_keep_their_distance_from_live_tracks(rng):
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    cfg = TrackerConfig(max_features=300, min_distance_px=10.0, shading_sigma_px=0.0, min_brightness=0.0)
    fe = OpenCVFrontEnd(cam, cfg)
    I = texture(rng)
    fe.process(make_frame(I, 0))
    obs = fe.process(make_frame(shifted(I, 5.0, 0.0), 1))
    d = np.linalg.norm(obs.uv[:, None] - obs.uv[None], axis=2) + np.eye(len(obs)) * 1e9
    assert d.min() > 10.0 - 1.5  # tracks may drift together by a pixel, new ones never start closer


def test_auto_pyramid_levels_follow_the_expected_motion_and_the_image_size():
    from lapreco_hil.config import config_from_dict
    from lapreco_hil.errors import ConfigError
    from lapreco_hil.frontend.image import pyramid_levels

    cfg = TrackerConfig()  # "auto", 80 px per frame, the coarsest level at least 32 px
    assert pyramid_levels(cfg, 1920, 1080) == 5  # 80 px -> 2.5 px on the coarsest level (60 x 34)
    assert pyramid_levels(cfg, 640, 480) == 3  # bounded by the size: 4 levels would leave 30 px
    assert pyramid_levels(cfg, 360, 288) == 3
    assert pyramid_levels(TrackerConfig(expected_motion_px=10.0), 1920, 1080) == 2
    assert pyramid_levels(TrackerConfig(pyramid_levels=4), 360, 288) == 4  # a number is taken as it is
    assert config_from_dict({"tracker": {"pyramid_levels": 2}}).tracker.pyramid_levels == 2
    with pytest.raises(ConfigError, match=r'\[tracker\] pyramid_levels .*"auto"'):
        config_from_dict({"tracker": {"pyramid_levels": "many"}})


def test_shading_level_at_reduced_resolution_is_the_full_resolution_blur():
    from lapreco_hil.frontend.image import shading_factor, shading_level

    rng = np.random.default_rng(3)
    log = cv2.GaussianBlur(rng.normal(0, 1, (1080, 1920)).astype(np.float32), (0, 0), 8.0) * 20
    assert shading_factor(24.0) == 1  # 3 levels: the full-resolution blur
    for sigma, factor in ((48.0, 2), (96.0, 4)):
        assert shading_factor(sigma) == factor  # the blur runs at sigma 24 px there
        ours = shading_level(log, sigma)
        ref = cv2.GaussianBlur(log, (0, 0), sigma)
        m = int(3 * sigma)  # the borders differ (reflected at reduced resolution)
        inner = np.abs(ours - ref)[m:-m, m:-m]
        assert inner.max() < 0.05 * np.abs(ref).max(), (sigma, inner.max(), np.abs(ref).max())
