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
