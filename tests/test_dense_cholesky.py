"""The dense camera system factorised and solved on the kernels' device (``dense_cholesky``: a blocked Cholesky of
Warp tile kernels, float64) against the host's LAPACK (``schur._solve_camera_system``): the same step to round-off
on random SPD systems of sizes that are not whole tiles, the same refusal of a system that is not positive
definite, and the same final pass (poses, landmarks, inlier labels) with the camera system never read back.
Warp's CPU device here (small systems: CI has two cores); LAPRECO_TEST_DEVICE=cuda:0 runs them on the GPU."""

import os

import numpy as np
import pytest

from lapreco_hil.bench.ba_live import FINAL_SCHEDULE, make_live_final_problem
from lapreco_hil.mapping import schur

from ba_checks import assert_same_answer

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")

dense_cholesky = pytest.importorskip("lapreco_hil.mapping.dense_cholesky")


def random_spd(rng, n: int, condition: float) -> np.ndarray:
    """A symmetric positive-definite matrix of about ``condition`` (eigenvalues log-spaced to it, random basis)."""
    Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
    S = (Q * np.logspace(0, np.log10(condition), n)) @ Q.T
    return 0.5 * (S + S.T)


def host_step(S: np.ndarray, rhs: np.ndarray):
    return schur._solve_camera_system(S.copy(), rhs.copy())


@pytest.mark.parametrize("tile", [16, 32])
@pytest.mark.parametrize("n", [1, 7, 33, 70, 131])
def test_the_device_factorisation_gives_lapacks_step(rng, tile, n):
    """Sizes under a tile, a tile and one, several tiles and a part (padded with the identity); condition 1e6."""
    S = random_spd(rng, n, 1e6)
    rhs = rng.normal(size=n)
    upper_garbage = S + np.triu(rng.normal(size=(n, n)), 1)  # (the lower triangle alone is read, as potrf reads it)
    x = dense_cholesky.solve_spd(upper_garbage, rhs, DEVICE, tile)
    expected = host_step(S, rhs)
    assert x is not None and expected is not None
    assert np.linalg.norm(x - expected) <= 1e-9 * np.linalg.norm(expected)


