"""The Schur-complement bundle adjustment against GTSAM, the reference: the same optimum, the same robust
schedule's answers and labels, fixed poses, full-covariance priors, rig ties; its Jacobians against finite
differences; the chunked elimination (a final pass's) against the one-block one (a local window's). Each solver
test runs the numpy path and the Warp kernels on Warp's CPU device (LAPRECO_TEST_DEVICE=cuda:0 runs them on the
GPU instead)."""

import dataclasses
import os

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.config import MapperConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import inv_T, pose_error
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping import schur
from lapreco_hil.mapping.mapper import Mapper
from lapreco_hil.mapping.robust import CAUCHY_K, TUKEY_C, RobustSchedule, RobustStage, mad_sigma, sigma_of_mad
from lapreco_hil.mapping.synthetic import make_problem, make_sweep_problem

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
DEVICES = pytest.mark.parametrize("device", ["numpy", DEVICE])


def rms_mm(poses, truth):
    return 1e3 * np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(poses, truth)]))


def full_covariances(rng, n):
    """Correlated 6x6 covariances (rotation, translation), as a robot's propagated joint noise gives."""
    A = rng.normal(0, 1, (n, 6, 6)) * np.array([0.003] * 3 + [0.0004] * 3)[None, :, None]
    return A @ np.transpose(A, (0, 2, 1)) + np.diag([0.002**2] * 3 + [0.0003**2] * 3)


def test_se3_maps_and_jacobian_agree_with_gtsam(rng):
    xi = rng.normal(0, 0.4, (5, 6))
    T = schur.se3_exp(xi)
    for x, M in zip(xi, T):
        np.testing.assert_allclose(M, gtsam.Pose3.Expmap(x).matrix(), atol=1e-12)
        np.testing.assert_allclose(schur.right_jacobian_inverse(x[None])[0], gtsam.Pose3.LogmapDerivative(x),
                                   atol=1e-9)
    np.testing.assert_allclose(schur.se3_log(T), xi, atol=1e-12)
    tiny = np.array([[1e-9, -2e-9, 1e-9, 1e-3, 2e-3, -1e-3]])
    np.testing.assert_allclose(schur.se3_log(schur.se3_exp(tiny)), tiny, atol=1e-15)


