"""``lapreco evaluate``: a finished run's points against a ground-truth surface (similarity ICP, coverage)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lapreco_hil.errors import ConfigError
from lapreco_hil.evaluation.compare import read_points_ply, read_tum
from lapreco_hil.evaluation.icp import evaluate_points


def evaluate(outdir: str, truth_path: str, coverage_mm: float = 3.0) -> dict:
    """ICP RMS, scale and coverage of ``outdir``'s points.ply against the mesh at ``truth_path`` (world frame,
    metres); the run's trajectory and camera, when present, give the visible part of the surface."""
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
    poses = K = size = None
    if (out / "trajectory.tum").is_file() and (out / "report.json").is_file():
        cam = json.loads((out / "report.json").read_text()).get("camera")
        if cam:
            _, poses = read_tum(out / "trajectory.tum")
            K, size = np.array(cam["K"]), (cam["width"], cam["height"])
    result = evaluate_points(read_points_ply(points_file), truth, poses, K, size, coverage_mm)
    if "error" in result:
        raise ConfigError(f"{points_file}: {result['error']}")
    return result
