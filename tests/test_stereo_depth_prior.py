"""A stereo partner searched near the depth the map gives a track (``frontend.stereo_depth``): on texture that
repeats along the epipolar line, the whole depth range holds several equally good places and the sweep calls
the match unclear; the map's depth picks the right one."""

import os

import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend import make_frontend, stereo_depth
from lapreco_hil.types import Frame, FrameMotion

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
W, H, F = 640, 480, 400.0
Z, BASELINE = 0.1, 0.0075  # a fronto-parallel plane 10 cm away, seen 7.5 mm apart: 30 px of disparity
PERIOD = 12  # px: the texture repeats along the (horizontal) epipolar lines


def striped_pair():
    """Left and right BGR images of a plane whose texture repeats every PERIOD px across, random down (so it
    has corners); the right view is the left one shifted by the disparity. -> (left, right, camera, T_right_left,
    disparity)."""
    rng = np.random.default_rng(3)
    disparity = int(round(F * BASELINE / Z))
    rows = cv2.GaussianBlur(rng.normal(0, 1, (H, 1)).astype(np.float32), (1, 9), 2).ravel()
    x = np.arange(W + disparity)
    wide = 128 + 50 * np.sin(2 * np.pi * x / PERIOD)[None, :] * np.sign(rows)[:, None] \
        + 25 * np.cos(2 * np.pi * 2 * x / PERIOD)[None, :] * rows[:, None]
    wide = np.clip(wide, 0, 255).astype(np.uint8)
    left = cv2.cvtColor(np.ascontiguousarray(wide[:, disparity:]), cv2.COLOR_GRAY2BGR)
    right = cv2.cvtColor(np.ascontiguousarray(wide[:, :W]), cv2.COLOR_GRAY2BGR)
    T = np.eye(4)
    T[0, 3] = -BASELINE
    return left, right, CameraModel(W, H, F, F, W / 2, H / 2), T, disparity


def matched(tracker, known_depth, config=TrackerConfig()):
    left, right, cam, T, disparity = striped_pair()
    fe = make_frontend(tracker, cam, config, DEVICE)
    obs0 = fe.process(Frame(left, 0, 0))
    # the next frame, the camera still: the map knows every track's depth (or none)
    ids, depth = (obs0.track_ids, np.full(len(obs0), Z)) if known_depth else (np.zeros(0, np.int64), np.zeros(0))
    obs = fe.process(Frame(left, 1, 1), FrameMotion(np.eye(4), ids, depth, (0.03, 0.3)))
    other = fe.match_view(right, cam, T, camera_index=1)
    pos = np.searchsorted(obs.track_ids, other.track_ids)
    err = np.linalg.norm(other.uv - (obs.uv[pos] - [disparity, 0]), axis=1)
    return len(obs), other, err


@pytest.mark.parametrize("tracker", ["opencv", "warp"])
def test_a_track_with_a_known_depth_finds_its_stereo_partner_on_repeating_texture(warp_cpu, tracker):
    n, other, err = matched(tracker, known_depth=True)
    assert n > 200, n
    assert len(other) >= 0.6 * n, (len(other), n)  # (a left track within the disparity of the edge has none)
    assert np.median(err) < 0.2 and np.mean(err < 1.0) > 0.95, (np.median(err), np.mean(err < 1.0))
    # without the map's depth the line holds a place every PERIOD px: most matches are unclear and left out
    n_blind, blind, _ = matched(tracker, known_depth=False)
    assert len(blind) < 0.1 * n_blind, (len(blind), n_blind)
    # and so with the map's depth where the option is off ([tracker] stereo_depth_prior)
    n_off, off, _ = matched(tracker, known_depth=True, config=TrackerConfig(stereo_depth_prior=False))
    assert len(off) < 0.1 * n_off, (len(off), n_off)


def test_search_ranges_come_from_a_tracks_own_depth_else_its_neighbours():
    uv = np.array([[100.0, 100.0], [110.0, 100.0], [105.0, 108.0], [600.0, 20.0]])
    own = np.array([0.1, 0.12, np.nan, np.nan])
    ranges = stereo_depth.search_ranges(uv, own, (640, 480), (0.03, 0.3))
    s, b = stereo_depth.STEREO_OWN_SPREAD, stereo_depth.STEREO_BORROWED_SPREAD
    np.testing.assert_allclose(ranges[0], [0.1 / (1 + s), 0.1 * (1 + s)])
    np.testing.assert_allclose(ranges[1], [0.12 / (1 + s), 0.12 * (1 + s)])
    np.testing.assert_allclose(ranges[2], [0.11 / (1 + b), 0.11 * (1 + b)])  # its neighbours' median
    np.testing.assert_allclose(ranges[3], [0.03, 0.3])  # no neighbour in reach: the whole range
    # a prior beyond the map's range is clipped to it
    np.testing.assert_allclose(stereo_depth.search_ranges(uv[:1], np.array([0.29]), (640, 480), (0.03, 0.3))[0],
                               [0.29 / (1 + s), 0.3])


def test_a_known_depth_is_carried_into_the_new_frame_by_the_camera_motion():
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.01, 0.0, -0.02]  # the camera moved 2 cm closer
    prev = stereo_depth.known_depths(np.array([5, 7, 9]), np.array([[320.0, 240.0], [400.0, 240.0], [0.0, 0.0]]),
                                     FrameMotion(T, np.array([5, 7]), np.array([0.1, 0.2])))
    z = stereo_depth.carried_depths(np.array([7, 3, 5, 9]), *prev, K)
    np.testing.assert_allclose(z[[0, 2]], [0.18, 0.08])
    assert np.isnan(z[1]) and np.isnan(z[3])  # not tracked before; tracked without a depth
    # without a motion nothing is known
    none = stereo_depth.known_depths(np.array([5]), np.array([[1.0, 2.0]]), None)
    assert np.isnan(stereo_depth.carried_depths(np.array([5]), *none, K)).all()
