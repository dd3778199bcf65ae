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

from ..geometry import make_T


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


def reprojection_residuals(K: np.ndarray, poses: np.ndarray, points: np.ndarray, obs_pose: np.ndarray,
                           obs_point: np.ndarray, obs_uv: np.ndarray) -> np.ndarray:
    T_cw = np.linalg.inv(poses)[obs_pose]
    Xc = np.einsum("oij,oj->oi", T_cw[:, :3, :3], points[obs_point]) + T_cw[:, :3, 3]
    z = np.where(np.abs(Xc[:, 2]) > 1e-9, Xc[:, 2], 1e-9)
    u = K[0, 0] * Xc[:, 0] / z + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / z + K[1, 2]
    r = np.hypot(u - obs_uv[:, 0], v - obs_uv[:, 1])
    return np.where(Xc[:, 2] > 0, r, np.inf)


def solve(problem: BAProblem, pixel_sigma: float = 1.0, loss: str | None = "cauchy", k: float = 2.0,
          max_iterations: int = 15) -> BAResult:
    t0 = time.perf_counter()
    p = problem
    cal = gtsam.Cal3_S2(p.K[0, 0], p.K[1, 1], 0.0, p.K[0, 2], p.K[1, 2])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, pid in enumerate(p.pose_ids):
        key = X(int(pid))
        values.insert(key, pose3(p.poses[i]))
        if p.fixed[i]:
            # a very tight prior rather than NonlinearEqualityPose3, which made LM 5x slower here
            graph.add(gtsam.PriorFactorPose3(key, pose3(p.poses[i]), _FIXED_NOISE))
        else:
            graph.add(gtsam.PriorFactorPose3(key, pose3(p.prior_poses[i]),
                                             gtsam.noiseModel.Gaussian.Covariance(p.prior_covs[i])))
    for j, lid in enumerate(p.point_ids):
        values.insert(L(int(lid)), gtsam.Point3(*p.points[j]))
    noise = robust_pixel_noise(pixel_sigma, loss, k)
    pose_keys = [X(int(pid)) for pid in p.pose_ids]
    point_keys = [L(int(lid)) for lid in p.point_ids]
    for o in range(len(p.obs_pose)):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(
            p.obs_uv[o], noise, pose_keys[p.obs_pose[o]], point_keys[p.obs_point[o]], cal, False, False))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-5)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_error = graph.error(values)
    result = optimizer.optimize()
    poses = np.array([matrix(result.atPose3(k)) for k in pose_keys]) if len(pose_keys) else p.poses.copy()
    points = np.array([result.atPoint3(k) for k in point_keys]).reshape(-1, 3)
    residuals = reprojection_residuals(p.K, poses, points, p.obs_pose, p.obs_point, p.obs_uv)
    return BAResult(poses, points, residuals, float(initial_error), float(graph.error(result)),
                    int(optimizer.iterations()), time.perf_counter() - t0)
