"""Synthetic bundle-adjustment problems with known truth, generated apart from the solver (as GTSAM's
examples do): cameras on a scan arc over a surface with relief, robot priors drawn from their covariance,
pixel noise, and the gross outliers a laparoscope meets:

- ``jump``: a track that jumps to other content half-way (its later observations are off),
- ``highlight``: a specular highlight that looks like a feature and stays at one image position as the
  camera moves (the light sits at the scope tip),
- ``instrument``: points on a tool that moves through the scene between views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lapreco_hil.geometry import Rotation, look_at, make_T
from lapreco_hil.mapping.bundle_adjustment import BAProblem


@dataclass
class SyntheticBA:
    problem: BAProblem
    true_poses: np.ndarray
    true_points: np.ndarray
    outlier_obs: np.ndarray  # (O,) bool: observation was corrupted
    outlier_points: np.ndarray  # (N,) bool: the whole track is not a rigid scene point


def make_problem(rng: np.random.Generator, n_views: int = 10, n_points: int = 600, pixel_noise: float = 0.5,
                 rot_sigma: float = 0.003, trans_sigma: float = 0.0004, jump: float = 0.0, highlight: float = 0.0,
                 instrument: float = 0.0, init_point_noise: float = 0.002) -> SyntheticBA:
    K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
    xy = np.column_stack([rng.uniform(-0.045, 0.045, n_points), rng.uniform(-0.035, 0.035, n_points)])
    z = 0.11 + 0.012 * np.sin(xy[:, 0] * 70) * np.cos(xy[:, 1] * 55)  # relief
    pts = np.column_stack([xy, z])
    angles = np.linspace(-0.12, 0.12, n_views)
    poses = np.array([look_at(np.array([0.1 * np.sin(a), 0.03 * np.sin(2 * a), 0.1 * (1 - np.cos(a))]),
                              np.array([0, 0, 0.11]), np.array([0, -1.0, 0])) for a in angles])
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    priors = np.array([T @ make_T(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                                  rng.normal(0, trans_sigma, 3)) for T in poses])

    def project(T, X):
        Tc = np.linalg.inv(T)
        Xc = X @ Tc[:3, :3].T + Tc[:3, 3]
        return np.column_stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]])

    uv = np.stack([project(T, pts) for T in poses], 1) + rng.normal(0, pixel_noise, (n_points, n_views, 2))
    kind = rng.choice(4, n_points, p=[1 - jump - highlight - instrument, jump, highlight, instrument])
    bad_obs = np.zeros((n_points, n_views), bool)
    half = n_views // 2
    for i in np.flatnonzero(kind == 1):  # jump: later half displaced by 6-25 px
        uv[i, half:] += rng.uniform(6, 25, 2) * rng.choice([-1, 1], 2)
        bad_obs[i, half:] = True
    for i in np.flatnonzero(kind == 2):  # highlight: stuck at its first-view image position
        uv[i, :] = uv[i, 0] + rng.normal(0, pixel_noise, (n_views, 2))
        bad_obs[i, 1:] = True
    for i in np.flatnonzero(kind == 3):  # instrument: moves 1.5 mm per view across the scene
        v = rng.normal(0, 1, 3)
        v *= 0.0015 / np.linalg.norm(v)
        uv[i] = np.stack([project(T, (pts[i] + m * v)[None])[0] for m, T in enumerate(poses)])
        bad_obs[i, 1:] = True
    obs_point = np.repeat(np.arange(n_points), n_views)
    obs_pose = np.tile(np.arange(n_views), n_points)
    problem = BAProblem(K, np.arange(n_views), priors.copy(), np.zeros(n_views, bool), priors,
                        np.repeat(cov[None], n_views, 0), np.arange(n_points),
                        pts + rng.normal(0, init_point_noise, pts.shape), obs_pose, obs_point,
                        uv.reshape(-1, 2))
    return SyntheticBA(problem, poses, pts, bad_obs.ravel(), kind != 0)


def observe_runs(rng: np.random.Generator, K: np.ndarray, true: np.ndarray, pts: np.ndarray, first: np.ndarray,
                 length: np.ndarray, pixel_noise: float, jump: float, min_jump_views: int = 0):
    """Each landmark ``pts[i]`` seen by the run of keyframes ``first[i]`` .. ``first[i] + length[i] - 1`` (poses
    ``true``, world from camera): (obs_pose, obs_point, uv with ``pixel_noise``, bad, jumped_track), where
    ``jump`` of the tracks of ``min_jump_views`` views or more jump 6-25 px half-way (their later views bad)."""
    obs_point = np.repeat(np.arange(len(pts)), length)
    within = np.arange(len(obs_point)) - np.repeat(np.cumsum(length) - length, length)
    obs_pose = first[obs_point] + within
    T_cw = np.linalg.inv(true)[obs_pose]
    Xc = np.einsum("oij,oj->oi", T_cw[:, :3, :3], pts[obs_point]) + T_cw[:, :3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2] + rng.normal(0, pixel_noise, (len(Xc), 2))
    jumped_track = rng.random(len(pts)) < jump
    bad = jumped_track[obs_point] & (within >= length[obs_point] // 2) & (length[obs_point] >= min_jump_views)
    uv[bad] += rng.uniform(6, 25, (int(bad.sum()), 2)) * rng.choice([-1, 1], (int(bad.sum()), 2))
    return obs_pose, obs_point, uv, bad, jumped_track


def make_sweep_problem(rng: np.random.Generator, n_views: int = 400, n_points: int = 5000,
                       min_track: int = 20, max_track: int = 300, step_m: float = 0.0002,
                       pixel_noise: float = 0.5, rot_sigma: float = 0.003, trans_sigma: float = 0.0004,
                       jump: float = 0.05, fixed_views: int = 2, init_point_noise: float = 0.0005) -> SyntheticBA:
    """A long session's final pass as a slowly moving scope makes it: ``n_views`` keyframes ``step_m`` apart
    along a sweep over tissue with relief (1080p camera), each landmark seen by a contiguous run of
    ``min_track``..``max_track`` keyframes (uniform, cut at the sweep's end) from a random first one, robot priors
    drawn from their covariance, the first ``fixed_views`` keyframes fixed (retired), ``jump`` of the tracks
    jumping 6-25 px half-way (the later half of their views corrupted)."""
    K = np.array([[1400.0, 0, 960], [0, 1400.0, 540], [0, 0, 1]])
    s = step_m * np.arange(n_views)
    eyes = np.column_stack([s, 0.004 * np.sin(s * 40), 0.002 * np.cos(s * 25)])
    true = np.array([look_at(e, e + np.array([0.0, 0.0, 0.1]), np.array([0, -1.0, 0])) for e in eyes])
    priors = np.array([T @ make_T(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                                  rng.normal(0, trans_sigma, 3)) for T in true])
    length = rng.integers(min_track, max_track + 1, n_points)
    first = rng.integers(0, n_views - min_track + 1, n_points)
    length = np.minimum(length, n_views - first)
    # each landmark lies near the middle of its run's views, within the part of the image it stays in
    mid = eyes[first + length // 2]
    half_travel = 0.5 * step_m * length
    spread = np.maximum(0.002, 0.05 - half_travel)[:, None]
    xy = mid[:, :2] + rng.uniform(-1.0, 1.0, (n_points, 2)) * spread * np.array([1.0, 0.6])
    pts = np.column_stack([xy, 0.1 + 0.01 * np.sin(xy[:, 0] * 70) * np.cos(xy[:, 1] * 55)])
    obs_pose, obs_point, uv, bad, jumped_track = observe_runs(rng, K, true, pts, first, length, pixel_noise, jump)
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    problem = BAProblem(K, np.arange(n_views), priors.copy(), np.arange(n_views) < fixed_views, priors,
                        np.repeat(cov[None], n_views, 0), np.arange(n_points),
                        pts + rng.normal(0, init_point_noise, pts.shape), obs_pose, obs_point, uv)
    return SyntheticBA(problem, true, pts, bad, jumped_track)
