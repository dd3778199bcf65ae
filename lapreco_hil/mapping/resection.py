"""Pose-only refinement of one frame against the map: its robot prior (full covariance) plus its observations
of known landmarks under Tukey's biweight with the map's MAD scale. This gives every frame, not only the
keyframes, a refined pose, as soon as it is seen.

One 6-DoF pose is small enough that a vectorised Gauss-Newton (IRLS) beats building a GTSAM graph per frame.
The pose is perturbed on the right, T = T0 Exp(xi), xi = (omega, v), as GTSAM's Pose3 is, so the prior's
covariance is in the same tangent space.
"""

from __future__ import annotations

import numpy as np

from ..geometry import Rotation, make_T
from .robust import RobustSchedule, irls_weight, mad_sigma


def _exp(xi: np.ndarray) -> np.ndarray:
    w, v = xi[:3], xi[3:]
    # first-order translation part is enough for the tiny steps of a converging Gauss-Newton
    return make_T(Rotation.from_rotvec(w).as_matrix(), v)


def _log(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


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
    w = np.zeros(len(points))
    for stage in schedule.stages:
        r, _ = _residuals(T, points, uv, K)
        sigma = min(mad_sigma(r, sigma_px), schedule.sigma_ceiling_px)
        T, w = _gauss_newton(T, T_prior, info, points, uv, K, stage.loss, stage.k * sigma, sigma, stage.iterations)
    return T, w > 0


def _residuals(T, points, uv, K):
    R, t = T[:3, :3], T[:3, 3]
    Xc = (points - t) @ R  # camera frame: R^T (X - t)
    front = Xc[:, 2] > 1e-6
    zs = np.where(front, Xc[:, 2], 1.0)
    r = np.column_stack([K[0, 0] * Xc[:, 0] / zs + K[0, 2] - uv[:, 0], K[1, 1] * Xc[:, 1] / zs + K[1, 2] - uv[:, 1]])
    r[~front] = np.nan
    return r, Xc


def _gauss_newton(T, T_prior, info, points, uv, K, loss, threshold, sigma_px, iterations):
    fx, fy = K[0, 0], K[1, 1]
    w = np.ones(len(points))
    for _ in range(iterations):
        r, Xc = _residuals(T, points, uv, K)
        front = np.isfinite(r[:, 0])
        r = np.nan_to_num(r)
        zs = np.where(front, Xc[:, 2], 1.0)
        e = np.linalg.norm(r, axis=1)
        w = np.where(front, irls_weight(loss, e, threshold), 0.0) / sigma_px**2
        # chain rule: d(pixel)/d(Xc), and for T Exp(xi): dXc/d(omega) = [Xc]_x, dXc/dv = -I
        du = np.zeros((len(points), 2, 3))
        du[:, 0, 0] = fx / zs
        du[:, 0, 2] = -fx * Xc[:, 0] / zs**2
        du[:, 1, 1] = fy / zs
        du[:, 1, 2] = -fy * Xc[:, 1] / zs**2
        skew = np.zeros((len(points), 3, 6))
        x, y, zz = Xc[:, 0], Xc[:, 1], Xc[:, 2]
        skew[:, 0, 1], skew[:, 0, 2] = -zz, y
        skew[:, 1, 0], skew[:, 1, 2] = zz, -x
        skew[:, 2, 0], skew[:, 2, 1] = -y, x
        skew[:, :, 3:] = -np.eye(3)
        J = du @ skew  # (N, 2, 6)
        H = np.einsum("n,nai,naj->ij", w, J, J)
        g = np.einsum("n,nai,na->i", w, J, r)
        # prior: residual log(T_prior^-1 T), Jacobian ~ identity near the prior
        rp = _log(np.linalg.inv(T_prior) @ T)
        H += info
        g += info @ rp
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = T @ _exp(step)
        if np.linalg.norm(step) < 1e-9:
            break
    return T, w > 0