def test_rotation_log_agrees_with_scipys_at_every_angle(rng):
    """The rotation log without scipy (atan2 of sine and cosine, the axis from R - R^T) against scipy's
    quaternion way, from 1e-9 rad to within 1e-5 rad of pi (beyond 3 rad it hands over to scipy's)."""
    axes = rng.normal(size=(7, 40, 3))
    axes /= np.linalg.norm(axes, axis=2, keepdims=True)
    for axis, angle in zip(axes, (1e-9, 1e-5, 1e-3, 0.3, 2.0, 2.999, np.pi - 1e-5)):
        w = axis * angle
        R = Rotation.from_rotvec(w).as_matrix()
        np.testing.assert_allclose(schur.so3_log(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-14)
        np.testing.assert_allclose(schur.se3_exp(np.column_stack([w, np.zeros_like(w)]))[:, :3, :3], R, atol=1e-15)


def test_the_robust_scale_is_numpys_median_by_one_selection(rng):
    """``mad_sigma``'s median (one partition each) is exactly ``np.median``'s: odd and even counts, ties, NaN and
    inf left out, and the caller's residuals left as they were."""
    def reference(r):
        e = np.asarray(r, float).ravel()
        e = e[np.isfinite(e)]
        return float(1.4826 * np.median(np.abs(e - np.median(e))))

    for n in (1, 2, 3, 4, 101, 4000, 40001):
        for values in (rng.normal(size=n), rng.standard_cauchy(size=n), rng.integers(0, 4, n).astype(float)):
            values = values.copy()
            values[rng.random(n) < 0.05] = np.nan
            values[rng.random(n) < 0.02] = -np.inf
            if not np.isfinite(values).any():
                continue
            before = values.copy()
            assert mad_sigma(values) == reference(values)
            np.testing.assert_array_equal(values, before)
    assert mad_sigma(np.full(6, np.nan), floor=0.3) == 1.0


def test_the_robust_scale_found_on_the_device_is_the_hosts(rng):
    """The medians found on the kernels' device by sorts (a GPU's way: one scalar read back) give exactly
    ``mad_sigma``'s scale: odd and even counts of finite components, ties, NaN and inf left out, none at all."""
    p = make_problem(np.random.default_rng(5), n_views=4, n_points=60, jump=0.03).problem
    kernels = schur._layout(schur.pose_major(p)[0], DEVICE, gpu_reductions=True).kernels
    n_obs = len(p.obs_pose)
    for n_finite in (0, 1, 2, 3, 4, 101, 2 * n_obs):
        for values in (rng.normal(size=2 * n_obs), rng.standard_cauchy(size=2 * n_obs),
                       rng.integers(0, 4, 2 * n_obs).astype(float)):
            values[rng.permutation(2 * n_obs)[n_finite:]] = rng.choice([np.nan, np.inf, -np.inf])
            kernels._upload(kernels.residual, values.reshape(-1, 2))
            kernels._launch_mad()
            count, mad = kernels._download(kernels.scale_sums)[0][:2]
            assert count == n_finite
            assert sigma_of_mad(float(mad) if count else None) == mad_sigma(values)


def test_observations_put_pose_major_as_by_a_stable_sort(rng):
    """``pose_major``'s permutation is the stable sort's by pose, whether the observations come in a few runs of
    one pose each (a live window's, keyframe by keyframe: the runs put in order), at random or sorted already."""
    p = make_problem(np.random.default_rng(1), n_views=12, n_points=50, jump=0.03).problem
    for trial in range(60):
        if trial % 3 == 0:  # runs, a pose's possibly in several, some empty
            runs = rng.integers(0, len(p.poses), int(rng.integers(1, 40)))
            obs_pose = np.repeat(runs, rng.integers(0, 50, len(runs)))
        else:
            obs_pose = rng.integers(0, len(p.poses), int(rng.integers(0, 600)))
            if trial % 3 == 2:
                obs_pose.sort()
        n = len(obs_pose)
        q = dataclasses.replace(p, obs_pose=obs_pose, obs_point=rng.integers(0, 50, n), obs_uv=rng.random((n, 2)))
        sorted_q, perm = schur.pose_major(q)
        np.testing.assert_array_equal(perm, np.argsort(obs_pose, kind="stable"))
        np.testing.assert_array_equal(sorted_q.obs_uv, q.obs_uv[perm])
        np.testing.assert_array_equal(sorted_q.obs_point, q.obs_point[perm])


def _numeric_jacobian(f, n, eps=1e-6):
    cols = []
    for i in range(n):
        d = np.zeros(n)
        d[i] = eps
        cols.append((f(d) - f(-d)) / (2 * eps))
    return np.stack(cols, -1)


def test_reprojection_jacobians_match_finite_differences(rng):
    p = make_problem(rng, n_views=3, n_points=20).problem
    p, _ = schur.pose_major(p)
    lay = schur._layout(p)
    r, Jc, Jp = schur._reprojection(p, lay, p.poses, p.points, jacobians=True)
    for o in (0, 7, 33, 59):
        i, j = p.obs_pose[o], p.obs_point[o]

        def moved_pose(d, i=i, o=o):
            poses = p.poses.copy()
            poses[i] = poses[i] @ schur.se3_exp(d[None])[0]  # GTSAM's retraction: T Exp(xi)
            return schur._reprojection(p, lay, poses, p.points, jacobians=False)[o]

        def moved_point(d, j=j, o=o):
            points = p.points.copy()
            points[j] += d
            return schur._reprojection(p, lay, p.poses, points, jacobians=False)[o]

        np.testing.assert_allclose(Jc[o], _numeric_jacobian(moved_pose, 6), rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(Jp[o], _numeric_jacobian(moved_point, 3), rtol=1e-5, atol=1e-2)


def test_prior_and_tie_jacobians_match_finite_differences(rng):
    p = make_problem(rng, n_views=4, n_points=10).problem
    # a tie measured a little off the current relative pose, so the error (and its Jacobian) is not trivial
    T_01 = inv_T(p.poses[0]) @ p.poses[1] @ schur.se3_exp(np.array([[0.02, -0.01, 0.03, 1e-3, -2e-3, 5e-4]]))[0]
    p = dataclasses.replace(p, prior_covs=full_covariances(rng, 4), tie_pairs=np.array([[0, 1]]),
                            tie_T=T_01[None], tie_covs=full_covariances(rng, 1))
    lay = schur._layout(p)
    factors = schur._pose_factors(p, lay, p.poses, jacobians=True)
    assert len(factors) == 2
    for n_factor, (_, blocks) in enumerate(factors):
        for idx, J in blocks:
            for n in range(len(idx)):

                def moved(d, i=idx[n], n=n, n_factor=n_factor):
                    poses = p.poses.copy()
                    poses[i] = poses[i] @ schur.se3_exp(d[None])[0]
                    return schur._pose_factors(p, lay, poses, jacobians=False)[n_factor][0][n]

                np.testing.assert_allclose(J[n], _numeric_jacobian(moved, 6), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("gpu_reductions", [False, True])
@pytest.mark.parametrize("loss", ["none", "cauchy", "tukey", "huber"])
def test_kernels_linearise_as_numpy_does(loss, gpu_reductions):
    """The Warp kernels' normal-equation blocks, error and elimination blocks against the numpy path's, with a
    fixed pose and a point behind a camera in the problem; one observation per thread (the CPU device's way) and
    runs of observations whose poses change within a run (a GPU's)."""
    syn = make_problem(np.random.default_rng(8), n_views=5, n_points=80, jump=0.1)
    q = syn.problem
    keep = np.ones(len(q.obs_pose), bool)
    keep[[5, 17, 200]] = False  # (80 views per pose: runs of 16 would never hold two poses)
    p, _ = schur.pose_major(dataclasses.replace(q, fixed=np.arange(5) == 0, obs_pose=q.obs_pose[keep],
                                                obs_point=q.obs_point[keep], obs_uv=q.obs_uv[keep]))
    p.points[3] = 2 * p.poses[1][:3, 3] - p.points[3]  # behind camera 1 (and others)
    ref, dev = schur._layout(p), schur._layout(p, DEVICE, gpu_reductions=gpu_reductions)
    runs = p.obs_pose[:len(p.obs_pose) // 16 * 16].reshape(-1, 16)
    assert dev.kernels.per_thread == (16 if gpu_reductions else 1) and np.any(runs[:, 0] != runs[:, -1])
    a = schur._linearize(p, ref, p.poses, p.points, 0.7, loss, 2.5)
    b = schur._linearize(p, dev, p.poses, p.points, 0.7, loss, 2.5)
    for x, y in ((a.Hcc, b.Hcc), (a.gc, b.gc), (a.Hpp, b.Hpp), (a.gp, b.gp),
                 (np.transpose(a.W, (2, 0, 1)), dev.kernels.W_host())):
        np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-9 * np.abs(x).max())
    assert b.error0 == pytest.approx(a.error0, rel=1e-12)
    e_ref = schur._error(p, ref, p.poses, p.points, 0.7, loss, 2.5)
    assert schur._error(p, dev, p.poses, p.points, 0.7, loss, 2.5) == pytest.approx(e_ref, rel=1e-12)
    for behind in (np.nan, np.inf):  # the residuals the robust scale and the labels are taken from
        np.testing.assert_allclose(schur._reprojection(p, dev, p.poses, p.points, False, behind),
                                   schur._reprojection(p, ref, p.poses, p.points, False, behind), atol=1e-9)
    timing = schur._new_timing()
    step_ref, step_dev = schur._solve_damped(ref, a, 1e-3, timing), schur._solve_damped(dev, b, 1e-3, timing)
    for x, y in zip(step_ref, step_dev):  # to 1 nm: Tukey leaves some landmarks one weighted view (ill-conditioned)
        np.testing.assert_allclose(y, x, rtol=1e-6, atol=1e-9)


@DEVICES
@pytest.mark.parametrize("loss, k", [(None, 0.0), ("cauchy", 3.0), ("tukey", 6.0), ("huber", 2.0)])
def test_same_optimum_as_gtsam_without_outliers(loss, k, device):
    # points start within ~1 px: far enough to move, near enough that Tukey (3 px) weighs every view (a landmark
    # left with one weighted view is free along its ray, and both solvers would move it by their round-off)
    syn = make_problem(np.random.default_rng(3), n_views=6, n_points=150, init_point_noise=0.0002)
    p = dataclasses.replace(syn.problem, prior_covs=full_covariances(np.random.default_rng(4), 6))
    ref = ba.solve(p, 0.5, loss, k, max_iterations=15)
    got = schur.solve_schur(p, 0.5, loss, k, max_iterations=15, device=device)
    assert got.iterations == ref.iterations
    assert got.final_error == pytest.approx(ref.final_error, rel=1e-9)
    # to 10 nm (Tukey's sharper weights carry round-off a little further than the other losses' 1e-14)
    np.testing.assert_allclose(got.poses, ref.poses, atol=1e-8)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-8)
    np.testing.assert_allclose(got.residuals_px, ref.residuals_px, atol=1e-5)
    # and it moved: the optimum is not the start
    assert np.abs(got.points - p.points).max() > 1e-4


@DEVICES
def test_a_pose_that_sees_a_point_twice_sums_both_views(device):
    syn = make_problem(np.random.default_rng(5), n_views=4, n_points=60)
    p = syn.problem
    twice = np.arange(0, len(p.obs_pose), 7)  # the same pose-point pair again, a pixel off
    p = dataclasses.replace(p, obs_pose=np.concatenate([p.obs_pose, p.obs_pose[twice]]),
                            obs_point=np.concatenate([p.obs_point, p.obs_point[twice]]),
                            obs_uv=np.concatenate([p.obs_uv, p.obs_uv[twice] + 1.0]))
    assert not schur._layout(schur.pose_major(p)[0]).unique_pairs
    ref, got = ba.solve(p, 0.5, None), schur.solve_schur(p, 0.5, None, device=device)
    np.testing.assert_allclose(got.poses, ref.poses, atol=1e-10)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-10)


@DEVICES
def test_robust_schedule_agrees_with_gtsam_under_gross_outliers(rng, device):
    syn = make_problem(np.random.default_rng(0), n_views=8, n_points=600, jump=0.03, highlight=0.02,
                       instrument=0.02)
    for schedule in (RobustSchedule(), RobustSchedule((RobustStage("cauchy", CAUCHY_K, 3),
                                                       RobustStage("tukey", TUKEY_C, 3)))):
        ref = ba.solve_robust(syn.problem, schedule)
        got = schur.solve_robust_schur(syn.problem, schedule, device=device)
        assert set(ref.stats) <= set(got.stats)
        assert [s["iterations"] for s in got.stats["stages"]] == [s["iterations"] for s in ref.stats["stages"]]
        assert got.stats["sigma_px"] == pytest.approx(ref.stats["sigma_px"], rel=1e-6)
        assert rms_mm(got.poses, syn.true_poses) == pytest.approx(rms_mm(ref.poses, syn.true_poses), rel=0.02)
        assert (got.stats["inlier_obs"] != ref.stats["inlier_obs"]).sum() <= 3
        assert (~got.stats["inlier_obs"]).sum() > 0.5 * syn.outlier_obs.sum()  # not all in
    # the labels catch what they should (test_robust_ba's case): tracks that jump by 6-25 px are out, clean
    # tracks in
    syn = make_problem(rng, jump=0.08)
    inlier = schur.solve_robust_schur(syn.problem, RobustSchedule(), device=device).stats["inlier_obs"]
    assert (~inlier[syn.outlier_obs]).mean() > 0.95
    assert (~inlier[~syn.outlier_points[syn.problem.obs_point]]).mean() < 0.01


@DEVICES
def test_fixed_poses_stay_fixed_and_the_rest_agree_with_gtsam(device):
    syn = make_problem(np.random.default_rng(1), n_views=6, n_points=200)
    fixed = np.array([True, True, False, False, False, False])
    p = dataclasses.replace(syn.problem, fixed=fixed)
    ref, got = ba.solve(p, 0.5, "cauchy", 3.0), schur.solve_schur(p, 0.5, "cauchy", 3.0, device=device)
    np.testing.assert_array_equal(got.poses[fixed], p.poses[fixed])
    assert np.abs(got.poses[~fixed] - p.poses[~fixed]).max() > 1e-5
    # GTSAM holds them by a prior of sigma 1e-7, which lets them (and so the rest) move by that much
    np.testing.assert_allclose(got.poses, ref.poses, atol=1e-6)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-6)
    # every pose fixed (a map held at two views): the points alone are refined
    held = dataclasses.replace(p, fixed=np.ones(6, bool))
    got = schur.solve_schur(held, 0.5, "cauchy", 3.0, device=device)
    np.testing.assert_array_equal(got.poses, p.poses)
    np.testing.assert_allclose(got.points, ba.solve(held, 0.5, "cauchy", 3.0).points, atol=1e-6)


