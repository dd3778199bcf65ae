"""``lapreco bench ba``: one local-BA window of 10 keyframes x 2000 points (~20k observations) with 5% gross
outliers, solved the ways the live loop could solve it (GTSAM, the Schur-complement solver), and final passes
over a long session's map (short tracks), over a slow sweep's (400 keyframes, tracks of 20-300 views) and over the
live run's active map at its end (400 keyframes, short tracks: ``ba_live``), timed on this machine."""

from __future__ import annotations

import platform
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lapreco_hil.bench.ba_live import make_live_final_problem
from lapreco_hil.geometry import Rotation, look_at, make_T, pose_error
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping.robust import CAUCHY_K, TUKEY_C, RobustSchedule, RobustStage, mad_sigma
from lapreco_hil.mapping.schur import final_pass_threads, solve_robust_schur
from lapreco_hil.mapping.schur_kernels import SchurWorkspace
from lapreco_hil.mapping.synthetic import make_problem, make_sweep_problem


def _pose_rms_mm(poses, truth) -> float:
    return float(1e3 * np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(poses, truth)])))


def _median_time(fn, repeats: int, cpu: dict | None = None):
    """Median wall time of ``fn`` over ``repeats`` runs (and its last result); ``cpu['s']`` gets the median
    CPU time of this process (what the wall time would be on cores of its own: 7 agents share this machine's 2)."""
    times, cpu_times, out = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    if cpu is not None:
        cpu["s"] = float(np.median(cpu_times))
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


