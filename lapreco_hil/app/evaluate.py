"""``lapreco evaluate``: a finished run's points against a ground-truth surface (similarity ICP, coverage), and
its dense surface (dense.ply) beside its sparse points when it has one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lapreco_hil.errors import ConfigError
from lapreco_hil.evaluation.accuracy import surface_report
from lapreco_hil.evaluation.compare import read_points_ply, read_tum
from lapreco_hil.evaluation.icp import evaluate_points


def evaluate(outdir: str, truth_path: str, coverage_mm: float = 3.0) -> dict:
    """ICP RMS, scale and coverage of ``outdir``'s points.ply against the mesh at ``truth_path`` (world frame,
    metres); the run's trajectory and camera, when present, give the visible part of the surface. With a
    dense.ply, ``surface`` puts the sparse and dense points side by side (distances unaligned, coverage within
    1 mm of the surface the trajectory's cameras saw)."""
    import pyvista as pv

    out = Path(outdir)
    points_file = out / "points.ply"
    if not points_file.is_file():
        raise ConfigError(f"{points_file}: missing; give a run's output folder (lapreco demo/replay/run --out)")
    truth_file = Path(truth_path)
    if not truth_file.is_file():
        raise ConfigError(f"{truth_file}: no such ground-truth mesh")
    try:
        truth = pv.read(str(truth_file))
    except Exception as exc:  # VTK raises several kinds for a file it cannot parse
        raise ConfigError(f"{truth_file}: cannot read the mesh ({exc})") from None
    if truth.n_points == 0 or truth.n_cells == 0:
        raise ConfigError(f"{truth_file}: the mesh is empty")
    poses = K = size = cam = None
    if (out / "trajectory.tum").is_file() and (out / "report.json").is_file():
        cam = json.loads((out / "report.json").read_text()).get("camera")
        if cam:
            _, poses = read_tum(out / "trajectory.tum")
            K, size = np.array(cam["K"]), (cam["width"], cam["height"])
    points = read_points_ply(points_file)
    result = evaluate_points(points, truth, poses, K, size, coverage_mm)
    if "error" in result:
        raise ConfigError(f"{points_file}: {result['error']}")
    if (out / "dense.ply").is_file() and poses is not None:
        dense = read_points_ply(out / "dense.ply")
        result["surface"] = surface_report(truth, poses, K, size, sparse=points, dense=dense, mask=_field_of_view(cam))
    return result


def _field_of_view(cam: dict) -> np.ndarray | None:
    """The lens's field of view in the undistorted image, from report.json's camera (None: not recorded)."""
    if not cam.get("fov_radius_px"):
        return None
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.dense.surface import undistortion

    K = np.array(cam["K"])
    camera = CameraModel(cam["width"], cam["height"], K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(cam["dist"]),
                         cam["fov_radius_px"])
    return undistortion(camera)[2]