def test_priors_pull_the_poses_to_them():
    syn = make_problem(np.random.default_rng(2), n_views=5, n_points=150)
    p = syn.problem
    # 1e-6 rad, 0.3 um: tighter than 750 observations at 0.5 px can argue with
    tight = dataclasses.replace(p, prior_covs=np.repeat(np.diag([1e-12] * 3 + [1e-13] * 3)[None], 5, 0),
                                poses=syn.true_poses.copy())
    got = schur.solve_schur(tight, 0.5, None)
    # started at the truth, a very tight prior takes each pose to its (wrong) prior
    assert max(pose_error(a, b)[0] for a, b in zip(got.poses, p.prior_poses)) < 2e-6
    np.testing.assert_allclose(got.poses, ba.solve(tight, 0.5, None).poses, atol=1e-10)
    assert max(pose_error(a, b)[0] for a, b in zip(p.prior_poses, syn.true_poses)) > 2e-4
    loose = schur.solve_schur(dataclasses.replace(tight, prior_covs=p.prior_covs), 0.5, None)
    assert rms_mm(loose.poses, syn.true_poses) < 0.7 * rms_mm(p.prior_poses, syn.true_poses)


@DEVICES
def test_rig_ties_hold_a_stereo_pair_as_gtsam_does(device):
    syn = make_problem(np.random.default_rng(6), n_views=8, n_points=300, jump=0.03)
    p = syn.problem
    pairs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])  # reference camera, partner
    T_ij = np.array([inv_T(syn.true_poses[i]) @ syn.true_poses[j] for i, j in pairs])
    has_prior = np.ones(8, bool)
    has_prior[pairs[:, 1]] = False
    tied = dataclasses.replace(p, has_prior=has_prior, tie_pairs=pairs, tie_T=T_ij,
                               tie_covs=np.repeat(np.diag([1e-4**2] * 3 + [1e-5**2] * 3)[None], 4, 0))
    schedule = RobustSchedule()
    ref, got = ba.solve_robust(tied, schedule), schur.solve_robust_schur(tied, schedule, device=device)
    # each partner with a prior of its own instead: the pair's relative pose is as loose as two priors
    loose = schur.solve_robust_schur(dataclasses.replace(p, has_prior=np.ones(8, bool)), schedule, device=device)

    def pair_error(poses):
        return max(pose_error(inv_T(poses[i]) @ poses[j], T)[0] for (i, j), T in zip(pairs, T_ij))

    assert pair_error(got.poses) < 0.25 * pair_error(loose.poses)
    assert pair_error(got.poses) < 1e-4
    np.testing.assert_allclose(got.poses, ref.poses, atol=1e-8)
    assert (got.stats["inlier_obs"] != ref.stats["inlier_obs"]).sum() <= 2


