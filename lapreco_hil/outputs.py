"""The outputs contract of a run (DESIGN.md): points.ply, mesh.ply, trajectory.tum, reconstruction.png,
report.json, all in one folder."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pyvista as pv

from .errors import OutputError
from .geometry import to_tum


def prepare_output_dir(path: str | Path) -> Path:
    """Create the folder and prove it is writable before any work is done."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".lapreco-write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write to output folder '{path}' ({exc.strerror}); choose another --out") from None
    return path


def _write_empty_ply(path: Path) -> None:
    # VTK refuses to write an empty PLY; an empty reconstruction is still a valid output
    path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")


def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    if len(points) == 0:
        _write_empty_ply(path)
        return
    cloud = pv.PolyData(np.asarray(points, np.float64).reshape(-1, 3))
    cloud.point_data["RGB"] = np.asarray(colors, np.uint8).reshape(-1, 3)
    cloud.save(str(path), texture="RGB", binary=True)


def write_mesh_ply(path: Path, mesh: pv.PolyData) -> None:
    if mesh.n_points == 0 or mesh.n_cells == 0:
        _write_empty_ply(path)
    elif "RGB" in mesh.point_data:
        mesh.save(str(path), texture="RGB", binary=True)
    else:
        mesh.save(str(path), binary=True)


def write_tum(path: Path, t_ns: np.ndarray, poses: np.ndarray) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw  (T_world_camera, metres, capture time in s)\n")
        for t, T in zip(t_ns, poses):
            fh.write(to_tum(t * 1e-9, T) + "\n")


def write_json(path: str | Path, doc: dict) -> None:
    """JSON (numpy values included), written to a temporary file and renamed into place."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(doc, indent=2, default=_json_default), encoding="utf-8")
        os.replace(tmp, path)
    except OSError as exc:
        raise OutputError(f"cannot write '{path}' ({exc.strerror}); choose another path") from None


def write_report(path: Path, report: dict) -> None:
    write_json(path, report)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")
