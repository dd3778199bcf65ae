"""Reconstruction against a ground-truth surface: similarity ICP (VTK's vtkIterativeClosestPointTransform in
similarity mode, against a dense area-uniform sample of the true surface), point-to-surface residuals (VTK's
implicit distance), and coverage of the visible true surface (lapreco_hil.evaluation.coverage).

The seed aligned by hand, then ran ICP. Here the start is the identity (the reconstruction and the truth share
the world frame of the robot's poses); if that start fits badly (a session whose truth is in another frame),
ICP is restarted from the centroids with the 24 axis-aligned rotations and the best fit is kept.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pyvista as pv

from lapreco_hil.evaluation.accuracy import distance_stats_mm, surface_distances
from lapreco_hil.evaluation.coverage import covered_fraction, sample_surface, visible_samples


@dataclass
class Alignment:
    T: np.ndarray  # 4x4 similarity applied to the reconstruction: x_truth ~ T x
    scale: float
    rms_m: float
    start: str


def _vtk_icp(source: np.ndarray, target: pv.PolyData, start: np.ndarray, iterations: int) -> np.ndarray:
    from vtkmodules.vtkCommonDataModel import vtkIterativeClosestPointTransform

    moved = pv.PolyData(source @ start[:3, :3].T + start[:3, 3])
    icp = vtkIterativeClosestPointTransform()
    icp.SetSource(moved)
    icp.SetTarget(target)
    icp.GetLandmarkTransform().SetModeToSimilarity()
    icp.SetMaximumNumberOfIterations(iterations)
    icp.SetMaximumNumberOfLandmarks(min(len(source), 5000))
    icp.StartByMatchingCentroidsOff()
    icp.CheckMeanDistanceOn()
    icp.SetMaximumMeanDistance(1e-9)
    icp.Modified()
    icp.Update()
    M = np.array([[icp.GetMatrix().GetElement(i, j) for j in range(4)] for i in range(4)])
    return M @ start


def align_similarity(points: np.ndarray, surface: pv.PolyData, target_points: np.ndarray | None = None,
                     iterations: int = 200, restart_above_m: float = 0.005) -> Alignment:
    if target_points is None:
        target_points = sample_surface(surface, 0.0005)
    target = pv.PolyData(target_points)
    candidates = []

    def fit(start: np.ndarray, name: str) -> None:
        T = _vtk_icp(points, target, start, iterations)
        moved = points @ T[:3, :3].T + T[:3, 3]
        rms = float(np.sqrt(np.mean(surface_distances(moved, surface) ** 2)))
        candidates.append(Alignment(T, float(np.cbrt(np.linalg.det(T[:3, :3]))), rms, name))

    fit(np.eye(4), "identity (shared world frame)")
    if candidates[0].rms_m > restart_above_m:
        c_src, c_dst = points.mean(axis=0), target_points.mean(axis=0)
        for R in _axis_rotations():
            start = np.eye(4)
            start[:3, :3] = R
            start[:3, 3] = c_dst - R @ c_src
            fit(start, "centroids + axis-aligned rotation")
    return min(candidates, key=lambda a: a.rms_m)


def _axis_rotations() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            R = np.zeros((3, 3))
            for i, (p, s) in enumerate(zip(perm, signs)):
                R[i, p] = s
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def evaluate_points(points: np.ndarray, surface: pv.PolyData, poses: np.ndarray | None = None,
                    K: np.ndarray | None = None, size: tuple | None = None, coverage_mm: float = 3.0) -> dict:
    """ICP-aligned residuals (mm), the fitted scale, and coverage of the visible true surface."""
    if len(points) < 3:
        return {"points": int(len(points)), "error": "fewer than 3 points: nothing to align"}
    samples = sample_surface(surface, 0.0005)
    aligned = align_similarity(points, surface, samples)
    moved = points @ aligned.T[:3, :3].T + aligned.T[:3, 3]
    raw = distance_stats_mm(surface_distances(points, surface))
    out = {
        "points": int(len(points)),
        "icp": {**distance_stats_mm(surface_distances(moved, surface)), "scale": aligned.scale,
                "start": aligned.start, "T_truth_reconstruction": aligned.T.tolist()},
        "unaligned": raw,
    }
    if poses is not None and K is not None and size is not None and len(poses):
        vis = visible_samples(samples, poses, K, size)
        if vis.any():
            out["coverage"] = {"radius_mm": coverage_mm, "visible_samples": int(vis.sum()),
                               "covered_fraction": covered_fraction(moved, samples[vis], coverage_mm * 1e-3)}
    return out
