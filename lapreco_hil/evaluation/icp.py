"""Reconstruction against a ground-truth surface: point-to-surface residuals (VTK's implicit distance) before
any alignment and after rigid ICP (VTK's vtkIterativeClosestPointTransform, scale fixed at 1, against a dense
area-uniform sample of the true surface), coverage of the visible true surface
(lapreco_hil.evaluation.coverage), and, as an extra, similarity ICP: the scale the map would need.

The world frame is metric (the robot's or the tracker's poses), so the headline figures keep the scale at 1: a
free scale can shrink the points onto a flat or low-relief truth and report an error better than the true one
(a 12 cm cloud on a plane: scale 0.31, RMS 1.07 mm against 3.48 mm unaligned). The similarity's scale is
reported beside them, with a warning when it is far from 1, and a warning when the truth under the points is
too flat to pin an alignment down (then the alignment's shift along the surface and its rotation about the
normal are free, and the ICP figures are not trusted: judge by the unaligned one).

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
from scipy.spatial import cKDTree

# the similarity's scale beyond this relative distance from 1 is worth a warning (the world frame is metric; the
# simulated skull and uterus stay within 1.5-6 %, docs/results.md)
SCALE_WARN = 0.05
# the truth under the points is "flat" (or low-relief) when its thinnest principal extent is below this share of
# its widest (a plane: 0; 5 mm of relief across 10 cm: about 0.05; the simulated skull's seen part: 0.4). Only
# that degeneracy is detected: a cylinder (free along its axis) or a sphere (free in rotation) is not
FLAT_RATIO = 0.1


@dataclass
class Alignment:
    T: np.ndarray  # 4x4 rigid or similarity transform applied to the reconstruction: x_truth ~ T x
    scale: float
    rms_m: float
    start: str


def _vtk_icp(source: np.ndarray, target: pv.PolyData, start: np.ndarray, iterations: int,
             similarity: bool = True) -> np.ndarray:
    from vtkmodules.vtkCommonDataModel import vtkIterativeClosestPointTransform

    moved = pv.PolyData(source @ start[:3, :3].T + start[:3, 3])
    icp = vtkIterativeClosestPointTransform()
    icp.SetSource(moved)
    icp.SetTarget(target)
    if similarity:
        icp.GetLandmarkTransform().SetModeToSimilarity()
    else:
        icp.GetLandmarkTransform().SetModeToRigidBody()
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
    """Similarity ICP (free scale): the scale the map would need to fit the truth best. Not a headline figure:
    on a flat or low-relief truth a smaller scale always fits better (see the module's docstring)."""
    return _align(points, surface, target_points, iterations, restart_above_m, similarity=True)


def align_rigid(points: np.ndarray, surface: pv.PolyData, target_points: np.ndarray | None = None,
                iterations: int = 200, restart_above_m: float = 0.005) -> Alignment:
    """Rigid ICP (scale fixed at 1), the same starts as :func:`align_similarity`."""
    return _align(points, surface, target_points, iterations, restart_above_m, similarity=False)


def _align(points: np.ndarray, surface: pv.PolyData, target_points: np.ndarray | None, iterations: int,
           restart_above_m: float, similarity: bool) -> Alignment:
    if target_points is None:
        target_points = sample_surface(surface, 0.0005)
    target = pv.PolyData(target_points)
    candidates = []

    def fit(start: np.ndarray, name: str) -> None:
        T = _vtk_icp(points, target, start, iterations, similarity)
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


def unit_mismatch(points: np.ndarray, surface: pv.PolyData, ratio: float = 300.0) -> str | None:
    """Why the truth and the points cannot be in one unit (None: they can): the truth's extent (its bounding
    box's diagonal) about 1000x the points' (the middle 96 % of them along each axis), or the points' about
    1000x the truth's. A truth larger than the seen part is normal; ``ratio`` leaves room for it."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) < 3:
        return None
    lo, hi = np.percentile(pts, [2, 98], axis=0)
    span_points = float(np.linalg.norm(hi - lo))
    span_truth = float(np.linalg.norm(np.ptp(np.asarray(surface.points, float), axis=0)))
    if span_points <= 0 or span_truth <= 0:
        return None
    if span_truth > ratio * span_points:
        return (f"the truth spans {span_truth:.4g} units against the points' {span_points:.4g} m "
                f"({span_truth / span_points:.0f}x): it looks like millimetres; give it in metres")
    if span_points > ratio * span_truth:
        return (f"the truth spans {span_truth:.4g} units against the points' {span_points:.4g} m "
                f"(1/{span_points / span_truth:.0f}): the points are far larger than the truth; is the truth in "
                f"metres and the run's map in metres?")
    return None


def principal_sd(points: np.ndarray) -> np.ndarray:
    """The standard deviations along the principal axes, widest first (m)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) < 3:
        return np.zeros(3)
    return np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov((pts - pts.mean(0)).T)), 0))[::-1]


