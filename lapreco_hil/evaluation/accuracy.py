"""Accuracy figures in millimetres (reports only; SI units inside)."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from lapreco_hil.geometry import pose_error
from lapreco_hil.ground_truth import GroundTruth


def surface_distances(points: np.ndarray, surface: pv.PolyData) -> np.ndarray:
    """Unsigned distance (m) from each point to the surface (VTK's implicit polydata distance)."""
    if len(points) == 0:
        return np.zeros(0)
    cloud = pv.PolyData(np.asarray(points, dtype=np.float64))
    return np.abs(np.asarray(cloud.compute_implicit_distance(surface)["implicit_distance"]))


def distance_stats_mm(d_m: np.ndarray) -> dict:
    if len(d_m) == 0:
        return {"n": 0, "rms_mm": None, "median_mm": None, "p95_mm": None}
    d = d_m * 1e3
    return {"n": int(len(d)), "rms_mm": float(np.sqrt(np.mean(d**2))), "median_mm": float(np.median(d)),
            "p95_mm": float(np.percentile(d, 95))}


def pose_error_stats(estimated: np.ndarray, truth: np.ndarray) -> dict:
    errs = np.array([pose_error(a, b) for a, b in zip(estimated, truth)]).reshape(-1, 2)
    pos = errs[:, 0] * 1e3
    rot = np.degrees(errs[:, 1])
    return {"n": int(len(pos)), "position_rms_mm": float(np.sqrt(np.mean(pos**2))),
            "position_median_mm": float(np.median(pos)), "position_max_mm": float(pos.max()),
            "rotation_rms_deg": float(np.sqrt(np.mean(rot**2)))}


def similarity_align(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (Umeyama 1991) mapping corresponding points: target ~ s R source + t.
    Returns (s, R, t)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    S, T = source - mu_s, target - mu_t
    U, D, Vt = np.linalg.svd(T.T @ S / len(source))
    E = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1
    R = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / (S**2).sum(1).mean())
    return s, R, mu_t - s * R @ mu_s


def shape_error(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-point error after the best similarity alignment: the error BA can be blamed for, free of the
    gauge (global pose and scale) that priors alone fix."""
    s, R, t = similarity_align(points, truth)
    return np.linalg.norm(s * points @ R.T + t - truth, axis=1)


def accuracy_report(m, truth: GroundTruth) -> dict:
    """Points to the true surface (mm) and camera poses before/after BA against the true poses (``m``: a
    MapResult)."""
    acc: dict = {}
    if truth.surface is not None:
        points = m.points[m.inlier]
        acc["points_to_surface"] = distance_stats_mm(surface_distances(points, truth.surface))
        acc["all_points_to_surface"] = distance_stats_mm(surface_distances(m.points, truth.surface))
    if truth.camera_pose is not None and m.frames:
        true_frames = np.array([truth.camera_pose(f.t_ns) for f in m.frames])
        raw = pose_error_stats(np.array([f.T_prior for f in m.frames]), true_frames)
        refined = pose_error_stats(m.frame_poses, true_frames)
        acc["camera_raw_fk"] = raw
        acc["camera_refined"] = refined
        if m.keyframes:
            true_kf = np.array([truth.camera_pose(k.t_ns) for k in m.keyframes])
            acc["keyframes_raw_fk"] = pose_error_stats(np.array([k.prior.T_world_camera for k in m.keyframes]),
                                                       true_kf)
            acc["keyframes_refined"] = pose_error_stats(np.array([k.T_world_camera for k in m.keyframes]), true_kf)
        acc["position_improvement_ratio"] = raw["position_rms_mm"] / max(refined["position_rms_mm"], 1e-9)
    return acc


def surface_report(surface: pv.PolyData, poses: np.ndarray, K: np.ndarray, size: tuple, *,
                   sparse: np.ndarray | None = None, dense: np.ndarray | None = None, mask: np.ndarray | None = None,
                   radius_mm: float = 1.0, beyond_mm: float = 5.0, max_points: int = 200_000) -> dict:
    """Sparse and dense reconstructions side by side against the true surface: distances to it (mm; the share
    beyond ``beyond_mm``) and coverage: the share of the true surface seen by the cameras at ``poses`` (the
    pinhole image of ``K``, ``size``, in ``mask``, unoccluded; a real camera's: ``coverage.camera_view``) with
    a reconstructed point within ``radius_mm``. No alignment: the reconstruction and
    the truth share the world frame of the robot's poses. Distances are taken on at most ``max_points`` points,
    evenly thinned."""
    from lapreco_hil.evaluation.coverage import covered_fraction, sample_surface, visible_samples

    samples = sample_surface(surface, 0.0005)
    spacing = float(np.sqrt(surface.area / max(len(samples), 1)))
    seen = samples[visible_samples(samples, poses, K, size, mask=mask, occlusion_m=0.001, spacing_m=spacing)]
    out: dict = {"radius_mm": radius_mm, "seen_samples": int(len(seen)), "views": int(len(poses))}
    for name, points in (("sparse", sparse), ("dense", dense)):
        if points is None:
            continue
        points = np.asarray(points, float).reshape(-1, 3)
        d = surface_distances(points[::max(1, len(points) // max_points)], surface)
        out[name] = {**distance_stats_mm(d), "points": int(len(points)),
                     f"beyond_{beyond_mm:g}mm": float(np.mean(d > beyond_mm * 1e-3)) if len(d) else None,
                     "coverage": covered_fraction(points, seen, radius_mm * 1e-3) if len(seen) else None}
    return out
