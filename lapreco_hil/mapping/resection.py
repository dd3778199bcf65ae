"""Pose-only refinement of one frame against the map: its robot prior (full covariance) plus its observations
of known landmarks under Tukey's biweight with the map's MAD scale. This gives every frame, not only the
keyframes, a refined pose, as soon as it is seen.

One 6-DoF pose is small enough that a vectorised Gauss-Newton (IRLS) beats building a GTSAM graph per frame.
The pose is perturbed on the right, T = T0 Exp(xi), xi = (omega, v), as GTSAM's Pose3 is, so the prior's
covariance is in the same tangent space.
"""

from __future__ import annotations

import numpy as np

from lapreco_hil.geometry import Rotation, make_T
from lapreco_hil.mapping.robust import MAD_TO_SIGMA, RobustSchedule, irls_weight, mad_sigma

# a stage stops when its step is shorter than this (rad, m): a micrometre, a hundredth of what a pixel resolves at
# laparoscopic distances; a tighter tolerance ran every stage to its iteration limit for no change in the pose
STEP_TOL = 1e-6


def _exp(xi: np.ndarray) -> np.ndarray:
    w, v = xi[:3], xi[3:]
    # Rodrigues by hand (scipy's Rotation costs more than the whole step here); the first-order translation
    # part is enough for the tiny steps of a converging Gauss-Newton
    theta = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        R = np.eye(3) + W
    else:
        R = np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * (W @ W)
    return make_T(R, v)


