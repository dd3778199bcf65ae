"""``lapreco bench ba``: one local-BA window of 10 keyframes x 2000 points (~20k observations) with 5% gross
outliers, solved the ways the live loop could solve it, timed on this machine."""

from __future__ import annotations

import platform
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lapreco_hil.geometry import pose_error
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping.robust import CAUCHY_K, TUKEY_C, RobustSchedule, RobustStage, mad_sigma
from lapreco_hil.mapping.synthetic import make_problem


def _pose_rms_mm(poses, truth) -> float:
    return float(1e3 * np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(poses, truth)])))


def _median_time(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _isam2_update(syn, sigma: float) -> tuple[float, float]:
    """Cost of the live loop's incremental update: 9 keyframes already in ISAM2, add the 10th keyframe's
    prior and its ~2000 reprojection factors (Cauchy at the running MAD scale) and update."""
    p = syn.problem
    cal = gtsam.Cal3_S2(p.K[0, 0], p.K[1, 1], 0.0, p.K[0, 2], p.K[1, 2])
    noise = ba.robust_pixel_noise(sigma, "cauchy", CAUCHY_K)
    last = int(p.pose_ids.max())

    def factors(views):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i in views:
            graph.add(gtsam.PriorFactorPose3(X(i), ba.pose3(p.prior_poses[i]),
                                             gtsam.noiseModel.Gaussian.Covariance(p.prior_covs[i])))
            values.insert(X(i), ba.pose3(p.prior_poses[i]))
        sel = np.isin(p.obs_pose, views)
        for o in np.flatnonzero(sel):
            graph.add(gtsam.GenericProjectionFactorCal3_S2(p.obs_uv[o], noise, X(int(p.obs_pose[o])),
                                                          L(int(p.obs_point[o])), cal, False, False))
        return graph, values

    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    graph, values = factors(list(range(last)))
    for j in range(len(p.point_ids)):
        values.insert(L(j), gtsam.Point3(*p.points[j]))
    isam.update(graph, values)
    for _ in range(3):
        isam.update()
    t0 = time.perf_counter()
    graph, values = factors([last])
    isam.update(graph, values)
    dt = time.perf_counter() - t0
    est = isam.calculateEstimate()
    poses = np.array([ba.matrix(est.atPose3(X(i))) for i in range(last + 1)])
    return dt, _pose_rms_mm(poses, syn.true_poses)


def run(repeats: int = 3, seed: int = 0) -> dict:
    syn = make_problem(np.random.default_rng(seed), n_views=10, n_points=2000, jump=0.02, highlight=0.015,
                       instrument=0.015)
    p = syn.problem
    rows = {}
    prior = _pose_rms_mm(p.prior_poses, syn.true_poses)
    t, r = _median_time(lambda: ba.solve(p, 1.0, "cauchy", 2.0, 15), repeats)
    rows["lm_cauchy_fixed_k_cold"] = {"s": t, "iterations": r.iterations, "pose_rms_mm": _pose_rms_mm(r.poses, syn.true_poses)}
    t, r = _median_time(lambda: ba.solve_robust(p, RobustSchedule()), repeats)
    rows["lm_mad_cauchy_tukey_cold"] = {"s": t, "iterations": r.iterations,
                                        "pose_rms_mm": _pose_rms_mm(r.poses, syn.true_poses)}
    warm = ba.BAProblem(**{**p.__dict__, "poses": r.poses.copy(), "points": r.points.copy()})
    # the next window starts from the last solution: one new keyframe from its prior
    warm.poses[-1] = p.prior_poses[-1]
    quick = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 3), RobustStage("tukey", TUKEY_C, 3)))
    t, rw = _median_time(lambda: ba.solve_robust(warm, quick), repeats)
    rows["lm_mad_cauchy_tukey_warm_3+3"] = {"s": t, "iterations": rw.iterations,
                                            "pose_rms_mm": _pose_rms_mm(rw.poses, syn.true_poses)}
    t, built = _median_time(lambda: ba._build(p, ba.robust_pixel_noise(1.0, "cauchy", 2.0)), repeats)
    rows["graph_build_only"] = {"s": t}
    graph, pose_keys, point_keys, _ = built
    values = ba._values(p, p.poses, p.points)
    t, linear = _median_time(lambda: graph.linearize(values), repeats)
    rows["linearize_once"] = {"s": t}
    for name, ordering in (("points_first", ba._points_first(pose_keys, point_keys)),
                           ("colamd", gtsam.Ordering.ColamdGaussianFactorGraph(linear))):
        t, _ = _median_time(lambda o=ordering: linear.optimize(o), repeats)
        rows[f"linear_solve_once_{name}"] = {"s": t}
    t, rg = _median_time(lambda: ba.solve_gnc(p, 0.5, "tls", 2.5), 1)
    rows["gnc_tls_cold"] = {"s": t, "pose_rms_mm": _pose_rms_mm(rg.poses, syn.true_poses)}
    sigma = mad_sigma(ba.residual_vectors(p.K, r.poses, r.points, p.obs_pose, p.obs_point, p.obs_uv))
    t, acc = _isam2_update(syn, sigma)
    rows["isam2_add_one_keyframe"] = {"s": t, "pose_rms_mm": acc}
    return {
        "benchmark": "ba",
        "problem": {"keyframes": 10, "points": 2000, "observations": int(len(p.obs_uv)),
                    "outlier_share": float(syn.outlier_obs.mean()), "prior_pose_rms_mm": prior},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "gtsam": gtsam.__version__ if hasattr(gtsam, "__version__") else "?"},
        "repeats": repeats,
        "results": rows,
    }


def format_table(result: dict) -> str:
    lines = [f"BA window: {result['problem']['keyframes']} keyframes x {result['problem']['points']} points, "
             f"{result['problem']['observations']} observations, {100 * result['problem']['outlier_share']:.1f}% "
             f"corrupted; prior pose RMS {result['problem']['prior_pose_rms_mm']:.3f} mm",
             f"{'method':32s} {'time ms':>9s} {'pose RMS mm':>12s}"]
    for name, row in result["results"].items():
        acc = f"{row['pose_rms_mm']:.3f}" if "pose_rms_mm" in row else "-"
        lines.append(f"{name:32s} {1e3 * row['s']:9.1f} {acc:>12s}")
    return "\n".join(lines)