@DEVICES
def test_chunked_elimination_equals_one_block(monkeypatch, device):
    """A final pass eliminates its landmarks chunk by chunk (bounded memory); a local window in one block."""
    syn = make_problem(np.random.default_rng(7), n_views=20, n_points=600)
    p = dataclasses.replace(syn.problem, fixed=np.arange(20) < 2)
    monkeypatch.setattr(schur, "CHUNK_POINTS", 10_000)
    one = schur.solve_schur(p, 0.5, "cauchy", 3.0, device=device)
    assert len(schur._layout(schur.pose_major(p)[0]).chunks) == 1
    monkeypatch.setattr(schur, "CHUNK_ENTRIES", 20_000)
    assert len(schur._layout(schur.pose_major(p)[0]).chunks) >= 10
    chunked = schur.solve_schur(p, 0.5, "cauchy", 3.0, device=device)
    assert chunked.iterations == one.iterations > 1
    np.testing.assert_allclose(chunked.poses, one.poses, atol=1e-10)
    np.testing.assert_allclose(chunked.points, one.points, atol=1e-10)


def test_a_slow_sweeps_chunks_follow_its_tracks_and_agree_with_gtsam(monkeypatch):
    """A slow sweep's final pass (tracks of many views, the camera system dense): the landmarks are chunked by
    their span of poses at a bounded cost over their own blocks, and the answer is GTSAM's; chunks whose poses
    are not one run (a track that skips keyframes) are eliminated as well as those that are."""
    syn = make_sweep_problem(np.random.default_rng(11), n_views=40, n_points=300, min_track=5, max_track=30,
                             step_m=0.0005, jump=0.05)
    p = syn.problem
    lay = schur._layout(schur.pose_major(p)[0])
    own = np.bincount(p.obs_point[~p.fixed[p.obs_pose]]).astype(float) ** 2
    cost = sum(len(c.points) * c.n_cols**2 for c in lay.chunks)
    assert len(lay.chunks) > 3 and cost <= schur.CHUNK_WASTE * own.sum()
    assert all(isinstance(c.idx, slice) for c in lay.chunks)
    schedule = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 8), RobustStage("tukey", TUKEY_C, 8)))
    ref = ba.solve_robust(p, schedule)
    got = schur.solve_robust_schur(p, schedule)
    assert rms_mm(got.poses, syn.true_poses) == pytest.approx(rms_mm(ref.poses, syn.true_poses), rel=0.02)
    assert rms_mm(got.poses, syn.true_poses) < 0.5 * rms_mm(p.prior_poses, syn.true_poses)
    assert (got.stats["inlier_obs"] != ref.stats["inlier_obs"]).sum() == 0
    assert (~got.stats["inlier_obs"][syn.outlier_obs]).mean() > 0.9
    # every landmark a chunk of its own (no waste) gives the same steps
    monkeypatch.setattr(schur, "CHUNK_POINTS", 1)
    single = schur.solve_robust_schur(p, schedule)
    np.testing.assert_allclose(single.poses, got.poses, atol=1e-10)
    np.testing.assert_array_equal(single.stats["inlier_obs"], got.stats["inlier_obs"])
    # tracks that skip every fourth keyframe: chunks whose poses are not one run
    monkeypatch.undo()
    keep = (p.obs_pose % 4 != 1) | (p.obs_pose < 2)
    gappy = dataclasses.replace(p, obs_pose=p.obs_pose[keep], obs_point=p.obs_point[keep], obs_uv=p.obs_uv[keep])
    assert not all(isinstance(c.idx, slice) for c in schur._layout(schur.pose_major(gappy)[0]).chunks)
    np.testing.assert_allclose(schur.solve_schur(gappy, 0.5, "cauchy", 3.0).poses,
                               ba.solve(gappy, 0.5, "cauchy", 3.0).poses, atol=1e-8)


