"""``lapreco evaluate``: a finished run's points against a ground-truth surface (unaligned and after rigid ICP;
similarity ICP's scale as an extra; coverage), and its dense surface (dense.ply) beside its sparse points when it
has one."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from lapreco_hil.errors import ConfigError
from lapreco_hil.evaluation.accuracy import surface_report
from lapreco_hil.evaluation.compare import read_points_ply, read_report_camera, read_tum
from lapreco_hil.evaluation.coverage import camera_view
from lapreco_hil.evaluation.icp import evaluate_points, unit_mismatch

log = logging.getLogger(__name__)

TRUTH_UNITS = {"m": 1.0, "mm": 1e-3}


def evaluate(outdir: str, truth_path: str, coverage_mm: float = 3.0, truth_unit: str | None = None) -> dict:
    """The RMS of ``outdir``'s points.ply to the mesh at ``truth_path`` (world frame) before alignment and after
    rigid ICP, similarity ICP's scale (an extra), coverage; the run's trajectory and camera, when present, give
    the visible part of the surface. ``truth_unit`` ('m' or 'mm'): the mesh's length unit; None: a session's
    truth/surface.ply (or a session folder) in its session.json's unit, any other mesh in metres. With a
    dense.ply, ``surface`` puts the sparse and dense points side by side (distances unaligned, coverage within
    1 mm of the surface the trajectory's cameras saw)."""
    import pyvista as pv

    out = Path(outdir)
    points_file = out / "points.ply"
    if not points_file.is_file():
        raise ConfigError(f"{points_file}: missing; give a run's output folder (lapreco demo/replay/run --out)")
    truth_file, unit, unit_from = _truth_file_and_unit(Path(truth_path), truth_unit)
    try:
        truth = pv.read(str(truth_file))
    except Exception as exc:  # VTK raises several kinds for a file it cannot parse
        raise ConfigError(f"{truth_file}: cannot read the mesh ({exc})") from None
    if truth.n_points == 0 or truth.n_cells == 0:
        raise ConfigError(f"{truth_file}: the mesh is empty")
    if TRUTH_UNITS[unit] != 1.0:
        truth = truth.scale(TRUTH_UNITS[unit])
    poses = K = size = mask = cam = None
    no_poses = None
    if not (out / "trajectory.tum").is_file():
        no_poses = f"{out / 'trajectory.tum'} is missing"
    elif not (out / "report.json").is_file():
        no_poses = f"{out / 'report.json'} is missing"
    else:
        cam = json.loads((out / "report.json").read_text()).get("camera")
        if cam:
            _, poses = read_tum(out / "trajectory.tum")
            # what the real camera saw: its distortion and field of view, not the undistorted frame's crop
            K, size, mask = camera_view(read_report_camera(cam))
        else:
            no_poses = f"{out / 'report.json'} records no camera"
    points = read_points_ply(points_file)
    mismatch = unit_mismatch(points, truth)
    if mismatch:
        hint = (" (--truth-unit mm reads it so)" if unit == "m" and "millimetres" in mismatch
                else f" (it was read in {unit}: {unit_from})")
        raise ConfigError(f"{truth_file}: {mismatch}{hint}")
    result = evaluate_points(points, truth, poses, K, size, coverage_mm, mask=mask)
    if "error" in result:
        raise ConfigError(f"{points_file}: {result['error']}")
    result["truth"] = {"file": str(truth_file), "unit": unit, "unit_from": unit_from}
    if no_poses and result["coverage"]["covered_fraction"] is None:
        result["coverage"]["why"] = f"no camera poses ({no_poses}): which part of the truth was seen is unknown"
    for warning in result["warnings"]:
        log.warning("%s", warning)
    if (out / "dense.ply").is_file() and poses is not None:
        dense = read_points_ply(out / "dense.ply")
        result["surface"] = surface_report(truth, poses, K, size, sparse=points, dense=dense, mask=mask)
    return result


def _truth_file_and_unit(path: Path, truth_unit: str | None) -> tuple[Path, str, str]:
    """The mesh to read, its length unit and where that unit came from. A session folder stands for its
    truth/surface.ply; a session's truth/surface.ply is in the session's unit (session.json), unless
    ``truth_unit`` says otherwise; any other mesh is in metres unless it says otherwise."""
    from lapreco_hil.sessions import format as fmt

    session = None
    if path.is_dir():
        if not (path / "session.json").is_file():
            raise ConfigError(f"{path}: a folder, not a session (no session.json); give a mesh or a session")
        session, path = path, path / fmt.TRUTH_SURFACE_FILE
        if not path.is_file():
            raise ConfigError(f"{path}: missing; session {session} has no ground-truth surface")
    elif not path.is_file():
        raise ConfigError(f"{path}: no such ground-truth mesh")
    elif path.parent.name == "truth" and (path.parent.parent / "session.json").is_file():
        session = path.parent.parent
    if truth_unit is not None:
        if truth_unit not in TRUTH_UNITS:
            raise ConfigError(f"truth unit {truth_unit!r}: use one of {', '.join(TRUTH_UNITS)}")
        return path, truth_unit, "--truth-unit"
    if session is not None:
        unit = fmt.read_meta(session).length_unit
        if unit not in TRUTH_UNITS:
            raise ConfigError(f"{session / 'session.json'}: length unit {unit!r}; give --truth-unit")
        return path, unit, f"{session / 'session.json'}"
    return path, "m", "the default"
