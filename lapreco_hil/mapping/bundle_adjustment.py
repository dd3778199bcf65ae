"""Bundle adjustment with GTSAM: reprojection factors under an m-estimator, robot pose priors with their
full covariance, some poses held fixed (the edge of a local window).

The problem is plain data (numpy) in, plain data out, so it can be generated apart from the solver and
tested against known answers; keys use GTSAM's symbol_shorthand (X: camera pose, L: landmark).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lapreco_hil.geometry import make_T
from lapreco_hil.mapping.robust import RobustSchedule, mad_sigma


@dataclass
class BAProblem:
    K: np.ndarray
    pose_ids: np.ndarray  # (P,) ids of every pose in the problem
    poses: np.ndarray  # (P, 4, 4) initial T_world_camera
    fixed: np.ndarray  # (P,) bool: held at its initial value
    prior_poses: np.ndarray  # (P, 4, 4) robot prior (ignored where fixed)
    prior_covs: np.ndarray  # (P, 6, 6) GTSAM tangent order (rotation, translation)
    point_ids: np.ndarray  # (N,)
    points: np.ndarray  # (N, 3) initial
    obs_pose: np.ndarray  # (O,) index into pose_ids
    obs_point: np.ndarray  # (O,) index into point_ids
    obs_uv: np.ndarray  # (O, 2) undistorted pixels
    # (P,) bool: the pose has its own prior (a stereo partner has none: it is tied to its rig's reference
    # camera by ``ties`` instead); None: every pose has one
    has_prior: np.ndarray | None = None
    # rig ties: (T, 2) pose indices (reference camera i, partner j), T_i_j (T, 4, 4) and its covariance
    # (T, 6, 6), held within the calibrated uncertainty of the rig's extrinsics
    tie_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    tie_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    tie_covs: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 6)))


@dataclass
class BAResult:
    poses: np.ndarray
    points: np.ndarray
    residuals_px: np.ndarray  # (O,) reprojection error norm per observation
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    stats: dict = field(default_factory=dict)


_FIXED_NOISE = gtsam.noiseModel.Isotropic.Sigma(6, 1e-7)


def pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3])


def matrix(p: gtsam.Pose3) -> np.ndarray:
    return make_T(p.rotation().matrix(), p.translation())


def robust_pixel_noise(pixel_sigma: float, loss: str | None, k: float) -> gtsam.noiseModel.Base:
    base = gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma)
    if loss is None:
        return base
    estimators = {
        "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
        "tukey": gtsam.noiseModel.mEstimator.Tukey,
        "huber": gtsam.noiseModel.mEstimator.Huber,
    }
    return gtsam.noiseModel.Robust.Create(estimators[loss].Create(k), base)


def _build(problem: BAProblem, noise: gtsam.noiseModel.Base):
    p = problem
    cal = gtsam.Cal3_S2(p.K[0, 0], p.K[1, 1], 0.0, p.K[0, 2], p.K[1, 2])
    graph = gtsam.NonlinearFactorGraph()
    for i, pid in enumerate(p.pose_ids):
        key = X(int(pid))
        if p.fixed[i]:
            # a very tight prior rather than NonlinearEqualityPose3, which made LM much slower (docs/benchmarks.md)
            graph.add(gtsam.PriorFactorPose3(key, pose3(p.poses[i]), _FIXED_NOISE))
        elif p.has_prior is None or p.has_prior[i]:
            graph.add(gtsam.PriorFactorPose3(key, pose3(p.prior_poses[i]),
                                             gtsam.noiseModel.Gaussian.Covariance(p.prior_covs[i])))
    for (i, j), T_ij, cov in zip(p.tie_pairs.tolist(), p.tie_T, p.tie_covs):
        graph.add(gtsam.BetweenFactorPose3(X(int(p.pose_ids[i])), X(int(p.pose_ids[j])), pose3(T_ij),
                                           gtsam.noiseModel.Gaussian.Covariance(cov)))
    n_priors = graph.size()
    pose_keys = [X(int(pid)) for pid in p.pose_ids]
    point_keys = [L(int(lid)) for lid in p.point_ids]
    for o in range(len(p.obs_pose)):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(
            p.obs_uv[o], noise, pose_keys[p.obs_pose[o]], point_keys[p.obs_point[o]], cal, False, False))
    return graph, pose_keys, point_keys, n_priors


def _values(problem: BAProblem, poses: np.ndarray, points: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    for i, pid in enumerate(problem.pose_ids):
        values.insert(X(int(pid)), pose3(poses[i]))
    for j, lid in enumerate(problem.point_ids):
        values.insert(L(int(lid)), gtsam.Point3(*points[j]))
    return values


def _unpack(result: gtsam.Values, pose_keys, point_keys, fallback_poses):
    poses = np.array([matrix(result.atPose3(k)) for k in pose_keys]) if pose_keys else fallback_poses.copy()
    points = np.array([result.atPoint3(k) for k in point_keys]).reshape(-1, 3)
    return poses, points


def _points_first(pose_keys, point_keys) -> gtsam.Ordering:
    """Eliminate landmarks before poses (the Schur-complement order), no slower than COLAMD here."""
    ordering = gtsam.Ordering()
    for k in point_keys:
        ordering.push_back(k)
    for k in pose_keys:
        ordering.push_back(k)
    return ordering


# Above this many poses the linear systems are solved by block-Jacobi preconditioned conjugate gradients: a
# direct solve eliminates each landmark into a dense factor over all the poses that see it, which long tracks
# over hundreds of keyframes make huge (the measurements: docs/benchmarks.md).
ITERATIVE_ABOVE_POSES = 50


def _lm(graph, values, iterations: int, ordering: gtsam.Ordering | None = None, iterative: bool = False):
    params = gtsam.LevenbergMarquardtParams()
    if iterative:
        params.setLinearSolverType("ITERATIVE")
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        params.setIterativeParams(pcg)
    elif ordering is not None:
        params.setOrdering(ordering)
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(1e-5)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, int(optimizer.iterations())


def solve(problem: BAProblem, pixel_sigma: float = 1.0, loss: str | None = "cauchy", k: float = 2.0,
          max_iterations: int = 15) -> BAResult:
    """One Levenberg-Marquardt run with a fixed pixel sigma and m-estimator (k in units of sigma)."""
    t0 = time.perf_counter()
    p = problem
    graph, pose_keys, point_keys, _ = _build(p, robust_pixel_noise(pixel_sigma, loss, k))
    values = _values(p, p.poses, p.points)
    initial_error = graph.error(values)
    result, iterations = _lm(graph, values, max_iterations, _points_first(pose_keys, point_keys))
    poses, points = _unpack(result, pose_keys, point_keys, p.poses)
    residuals = reprojection_residuals(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    return BAResult(poses, points, residuals, float(initial_error), float(graph.error(result)), iterations,
                    time.perf_counter() - t0)


def residual_vectors(K, poses, points, obs_pose, obs_point, obs_uv) -> np.ndarray:
    """(O, 2) reprojection error vectors (NaN behind the camera)."""
    T_cw = np.linalg.inv(poses)[obs_pose]
    Xc = np.einsum("oij,oj->oi", T_cw[:, :3, :3], points[obs_point]) + T_cw[:, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]
    r = np.column_stack([u - obs_uv[:, 0], v - obs_uv[:, 1]])
    r[Xc[:, 2] <= 0] = np.nan
    return r


def reprojection_residuals(K, poses, points, obs_pose, obs_point, obs_uv) -> np.ndarray:
    """(O,) reprojection error norms; inf behind the camera."""
    e = np.linalg.norm(residual_vectors(K, poses, points, obs_pose, obs_point, obs_uv), axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def redundancy(problem: BAProblem) -> float:
    """The share of the residual components that the fit leaves free: (2 O - 3 N) / 2 O. Each landmark's three
    coordinates absorb part of its own observations' noise, so the residuals of a fit are smaller than the
    pixel noise by sqrt(redundancy): a point seen twice keeps a quarter of it. The scale is divided by it."""
    n_components = 2 * len(problem.obs_pose)
    free = n_components - 3 * len(problem.point_ids)
    return max(free, 1) / max(n_components, 1)


def pixel_sigma(problem: BAProblem, r: np.ndarray, schedule: RobustSchedule) -> float:
    """The pixel-noise scale of residual vectors ``r`` (MAD, corrected for the fit's redundancy), kept between
    the schedule's floor and ceiling."""
    sigma = mad_sigma(r) / np.sqrt(redundancy(problem))
    return float(min(max(sigma, schedule.sigma_floor_px), schedule.sigma_ceiling_px))


def solve_robust(problem: BAProblem, schedule: RobustSchedule) -> BAResult:
    """The seed's schedule: each stage re-estimates the (redundancy-corrected) MAD scale from the current
    residuals, whitens the reprojection errors with it and runs LM under its m-estimator (Cauchy, then Tukey).
    Observations beyond the last stage's threshold are the outliers (``stats['inlier_obs']``)."""
    t0 = time.perf_counter()
    p = problem
    poses, points = p.poses.copy(), p.points.copy()
    stages, iterations = [], 0
    initial_error = final_error = 0.0
    sigma = 1.0
    for n, stage in enumerate(schedule.stages):
        r = residual_vectors(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
        sigma = pixel_sigma(p, r, schedule)
        noise = robust_pixel_noise(sigma, None if stage.loss == "none" else stage.loss, stage.k)
        graph, pose_keys, point_keys, _ = _build(p, noise)
        values = _values(p, poses, points)
        error0 = graph.error(values)
        result, its = _lm(graph, values, stage.iterations, _points_first(pose_keys, point_keys),
                          iterative=len(pose_keys) > ITERATIVE_ABOVE_POSES)
        poses, points = _unpack(result, pose_keys, point_keys, poses)
        final_error = float(graph.error(result))
        if n == 0:
            initial_error = float(error0)
        iterations += its
        stages.append({"loss": stage.loss, "sigma_px": sigma, "k": stage.k, "iterations": its,
                       "error_before": float(error0), "error_after": final_error})
    r = residual_vectors(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    residuals = np.linalg.norm(r, axis=1)
    residuals[~np.isfinite(residuals)] = np.inf
    sigma_final = pixel_sigma(p, r, schedule)
    threshold = schedule.inlier_threshold_px(sigma_final)
    return BAResult(poses, points, residuals, initial_error, final_error, iterations, time.perf_counter() - t0,
                    {"stages": stages, "sigma_px": sigma_final, "inlier_threshold_px": threshold,
                     "inlier_obs": residuals <= threshold})


def solve_gnc(problem: BAProblem, pixel_sigma: float, loss: str = "tls", inlier_threshold_px: float = 3.0,
              max_iterations: int = 20) -> BAResult:
    """GTSAM's graduated non-convexity (Yang et al. 2020) over the reprojection factors, robot priors known
    inliers: the alternative the seed's schedule is compared with."""
    t0 = time.perf_counter()
    p = problem
    graph, pose_keys, point_keys, n_priors = _build(p, gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma))
    values = _values(p, p.poses, p.points)
    initial_error = graph.error(values)
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.TLS if loss == "tls" else gtsam.GncLossType.GM)
    params.setKnownInliers(list(range(n_priors)))
    params.setMaxIterations(max_iterations)
    optimizer = gtsam.GncLMOptimizer(graph, values, params)
    # threshold on the whitened squared error of one factor (0.5 ||e/sigma||^2)
    optimizer.setInlierCostThresholds(0.5 * (inlier_threshold_px / pixel_sigma) ** 2)
    result = optimizer.optimize()
    poses, points = _unpack(result, pose_keys, point_keys, p.poses)
    residuals = reprojection_residuals(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    weights = np.asarray(optimizer.getWeights())[n_priors:]
    return BAResult(poses, points, residuals, float(initial_error), float(graph.error(result)), -1,
                    time.perf_counter() - t0, {"inlier_obs": weights > 0.5})
