"""Triangulation and bundle adjustment on synthetic problems with known answers (data generated apart from
the solver)."""

import numpy as np

from lapreco_hil.geometry import Rotation, look_at, make_T, pose_error
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping.triangulation import triangulate

K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])


def scene(rng, n_points=400, n_views=8):
    pts = np.column_stack([rng.uniform(-0.04, 0.04, n_points), rng.uniform(-0.03, 0.03, n_points),
                           0.11 + 0.015 * rng.standard_normal(n_points)])
    poses = np.array([look_at(np.array([0.003 * i - 0.012, 0.0015 * i, 0.0]), np.array([0, 0, 0.11]),
                              np.array([0, -1.0, 0])) for i in range(n_views)])
    return pts, poses


def project(T_world_camera, pts):
    T = np.linalg.inv(T_world_camera)
    Xc = pts @ T[:3, :3].T + T[:3, 3]
    return np.column_stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]])


def test_triangulation_recovers_points_exactly(rng):
    pts, poses = scene(rng)
    uv = np.stack([project(T, pts) for T in poses], axis=1)
    res = triangulate(uv, np.ones(uv.shape[:2], bool), poses, K, 1.0, 1.0)
    assert res.valid.all()
    np.testing.assert_allclose(res.points, pts, atol=1e-9)


def test_triangulation_with_each_tracks_own_views(rng):
    """The mapper triangulates each track from a few of its own views (N, V, 4, 4): every track here sees a
    different random subset of 3 of the 8 cameras, and its point comes back exactly."""
    pts, poses = scene(rng, n_points=200)
    views = np.array([rng.choice(len(poses), 3, replace=False) for _ in pts])
    own = poses[views]  # (N, 3, 4, 4)
    uv = np.stack([project(T, p[None])[0] for Ts, p in zip(own, pts) for T in Ts]).reshape(len(pts), 3, 2)
    seen = np.ones((len(pts), 3), bool)
    seen[::4, 1] = False  # some tracks with only two views
    res = triangulate(uv, seen, own, K, 0.5, 1.0)
    wide = res.parallax_deg >= 0.5
    assert wide.mean() > 0.8 and np.array_equal(res.valid, wide)
    np.testing.assert_allclose(res.points, pts, atol=1e-9)


def test_triangulation_rejects_low_parallax_and_points_behind(rng):
    pts, poses = scene(rng, n_points=20)
    uv = np.stack([project(T, pts) for T in poses[:2]], axis=1)
    res = triangulate(uv, np.ones(uv.shape[:2], bool), poses[:2], K, 20.0, 1.0)
    assert not res.valid.any()  # 3 mm baseline at 110 mm: a few degrees, not 20
    behind = pts * [1, 1, -1]  # behind every camera: the pinhole equations still give pixels
    uvb = np.stack([project(T, behind) for T in poses], axis=1)
    res = triangulate(uvb, np.ones(uvb.shape[:2], bool), poses, K, 0.1, 1.0)
    np.testing.assert_allclose(res.points, behind, atol=1e-9)
    assert not res.valid.any()


def make_problem(rng, rot_sigma=0.004, trans_sigma=0.0005, outliers=0.0):
    pts, poses = scene(rng)
    M, N = len(poses), len(pts)
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    priors = np.array([T @ make_T(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                                  rng.normal(0, trans_sigma, 3)) for T in poses])
    obs_pose = np.repeat(np.arange(M), N)
    obs_point = np.tile(np.arange(N), M)
    uv = np.vstack([project(T, pts) for T in poses]) + rng.normal(0, 0.5, (M * N, 2))
    n_out = int(outliers * len(uv))
    bad = rng.choice(len(uv), n_out, replace=False)
    uv[bad] += rng.uniform(8, 40, (n_out, 2)) * rng.choice([-1, 1], (n_out, 2))
    problem = ba.BAProblem(K, np.arange(M), priors.copy(), np.zeros(M, bool), priors, np.repeat(cov[None], M, 0),
                           np.arange(N), pts + rng.normal(0, 0.002, pts.shape), obs_pose, obs_point, uv)
    return problem, poses, pts


def rms_position_mm(est, truth):
    return 1e3 * np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(est, truth)]))


def test_ba_with_robot_priors_beats_the_priors(rng):
    problem, poses, pts = make_problem(rng)
    result = ba.solve(problem, pixel_sigma=0.5, loss="cauchy", k=2.0)
    prior_err = rms_position_mm(problem.prior_poses, poses)
    refined_err = rms_position_mm(result.poses, poses)
    assert refined_err < 0.5 * prior_err, (prior_err, refined_err)
    assert np.median(np.linalg.norm(result.points - pts, axis=1)) < 0.5 * np.median(
        np.linalg.norm(problem.points - pts, axis=1))
    assert np.median(result.residuals_px) < 1.0


def test_fixed_poses_do_not_move(rng):
    problem, poses, _ = make_problem(rng)
    problem.fixed[:2] = True
    problem.poses[:2] = poses[:2]
    result = ba.solve(problem, pixel_sigma=0.5)
    np.testing.assert_allclose(result.poses[:2], poses[:2], atol=1e-6)


def test_robust_loss_resists_gross_outliers_where_least_squares_does_not(rng):
    problem, poses, _ = make_problem(np.random.default_rng(7), outliers=0.05)
    robust = ba.solve(problem, pixel_sigma=0.5, loss="cauchy", k=2.0)
    plain = ba.solve(problem, pixel_sigma=0.5, loss=None)
    assert rms_position_mm(robust.poses, poses) < 0.5 * rms_position_mm(plain.poses, poses)


def test_widest_ray_angle_between_a_points_views():
    from lapreco_hil.mapping.triangulation import widest_ray_angle_deg

    points = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.1], [1.0, 1.0, 1.0]])
    # point 0 seen from two centres 10 mm apart at 100 mm (5.7 deg), point 1 from three (the widest pair is 0-2:
    # 11.4 deg), point 2 once
    centres = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0],
                        [-0.01, 0.0, 0.0], [0.0, 0.0, 0.0], [0.01, 0.0, 0.0],
                        [0.0, 0.0, 0.0]])
    obs_point = np.array([0, 0, 1, 1, 1, 2])
    angle = widest_ray_angle_deg(points, obs_point, centres, 4)
    assert np.allclose(angle[:3], [np.degrees(np.arctan(0.1)), 2 * np.degrees(np.arctan(0.1)), 0.0])
    assert angle[3] == 0.0  # a point with no observation