@pytest.mark.parametrize("case", ["outliers", "twice", "fixed", "tied", "sweep"])
def test_landmarks_eliminated_on_the_device_as_on_the_host(case):
    """The device's elimination (one launch, atomics: a GPU's way) against the host's chunked BLAS one, on the
    kernels' device: the same steps, the same answers and labels; and GTSAM's answer under gross outliers."""
    syn = make_problem(np.random.default_rng(12), n_views=8, n_points=400, jump=0.03, highlight=0.02,
                       instrument=0.02)
    p = syn.problem
    if case == "sweep":  # long tracks, two poses fixed
        syn = make_sweep_problem(np.random.default_rng(13), n_views=30, n_points=200, min_track=5, max_track=25,
                                 step_m=0.0005)
        p = syn.problem
    elif case == "twice":
        again = np.arange(0, len(p.obs_pose), 5)
        p = dataclasses.replace(p, obs_pose=np.concatenate([p.obs_pose, p.obs_pose[again]]),
                                obs_point=np.concatenate([p.obs_point, p.obs_point[again]]),
                                obs_uv=np.concatenate([p.obs_uv, p.obs_uv[again] + 0.7]))
    elif case == "fixed":
        p = dataclasses.replace(p, fixed=np.arange(8) < 3)
    elif case == "tied":
        pairs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
        has_prior = np.ones(8, bool)
        has_prior[pairs[:, 1]] = False
        p = dataclasses.replace(p, has_prior=has_prior, tie_pairs=pairs,
                                tie_T=np.array([inv_T(syn.true_poses[i]) @ syn.true_poses[j] for i, j in pairs]),
                                tie_covs=np.repeat(np.diag([1e-4**2] * 3 + [1e-5**2] * 3)[None], 4, 0))
    host = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=False, gpu_reductions=False)
    for gpu_reductions in (False, True):
        # (a GPU's reductions: sums per thread, the window's elimination by pose pairs, the scales by sorts)
        dev = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=True,
                                       gpu_reductions=gpu_reductions)
        assert [s["iterations"] for s in dev.stats["stages"]] == [s["iterations"] for s in host.stats["stages"]]
        np.testing.assert_allclose(dev.poses, host.poses, atol=1e-9)
        assert [s["sigma_px"] for s in dev.stats["stages"]] == pytest.approx(
            [s["sigma_px"] for s in host.stats["stages"]], rel=1e-9)
        # the landmarks that keep inlier views by two poses; one that Tukey leaves a single weighted view (or two
        # by one pose) is free along its ray, and moves by the round-off
        inlier_pairs = np.unique(np.column_stack([p.obs_point, p.obs_pose])[dev.stats["inlier_obs"]], axis=0)
        kept = np.bincount(inlier_pairs[:, 0], minlength=len(p.points)) >= 2
        assert kept.mean() > 0.9
        np.testing.assert_allclose(dev.points[kept], host.points[kept], atol=1e-8)
        np.testing.assert_array_equal(dev.stats["inlier_obs"], host.stats["inlier_obs"])
    # the window's elimination by pose pairs where each landmark is seen once by a pose (else by observations)
    assert schur._layout(schur.pose_major(p)[0], DEVICE, True, gpu_reductions=True).kernels.window == (case != "twice")
    if case == "outliers":
        ref = ba.solve_robust(p, RobustSchedule())
        assert rms_mm(dev.poses, syn.true_poses) == pytest.approx(rms_mm(ref.poses, syn.true_poses), rel=0.02)
        assert (dev.stats["inlier_obs"] != ref.stats["inlier_obs"]).sum() <= 3


def _live_like_window(rng, n_views: int, n_points: int, n_fixed: int, keep: float, behind: float):
    """A local window as the live mapper hands it over: its older keyframes fixed and last in the pose list, some
    observations missing (every landmark keeps two), the observations in no pose's order, a few landmarks behind
    a camera."""
    p = make_problem(rng, n_views=n_views, n_points=n_points, jump=0.03, highlight=0.02, instrument=0.01).problem
    kept = rng.random(len(p.obs_pose)) < keep
    kept |= np.bincount(p.obs_point[kept], minlength=n_points)[p.obs_point] < 2
    order = rng.permutation(np.flatnonzero(kept))
    points = p.points.copy()
    away = rng.random(n_points) < behind
    points[away, 2] *= -1.0
    return dataclasses.replace(p, fixed=np.arange(n_views) >= n_views - n_fixed, points=points,
                               obs_pose=p.obs_pose[order], obs_point=p.obs_point[order], obs_uv=p.obs_uv[order])


