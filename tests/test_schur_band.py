"""The Schur solver's camera system held and factorised as a band matrix (a final pass over a long map) against
the dense one: the same steps to round-off, the same poses, landmarks and inlier labels, on every elimination path
(numpy, the host's chunks with the kernels on Warp's CPU device, the device's atomics into a band array); the
automatic choice (banded for a long map whose keyframes co-observe only their neighbours, through a reverse
Cuthill-McKee order where they are shuffled; dense for a local window, untouched). LAPRECO_TEST_DEVICE=cuda:0 runs
the Warp paths on the GPU instead."""

import dataclasses
import os

import numpy as np
import pytest

from lapreco_hil.bench.ba_live import FINAL_SCHEDULE, make_live_final_problem
from lapreco_hil.mapping import schur
from lapreco_hil.mapping.robust import RobustSchedule, RobustStage

from ba_checks import assert_same_answer

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")


def small_map(seed: int = 3, n_free: int = 72, shuffle: bool = False):
    """A live run's final pass in small, without its long-lived tracks: 72 free keyframes past 2 retired ones,
    short tracks (at most 12 views) with 5% jumping half-way; ``shuffle``: its keyframes in a random order (the
    band only after reordering)."""
    syn = make_live_final_problem(np.random.default_rng(seed), n_free=n_free, n_fixed=2, new_points_per_view=12,
                                  max_track=12, long_share=0.0)
    p = syn.problem
    if shuffle:
        order = np.concatenate([np.arange(2), 2 + np.random.default_rng(seed).permutation(n_free)])
        where = np.empty_like(order)
        where[order] = np.arange(len(order))
        p = dataclasses.replace(p, poses=p.poses[order], fixed=p.fixed[order], prior_poses=p.prior_poses[order],
                                prior_covs=p.prior_covs[order], pose_ids=p.pose_ids[order],
                                obs_pose=where[p.obs_pose])
        syn = dataclasses.replace(syn, problem=p, true_poses=syn.true_poses[order])
    return syn


@pytest.mark.parametrize("device, device_schur", [("numpy", None), (DEVICE, False), (DEVICE, True)])
def test_the_banded_camera_system_gives_the_dense_ones_answer(device, device_schur):
    syn = small_map()
    p = syn.problem
    dense = schur.solve_robust_schur(p, FINAL_SCHEDULE, device=device, device_schur=device_schur,
                                     camera_solver="dense")
    banded = schur.solve_robust_schur(p, FINAL_SCHEDULE, device=device, device_schur=device_schur,
                                      camera_solver="banded")
    assert (dense.stats["camera_solver"], banded.stats["camera_solver"]) == ("dense", "banded")
    assert_same_answer(dense, banded, p, device)
    # and it found the map: outliers labelled, poses nearer the truth than the priors
    assert (banded.stats["inlier_obs"] & syn.outlier_obs).sum() <= 0.02 * syn.outlier_obs.sum()
    prior = np.linalg.norm(p.prior_poses[:, :3, 3] - syn.true_poses[:, :3, 3], axis=1).mean()
    assert np.linalg.norm(banded.poses[:, :3, 3] - syn.true_poses[:, :3, 3], axis=1).mean() < 0.5 * prior


def test_a_long_map_is_solved_banded_and_a_local_window_dense():
    """Automatic: a final pass over 72 keyframes co-observing their neighbours (tracks of at most 12 views) is
    banded, in its own order; a problem of at most BAND_MIN_FREE_POSES free poses (every local window) stays
    dense, as before, whatever its pattern."""
    p = small_map().problem
    lay = schur._layout(schur.pose_major(p)[0])
    views = np.bincount(p.obs_point)
    assert lay.band is not None and lay.band <= 6 * views.max() - 1
    assert np.array_equal(lay.free, np.flatnonzero(~p.fixed))  # (no reordering needed)
    result = schur.solve_robust_schur(p, RobustSchedule((RobustStage("cauchy", 2.0, 2),)))
    assert (result.stats["camera_solver"], result.stats["camera_band"]) == ("banded", lay.band)
    window = small_map(n_free=schur.BAND_MIN_FREE_POSES).problem
    assert schur._layout(schur.pose_major(window)[0]).band is None
    assert schur._layout(schur.pose_major(window)[0], camera_solver="banded").band is not None


def test_shuffled_keyframes_are_banded_after_a_reverse_cuthill_mckee_order():
    syn = small_map(shuffle=True)
    p = syn.problem
    natural = small_map().problem
    lay = schur._layout(schur.pose_major(p)[0])
    assert lay.band is not None and lay.band <= schur._layout(schur.pose_major(natural)[0]).band + 6
    assert not np.array_equal(lay.free, np.flatnonzero(~p.fixed))  # (reordered)
    assert sorted(lay.free.tolist()) == np.flatnonzero(~p.fixed).tolist()
    dense = schur.solve_robust_schur(p, FINAL_SCHEDULE, device="numpy", camera_solver="dense")
    banded = schur.solve_robust_schur(p, FINAL_SCHEDULE, device="numpy")
    assert banded.stats["camera_solver"] == "banded"
    assert_same_answer(dense, banded, p)


