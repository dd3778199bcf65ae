"""Bundle adjustment by Levenberg-Marquardt on the reduced camera system (the Schur complement), vectorised
with numpy: the same problem, robust schedule and answers as the GTSAM solver in ``bundle_adjustment``, a few
times faster on a local window because nothing is built per factor.

What is kept identical to GTSAM, so that the optimum and the path to it are the same:

- the variables and their retraction: a pose is T_world_camera moved by ``T Exp(xi)``, xi = (rotation,
  translation) in the body frame (GTSAM's Pose3 with full Expmap); a point moves in world coordinates;
- the factors: the pinhole reprojection error ``project(X) - uv`` (a point at or behind the camera gives the
  constant error 2 fx and no gradient, as GenericProjectionFactor does), pose priors ``Log(prior^-1 T)`` and
  rig ties ``Log(T_ij^-1 T_i^-1 T_j)`` whitened by the Cholesky factor of their information;
- the m-estimators (GTSAM's Cauchy and Tukey: weight and loss in whitened units) applied by reweighting the
  whitened system, the nonlinear error that LM compares (sum of losses), and LM's own schedule: lambda from
  1e-5 times/divided by 10, damping lambda*I on every variable, the model-fidelity test, the relative and
  absolute error tolerances, lambda's upper bound.

Fixed poses are left out of the unknowns (GTSAM holds them with a 1e-7 prior: the same to that precision).
The camera system is dense (6 free poses x 6 free poses): a local window's is a few hundred wide, a final
pass over a few hundred keyframes a few thousand. It is assembled point-chunk by point-chunk, each chunk's
landmark blocks eliminated into the rows of the poses that see it, so memory stays bounded however many
landmarks there are; it is solved by a dense Cholesky factorisation.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.spatial.transform import Rotation

from lapreco_hil.errors import ConfigError
from lapreco_hil.mapping.bundle_adjustment import BAProblem, BAResult, pixel_sigma, residual_vectors
from lapreco_hil.mapping.robust import RobustSchedule

log = logging.getLogger(__name__)

# GTSAM's LevenbergMarquardtParams defaults (the GTSAM solver sets relativeErrorTol 1e-5 too)
LAMBDA_INITIAL = 1e-5
LAMBDA_FACTOR = 10.0
LAMBDA_UPPER = 1e5
RELATIVE_ERROR_TOL = 1e-5
ABSOLUTE_ERROR_TOL = 1e-5
MIN_MODEL_FIDELITY = 1e-3
# a chunk of landmarks is eliminated at a time through a dense (3 x chunk) x (6 x its poses) block of at most
# this many entries: one chunk for a local window, bounded memory for a final pass
CHUNK_ENTRIES = 4_000_000
# terms of the series of SE(3)'s right Jacobian (exact to 1e-13 for rotations up to 1 rad)
_JR_TERMS = 16


# --- SE(3) in GTSAM's convention: xi = (omega, v), T Exp(xi) ------------------------------------------------
def hat(w: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, 3, 3) cross-product matrices."""
    z = np.zeros(len(w))
    return np.stack([np.stack([z, -w[:, 2], w[:, 1]], -1), np.stack([w[:, 2], z, -w[:, 0]], -1),
                     np.stack([-w[:, 1], w[:, 0], z], -1)], 1)


def _v_coefficients(theta: np.ndarray):
    """(1 - cos t) / t^2 and (t - sin t) / t^3, by their series near 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return a, b


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(n, 6) -> (n, 4, 4): GTSAM's Pose3::Expmap."""
    w, v = xi[:, :3], xi[:, 3:]
    W = hat(w)
    a, b = _v_coefficients(np.linalg.norm(w, axis=1))
    V = np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = Rotation.from_rotvec(w).as_matrix()
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, v)
    T[:, 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """(n, 4, 4) -> (n, 6): GTSAM's Pose3::Logmap."""
    w = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
    theta = np.linalg.norm(w, axis=1)
    W = hat(w)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    # V^-1 = I - W/2 + c W^2, c = (1 - t sin t / (2 (1 - cos t))) / t^2
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / t**2)
    Vinv = np.eye(3) - 0.5 * W + c[:, None, None] * (W @ W)
    return np.concatenate([w, np.einsum("nij,nj->ni", Vinv, T[:, :3, 3])], axis=1)