def long_session_problem(rng: np.random.Generator, n_views: int = 300, new_points_per_view: int = 50,
                         track_views: int = 15, pixel_noise: float = 0.5, outliers: float = 0.05):
    """A final pass's problem: a scope sweeping 0.5 mm per keyframe over tissue with relief, every landmark seen
    by ``track_views`` consecutive keyframes, robot priors drawn from their covariance, the first two keyframes
    fixed (retired), ``outliers`` of the tracks jumping by 6-25 px half-way. Returns (problem, true poses)."""
    K = np.array([[1400.0, 0, 960], [0, 1400.0, 540], [0, 0, 1]])  # 1080p
    rot_sigma, trans_sigma = 0.003, 0.0004
    s = 0.0005 * np.arange(n_views)
    eyes = np.column_stack([s, 0.004 * np.sin(s * 40), np.zeros(n_views)])
    true = np.array([look_at(e, e + np.array([0.0, 0.0, 0.1]), np.array([0, -1.0, 0])) for e in eyes])
    priors = np.array([T @ make_T(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                                  rng.normal(0, trans_sigma, 3)) for T in true])
    first = np.repeat(np.arange(n_views - track_views + 1), new_points_per_view)
    mid = eyes[first + track_views // 2]
    xy = mid[:, :2] + rng.uniform(-0.02, 0.02, (len(first), 2))
    pts = np.column_stack([xy, 0.1 + 0.01 * np.sin(xy[:, 0] * 70) * np.cos(xy[:, 1] * 55)])
    obs_point = np.repeat(np.arange(len(pts)), track_views)
    obs_pose = (first[:, None] + np.arange(track_views)).ravel()
    T_cw = np.linalg.inv(true)[obs_pose]
    Xc = np.einsum("oij,oj->oi", T_cw[:, :3, :3], pts[obs_point]) + T_cw[:, :3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2] + rng.normal(0, pixel_noise, (len(Xc), 2))
    jumped = np.repeat(rng.random(len(pts)) < outliers, track_views) & (np.tile(np.arange(track_views),
                                                                                 len(pts)) >= track_views // 2)
    uv[jumped] += rng.uniform(6, 25, (int(jumped.sum()), 2)) * rng.choice([-1, 1], (int(jumped.sum()), 2))
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    problem = ba.BAProblem(K, np.arange(n_views), priors.copy(), np.arange(n_views) < 2, priors,
                           np.repeat(cov[None], n_views, 0), np.arange(len(pts)),
                           pts + rng.normal(0, 0.0005, pts.shape), obs_pose, obs_point, uv)
    return problem, true


def _schur_row(seconds: float, cpu_s: float, result: ba.BAResult, reference: ba.BAResult, syn) -> dict:
    """A Schur solver row: its time, accuracy, how many inlier labels differ from GTSAM's (``reference``), where
    the time goes, per stage and per LM iteration (linearise, Schur complement, solve, error), and what the Warp
    device was asked for in the solve (launches, uploads, downloads, allocations; none on numpy)."""
    return {"s": seconds, "cpu_s": cpu_s, "iterations": result.iterations,
            "pose_rms_mm": _pose_rms_mm(result.poses, syn.true_poses),
            "labels_differing_from_gtsam": int((result.stats["inlier_obs"] != reference.stats["inlier_obs"]).sum()),
            "timing": result.stats["timing"], "device_ops": result.stats.get("device_ops", {}),
            "stages": [{"loss": st["loss"], "iterations": st["iterations"], "timing": st["timing"],
                        "iteration_timing": st["iteration_timing"]} for st in result.stats["stages"]]}


def run(repeats: int = 3, seed: int = 0, device: str = "cpu") -> dict:
    """``device``: the Warp device of the Schur solver's kernels (its numpy path is timed too)."""
    syn = make_problem(np.random.default_rng(seed), n_views=10, n_points=2000, jump=0.02, highlight=0.015,
                       instrument=0.015)
    p = syn.problem
    rows = {}
    prior = _pose_rms_mm(p.prior_poses, syn.true_poses)
    t, r = _median_time(lambda: ba.solve(p, 1.0, "cauchy", 2.0, 15), repeats)
    rows["lm_cauchy_fixed_k_cold"] = {"s": t, "iterations": r.iterations, "pose_rms_mm": _pose_rms_mm(r.poses, syn.true_poses)}
    cpu = {}
    t, r = _median_time(lambda: ba.solve_robust(p, RobustSchedule()), repeats, cpu)
    rows["lm_mad_cauchy_tukey_cold"] = {"s": t, "cpu_s": cpu["s"], "iterations": r.iterations,
                                        "pose_rms_mm": _pose_rms_mm(r.poses, syn.true_poses)}
    solve_robust_schur(p, RobustSchedule((RobustStage("cauchy", CAUCHY_K, 1),)), device=device)  # compile/load
    t, rs = _median_time(lambda: solve_robust_schur(p, RobustSchedule(), device=device), repeats, cpu)
    rows["schur_mad_cauchy_tukey_cold"] = _schur_row(t, cpu["s"], rs, r, syn)
    t, rs = _median_time(lambda: solve_robust_schur(p, RobustSchedule(), device="numpy"), repeats, cpu)
    rows["schur_numpy_mad_cauchy_tukey_cold"] = _schur_row(t, cpu["s"], rs, r, syn)
    warm = ba.BAProblem(**{**p.__dict__, "poses": r.poses.copy(), "points": r.points.copy()})
    # the next window starts from the last solution: one new keyframe from its prior
    warm.poses[-1] = p.prior_poses[-1]
    quick = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 3), RobustStage("tukey", TUKEY_C, 3)))
    t, rw = _median_time(lambda: ba.solve_robust(warm, quick), repeats, cpu)
    rows["lm_mad_cauchy_tukey_warm_3+3"] = {"s": t, "cpu_s": cpu["s"], "iterations": rw.iterations,
                                            "pose_rms_mm": _pose_rms_mm(rw.poses, syn.true_poses)}
    t, rsw = _median_time(lambda: solve_robust_schur(warm, quick, device=device), repeats, cpu)
    rows["schur_mad_cauchy_tukey_warm_3+3"] = _schur_row(t, cpu["s"], rsw, rw, syn)
    # as the live BA worker solves its windows: their device buffers (a GPU's page-locked mirrors) kept in one
    # workspace from solve to solve (allocated by the first: the one before the timing)
    workspace = SchurWorkspace()
    solve_robust_schur(warm, quick, device=device, workspace=workspace)
    t, rsw = _median_time(lambda: solve_robust_schur(warm, quick, device=device, workspace=workspace), repeats, cpu)
    rows["schur_workspace_mad_cauchy_tukey_warm_3+3"] = _schur_row(t, cpu["s"], rsw, rw, syn)
    t, rsw = _median_time(lambda: solve_robust_schur(warm, quick, device="numpy"), repeats, cpu)
    rows["schur_numpy_mad_cauchy_tukey_warm_3+3"] = _schur_row(t, cpu["s"], rsw, rw, syn)
    if device.startswith("cuda"):  # the landmarks eliminated chunk by chunk through host BLAS instead of on the GPU
        t, rsw = _median_time(lambda: solve_robust_schur(warm, quick, device=device, device_schur=False), repeats,
                              cpu)
        rows["schur_host_elimination_mad_cauchy_tukey_warm_3+3"] = _schur_row(t, cpu["s"], rsw, rw, syn)
        # the opt-in GPU reductions: sums over runs of observations, the window's elimination by pose pairs, the
        # robust scales by sorts on the device
        t, rsw = _median_time(lambda: solve_robust_schur(warm, quick, device=device, gpu_reductions=True), repeats,
                              cpu)
        rows["schur_gpu_reductions_mad_cauchy_tukey_warm_3+3"] = _schur_row(t, cpu["s"], rsw, rw, syn)
    # a final pass over a long session's map (GTSAM's PCG path takes minutes here: docs/benchmarks.md)
    long_problem, long_truth = long_session_problem(np.random.default_rng(seed))
    final = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 15), RobustStage("tukey", TUKEY_C, 15)))
    t, rl = _median_time(lambda: solve_robust_schur(long_problem, final, device=device), 1, cpu)
    rows["schur_final_ba_300kf_15+15"] = {"s": t, "cpu_s": cpu["s"], "iterations": rl.iterations,
                                          "pose_rms_mm": _pose_rms_mm(rl.poses, long_truth),
                                          "timing": rl.stats["timing"]}
    # the final pass of a slow sweep: 400 keyframes, tracks of 20-300 views (the camera system is dense), its BLAS
    # on one thread, and on as many as the mapper's final pass takes here where that is more (every core of a
    # machine of 8 or more)
    sweep = make_sweep_problem(np.random.default_rng(seed))
    sweep_rows = [(1, "schur_final_ba_sweep_400kf_15+15_1_thread")]
    if final_pass_threads() > 1:
        sweep_rows.append((final_pass_threads(), "schur_final_ba_sweep_400kf_15+15_all_cores"))
    for threads, name in sweep_rows:
        t, rl = _median_time(lambda n=threads: solve_robust_schur(sweep.problem, final, device=device,
                                                                  blas_threads=n), 1, cpu)
        rows[name] = {"s": t, "cpu_s": cpu["s"], "iterations": rl.iterations, "blas_threads": threads,
                      "pose_rms_mm": _pose_rms_mm(rl.poses, sweep.true_poses),
                      "outlier_obs_labelled_inlier": int((rl.stats["inlier_obs"] & sweep.outlier_obs).sum()),
                      "timing": rl.stats["timing"]}
    # the live run's final global BA (issue 23): 400 active keyframes, most tracks short, 4% long-lived (which fill
    # its camera system: dense); and the same map without its long-lived tracks (its camera system banded, the
    # default there, and dense); solved as the mapper's final pass solves them (its BLAS threads, on a GPU the
    # landmarks eliminated there)
    live = make_live_final_problem(np.random.default_rng(seed))
    banded_map = make_live_final_problem(np.random.default_rng(seed), long_share=0.0)
    labels = {}
    for name, syn_live, camera_solver in (
            ("schur_final_ba_live_400kf_15+15", live, "auto"),
            ("schur_final_ba_live_short_tracks_400kf_15+15", banded_map, "auto"),
            ("schur_final_ba_live_short_tracks_400kf_15+15_dense", banded_map, "dense")):
        t, rl = _median_time(lambda s_=syn_live, c=camera_solver: solve_robust_schur(
            s_.problem, final, device=device, blas_threads=final_pass_threads(), camera_solver=c), 1, cpu)
        rows[name] = {"s": t, "cpu_s": cpu["s"], "iterations": rl.iterations, "blas_threads": final_pass_threads(),
                      "camera_solver": rl.stats["camera_solver"], "camera_band": rl.stats["camera_band"],
                      "solves": [st["solves"] for st in rl.stats["stages"]],
                      "pose_rms_mm": _pose_rms_mm(rl.poses, syn_live.true_poses),
                      "inlier_obs": int(rl.stats["inlier_obs"].sum()),
                      "outlier_obs_labelled_inlier": int((rl.stats["inlier_obs"] & syn_live.outlier_obs).sum()),
                      "timing": rl.stats["timing"],
                      "stages": [{"loss": st["loss"], "iterations": st["iterations"], "timing": st["timing"],
                                  "iteration_timing": st["iteration_timing"]} for st in rl.stats["stages"]]}
        labels[name] = rl.stats["inlier_obs"]
    rows["schur_final_ba_live_short_tracks_400kf_15+15"]["labels_differing_from_dense"] = int(
        (labels["schur_final_ba_live_short_tracks_400kf_15+15"]
         != labels["schur_final_ba_live_short_tracks_400kf_15+15_dense"]).sum())
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
        "final_ba_problem": {"keyframes": int(len(long_problem.poses)), "points": int(len(long_problem.points)),
                             "observations": int(len(long_problem.obs_uv)),
                             "prior_pose_rms_mm": _pose_rms_mm(long_problem.prior_poses, long_truth)},
        "sweep_final_ba_problem": {
            "keyframes": int(len(sweep.problem.poses)), "points": int(len(sweep.problem.points)),
            "observations": int(len(sweep.problem.obs_uv)),
            "track_views_min_mean_max": [int(np.bincount(sweep.problem.obs_point).min()),
                                         float(np.bincount(sweep.problem.obs_point).mean()),
                                         int(np.bincount(sweep.problem.obs_point).max())],
            "outlier_obs": int(sweep.outlier_obs.sum()),
            "prior_pose_rms_mm": _pose_rms_mm(sweep.problem.prior_poses, sweep.true_poses)},
        "live_final_ba_problem": {
            "keyframes": int(len(live.problem.poses)), "free_keyframes": int((~live.problem.fixed).sum()),
            "points": int(len(live.problem.points)), "observations": int(len(live.problem.obs_uv)),
            "track_views_min_mean_max": [int(np.bincount(live.problem.obs_point).min()),
                                         float(np.bincount(live.problem.obs_point).mean()),
                                         int(np.bincount(live.problem.obs_point).max())],
            "outlier_obs": int(live.outlier_obs.sum()),
            "start_pose_rms_mm": _pose_rms_mm(live.problem.poses, live.true_poses),
            "prior_pose_rms_mm": _pose_rms_mm(live.problem.prior_poses, live.true_poses)},
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "gtsam": gtsam.__version__ if hasattr(gtsam, "__version__") else "?"},
        "repeats": repeats,
        "schur_device": device,
        "results": rows,
    }