def _motion(T: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) of a rigid transform."""
    c = np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(c))), float(np.linalg.norm(T[:3, 3]) * 1e3)


def evaluate_points(points: np.ndarray, surface: pv.PolyData, poses: np.ndarray | None = None,
                    K: np.ndarray | None = None, size: tuple | None = None, coverage_mm: float = 3.0,
                    mask: np.ndarray | None = None) -> dict:
    """The points against a true surface (mm): ``unaligned`` (the shared world frame, no alignment) and ``icp``
    (after rigid ICP, scale fixed at 1) are the headline; ``similarity`` (after similarity ICP: the scale the
    map would need) is an extra. ``relief``: the principal extents of the truth under the points; ``warnings``:
    a scale far from 1, a truth too flat to pin an alignment down, a truth in another frame. ``coverage``: the
    share of the visible true surface (in the pinhole image of ``K``, ``size``, in ``mask``: a real camera's
    view is ``coverage.camera_view``) with a rigidly aligned point (an unaligned one on a flat truth) within
    ``coverage_mm`` (None, with ``why``, when it cannot be told)."""
    if len(points) < 3:
        return {"points": int(len(points)), "error": "fewer than 3 points: nothing to align"}
    mismatch = unit_mismatch(points, surface)
    if mismatch:
        return {"points": int(len(points)), "error": mismatch}
    samples = sample_surface(surface, 0.0005)
    rigid = align_rigid(points, surface, samples)
    moved = points @ rigid.T[:3, :3].T + rigid.T[:3, 3]
    similar = align_similarity(points, surface, samples)
    scaled = points @ similar.T[:3, :3].T + similar.T[:3, 3]
    raw = distance_stats_mm(surface_distances(points, surface))
    rot_deg, shift_mm = _motion(rigid.T)
    # the truth under the points: the samples nearest to the aligned points
    _, nearest = cKDTree(samples).query(moved)
    under = samples[np.unique(nearest)]
    sd_under = principal_sd(under if len(under) >= 10 else samples)
    sd_truth = principal_sd(samples)
    flat = bool(sd_under[2] < FLAT_RATIO * sd_under[0])
    out = {
        "points": int(len(points)),
        "unaligned": raw,
        "icp": {**distance_stats_mm(surface_distances(moved, surface)), "alignment": "rigid (scale fixed at 1)",
                "scale": 1.0,
                "start": rigid.start, "rotation_deg": rot_deg, "translation_mm": shift_mm,
                "T_truth_reconstruction": rigid.T.tolist(), "transform_trusted": not flat},
        "similarity": {**distance_stats_mm(surface_distances(scaled, surface)), "scale": similar.scale,
                       "start": similar.start, "T_truth_reconstruction": similar.T.tolist(),
                       "trusted": not flat},
        "relief": {"under_points_sd_mm": (sd_under * 1e3).tolist(), "truth_sd_mm": (sd_truth * 1e3).tolist(),
                   "flat": flat, "flat_ratio": FLAT_RATIO},
        "warnings": [],
    }
    warnings = out["warnings"]
    if rigid.start != "identity (shared world frame)":
        warnings.append(f"the points are {raw['rms_mm']:.1f} mm RMS from the truth unaligned: the truth looks like "
                        f"it is in another frame (ICP restarted from the centroids); the before-alignment figure "
                        f"means nothing here")
    if flat:
        where = ("the true surface" if sd_truth[2] < FLAT_RATIO * sd_truth[0]
                 else "the part of the true surface under the points")
        warnings.append(f"{where} is nearly flat ({sd_under[2] * 1e3:.2f} mm SD across its thinnest axis against "
                        f"{sd_under[0] * 1e3:.1f} mm across its widest): it pins an alignment only along its "
                        f"normal and in tilt. The rigid ICP's shift along it and rotation about its normal are "
                        f"arbitrary (its RMS stays honest: a rigid motion cannot shrink the map; the coverage uses "
                        f"the unaligned points), and the similarity's scale ({similar.scale:.4f}) is free too, "
                        f"so it and its figures mean nothing (shrinking a map onto a plane only improves the "
                        f"fit)")
    elif abs(similar.scale - 1) > SCALE_WARN:
        warnings.append(f"similarity ICP would scale the map by {similar.scale:.4f} "
                        f"({abs(similar.scale - 1):.1%} from 1, beyond {SCALE_WARN:.0%}): the world frame is metric, "
                        f"so the map's scale disagrees with the truth's; check the hand-eye, the poses' and the "
                        f"truth's units, or a truth that constrains the fit poorly")
    if poses is None or K is None or size is None or not len(poses):
        out["coverage"] = {"radius_mm": coverage_mm, "covered_fraction": None,
                           "why": "no camera poses: which part of the truth was seen is unknown"}
    else:
        vis = visible_samples(samples, poses, K, size, mask=mask)
        # on a flat truth the rigid ICP may slide the points along it: the shared world frame is the better guess
        covering = points if flat and rigid.start == "identity (shared world frame)" else moved
        if vis.any():
            out["coverage"] = {"radius_mm": coverage_mm, "visible_samples": int(vis.sum()),
                               "covered_fraction": covered_fraction(covering, samples[vis], coverage_mm * 1e-3),
                               "points": "unaligned" if covering is points else "after rigid ICP"}
        else:
            out["coverage"] = {"radius_mm": coverage_mm, "visible_samples": 0, "covered_fraction": None,
                               "why": "no part of the true surface was in view of the run's cameras (1-30 cm in "
                                      "front, inside the image): is the truth in the run's world frame?"}
    return out