def _log(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    if cos > 0.999:  # small angles (a prior and its refinement differ by milliradians): no division by sin
        w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    else:
        w = Rotation.from_matrix(R).as_rotvec()
    return np.concatenate([w, T[:3, 3]])


def refine_pose(T_prior: np.ndarray, cov: np.ndarray, points: np.ndarray, uv: np.ndarray, K: np.ndarray,
                sigma_px: float, schedule: RobustSchedule = RobustSchedule(),
                T_init: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Refined T_world_camera and the inlier mask of the observations (N landmarks ``points`` seen at ``uv``).

    The seed's schedule again: Cauchy first (converges from a start millimetres off), then Tukey; each stage's
    scale is the MAD of the current residuals, never below ``sigma_px`` (the map's pixel noise)."""
    T = (T_prior if T_init is None else T_init).copy()
    if len(points) < 6:
        return T, np.zeros(len(points), bool)
    info = np.linalg.inv(cov)
    prior_inv = np.linalg.inv(T_prior)
    w = np.zeros(len(points))
    for stage in schedule.stages:
        at_T = _residuals(T, points, uv, K)  # the stage's scale, and its first step's residuals
        sigma = min(mad_sigma(at_T[0], sigma_px), schedule.sigma_ceiling_px)
        T, w = _gauss_newton(T, prior_inv, info, points, uv, K, stage.loss, stage.k * sigma, sigma, stage.iterations,
                             at_T)
    return T, w > 0


def _residuals(T, points, uv, K, have=None):
    """Residuals (..., P, 2) of one frame (T (4, 4), points (P, 3)) or a batch (T (F, 4, 4), points (F, P, 3)),
    NaN behind the camera (or where ``have`` is False: padding), and the camera-frame points (..., P, 3)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    Xc = np.matmul(points - t[..., None, :], R)  # camera frame: R^T (X - t)
    front = Xc[..., 2] > 1e-6
    if have is not None:
        front &= have
    zs = np.where(front, Xc[..., 2], 1.0)
    r = np.empty(Xc.shape[:-1] + (2,))
    r[..., 0] = K[0, 0] * Xc[..., 0] / zs + K[0, 2] - uv[..., 0]
    r[..., 1] = K[1, 1] * Xc[..., 1] / zs + K[1, 2] - uv[..., 1]
    r[~front] = np.nan
    return r, Xc


def _jacobians(Xc, front, K):
    """d(pixel residual)/d(xi) of T Exp(xi), (..., P, 2, 6). The chain rule: d(pixel)/d(Xc) = [[a, 0, b], [0, c,
    d]], and dXc/d(omega) = [Xc]_x, dXc/dv = -I; multiplied out by hand (no (P, 3, 6) temporaries)."""
    fx, fy = K[0, 0], K[1, 1]
    x, y, zz = Xc[..., 0], Xc[..., 1], Xc[..., 2]
    zs = np.where(front, zz, 1.0)
    a, b = fx / zs, -fx * x / zs**2
    c, d = fy / zs, -fy * y / zs**2
    J = np.empty(x.shape + (2, 6))
    Ju, Jv = J[..., 0, :], J[..., 1, :]
    np.multiply(-b, y, out=Ju[..., 0])
    Ju[..., 1] = -a * zz + b * x
    np.multiply(a, y, out=Ju[..., 2])
    np.negative(a, out=Ju[..., 3])
    Ju[..., 4] = 0.0
    np.negative(b, out=Ju[..., 5])
    Jv[..., 0] = c * zz - d * y
    np.multiply(d, x, out=Jv[..., 1])
    np.multiply(-c, x, out=Jv[..., 2])
    Jv[..., 3] = 0.0
    np.negative(c, out=Jv[..., 4])
    np.negative(d, out=Jv[..., 5])
    return J


def _gauss_newton(T, prior_inv, info, points, uv, K, loss, threshold, sigma_px, iterations, at_T=None):
    """``iterations`` IRLS steps from T (``prior_inv``: the prior's inverse; ``at_T``: ``_residuals`` at T, if
    known). Every live frame runs this: each step in as few numpy calls as its arithmetic allows."""
    w = np.ones(len(points))
    for _ in range(iterations):
        r, Xc = _residuals(T, points, uv, K) if at_T is None else at_T
        at_T = None
        front = np.isfinite(r[:, 0])
        r = np.where(front[:, None], r, 0.0)  # (a fresh array: the caller's residuals keep their NaN)
        e = np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1])  # (np.linalg.norm's own sum, bit for bit)
        w = np.where(front, irls_weight(loss, e, threshold), 0.0) / sigma_px**2
        J = _jacobians(Xc, front, K).reshape(-1, 6)  # (2N, 6): rows u, v of each observation
        wJ = J * np.repeat(w, 2)[:, None]
        H = wJ.T @ J  # a matrix product (BLAS), not a three-operand einsum: far faster
        g = wJ.T @ r.ravel()
        # prior: residual log(T_prior^-1 T), Jacobian ~ identity near the prior
        rp = _log(prior_inv @ T)
        H += info
        g += info @ rp
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = T @ _exp(step)
        if np.linalg.norm(step) < STEP_TOL:
            break
    return T, w > 0


# frames refined together by ``refine_poses``: their padded arrays stay a few tens of megabytes
BATCH_FRAMES = 256


def refine_poses(T_priors: np.ndarray, covs: np.ndarray, points: list[np.ndarray], uvs: list[np.ndarray],
                 K: np.ndarray, sigma_px: float, schedule: RobustSchedule = RobustSchedule(),
                 T_inits: np.ndarray | None = None) -> np.ndarray:
    """``refine_pose`` for many frames at once (the map's end refines every frame not yet final: thousands of
    them one by one took most of a 2-minute 1080p60 run's end): the same steps, stopping rules and answers,
    vectorised over frames. Frame i sees ``points[i]`` at ``uvs[i]``. Returns the refined T_world_camera.
    ``refine_pose`` stays for one frame at a time (the live mapper's every frame): these padded arrays cost it
    half as much again."""
    T_priors = np.asarray(T_priors, float)
    out = (T_priors if T_inits is None else np.asarray(T_inits, float)).copy()
    for start in range(0, len(out), BATCH_FRAMES):
        sl = slice(start, start + BATCH_FRAMES)
        out[sl] = _refine_batch(T_priors[sl], np.asarray(covs[sl], float), points[sl], uvs[sl], K, sigma_px,
                                schedule, out[sl])
    return out


def _refine_batch(T_priors, covs, points, uvs, K, sigma_px, schedule, T):
    n = np.array([len(p) for p in points])
    solved = np.flatnonzero(n >= 6)  # fewer: the start stays (refine_pose's rule)
    if not len(solved):
        return T
    P = int(n[solved].max())
    X = np.zeros((len(solved), P, 3))
    uv = np.zeros((len(solved), P, 2))
    have = np.zeros((len(solved), P), bool)
    for row, i in enumerate(solved.tolist()):
        X[row, :n[i]], uv[row, :n[i]], have[row, :n[i]] = points[i], uvs[i], True
    Ts, priors = T[solved].copy(), T_priors[solved]
    info = np.linalg.inv(covs[solved])
    for stage in schedule.stages:
        r, _ = _residuals(Ts, X, uv, K, have)
        sigma = np.minimum(_batch_mad_sigma(r, sigma_px), schedule.sigma_ceiling_px)
        Ts = _batch_gauss_newton(Ts, priors, info, X, uv, have, K, stage.loss, stage.k * sigma, sigma,
                                 stage.iterations)
    T = T.copy()
    T[solved] = Ts
    return T


def _batch_mad_sigma(r, floor):
    """``mad_sigma`` of each frame's residual components (NaN ignored)."""
    e = r.reshape(len(r), -1)
    with np.errstate(all="ignore"):
        median = np.nanmedian(e, axis=1)
        mad = np.nanmedian(np.abs(e - median[:, None]), axis=1)
    sigma = np.maximum(MAD_TO_SIGMA * mad, floor)
    return np.where(np.isfinite(mad), sigma, max(floor, 1.0))


def _batch_log(T):
    R = T[:, :3, :3]
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    w = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    wide = cos <= 0.999
    if wide.any():
        w[wide] = Rotation.from_matrix(R[wide]).as_rotvec()
    return np.concatenate([w, T[:, :3, 3]], axis=1)


def _batch_exp(xi):
    w, v = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(w, axis=1)
    W = np.zeros((len(xi), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    safe = np.where(theta < 1e-12, 1.0, theta)
    a = np.where(theta < 1e-12, 1.0, np.sin(safe) / safe)
    b = np.where(theta < 1e-12, 0.0, (1 - np.cos(safe)) / safe**2)
    out = np.tile(np.eye(4), (len(xi), 1, 1))
    out[:, :3, :3] = np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)
    out[:, :3, 3] = v
    return out


def _batch_gauss_newton(T, T_prior, info, X, uv, have, K, loss, threshold, sigma_px, iterations):
    F, P = have.shape
    active = np.ones(F, bool)
    prior_inv = np.linalg.inv(T_prior)
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        r, Xc = _residuals(T[idx], X[idx], uv[idx], K, have[idx])
        front = np.isfinite(r[..., 0])
        r = np.nan_to_num(r)
        e = np.linalg.norm(r, axis=-1)
        w = np.where(front, irls_weight(loss, e, threshold[idx, None]), 0.0) / sigma_px[idx, None] ** 2
        J = _jacobians(Xc, front, K).reshape(len(idx), 2 * P, 6)
        wJ = J * np.repeat(w, 2, axis=1)[..., None]
        H = np.matmul(wJ.transpose(0, 2, 1), J) + info[idx]
        rp = _batch_log(prior_inv[idx] @ T[idx])
        g = (np.matmul(wJ.transpose(0, 2, 1), r.reshape(len(idx), -1, 1)) + np.matmul(info[idx], rp[..., None]))[..., 0]
        try:
            step = -np.linalg.solve(H, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        T[idx] = T[idx] @ _batch_exp(step)
        active[idx[np.linalg.norm(step, axis=1) < STEP_TOL]] = False
    return T
