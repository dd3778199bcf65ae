"""The live run's final global BA, reproduced apart from the solver (as GTSAM's examples generate theirs): the
active map at the end of a 2-minute 1080p60 run (issue 23). A scope surveys one operative field, a keyframe every
``step_m`` or so; every landmark is one track, seen by a run of consecutive keyframes: most by a handful, a few
percent by many up to every keyframe (features that stay in view while the scope moves around them, as in the
skull demo's final map), which fill the camera system; without those it is banded in keyframe order. The oldest
keyframes that still see active landmarks are fixed (retired). The map starts where the local windows left it:
poses and points near the truth, not at the robot priors. ``python -m lapreco_hil.bench.ba_live --device cuda``
times the final pass alone; ``--camera-solver dense --camera-solver dense-device --camera-tile 32 --camera-tile 64``
compares the camera system factorised by the host's LAPACK (read back from the device) and on the device (tiles of
32 and 64), and ``--factorisation N`` the factorisation alone of an N-wide system, both ways."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from lapreco_hil.geometry import Rotation, look_at, make_T, pose_error
from lapreco_hil.mapping.bundle_adjustment import BAProblem
from lapreco_hil.mapping.robust import CAUCHY_K, TUKEY_C, RobustSchedule, RobustStage
from lapreco_hil.mapping.synthetic import SyntheticBA, observe_runs

FINAL_SCHEDULE = RobustSchedule((RobustStage("cauchy", CAUCHY_K, 15), RobustStage("tukey", TUKEY_C, 15)))


def make_live_final_problem(rng: np.random.Generator, n_free: int = 400, n_fixed: int = 8,
                            new_points_per_view: int = 52, min_track: int = 3, mean_track: float = 8.0,
                            max_track: int = 80, long_share: float = 0.04, long_min: int = 40,
                            step_m: float = 0.002, pixel_noise: float = 0.5,
                            rot_sigma: float = 0.003, trans_sigma: float = 0.0004, drift_rot_rad: float = 0.001,
                            drift_trans_m: float = 0.0002, warm_point_m: float = 0.00002,
                            jump: float = 0.05) -> SyntheticBA:
    """The live run's active map at its end: ``n_fixed`` retired keyframes then ``n_free`` active ones, about
    ``step_m`` apart along a scope's survey of one operative field (a Lissajous path over +-25 x +-15 mm, 10 cm
    above tissue with relief; 1080p camera); ``new_points_per_view`` landmarks start at each keyframe, each seen by
    a run of consecutive keyframes: most by ``min_track`` - 1 + geometric(1 / (``mean_track`` - ``min_track`` + 1))
    (at most ``max_track``), ``long_share`` of them by ``long_min`` up to every keyframe (log-uniform: features
    that stay in view while the scope surveys around them), cut at the map's end; each landmark where every view
    of its run sees it; robot priors drawn from their covariance; the start where the local windows left it: the
    map drifted from the truth as a whole, slowly along the run (up to ``drift_*``), each landmark with the drift
    of its middle view and ``warm_point_m`` of noise; ``jump`` of the tracks of 4 views or more jumping 6-25 px
    half-way (their later views corrupted). ``long_share=0`` gives a map whose camera system is banded."""
    K = np.array([[1400.0, 0, 960], [0, 1400.0, 540], [0, 0, 1]])
    n_views = n_fixed + n_free
    phase = np.arange(n_views) * (step_m / 0.002)
    eyes = np.column_stack([0.025 * np.sin(2 * np.pi * phase / 97), 0.015 * np.sin(2 * np.pi * phase / 61 + 0.7),
                            0.003 * np.cos(phase * 0.03)])
    true = np.array([look_at(e, e + np.array([0.0, 0.0, 0.1]), np.array([0, -1.0, 0])) for e in eyes])
    priors = np.array([T @ make_T(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                                  rng.normal(0, trans_sigma, 3)) for T in true])
    first = np.repeat(np.arange(n_views - 1), new_points_per_view)
    length = np.minimum(min_track - 1 + rng.geometric(1.0 / (mean_track - min_track + 1.0), len(first)), max_track)
    long = rng.random(len(first)) < long_share
    length[long] = np.exp(rng.uniform(np.log(long_min), np.log(n_views), int(long.sum()))).astype(np.int64)
    length = np.minimum(length, n_views - first)
    # the retired keyframes keep only the tracks that reach the active ones (the rest were archived with them)
    keep = first + length > n_fixed
    first, length = first[keep], length[keep]
    n_points = len(first)
    # each landmark where all its views see it: in the overlap of their footprints (10% in from the edges)
    run_starts = np.cumsum(length) - length
    views_of = first[np.repeat(np.arange(n_points), length)] + (np.arange(length.sum())
                                                                 - np.repeat(run_starts, length))
    lo = np.minimum.reduceat(eyes[views_of, :2], run_starts)
    hi = np.maximum.reduceat(eyes[views_of, :2], run_starts)
    half = 0.9 * 0.1 * np.array([K[0, 2], K[1, 2]]) / K[0, 0]
    xy = rng.uniform(hi - half, lo + half)
    pts = np.column_stack([xy, 0.1 + 0.01 * np.sin(xy[:, 0] * 70) * np.cos(xy[:, 1] * 55)])
    obs_pose, obs_point, uv, bad, jumped_track = observe_runs(rng, K, true, pts, first, length, pixel_noise, jump,
                                                              min_jump_views=4)
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    # the local windows' answer: the map drifted from the truth, slowly along the run, each landmark with the
    # drift of its middle view (a locally consistent map)
    walks = np.cumsum(np.cumsum(rng.normal(0, 1.0, (2, n_views, 3)), axis=1), axis=1)
    walks -= walks.mean(axis=1, keepdims=True)
    walks /= np.maximum(1e-12, np.abs(walks).max(axis=(1, 2), keepdims=True))
    drift = np.array([make_T(Rotation.from_rotvec(drift_rot_rad * r).as_matrix(), drift_trans_m * t)
                      for r, t in zip(walks[0], walks[1])])
    fixed = np.arange(n_views) < n_fixed
    drift[fixed] = np.eye(4)  # (a retired keyframe keeps the pose it was archived with)
    warm = drift @ true
    D = drift[first + length // 2]
    warm_pts = np.einsum("nij,nj->ni", D[:, :3, :3], pts) + D[:, :3, 3] + rng.normal(0, warm_point_m, pts.shape)
    problem = BAProblem(K, np.arange(n_views), warm, fixed, priors, np.repeat(cov[None], n_views, 0),
                        np.arange(n_points), warm_pts, obs_pose, obs_point, uv)
    return SyntheticBA(problem, true, pts, bad, jumped_track)


def pose_rms_mm(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(1e3 * np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(poses, truth)])))


def factorisation_bench(device: str, n: int, tiles: list[int], threads: int, repeats: int = 5,
                        seed: int = 0) -> dict:
    """The dense factorisation and solve alone, of an ``n``-wide SPD system like a final pass's camera system:
    the host's LAPACK (potrf, potrs on ``threads`` BLAS threads) with, apart, the read-back of the system from
    ``device`` that it needs there (into pageable memory, as the solver's), against ``dense_cholesky`` on
    ``device`` per tile's side, with and without libmathdx (the system formed on the device beforehand, as the
    solver forms it; timed: the launches, the wait, the step's read-back). Median seconds of ``repeats``; the
    first call (the kernels' load, a CUDA graph's capture) apart; the step's largest difference, relative."""
    import scipy.linalg.lapack
    import warp as wp

    from lapreco_hil.mapping import dense_cholesky
    from lapreco_hil.mapping.schur import _blas_threads

    rng = np.random.default_rng(seed)
    B = rng.normal(size=(n, n + 200))
    S = B @ B.T / n + 1e-3 * np.eye(n)  # (a Gram matrix: condition about 1e4 to 1e6, as a damped camera system's)
    rhs = rng.normal(size=n)
    host_s = []
    with _blas_threads(threads):
        for _ in range(repeats):
            t0 = time.perf_counter()
            factor, info = scipy.linalg.lapack.dpotrf(S, lower=1, clean=0)
            x_host, _info = scipy.linalg.lapack.dpotrs(factor, rhs, lower=1)
            host_s.append(time.perf_counter() - t0)
    out = {"n": n, "host_lapack_s": float(np.median(host_s)), "blas_threads": threads}
    on_device = wp.array(S, dtype=wp.float64, device=device)
    readback_s = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        on_device.numpy()
        readback_s.append(time.perf_counter() - t0)
    out["readback_46MB_s" if n == 2400 else "readback_s"] = float(np.median(readback_s))
    for tile in tiles:
        for mathdx in ((True, False) if wp.get_device(device).is_cuda else (None,)):
            name = f"device_tile{tile}" + ("" if mathdx is None else "_mathdx" if mathdx else "_warp")
            try:  # (a variant that does not compile or launch on this device is reported, the others still run)
                t0 = time.perf_counter()
                dense_cholesky.load(tile, device, mathdx)
                load_s = time.perf_counter() - t0
                chol = dense_cholesky.DeviceCholesky(n, device, tile, mathdx=mathdx)
                pristine = wp.array(dense_cholesky.to_storage(S, rhs, tile), dtype=wp.float64, device=device)
                storage = wp.empty_like(pristine)
                info = wp.zeros(1, dtype=wp.int32, device=device)
                times = []
                for _ in range(repeats + 1):
                    wp.copy(storage, pristine)
                    wp.synchronize_device(device)
                    t0 = time.perf_counter()
                    chol.launch(storage, info)
                    x = chol.solution(storage).numpy()[:n]
                    times.append(time.perf_counter() - t0)
                out[name] = {"s": float(np.median(times[1:])), "first_s": times[0], "load_s": load_s,
                             "info": int(info.numpy()[0]), "launches": chol.launches, "graph": chol.graph,
                             "step_relative_difference": float(np.abs(x - x_host).max() / np.abs(x_host).max())}
            except Exception as e:
                out[name] = {"error": f"{type(e).__name__}: {e}"}
    return out


def main(argv: list[str] | None = None) -> int:
    """Time the live run's final pass (its camera system as chosen by default, then dense) and print the figures
    as JSON."""
    from lapreco_hil.mapping.schur import DEVICE_TILE, final_pass_threads, solve_robust_schur

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="Warp device of the solver's kernels (cpu, cuda) or numpy")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=0, help="BLAS threads (0: the mapper's final pass's)")
    parser.add_argument("--camera-solver", action="append", choices=("auto", "dense", "banded", "dense-device"),
                        help="repeatable; default: auto, then dense (dense: the host's LAPACK; dense-device: on the "
                             "kernels' device)")
    parser.add_argument("--camera-tile", type=int, action="append",
                        help=f"repeatable: the device factorisation's tile side(s) (16, 32, 64; default {DEVICE_TILE})")
    parser.add_argument("--factorisation", type=int, default=0, metavar="N",
                        help="time the factorisation alone of an N-wide system (2400: the live map's), host against "
                             "device; the final pass too where --camera-solver is given")
    parser.add_argument("--no-mathdx", action="store_true",
                        help="the solver's tile kernels without libmathdx (Warp's own code): the whole process")
    parser.add_argument("--long-share", type=float, default=0.04,
                        help="share of long-lived tracks (0: a map whose camera system is banded)")
    parser.add_argument("--free-keyframes", type=int, default=400,
                        help="the map's active keyframes (400: the live run's; fewer for a check on a CPU)")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.no_mathdx:
        import warp as wp

        wp.config.enable_mathdx_gemm = wp.config.enable_mathdx_solver = False
    syn = make_live_final_problem(np.random.default_rng(args.seed), n_free=args.free_keyframes,
                                  long_share=args.long_share)
    p = syn.problem
    threads = args.threads or final_pass_threads()
    solve_robust_schur(p, RobustSchedule((RobustStage("cauchy", CAUCHY_K, 1),)), device=args.device)  # (loads)
    load_s = {}
    if args.device != "numpy":  # (the device factorisation's kernels of every tile asked for, compiled now)
        from lapreco_hil.mapping import dense_cholesky
        from lapreco_hil.warp_device import resolve_device

        for tile in args.camera_tile or [DEVICE_TILE]:
            t0 = time.perf_counter()
            try:
                dense_cholesky.load(tile, resolve_device(args.device))
                load_s[tile] = time.perf_counter() - t0
            except Exception as e:  # (its rows report it too)
                load_s[tile] = f"{type(e).__name__}: {e}"
    views = np.bincount(p.obs_point)
    out = {"problem": {"keyframes": len(p.poses), "free_keyframes": int((~p.fixed).sum()), "points": len(p.points),
                       "observations": len(p.obs_uv), "long_share": args.long_share,
                       "track_views_mean_max": [float(views.mean()), int(views.max())],
                       "start_pose_rms_mm": pose_rms_mm(p.poses, syn.true_poses),
                       "prior_pose_rms_mm": pose_rms_mm(p.prior_poses, syn.true_poses)},
           "device": args.device, "blas_threads": threads, "mathdx": not args.no_mathdx,
           "dense_cholesky_load_s": load_s, "runs": {}}
    if args.factorisation:
        out["factorisation"] = factorisation_bench(args.device, args.factorisation, args.camera_tile or [DEVICE_TILE],
                                                   threads)
    first = None
    # (the factorisation alone, asked for with no camera solver: no final pass)
    rows = [(c, t) for c in args.camera_solver or ([] if args.factorisation else ["auto", "dense"])
            for t in (args.camera_tile or [DEVICE_TILE] if c in ("auto", "dense-device") else [DEVICE_TILE])]
    for camera_solver, tile in rows:
        name = camera_solver if len(args.camera_tile or []) <= 1 or camera_solver not in ("auto", "dense-device") \
            else f"{camera_solver}-{tile}"
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            r = solve_robust_schur(p, FINAL_SCHEDULE, device=args.device, blas_threads=threads,
                                   camera_solver=camera_solver, camera_tile=tile)
        except Exception as e:  # (reported: the other rows still run)
            out["runs"][name] = {"error": f"{type(e).__name__}: {e}"}
            continue
        run = {"s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
               "camera_solver": r.stats["camera_solver"], "camera_band": r.stats["camera_band"],
               "camera_tile": r.stats["camera_tile"],
               "iterations_solves": [(st["iterations"], st["solves"]) for st in r.stats["stages"]],
               "pose_rms_mm": pose_rms_mm(r.poses, syn.true_poses), "inlier_obs": int(r.stats["inlier_obs"].sum()),
               "outlier_obs_labelled_inlier": int((r.stats["inlier_obs"] & syn.outlier_obs).sum()),
               "timing": r.stats["timing"],
               "downloaded_MB": r.stats.get("device_ops", {}).get("downloaded_bytes", 0) / 1e6}
        if first is None:
            first = r
        run["labels_differing_from_the_first"] = int((r.stats["inlier_obs"] != first.stats["inlier_obs"]).sum())
        run["poses_max_difference_from_the_first"] = float(np.abs(r.poses - first.poses).max())
        out["runs"][name] = run
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
