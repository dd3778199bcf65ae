"""Accuracy figures in millimetres (reports only; SI units inside)."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from ..geometry import pose_error


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