def test_windows_in_a_row_with_a_gpus_reductions_as_without():
    """A live worker's run of windows (sizes, fixed poses, missing observations, landmarks behind a camera),
    solved with a GPU's reductions (sums per run of observations, the elimination by pose pairs, the scales by
    sorts) and without: the same labels, scales and poses. Among them windows whose landmark x free-pose table
    (int32, ``_schur_window``'s) has N F = 1 mod 64 entries: its arena part's words were counted rounded down, so
    that its last entry lay in the next part, the whitened blocks, whose writes overwrote it with a garbage
    observation index (a crash on the CPU device; on a GPU an illegal address, after which every later window in
    that worker failed)."""
    rng = np.random.default_rng(23)
    windows = [(5, 333, 0, 1.0, 0.0), (9, 183, 2, 0.8, 0.01), (4, 60, 1, 0.7, 0.0), (12, 250, 3, 0.6, 0.02),
               (3, 43, 0, 1.0, 0.0), (7, 300, 0, 0.9, 0.0)]
    for n_views, n_points, n_fixed, keep, behind in windows:
        p = _live_like_window(rng, n_views, n_points, n_fixed, keep, behind)
        kernels = schur._layout(schur.pose_major(p)[0], DEVICE, True, gpu_reductions=True).kernels
        n_free = n_views - n_fixed
        assert kernels.window
        assert kernels.table.ptr + 4 * n_points * n_free <= kernels.Z.ptr  # the table's last entry its own
        default = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=True)
        gpu = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=True, gpu_reductions=True)
        np.testing.assert_array_equal(gpu.stats["inlier_obs"], default.stats["inlier_obs"])
        assert [s["sigma_px"] for s in gpu.stats["stages"]] + [gpu.stats["sigma_px"]] == pytest.approx(
            [s["sigma_px"] for s in default.stats["stages"]] + [default.stats["sigma_px"]], rel=1e-7)
        np.testing.assert_allclose(gpu.poses, default.poses, atol=1e-8)


@pytest.mark.parametrize("device_schur, gpu_reductions, host_mirror",
                         [(True, None, False), (True, None, True), (False, None, False), (True, True, True)])
def test_windows_of_varying_sizes_through_one_workspace_as_fresh_solves(monkeypatch, device_schur, gpu_reductions,
                                                                        host_mirror):
    """A live worker's windows in a row through one ``SchurWorkspace`` (its buffers sized by capacity: grown for
    a larger window, kept for a smaller one, each window's parts cut by its own counts): the same labels, scales,
    poses and landmarks as each window solved alone, and nothing allocated where the buffers are large enough
    already. ``host_mirror``: the transfers through the workspace's one host mirror of the arena (a GPU's
    page-locked one), forced on the CPU device, so that every part's offset in it is checked too."""
    from lapreco_hil.mapping import schur_kernels

    if host_mirror:
        if not str(DEVICE).startswith("cpu"):
            pytest.skip("on CUDA the host mirror is the real path (the other cases)")
        monkeypatch.setattr(schur_kernels.ObservationKernels, "_host_arena_mirror",
                            lambda self: self._workspace is not None)
    exact = str(DEVICE).startswith("cpu")  # (a GPU's atomic sums differ from run to run in their last bits)
    rng = np.random.default_rng(15)
    # (views, landmarks, fixed, kept share, behind share): shrinking, growing past the capacity, odd N F
    windows = [(6, 300, 1, 0.9, 0.0), (4, 80, 0, 0.7, 0.02), (9, 451, 2, 0.8, 0.01), (5, 333, 0, 1.0, 0.0),
               (12, 700, 3, 0.6, 0.0), (3, 43, 0, 1.0, 0.0), (9, 450, 2, 0.9, 0.01)]
    workspace = schur_kernels.SchurWorkspace()
    schedule = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 3), RobustStage("tukey", TUKEY_C, 3)))
    fitted = grown = 0
    for n_views, n_points, n_fixed, keep, behind in windows:
        p = _live_like_window(rng, n_views, n_points, n_fixed, keep, behind)
        kwargs = dict(device=DEVICE, device_schur=device_schur, gpu_reductions=gpu_reductions)
        capacity = workspace.capacity(DEVICE, "arena")
        reused = schur.solve_robust_schur(p, schedule, workspace=workspace, **kwargs)
        fresh = schur.solve_robust_schur(p, schedule, **kwargs)
        np.testing.assert_array_equal(reused.stats["inlier_obs"], fresh.stats["inlier_obs"])
        scales = [s["sigma_px"] for s in reused.stats["stages"]] + [reused.stats["sigma_px"]]
        fresh_scales = [s["sigma_px"] for s in fresh.stats["stages"]] + [fresh.stats["sigma_px"]]
        if exact:
            assert scales == fresh_scales
            np.testing.assert_array_equal(reused.poses, fresh.poses)
            np.testing.assert_array_equal(reused.points, fresh.points)
            np.testing.assert_array_equal(reused.residuals_px, fresh.residuals_px)
        else:
            assert scales == pytest.approx(fresh_scales, rel=1e-7)
            np.testing.assert_allclose(reused.poses, fresh.poses, atol=1e-8)
        # the arena grows for a window larger than any before, never shrinks; a window that fits allocates nothing
        # (where the host eliminates the landmarks its chunks' index arrays are its own)
        assert workspace.capacity(DEVICE, "arena") >= capacity
        if workspace.capacity(DEVICE, "arena") == capacity:
            fitted += 1
            if device_schur:
                assert reused.stats["device_ops"]["allocations"] == 0
        else:
            grown += 1
    assert fitted >= 2 and grown >= 3  # (the first window's buffers, then two larger windows)
    with workspace.claim(), pytest.raises(RuntimeError, match="one solve at a time"):
        schur.solve_robust_schur(p, schedule, workspace=workspace, device=DEVICE)