def adjoint(T: np.ndarray) -> np.ndarray:
    """(n, 4, 4) -> (n, 6, 6) adjoint in (rotation, translation) order."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    A = np.zeros((len(T), 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    A[:, 3:, :3] = hat(t) @ R
    return A


def right_jacobian_inverse(xi: np.ndarray) -> np.ndarray:
    """(n, 6) -> (n, 6, 6): d Log(E Exp(d)) / d d at E = Exp(xi) (GTSAM's Pose3::LogmapDerivative)."""
    ad = np.zeros((len(xi), 6, 6))
    ad[:, :3, :3] = hat(xi[:, :3])
    ad[:, 3:, 3:] = ad[:, :3, :3]
    ad[:, 3:, :3] = hat(xi[:, 3:])
    term = np.broadcast_to(np.eye(6), ad.shape).copy()
    Jr = term.copy()
    for k in range(1, _JR_TERMS):  # Jr = sum (-ad)^k / (k + 1)!
        term = -(term @ ad) / (k + 1)
        Jr += term
    return np.linalg.inv(Jr)


def whitening(covs: np.ndarray) -> np.ndarray:
    """(n, 6, 6) covariances -> (n, 6, 6) matrices R with R^T R = cov^-1 (whitened error = R e)."""
    if not len(covs):
        return np.zeros((0, 6, 6))
    return np.transpose(np.linalg.cholesky(np.linalg.inv(covs)), (0, 2, 1))


# --- m-estimators as GTSAM defines them (whitened units) ----------------------------------------------------
def robust_weight(loss: str, e: np.ndarray, k: float) -> np.ndarray:
    if loss == "cauchy":
        return k * k / (k * k + e * e)
    if loss == "tukey":
        return np.where(np.abs(e) <= k, (1.0 - (e / k) ** 2) ** 2, 0.0)
    if loss == "huber":
        return np.where(np.abs(e) <= k, 1.0, k / np.maximum(np.abs(e), 1e-300))
    return np.ones_like(e)


def robust_loss(loss: str, e: np.ndarray, k: float) -> np.ndarray:
    if loss == "cauchy":
        return 0.5 * k * k * np.log1p((e / k) ** 2)
    if loss == "tukey":
        return np.where(np.abs(e) <= k, k * k / 6.0 * (1.0 - (1.0 - (e / k) ** 2) ** 3), k * k / 6.0)
    if loss == "huber":
        a = np.abs(e)
        return np.where(a <= k, 0.5 * e * e, k * a - 0.5 * k * k)
    return 0.5 * e * e


# --- the problem's fixed structure ----------------------------------------------------------------------------
@dataclass
class _Layout:
    free: np.ndarray  # (F,) pose indices of the unknown poses
    obs_point: np.ndarray  # (O,) landmark of each observation
    col: np.ndarray  # (P,) column block of a pose, -1 where fixed
    obs_col: np.ndarray  # (O,) column block of the observing pose, -1 where fixed
    order: np.ndarray  # (O,) observations sorted by point
    pose_order: np.ndarray  # observations of free poses, sorted by pose
    pose_starts: np.ndarray  # (F + 1,) each free pose's range in ``pose_order``
    starts: np.ndarray  # (N + 1,) each point's range in ``order``
    to_pose: scipy.sparse.csr_matrix  # (F, O) sums observation terms into their pose
    to_point: scipy.sparse.csr_matrix  # (N, O) sums observation terms into their point
    chunks: list  # [(point slice, observation slice in ``order``, column blocks it touches)]
    unique_pairs: bool  # no pose sees a point twice (the landmark-pose blocks can be assigned, not summed)
    prior_idx: np.ndarray  # poses with a prior (free ones)
    prior_R: np.ndarray  # their whitening
    tie_R: np.ndarray


def _layout(p: BAProblem) -> _Layout:
    n_poses, n_points, n_obs = len(p.poses), len(p.points), len(p.obs_pose)
    fixed = np.asarray(p.fixed, bool)
    free = np.flatnonzero(~fixed)
    col = np.full(n_poses, -1, np.int64)
    col[free] = np.arange(len(free))
    obs_col = col[p.obs_pose]
    order = np.argsort(p.obs_point, kind="stable")
    counts = np.bincount(p.obs_point, minlength=n_points)
    starts = np.concatenate([[0], np.cumsum(counts)])
    seen = obs_col >= 0
    ones = np.ones(int(seen.sum()))
    to_pose = scipy.sparse.csr_matrix((ones, (obs_col[seen], np.flatnonzero(seen))), shape=(len(free), n_obs))
    to_point = scipy.sparse.csr_matrix((np.ones(n_obs), (p.obs_point, np.arange(n_obs))), shape=(n_points, n_obs))
    pair = p.obs_point.astype(np.int64) * (n_poses + 1) + p.obs_pose
    unique_pairs = len(np.unique(pair)) == n_obs
    # chunks of consecutive points whose dense landmark-pose block stays under CHUNK_ENTRIES
    chunks = []
    sorted_col = obs_col[order]
    j = 0
    while j < n_points:
        hi = n_points
        while True:
            cols = np.unique(sorted_col[starts[j]:starts[hi]])
            cols = cols[cols >= 0]
            if (hi - j) * 3 * 6 * len(cols) <= CHUNK_ENTRIES or hi - j <= 1:
                break
            hi = j + max(1, (hi - j) // 2)
        chunks.append((slice(j, hi), slice(starts[j], starts[hi]), cols))
        j = hi
    has_prior = np.ones(n_poses, bool) if p.has_prior is None else np.asarray(p.has_prior, bool)
    prior_idx = np.flatnonzero(has_prior & ~fixed)
    seen_sorted = np.argsort(obs_col, kind="stable")
    pose_order = seen_sorted[obs_col[seen_sorted] >= 0]
    pose_starts = np.concatenate([[0], np.cumsum(np.bincount(obs_col[seen], minlength=len(free)))])
    return _Layout(free, np.asarray(p.obs_point, np.int64), col, obs_col, order, pose_order, pose_starts, starts,
                   to_pose, to_point, chunks, unique_pairs, prior_idx, whitening(np.asarray(p.prior_covs)[prior_idx]), whitening(np.asarray(p.tie_covs)))


# --- residuals, Jacobians, errors -------------------------------------------------------------------------------
@dataclass
class _Linear:
    """One linearisation: the normal equations' blocks (landmark-pose blocks per observation)."""

    Hcc: np.ndarray  # (6F, 6F) pose block, priors and ties included
    gc: np.ndarray  # (6F,)
    Hpp: np.ndarray  # (N, 3, 3)
    gp: np.ndarray  # (N, 3)
    W: np.ndarray  # (O, 3, 6) s Jp^T Jc per observation (zero where the pose is fixed)
    error0: float  # the linear system's error at zero (0.5 |b|^2, the weighted one LM compares with)


def _camera_points(p: BAProblem, poses: np.ndarray, points: np.ndarray):
    """Each observation's landmark in its camera's frame (O, 3), and the world-to-camera rotation (O, 3, 3)."""
    Rcw = np.transpose(poses[:, :3, :3], (0, 2, 1))
    t_cw = -np.einsum("nij,nj->ni", Rcw, poses[:, :3, 3])
    Rc = Rcw[p.obs_pose]
    Xw = points[p.obs_point]
    Xc = (Rc[:, :, 0] * Xw[:, 0, None] + Rc[:, :, 1] * Xw[:, 1, None] + Rc[:, :, 2] * Xw[:, 2, None]
          + t_cw[p.obs_pose])
    return Xc, Rc


def _project(p: BAProblem, Xc: np.ndarray):
    """Residuals (O, 2), normalised coordinates and which points are in front; behind the camera the residual
    is GTSAM's constant 2 fx (and its Jacobians are zero)."""
    z = Xc[:, 2]
    front = z > 0
    zs = np.where(front, z, 1.0)
    xn, yn = Xc[:, 0] / zs, Xc[:, 1] / zs
    r = np.empty((len(z), 2))
    r[:, 0] = p.K[0, 0] * xn + p.K[0, 2] - p.obs_uv[:, 0]
    r[:, 1] = p.K[1, 1] * yn + p.K[1, 2] - p.obs_uv[:, 1]
    r[~front] = 2.0 * p.K[0, 0]
    return r, xn, yn, zs, front


def _reprojection(p: BAProblem, poses: np.ndarray, points: np.ndarray):
    """Residuals (O, 2) and their Jacobians wrt the pose (O, 2, 6) and the point (O, 2, 3)."""
    Xc, Rc = _camera_points(p, poses, points)
    r, xn, yn, zs, front = _project(p, Xc)
    fx, fy = p.K[0, 0], p.K[1, 1]
    a, b = fx / zs, fy / zs
    Jc = np.empty((len(zs), 2, 6))
    Jc[:, 0, 0] = fx * xn * yn
    Jc[:, 0, 1] = -fx * (1.0 + xn * xn)
    Jc[:, 0, 2] = fx * yn
    Jc[:, 0, 3] = -a
    Jc[:, 0, 4] = 0.0
    Jc[:, 0, 5] = a * xn
    Jc[:, 1, 0] = fy * (1.0 + yn * yn)
    Jc[:, 1, 1] = -Jc[:, 0, 0] * (fy / fx)
    Jc[:, 1, 2] = -fy * xn
    Jc[:, 1, 3] = 0.0
    Jc[:, 1, 4] = -b
    Jc[:, 1, 5] = b * yn
    Jp = np.empty((len(zs), 2, 3))
    Jp[:, 0] = a[:, None] * (Rc[:, 0] - xn[:, None] * Rc[:, 2])
    Jp[:, 1] = b[:, None] * (Rc[:, 1] - yn[:, None] * Rc[:, 2])
    if not front.all():
        Jc[~front] = 0.0
        Jp[~front] = 0.0
    return r, Jc, Jp


def _pose_factors(p: BAProblem, lay: _Layout, poses: np.ndarray, jacobians: bool):
    """Whitened prior and tie errors, and (optionally) their Jacobians: [(error (n, 6), [(pose idx (n,),
    J (n, 6, 6))])]."""
    out = []
    if len(lay.prior_idx):
        i = lay.prior_idx
        e = se3_log(np.linalg.inv(p.prior_poses[i]) @ poses[i])
        J = lay.prior_R @ right_jacobian_inverse(e) if jacobians else None
        out.append((np.einsum("nij,nj->ni", lay.prior_R, e), [(i, J)]))
    if len(p.tie_pairs):
        i, j = p.tie_pairs[:, 0], p.tie_pairs[:, 1]
        B = np.linalg.inv(poses[i]) @ poses[j]
        e = se3_log(np.linalg.inv(p.tie_T) @ B)
        blocks = []
        if jacobians:
            Jj = lay.tie_R @ right_jacobian_inverse(e)
            blocks = [(i, -Jj @ adjoint(np.linalg.inv(B))), (j, Jj)]
        out.append((np.einsum("nij,nj->ni", lay.tie_R, e), blocks))
    return out


def _error(p: BAProblem, lay: _Layout, poses, points, sigma: float, loss: str, k: float) -> float:
    """GTSAM's graph.error: the sum of the reprojection losses plus 0.5 |whitened error|^2 of priors, ties."""
    r = _project(p, _camera_points(p, poses, points)[0])[0]
    e = np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2) / sigma
    total = float(np.sum(robust_loss(loss, e, k)))
    for err, _ in _pose_factors(p, lay, poses, jacobians=False):
        total += 0.5 * float(np.sum(err * err))
    return total


def _linearize(p: BAProblem, lay: _Layout, poses, points, sigma: float, loss: str, k: float) -> _Linear:
    r, Jc, Jp = _reprojection(p, poses, points)
    r2 = r[:, 0] ** 2 + r[:, 1] ** 2
    s = robust_weight(loss, np.sqrt(r2) / sigma, k) / sigma**2  # whitening and the robust reweighting, squared
    sJpT = (s[:, None, None] * Jp).transpose(0, 2, 1)
    n_free = len(lay.free)
    error0 = 0.5 * float(np.sum(s * r2))
    Hpp = (lay.to_point @ (sJpT @ Jp).reshape(-1, 9)).reshape(-1, 3, 3)
    gp = lay.to_point @ (sJpT[:, :, 0] * r[:, 0, None] + sJpT[:, :, 1] * r[:, 1, None])
    W = sJpT @ Jc
    W[lay.obs_col < 0] = 0.0
    Hcc = np.zeros((6 * n_free, 6 * n_free))
    gc = np.zeros(6 * n_free)
    if n_free:
        # each pose's block by one product of its whitened Jacobian rows
        Jw = (np.sqrt(s)[:, None, None] * Jc)[lay.pose_order].reshape(-1, 6)
        for c in range(n_free):
            rows = Jw[2 * lay.pose_starts[c]:2 * lay.pose_starts[c + 1]]
            Hcc[6 * c:6 * c + 6, 6 * c:6 * c + 6] = rows.T @ rows
        sr = s[:, None] * r
        gc[:] = (lay.to_pose @ (Jc[:, 0] * sr[:, 0, None] + Jc[:, 1] * sr[:, 1, None])).ravel()
    H4 = Hcc.reshape(n_free, 6, n_free, 6)  # a view: (pose, row, pose, column)
    g2 = gc.reshape(n_free, 6)
    for err, jac in _pose_factors(p, lay, poses, jacobians=True):
        error0 += 0.5 * float(np.sum(err * err))
        for idx_a, Ja in jac:
            ca = lay.col[idx_a]
            ok = ca >= 0
            np.add.at(g2, ca[ok], np.einsum("nji,nj->ni", Ja[ok], err[ok]))
            for idx_b, Jb in jac:
                cb = lay.col[idx_b]
                both = ok & (cb >= 0)
                np.add.at(H4, (ca[both], slice(None), cb[both], slice(None)),
                          np.transpose(Ja[both], (0, 2, 1)) @ Jb[both])
    return _Linear(Hcc, gc, Hpp, gp, W, error0)


# --- one damped step ------------------------------------------------------------------------------------------------
def _solve_damped(lay: _Layout, lin: _Linear, lam: float, timing: dict):
    """The step (pose tangents (F, 6), point moves (N, 3)) of the damped system, landmarks eliminated;
    None where the reduced system is not positive definite."""
    t0 = time.perf_counter()
    n_points = len(lin.Hpp)
    V = lin.Hpp + lam * np.eye(3)
    try:
        # a landmark left with one weighted view is singular along its ray to the damping's precision: the
        # step fails and lambda grows (GTSAM's elimination throws IndeterminateSystemException there)
        np.linalg.cholesky(V)
        Vinv = np.linalg.inv(V)
    except np.linalg.LinAlgError:
        timing["schur_s"] += time.perf_counter() - t0
        return None
    Vg = np.einsum("nij,nj->ni", Vinv, lin.gp)
    n6 = lin.Hcc.shape[0]
    S = lin.Hcc + lam * np.eye(n6)
    rhs = -lin.gc.copy()
    order = lay.order
    for pts, obs, cols in lay.chunks:
        if not len(cols):
            continue
        o = order[obs]
        local = np.searchsorted(cols, lay.obs_col[o])
        keep = lay.obs_col[o] >= 0
        o, local = o[keep], local[keep]
        n_c = pts.stop - pts.start
        Wd = np.zeros((n_c, len(cols), 3, 6))
        row = lay.obs_point[o] - pts.start  # the chunk-local landmark
        if lay.unique_pairs:
            Wd[row, local] = lin.W[o]
        else:
            np.add.at(Wd, (row, local), lin.W[o])
        Wd = Wd.transpose(0, 2, 1, 3).reshape(n_c, 3, 6 * len(cols))
        Y = Vinv[pts] @ Wd  # (n_c, 3, 6m)
        idx = (6 * cols[:, None] + np.arange(6)).ravel()
        Wf = Wd.reshape(3 * n_c, -1)
        S[np.ix_(idx, idx)] -= Wf.T @ Y.reshape(3 * n_c, -1)
        rhs[idx] += Wf.T @ Vg[pts].ravel()
    t1 = time.perf_counter()
    timing["schur_s"] += t1 - t0
    try:
        dc = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, lower=True, check_finite=False), rhs,
                                    check_finite=False) if n6 else np.zeros(0)
    except np.linalg.LinAlgError:
        timing["solve_s"] += time.perf_counter() - t1
        return None
    if not np.all(np.isfinite(dc)):
        timing["solve_s"] += time.perf_counter() - t1
        return None
    # back-substitution: dp = V^-1 (-gp - W^T dc) per landmark
    Wdc = np.zeros((n_points, 3))
    if n6:
        dc_of_obs = np.vstack([dc.reshape(-1, 6), np.zeros((1, 6))])[lay.obs_col]  # fixed poses: row -1, zero
        Wdc = lay.to_point @ np.einsum("oij,oj->oi", lin.W, dc_of_obs)
    dp = -np.einsum("nij,nj->ni", Vinv, lin.gp + Wdc)
    timing["solve_s"] += time.perf_counter() - t1
    return dc.reshape(-1, 6), dp