def test_a_map_with_long_lived_tracks_stays_dense():
    """A few landmarks seen across most of the map (as the skull demo's final map has them) fill the camera
    system: dense, even past the size bound; and the dense system made from the pose system's blocks alone
    (``_damped_minus``) is the whole-matrix one bit for bit."""
    syn = make_live_final_problem(np.random.default_rng(0), n_free=80, n_fixed=2, new_points_per_view=8,
                                  long_share=0.05)
    p = schur.pose_major(syn.problem)[0]
    lay = schur._layout(p)
    assert lay.band is None and schur._wide_dense(lay)
    lin = schur._linearize(p, lay, p.poses, p.points, 0.7, "cauchy", 2.5)
    M = np.random.default_rng(1).normal(size=lin.Hcc.shape)
    expected = lin.Hcc + 1e-3 * np.eye(len(lin.Hcc)) - M
    assert np.array_equal(schur._damped_minus(lay, lin, 1e-3, M.copy()), expected)
    assert np.array_equal(schur._damped(lay, lin, 1e-3), lin.Hcc + 1e-3 * np.eye(len(lin.Hcc)))
    with pytest.raises(ValueError, match="camera_solver"):
        schur._layout(p, camera_solver="sparse")
    with pytest.raises(ValueError, match="camera_solver"):
        schur._layout(schur.pose_major(syn.problem)[0], camera_solver="sparse")


def test_gram_updates_into_a_band_array_match_the_dense_ones(rng):
    """``_subtract_gram_band`` (BLAS in place where the block fits the band, a Gram matrix where not, scattered
    columns) against the dense update's band."""
    n, band = 60, 17
    S = np.zeros((n, n))
    B = np.zeros((n, band + 1))
    for idx in (slice(6, 18), slice(30, 48), slice(0, 24), np.array([6, 7, 8, 9, 10, 11, 24, 25, 26, 27, 28, 29])):
        at = np.arange(n)[idx]
        # each row (a landmark's) couples only columns within the band of each other
        Z = rng.normal(size=(9, len(at)))
        for row in Z:
            first = at[rng.integers(len(at))]
            row[(at < first) | (at > first + band)] = 0.0
        S[np.ix_(at, at)] -= Z.T @ Z
        schur._subtract_gram_band(B, band, idx, Z)
    i, j = np.tril_indices(n)
    near = i - j <= band
    expected = np.zeros_like(B)
    expected[j[near], (i - j)[near]] = S[i[near], j[near]]
    np.testing.assert_allclose(B, expected, rtol=0, atol=1e-12)
    assert np.all(S[i[~near], j[~near]] == 0.0)


def test_the_band_solve_matches_the_dense_one_and_refuses_an_indefinite_system(rng):
    n, band = 48, 11
    A = rng.normal(size=(n, n))
    S = A @ A.T + n * np.eye(n)
    S[np.abs(np.subtract.outer(np.arange(n), np.arange(n))) > band] = 0.0
    S += 2 * n * np.eye(n)  # (positive definite with the band cut)
    B = np.zeros((n, band + 1))
    for k in range(band + 1):
        B[:n - k, k] = np.diagonal(S, -k)
    rhs = rng.normal(size=n)
    np.testing.assert_allclose(schur._solve_band_system(B.copy(), rhs), np.linalg.solve(S, rhs), rtol=1e-10)
    B[n // 2, 0] = -1.0
    assert schur._solve_band_system(B, rhs) is None


def test_the_final_pass_reports_its_size_and_where_its_time_went():
    """``final_ba_profile`` (the mapper's report of its global BA): the problem's size and the solver's stages."""
    syn = small_map()
    p = syn.problem
    result = schur.solve_robust_schur(p, FINAL_SCHEDULE, device="numpy")
    profile = schur.final_ba_profile(p, result)
    views = np.bincount(p.obs_point)
    assert (profile["free_poses"], profile["landmarks"], profile["observations"]) == (72, len(p.points), len(p.obs_uv))
    assert profile["track_views_mean_max"] == [pytest.approx(views.mean()), int(views.max())]
    assert profile["camera_solver"] == "banded" and profile["camera_band"] == result.stats["camera_band"]
    assert [st["loss"] for st in profile["stages"]] == ["cauchy", "tukey"]
    assert sum(st["iterations"] for st in profile["stages"]) == result.iterations
    assert all(st["solves"] >= st["iterations"] for st in profile["stages"])
    assert profile["timing"]["solve_s"] > 0 and profile["solve_s"] == result.seconds