@pytest.mark.parametrize("where", ["first tile", "a later tile", "the last row"])
def test_a_system_that_is_not_positive_definite_is_refused_as_lapack_refuses_it(rng, where):
    """A negative pivot, a zero one (a pose that nothing holds), a NaN: None from both, wherever it falls."""
    n = 45
    at = {"first tile": 3, "a later tile": 29, "the last row": n - 1}[where]
    S = random_spd(rng, n, 1e3)
    rhs = rng.normal(size=n)
    for broken in ("negative", "zero", "nan"):
        B = S.copy()
        if broken == "negative":
            B[at, at] = -1.0
        elif broken == "zero":
            B[at, :] = B[:, at] = 0.0
        else:
            B[at, at // 2] = B[at // 2, at] = np.nan
        assert host_step(B, rhs) is None
        assert dense_cholesky.solve_spd(B, rhs, DEVICE, 16) is None, broken
    # and a system near the edge that LAPACK still takes is taken: the smallest eigenvalue 1e-10 of the largest
    S = random_spd(rng, n, 1e10)
    assert host_step(S, rhs) is not None and dense_cholesky.solve_spd(S, rhs, DEVICE, 16) is not None


def test_a_recorded_graph_replays_on_new_values_in_the_same_storage(rng):
    """The Schur solver forms each damped system in one storage: the launches recorded once (a CUDA graph; on the
    CPU device Warp's recorded graph) solve every new system put there, as launching one by one does."""
    wp = dense_cholesky.wp
    n, tile = 50, 16
    recorded = dense_cholesky.DeviceCholesky(n, DEVICE, tile, graph=True)
    one_by_one = dense_cholesky.DeviceCholesky(n, DEVICE, tile, graph=False)
    storage = wp.zeros(dense_cholesky.storage_shape(n, tile), dtype=wp.float64, device=DEVICE)
    info = wp.zeros(1, dtype=wp.int32, device=DEVICE)
    for k in range(3):
        S, rhs = random_spd(rng, n, 10.0 ** (k + 2)), rng.normal(size=n)
        if k == 2:
            S[20, 20] = -1.0
        solutions = []
        for chol in (recorded, one_by_one):
            storage.assign(dense_cholesky.to_storage(S, rhs, tile))
            chol.launch(storage, info)
            solutions.append((chol.solution(storage).numpy()[:n].copy(), int(info.numpy()[0])))
        (x_recorded, info_recorded), (x_one_by_one, info_one_by_one) = solutions
        assert np.array_equal(x_recorded, x_one_by_one, equal_nan=True) and info_recorded == info_one_by_one
        assert (info_recorded == 0) == (k < 2)  # (the third: a negative pivot)
        if k < 2:
            expected = host_step(S, rhs)
            assert np.linalg.norm(x_recorded - expected) <= 1e-9 * np.linalg.norm(expected)
    assert len(recorded._graphs) == 1  # (recorded once, replayed twice)


def test_bad_arguments_are_named():
    wp = dense_cholesky.wp
    with pytest.raises(ValueError, match="tile 24"):
        dense_cholesky.DeviceCholesky(10, DEVICE, 24)
    chol = dense_cholesky.DeviceCholesky(10, DEVICE, 16)
    with pytest.raises(ValueError, match="storage"):
        chol.launch(wp.zeros((16, 16), dtype=wp.float64, device=DEVICE), wp.zeros(1, dtype=wp.int32, device=DEVICE))
    with pytest.raises(ValueError, match="square"):
        dense_cholesky.solve_spd(np.eye(3), np.ones(4), DEVICE)


def live_map(seed: int = 3):
    """The live run's final pass in small, its long-lived tracks kept (a dense camera system): 40 free keyframes
    past 2 retired ones, 10 landmarks a keyframe, 5% of them seen by 10 up to every keyframe, 5% jumping."""
    return make_live_final_problem(np.random.default_rng(seed), n_free=40, n_fixed=2, new_points_per_view=10,
                                   long_share=0.05, long_min=10)


def test_the_final_pass_on_the_device_gives_the_hosts_answer():
    """Dense on the device against dense on the host's LAPACK, both eliminating the landmarks on the kernels'
    device: the same poses and well-seen landmarks to round-off, the same inlier labels and iterations (a damped
    system's refusal may differ where a landmark left with one weighted view is singular to round-off: the solves
    are not compared), and the camera system never read back."""
    syn = live_map()
    p = syn.problem
    host = schur.solve_robust_schur(p, FINAL_SCHEDULE, device=DEVICE, device_schur=True, camera_solver="dense")
    device = schur.solve_robust_schur(p, FINAL_SCHEDULE, device=DEVICE, device_schur=True,
                                      camera_solver="dense-device", camera_tile=16)
    assert (host.stats["camera_solver"], device.stats["camera_solver"]) == ("dense", "dense-device")
    assert device.stats["camera_tile"] == 16 and schur.final_ba_profile(p, device)["camera_solver"] == "dense-device"
    assert_same_answer(host, device, p, DEVICE)
    # the host read back a 240 x 240 camera system per damped system; the device's step and flags alone
    camera_bytes = 8 * (6 * 40) ** 2
    host_solves = sum(st["solves"] for st in host.stats["stages"])
    assert host.stats["device_ops"]["downloaded_bytes"] > host_solves * camera_bytes
    assert device.stats["device_ops"]["downloaded_bytes"] < 0.2 * host.stats["device_ops"]["downloaded_bytes"]
    # and it found the map: outliers labelled, poses nearer the truth than the priors
    assert (device.stats["inlier_obs"] & syn.outlier_obs).sum() <= 0.02 * syn.outlier_obs.sum()
    prior = np.linalg.norm(p.prior_poses[:, :3, 3] - syn.true_poses[:, :3, 3], axis=1).mean()
    assert np.linalg.norm(device.poses[:, :3, 3] - syn.true_poses[:, :3, 3], axis=1).mean() < 0.5 * prior


def test_rig_ties_go_into_the_devices_pose_blocks():
    """Tied pairs of free poses (a stereo rig's) add off-diagonal pose blocks: the device's system holds their
    lower blocks, each once (two ties of one pair included), and gives the host's answer."""
    import dataclasses

    from lapreco_hil.geometry import inv_T

    syn = make_live_final_problem(np.random.default_rng(5), n_free=24, n_fixed=2, new_points_per_view=10,
                                  long_share=0.05, long_min=8)
    p = syn.problem
    pairs = np.array([[4, 5], [9, 8], [12, 13], [4, 5], [1, 2]])  # (one twice; one with a retired pose)
    has_prior = np.ones(len(p.poses), bool)
    has_prior[[5, 8, 13]] = False
    p = dataclasses.replace(p, has_prior=has_prior, tie_pairs=pairs,
                            tie_T=np.array([inv_T(syn.true_poses[i]) @ syn.true_poses[j] for i, j in pairs]),
                            tie_covs=np.repeat(np.diag([1e-4**2] * 3 + [1e-5**2] * 3)[None], len(pairs), 0))
    lay = schur._layout(schur.pose_major(p)[0], DEVICE, True, camera_solver="dense-device", camera_tile=16)
    F = len(lay.free)
    rows, cols = lay.device_block_keys // F, lay.device_block_keys % F
    assert np.all(rows >= cols) and len(np.unique(lay.device_block_keys)) == len(rows) == F + 3
    schedule = FINAL_SCHEDULE
    host = schur.solve_robust_schur(p, schedule, device=DEVICE, device_schur=True, camera_solver="dense")
    device = schur.solve_robust_schur(p, schedule, device=DEVICE, camera_solver="dense-device", camera_tile=16)
    np.testing.assert_allclose(device.poses, host.poses, rtol=0, atol=1e-9)
    assert np.array_equal(device.stats["inlier_obs"], host.stats["inlier_obs"])


def test_where_the_camera_system_is_solved_on_the_device():
    """Automatically on a CUDA device that eliminates the landmarks, for a dense system past
    DEVICE_DENSE_MIN_FREE_POSES free poses (a final pass, never a local window); asked for, on any Warp device;
    never without the landmarks eliminated there."""
    wide = schur.DEVICE_DENSE_MIN_FREE_POSES + 1
    assert schur._dense_on_device("cuda:0", True, None, wide, "auto")
    assert not schur._dense_on_device("cuda:0", True, None, wide - 1, "auto")
    assert not schur._dense_on_device("cpu", True, None, wide, "auto")
    assert not schur._dense_on_device("cuda:0", False, None, wide, "auto")
    assert not schur._dense_on_device("cuda:0", True, 35, wide, "auto")  # (banded)
    assert not schur._dense_on_device("cuda:0", True, None, wide, "dense")
    assert schur._dense_on_device("cpu", True, None, 3, "dense-device")
    with pytest.raises(ValueError, match="dense-device"):
        schur._dense_on_device("numpy", False, None, wide, "dense-device")
    with pytest.raises(ValueError, match="dense-device"):
        schur.solve_robust_schur(live_map().problem, FINAL_SCHEDULE, device=DEVICE, device_schur=False,
                                 camera_solver="dense-device")


def test_a_map_that_no_order_makes_narrow_skips_the_reverse_cuthill_mckee_order():
    """The landmarks seen by most keyframes bound the bandwidth from below in every order (``_clique_bound``):
    "auto" decides dense from them at once, as the reverse Cuthill-McKee order's width decides; a map of short
    tracks keeps its band."""
    syn = make_live_final_problem(np.random.default_rng(0), n_free=80, n_fixed=2, new_points_per_view=8,
                                  long_share=0.05)
    lay = schur._layout(schur.pose_major(syn.problem)[0], camera_solver="dense")
    seen = lay.obs_col >= 0
    bound = schur._clique_bound(lay.obs_point[seen], lay.obs_col[seen], lay.n_points)
    views = np.bincount(lay.obs_point[seen])
    assert bound == views.max() and bound * schur.BAND_MAX_SHARE > len(lay.free)
    no_ties = np.zeros((0, 2), np.int64)
    band, order = schur._camera_band(lay.obs_point, lay.obs_col, lay.n_points, len(lay.free), no_ties, "banded")
    assert (band - 5) // 6 + 1 >= bound  # (the narrowest order found is no narrower than the bound)
    assert schur._camera_band(lay.obs_point, lay.obs_col, lay.n_points, len(lay.free), no_ties, "auto") == (None,
                                                                                                          None)
    short = make_live_final_problem(np.random.default_rng(0), n_free=80, n_fixed=2, new_points_per_view=8,
                                    long_share=0.0, max_track=12)
    assert schur._layout(schur.pose_major(short.problem)[0]).band is not None