# --- Levenberg-Marquardt as GTSAM runs it -------------------------------------------------------------------------
def _lm(p: BAProblem, lay: _Layout, poses, points, sigma: float, loss: str, k: float, max_iterations: int,
        timing: dict):
    """One LM run: (poses, points, error before, error after, iterations, per-iteration times)."""
    t0 = time.perf_counter()
    error = _error(p, lay, poses, points, sigma, loss, k)
    timing["error_s"] += time.perf_counter() - t0
    error_before = error
    lam, iterations, per_iteration = LAMBDA_INITIAL, 0, []
    if max_iterations == 0 or error <= 0.0:
        return poses, points, error_before, error, iterations, per_iteration
    while True:
        it_times = {k_: timing[k_] for k_ in ("linearize_s", "schur_s", "solve_s", "error_s")}
        t0 = time.perf_counter()
        lin = _linearize(p, lay, poses, points, sigma, loss, k)
        timing["linearize_s"] += time.perf_counter() - t0
        new_error, accepted = error, False
        while True:
            step = _solve_damped(lay, lin, lam, timing)
            stop_searching = success = False
            if step is not None:
                dc, dp = step
                g_dot = float(dc.ravel() @ lin.gc + dp.ravel() @ lin.gp.ravel())
                step2 = float(dc.ravel() @ dc.ravel() + dp.ravel() @ dp.ravel())
                # the undamped linear model's decrease: -g.d - d^T H d / 2, with (H + lam I) d = -g
                linear_change = -0.5 * g_dot + 0.5 * lam * step2
                if linear_change >= 0:
                    t0 = time.perf_counter()
                    trial_poses = poses.copy()
                    if len(lay.free):
                        trial_poses[lay.free] = poses[lay.free] @ se3_exp(dc)
                    trial_points = points + dp
                    trial_error = _error(p, lay, trial_poses, trial_points, sigma, loss, k)
                    timing["error_s"] += time.perf_counter() - t0
                    cost_change = error - trial_error
                    if linear_change > np.finfo(float).eps * lin.error0:
                        success = cost_change / linear_change > MIN_MODEL_FIDELITY
                    stop_searching = abs(cost_change) < RELATIVE_ERROR_TOL * error
            if success:
                poses, points, new_error, accepted = trial_poses, trial_points, trial_error, True
                lam = max(0.0, lam / LAMBDA_FACTOR)
                iterations += 1
                break
            if stop_searching:
                break
            lam *= LAMBDA_FACTOR
            if lam >= LAMBDA_UPPER:
                log.debug("LM gives up: cannot decrease the error with the largest lambda")
                break
        per_iteration.append({k_: timing[k_] - it_times[k_] for k_ in it_times})
        decrease = error - new_error
        converged = (not accepted or new_error <= 0.0 or decrease / error <= RELATIVE_ERROR_TOL
                     or decrease <= ABSOLUTE_ERROR_TOL)
        error = new_error
        if iterations >= max_iterations or converged or not np.isfinite(error):
            break
    return poses, points, error_before, error, iterations, per_iteration