def test_the_ba_worker_solves_its_windows_through_its_workspace_as_fresh_solves():
    """The live BA worker (its own process, as the live runtime spawns it) keeps one workspace for its windows:
    windows of three sizes in a row come back as each solved alone here."""
    import multiprocessing as mp

    from lapreco_hil.mapping.mapper import local_schedule
    from lapreco_hil.runtime.mapper_process import ba_worker_main
    from lapreco_hil.runtime.messages import BAJob, EndOfJobs

    config = MapperConfig(ba_solver="schur", ba_device=DEVICE)
    rng = np.random.default_rng(16)
    windows = [_live_like_window(rng, *w) for w in [(6, 200, 1, 0.9, 0.0), (9, 400, 2, 0.8, 0.01),
                                                    (4, 90, 0, 1.0, 0.0)]]
    ctx = mp.get_context("spawn")
    jobs, results = ctx.Queue(), ctx.Queue()
    worker = ctx.Process(target=ba_worker_main, args=(local_schedule(config), jobs, results, os.getpid(), config),
                         daemon=True)
    worker.start()
    try:
        for i, p in enumerate(windows):
            jobs.put(BAJob(i, p))
        jobs.put(EndOfJobs())
        replies = sorted((results.get(timeout=120) for _ in windows), key=lambda r: r.job_id)
    finally:
        worker.join(timeout=30)
        if worker.is_alive():
            worker.kill()
    for p, reply in zip(windows, replies):
        assert reply.error == ""
        fresh = schur.solve_robust_schur(p, local_schedule(config), device=DEVICE)
        np.testing.assert_array_equal(reply.solved.stats["inlier_obs"], fresh.stats["inlier_obs"])
        np.testing.assert_allclose(reply.solved.poses, fresh.poses, atol=0 if DEVICE == "cpu" else 1e-8)
    # the second window is the largest: the third's arenas were there already (where the host eliminates the
    # landmarks, the CPU device's default, its chunks' index arrays are the window's own)
    assert replies[2].solved.stats["device_ops"]["allocations"] < fresh.stats["device_ops"]["allocations"]


@pytest.mark.parametrize("device_schur", [True, False])
def test_the_state_stays_on_the_device_across_lm(device_schur):
    """On a Warp device the buffers are allocated once per solve, and the host reads back, per damped system,
    no more than the camera system and a few scalars: per-observation arrays only for the robust scales and
    labels (once per stage and at the end), the landmarks once. Uploads: the problem, the state once, then per
    step only its poses and pose tangents (and, where the host eliminates the landmarks, their factors and
    moves). The same answer as the numpy path."""
    syn = make_problem(np.random.default_rng(3), n_views=6, n_points=300, jump=0.03, highlight=0.02)
    p = syn.problem
    n_obs, n_points, n6 = len(p.obs_pose), len(p.points), 6 * len(p.poses)
    runs = {}
    for its in (1, 3):
        schedule = RobustSchedule((RobustStage("cauchy", CAUCHY_K, its), RobustStage("tukey", TUKEY_C, its)))
        runs[its] = schur.solve_robust_schur(p, schedule, device=DEVICE, device_schur=device_schur)
    ref = schur.solve_robust_schur(p, schedule, device="numpy")
    np.testing.assert_allclose(runs[3].poses, ref.poses, atol=1e-9)
    np.testing.assert_array_equal(runs[3].stats["inlier_obs"], ref.stats["inlier_obs"])
    few, many = runs[1].stats["device_ops"], runs[3].stats["device_ops"]
    solves = sum(s["solves"] for s in runs[3].stats["stages"])
    assert sum(s["iterations"] for s in runs[3].stats["stages"]) > sum(s["iterations"] for s in runs[1].stats["stages"])
    if device_schur:
        assert many["allocations"] == few["allocations"]
    else:  # (the host's elimination allocates its batches' blocks at their first use, once)
        assert many["allocations"] <= few["allocations"] + 2
    # the residuals before each stage and at the end, the landmarks at the end, the error before each stage
    per_solve = 16 * n_obs * 3 + 24 * n_points + 2 * 24
    linearisations = sum(len(s["iteration_timing"]) for s in runs[3].stats["stages"])
    if device_schur:  # the camera system (with the pose blocks and gradients) per step, scalars
        per_step = 8 * (n6 * n6 + n6 + 1) + 8 * 3
        assert many["downloaded_bytes"] <= per_solve + solves * per_step + linearisations * 8 * (7 * n6 + 1)
        assert many["downloads"] <= 2 * 2 + 2 + linearisations + 2 * solves
        assert many["uploads"] <= few["uploads"] + 2 * (solves - sum(s["solves"] for s in runs[1].stats["stages"]))
    else:  # the landmark blocks too: the host eliminates them
        assert many["downloaded_bytes"] > per_solve + linearisations * 8 * 12 * n_points


def test_a_solve_with_its_scales_found_on_the_device_reads_the_residuals_once():
    """With a GPU's reductions (CUDA's default) the robust scales' medians are found on the kernels' device: the
    residuals are read back once, at the end, and the scales are the host's (the sums differ by round-off only)."""
    syn = make_problem(np.random.default_rng(6), n_views=6, n_points=300, jump=0.03, highlight=0.02)
    host = schur.solve_robust_schur(syn.problem, RobustSchedule(), device=DEVICE, gpu_reductions=False)
    dev = schur.solve_robust_schur(syn.problem, RobustSchedule(), device=DEVICE, gpu_reductions=True)
    n_obs = len(syn.problem.obs_pose)
    # (two stages: the residuals (O, 2) read back before each on the host's way; a count and a MAD on the GPU's)
    saved = host.stats["device_ops"]["downloaded_bytes"] - dev.stats["device_ops"]["downloaded_bytes"]
    if [s["solves"] for s in dev.stats["stages"]] != [s["solves"] for s in host.stats["stages"]]:
        # on CUDA the atomic sums differ from run to run in their last bits, and a damped step on the edge of
        # LM's acceptance can go either way (seen: 14, 15 or 16 solves in the Tukey stage, on either path): then
        # the same scales and answer within round-off, which the step counts cannot show
        assert not str(DEVICE).startswith("cpu")
        assert dev.stats["stages"][0]["sigma_px"] == pytest.approx(host.stats["stages"][0]["sigma_px"], rel=1e-9)
        np.testing.assert_allclose(dev.poses, host.poses, atol=1e-5)
        assert np.mean(dev.stats["inlier_obs"] == host.stats["inlier_obs"]) > 0.995
        return
    assert saved == 2 * 16 * n_obs - 3 * 16
    assert [s["sigma_px"] for s in dev.stats["stages"]] == pytest.approx(
        [s["sigma_px"] for s in host.stats["stages"]], rel=1e-9)
    assert dev.stats["sigma_px"] == pytest.approx(host.stats["sigma_px"], rel=1e-9)
    np.testing.assert_allclose(dev.poses, host.poses, atol=1e-9)
    np.testing.assert_array_equal(dev.stats["inlier_obs"], host.stats["inlier_obs"])