def format_table(result: dict) -> str:
    lines = [f"BA window: {result['problem']['keyframes']} keyframes x {result['problem']['points']} points, "
             f"{result['problem']['observations']} observations, {100 * result['problem']['outlier_share']:.1f}% "
             f"corrupted; prior pose RMS {result['problem']['prior_pose_rms_mm']:.3f} mm",
             f"final BA: {result['final_ba_problem']['keyframes']} keyframes x {result['final_ba_problem']['points']} "
             f"points, {result['final_ba_problem']['observations']} observations; prior pose RMS "
             f"{result['final_ba_problem']['prior_pose_rms_mm']:.3f} mm",
             "sweep final BA: {keyframes} keyframes x {points} points, {observations} observations, track views "
             "{track_views_min_mean_max}; prior pose RMS {prior_pose_rms_mm:.3f} mm".format(
                 **result["sweep_final_ba_problem"]) if "sweep_final_ba_problem" in result else "",
             "live final BA: {keyframes} keyframes ({free_keyframes} free) x {points} points, {observations} "
             "observations, track views {track_views_min_mean_max}; start pose RMS {start_pose_rms_mm:.3f} mm, priors "
             "{prior_pose_rms_mm:.3f} mm".format(**result["live_final_ba_problem"])
             if "live_final_ba_problem" in result else "",
             f"Schur solver rows: kernels on Warp device {result.get('schur_device', 'cpu')} (schur_numpy_*: numpy)",
             f"{'method':38s} {'time ms':>9s} {'CPU ms':>8s} {'pose RMS mm':>12s} {'iterations':>10s} "
             f"{'labels != gtsam':>15s}"]
    for name, row in result["results"].items():
        acc = f"{row['pose_rms_mm']:.3f}" if "pose_rms_mm" in row else "-"
        cpu = f"{1e3 * row['cpu_s']:.1f}" if "cpu_s" in row else "-"
        its = str(row.get("iterations", "-"))
        labels = str(row.get("labels_differing_from_gtsam", "-"))
        lines.append(f"{name:38s} {1e3 * row['s']:9.1f} {cpu:>8s} {acc:>12s} {its:>10s} {labels:>15s}")
    lines.append("Schur solver, where the time goes (ms per LM iteration: linearise / Schur complement / solve / "
                 "error evaluations):")
    for name, row in result["results"].items():
        for stage in row.get("stages", []):
            per = " ".join("{:.1f}/{:.1f}/{:.1f}/{:.1f}".format(*(1e3 * it[k] for k in (
                "linearize_s", "schur_s", "solve_s", "error_s"))) for it in stage["iteration_timing"])
            lines.append(f"  {name} {stage['loss']}: {per}")
    ops = [(name, row) for name, row in result["results"].items() if row.get("device_ops")]
    if ops:
        lines.append("Schur solver, per solve: Warp launches / uploads / downloads / allocations; setup and robust "
                     "scale ms:")
    for name, row in ops:
        o, t = row["device_ops"], row["timing"]
        lines.append(f"  {name}: {o['launches']} / {o['uploads']} / {o['downloads']} / {o['allocations']}; "
                     f"{1e3 * t.get('setup_s', 0.0):.2f} / {1e3 * t.get('scale_s', 0.0):.2f}")
    return "\n".join(lines)