def _check_device(device: str) -> None:
    if device != "cpu":
        raise ConfigError(f"Schur bundle adjustment device '{device}': only 'cpu' (numpy) is implemented")


def _new_timing() -> dict:
    return {"linearize_s": 0.0, "schur_s": 0.0, "solve_s": 0.0, "error_s": 0.0}


def solve_schur(problem: BAProblem, pixel_sigma: float = 1.0, loss: str | None = "cauchy", k: float = 2.0,
                max_iterations: int = 15, device: str = "cpu") -> BAResult:
    """``bundle_adjustment.solve`` (one LM run, fixed pixel sigma and m-estimator) on the reduced camera system."""
    _check_device(device)
    t0 = time.perf_counter()
    p = problem
    lay = _layout(p)
    timing = _new_timing()
    poses, points, e0, e1, its, per_it = _lm(p, lay, np.array(p.poses, float), np.array(p.points, float),
                                             pixel_sigma, loss or "none", k, max_iterations, timing)
    r = residual_vectors(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    residuals = np.linalg.norm(r, axis=1)
    residuals[~np.isfinite(residuals)] = np.inf
    return BAResult(poses, points, residuals, e0, e1, its, time.perf_counter() - t0,
                    {"timing": timing, "iteration_timing": per_it})


def solve_robust_schur(problem: BAProblem, schedule: RobustSchedule, device: str = "cpu") -> BAResult:
    """``bundle_adjustment.solve_robust`` on the reduced camera system: the same stages (the redundancy-corrected
    MAD scale re-estimated before each, GTSAM's Cauchy and Tukey), the same inlier threshold and ``stats`` keys
    (plus ``timing``: seconds spent linearising, forming the Schur complement, solving, evaluating the error;
    and per stage ``iteration_timing``)."""
    _check_device(device)
    t0 = time.perf_counter()
    p = problem
    lay = _layout(p)
    poses, points = np.array(p.poses, float), np.array(p.points, float)
    stages, iterations = [], 0
    initial_error = final_error = 0.0
    timing = _new_timing()
    for n, stage in enumerate(schedule.stages):
        r = residual_vectors(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
        sigma = pixel_sigma(p, r, schedule)
        stage_timing = _new_timing()
        poses, points, e0, e1, its, per_it = _lm(p, lay, poses, points, sigma, stage.loss, stage.k,
                                                 stage.iterations, stage_timing)
        for key in timing:
            timing[key] += stage_timing[key]
        final_error = e1
        if n == 0:
            initial_error = e0
        iterations += its
        stages.append({"loss": stage.loss, "sigma_px": sigma, "k": stage.k, "iterations": its,
                       "error_before": e0, "error_after": e1, "timing": stage_timing,
                       "iteration_timing": per_it})
    r = residual_vectors(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    residuals = np.linalg.norm(r, axis=1)
    residuals[~np.isfinite(residuals)] = np.inf
    sigma_final = pixel_sigma(p, r, schedule)
    threshold = schedule.inlier_threshold_px(sigma_final)
    return BAResult(poses, points, residuals, initial_error, final_error, iterations, time.perf_counter() - t0,
                    {"stages": stages, "sigma_px": sigma_final, "inlier_threshold_px": threshold,
                     "inlier_obs": residuals <= threshold, "timing": timing})