@pytest.mark.parametrize("device_schur", [True, False])
def test_transfers_through_host_copies_as_on_a_gpu(monkeypatch, device_schur):
    """On CUDA every upload and download goes through a host array of its own (``_Mirror``); on Warp's CPU device
    the device array's memory is used directly. Host copies forced on the CPU device: the same steps and answer,
    so that what is read back is what was written, at the right offsets, whichever state is current."""
    from lapreco_hil.mapping import schur_kernels

    if not str(DEVICE).startswith("cpu"):
        # (there the copies are the real path, and the device's atomic sums differ from run to run in their last
        # bits, so two solves need not take the same LM steps)
        pytest.skip("a CPU-device test: on CUDA every transfer already goes through its own host copy")

    def separate(self, array, host=None):
        self.array, self.pinned = array, host is not None
        self.host = schur_kernels.wp.empty(array.shape, dtype=array.dtype, device="cpu") if host is None else host
        self.view = self.host.numpy()

    syn = make_problem(np.random.default_rng(4), n_views=6, n_points=300, jump=0.03, highlight=0.02)
    p = dataclasses.replace(syn.problem, fixed=np.arange(6) == 0)
    direct = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=device_schur)
    monkeypatch.setattr(schur_kernels._Mirror, "__init__", separate)
    copied = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=device_schur)
    assert [s["solves"] for s in copied.stats["stages"]] == [s["solves"] for s in direct.stats["stages"]]
    np.testing.assert_array_equal(copied.poses, direct.poses)
    np.testing.assert_array_equal(copied.points, direct.points)
    np.testing.assert_array_equal(copied.residuals_px, direct.residuals_px)


@pytest.mark.parametrize("device_schur", [True, False])
def test_a_window_of_fixed_poses_moves_its_landmarks_only_as_numpy_does(device_schur):
    """No free pose (an empty camera system): the device's state and step still move the landmarks as the numpy
    path does."""
    syn = make_problem(np.random.default_rng(5), n_views=5, n_points=150, jump=0.03)
    p = dataclasses.replace(syn.problem, fixed=np.ones(5, bool))
    ref = schur.solve_robust_schur(p, RobustSchedule(), device="numpy")
    got = schur.solve_robust_schur(p, RobustSchedule(), device=DEVICE, device_schur=device_schur)
    assert got.iterations == ref.iterations > 0
    np.testing.assert_array_equal(got.poses, p.poses)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-10)
    assert np.abs(got.points - p.points).max() > 1e-6
    np.testing.assert_array_equal(got.stats["inlier_obs"], ref.stats["inlier_obs"])


def test_the_final_pass_takes_every_core_of_a_large_machine_only(monkeypatch):
    """BLAS threads for the final pass: every core of a machine of 8 or more, one on a small (shared) one, as
    many as ``[mapper] final_ba_threads`` says where it is set."""
    from lapreco_hil.mapping import mapper as mapper_module

    monkeypatch.setattr(schur, "all_cores", lambda: 16)
    assert schur.final_pass_threads() == 16
    monkeypatch.setattr(schur, "all_cores", lambda: 2)
    assert schur.final_pass_threads() == 1
    asked = []
    monkeypatch.setattr(mapper_module, "solve_robust_schur", lambda problem, schedule, **kw: asked.append(kw))
    K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
    Mapper(K, MapperConfig(ba_device="cpu"))._solve_final(None)
    Mapper(K, MapperConfig(final_ba_threads=3, ba_device="numpy"))._solve_final(None)
    assert asked == [{"device": "cpu", "blas_threads": 1}, {"device": "numpy", "blas_threads": 3}]


def test_the_mapper_uses_the_configured_solver():
    K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
    assert Mapper(K, MapperConfig(ba_device="cpu")).solve_ba is schur.solve_robust_schur
    # the default, auto: CUDA where Warp sees one, else the CPU
    from lapreco_hil.warp_device import resolve_device

    on_auto = Mapper(K, MapperConfig()).solve_ba
    if resolve_device("auto") == "cpu":
        assert on_auto is schur.solve_robust_schur
    else:
        assert on_auto.keywords == {"device": resolve_device("auto")}
    assert Mapper(K, MapperConfig(ba_solver="gtsam")).solve_ba is ba.solve_robust
    with pytest.raises(ConfigError, match=r"\[mapper\] ba_solver = 'ceres': use schur or gtsam"):
        Mapper(K, MapperConfig(ba_solver="ceres"))
    on_numpy = Mapper(K, MapperConfig(ba_device="numpy")).solve_ba
    assert on_numpy.func is schur.solve_robust_schur and on_numpy.keywords == {"device": "numpy"}
    with pytest.raises(ConfigError, match=r"\[mapper\] ba_device = 'tpu': use auto, cpu, numpy, cuda or cuda:N"):
        Mapper(K, MapperConfig(ba_device="tpu"))


def test_a_live_run_refuses_an_unknown_solver_before_it_starts():
    from lapreco_hil.config import PipelineConfig
    from lapreco_hil.runtime.live import LiveRun

    config = PipelineConfig()
    config = dataclasses.replace(config, mapper=dataclasses.replace(config.mapper, ba_solver="ceres"))
    with pytest.raises(ConfigError, match=r"\[mapper\] ba_solver = 'ceres'"):
        LiveRun(None, None, None, config, tracker="opencv", device="cpu")
