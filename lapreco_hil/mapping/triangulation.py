"""Multi-view triangulation from known poses (linear DLT on normalised coordinates), with the checks that
decide whether a point may enter the map: cheirality, parallax angle, reprojection error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TriangulationResult:
    points: np.ndarray  # (N, 3) world
    valid: np.ndarray  # (N,) bool: passed every check
    parallax_deg: np.ndarray  # (N,) largest angle between two observing rays
    max_error_px: np.ndarray  # (N,) worst reprojection error over the observing views


def triangulate(uv: np.ndarray, seen: np.ndarray, T_world_cameras: np.ndarray, K: np.ndarray,
                min_parallax_deg: float, max_error_px: float) -> TriangulationResult:
    """uv: (N, M, 2) undistorted pixels of N tracks in M views, ``seen`` (N, M) marks which exist;
    T_world_cameras: (M, 4, 4) views shared by every track, or (N, M, 4, 4) each track's own views."""
    N, M = seen.shape
    T_wc = T_world_cameras if T_world_cameras.ndim == 4 else T_world_cameras[None]  # (N or 1, M, 4, 4)
    T_cw = np.linalg.inv(T_wc)  # world -> camera
    P = T_cw[..., :3, :]  # normalised projection matrices
    xn = (uv[..., 0] - K[0, 2]) / K[0, 0]
    yn = (uv[..., 1] - K[1, 2]) / K[1, 1]
    w = seen.astype(float)
    rows_x = (xn[..., None] * P[..., 2, :] - P[..., 0, :]) * w[..., None]
    rows_y = (yn[..., None] * P[..., 2, :] - P[..., 1, :]) * w[..., None]
    A = np.concatenate([rows_x, rows_y], axis=1)  # (N, 2M, 4)
    _, _, vh = np.linalg.svd(A, full_matrices=False)  # (the full U of every track would be (2M, 2M))
    Xh = vh[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    finite = np.all(np.isfinite(X), axis=1) & (np.abs(Xh[:, 3]) > 1e-12)
    X = np.where(finite[:, None], X, 0.0)
    # depth and reprojection in every view
    R_cw = T_cw[..., :3, :3]
    if len(T_cw) == N and T_world_cameras.ndim == 4:
        Xc = np.einsum("nmij,nj->nmi", R_cw, X) + T_cw[..., :3, 3]  # (N, M, 3)
    else:
        Xc = np.einsum("mij,nj->nmi", R_cw[0], X) + T_cw[..., :3, 3]
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * Xc[..., 0] / z + K[0, 2]
        v = K[1, 1] * Xc[..., 1] / z + K[1, 2]
    err = np.hypot(u - uv[..., 0], v - uv[..., 1])
    err = np.where(seen, err, 0.0)
    cheiral = np.all(~seen | (z > 1e-4), axis=1)
    # parallax: the largest angle between rays from the observing camera centres, taken against the first
    # and the last observing ray (a track's widest baseline has one of its ends there; checking every pair
    # would cost N x M x M)
    rays = X[:, None, :] - T_wc[..., :3, 3]
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    rows = np.arange(N)
    first, last = np.argmax(seen, axis=1), M - 1 - np.argmax(seen[:, ::-1], axis=1)
    min_cos = np.ones(N)
    for end in (first, last):
        cosines = np.einsum("nmi,ni->nm", rays, rays[rows, end])
        min_cos = np.minimum(min_cos, np.where(seen, cosines, 1.0).min(axis=1))
    parallax = np.degrees(np.arccos(np.clip(min_cos, -1.0, 1.0)))
    max_err = np.where(np.isfinite(err), err, np.inf).max(axis=1)
    valid = finite & cheiral & (parallax >= min_parallax_deg) & (max_err <= max_error_px) & (seen.sum(1) >= 2)
    return TriangulationResult(X, valid, parallax, max_err)


def widest_ray_angle_deg(points: np.ndarray, obs_point: np.ndarray, centres: np.ndarray,
                         n_points: int) -> np.ndarray:
    """Per point, the widest angle (degrees) between the rays from its observations' camera ``centres`` (O, 3,
    one per row of ``obs_point``) to it: how well its views fix its depth. 0 for a point seen once or not at all.
    Exact for two views; with more, the widest angle to the first view's ray (a lower bound, enough to tell a
    wide pair from a narrow one)."""
    if len(obs_point) == 0:
        return np.zeros(n_points)
    rays = np.asarray(points)[obs_point] - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    seen, first_obs = np.unique(obs_point, return_index=True)  # each point's first observation
    first = np.full(n_points, -1)
    first[seen] = first_obs
    cos = np.sum(rays * rays[first[obs_point]], axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    widest = np.zeros(n_points)
    np.maximum.at(widest, obs_point, angle)
    return widest
