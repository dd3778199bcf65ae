"""The outputs contract of a run (DESIGN.md): points.ply, mesh.ply, trajectory.tum, reconstruction.png,
report.json, and dense.ply when the dense surface runs, all in one folder, written from a finished map by
:func:`write_outputs`."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import pyvista as pv

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import OutputError
from lapreco_hil.evaluation.accuracy import accuracy_report, surface_report
from lapreco_hil.geometry import to_tum
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.surface.mesh import alpha_shape
from lapreco_hil.surface.render import ENABLE_RENDERING, offscreen_unavailable, render_reconstruction

log = logging.getLogger(__name__)


def check_output_dir(path: str | Path) -> Path:
    """Prove, before devices are opened, that the folder can be created and written, without creating it:
    a run that never starts leaves nothing behind."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"output folder '{path}' is a file; choose another --out")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write to output folder '{path}' ('{existing}' is not writable); "
                          f"choose another --out")
    return path


def prepare_output_dir(path: str | Path) -> Path:
    """Create the folder (once the run's devices are open) and prove it is writable."""
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


def write_dense_ply(path: Path, points: np.ndarray, normals: np.ndarray, colours: np.ndarray) -> None:
    """The dense surface's points with their normals ("Normals": nx ny nz) and colours ("RGB"), metres."""
    if len(points) == 0:
        _write_empty_ply(path)
        return
    cloud = pv.PolyData(np.asarray(points, np.float64).reshape(-1, 3))
    cloud.point_data["Normals"] = np.asarray(normals, np.float32).reshape(-1, 3)
    cloud.point_data["RGB"] = np.asarray(colours, np.uint8).reshape(-1, 3)
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
            fh.write(to_tum(t, T) + "\n")


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
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)  # a configuration section
    raise TypeError(f"not JSON serialisable: {type(o)}")


def write_outputs(m, camera: CameraModel, config: PipelineConfig, out_dir: Path, *, tracker: str, device: str,
                  truth: GroundTruth | None, report_fields: dict | None, metrics: dict, run_wall_s: float,
                  dense=None, surface_note: str | None = None) -> dict:
    """The outputs contract from a finished map: mesh, PLYs, TUM trajectory, picture, report.json. ``dense``:
    the run's DenseResult ([surface] mode "dense"): mesh.ply is its mesh and dense.ply its points; without it
    the alpha shape of the inlier points (``surface_note`` says why, when the dense surface was asked for)."""
    t0 = time.perf_counter()
    points, colors = m.points[m.inlier], m.colors[m.inlier]
    if dense is None and config.surface.mode == "dense" and surface_note is None:  # (asked for, not built)
        surface_note = "no dense surface was built (its stage was switched off after an error); the alpha shape instead"
        log.warning("dense surface off: %s", surface_note)
    mesh = dense.mesh if dense is not None else alpha_shape(points, colors, config.surface.alpha_factor)
    surface_s = time.perf_counter() - t0
    accuracy = accuracy_report(m, truth) if truth is not None else None
    if accuracy is not None and truth.surface is not None:
        accuracy["surface"] = _surface_accuracy(m, camera, truth, points, dense)

    t1 = time.perf_counter()
    write_points_ply(out_dir / "points.ply", points, colors)
    write_mesh_ply(out_dir / "mesh.ply", mesh)
    if dense is not None:
        write_dense_ply(out_dir / "dense.ply", dense.points, dense.normals, dense.colours)
    t_ns, poses = [f.t_ns for f in m.frames], list(m.frame_poses)
    pair = (report_fields or {}).get("two_frames_as_rig")
    second = next((k for k in m.keyframes if k.reference is not None), None) if pair else None
    if second is not None:  # a pair read as a rig: the second frame's refined pose is its camera-1 view's
        t_ns.append(pair["second_frame_t_ns"])
        poses.append(second.T_world_camera)
    write_tum(out_dir / "trajectory.tum", np.array(t_ns), np.array(poses))
    cams = [(k.T_world_camera, k.refined) for k in m.keyframes if k.reference is None]
    picture = _render_picture(out_dir / "reconstruction.png", mesh, points, colors, cams, camera, config)
    output_s = time.perf_counter() - t1

    metrics = dict(metrics)  # the caller's figures stay as they were
    stage_ms = dict(metrics.pop("stage_ms", {}))
    stage_ms["surface"] = {"mean": surface_s * 1e3}
    stage_ms["outputs"] = {"mean": output_s * 1e3}
    report = {
        "lapreco_version": __import__("lapreco_hil").__version__,
        **(report_fields or {}),
        "tracker": tracker,
        "drift_check": config.tracker.drift_check,
        "device": device,
        "resolution": [camera.width, camera.height],
        "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), "dist": list(camera.dist),
                   "fov_radius_px": camera.fov_radius_px,
                   # any other field of view (evaluate's coverage reads it back: evaluation.compare.read_report_camera)
                   **({"fov": _fov_fields(camera.fov)} if camera.fov is not None else {})},
        "out": str(out_dir),
        **metrics,
        "wall_s": run_wall_s + surface_s + output_s,
        "stage_ms": stage_ms,
        "tracks": m.stats["tracks"],
        "keyframes": m.stats["keyframes"],
        # a stereo scope's other cameras' views of the keyframes, each tied to its keyframe by the rig
        "partner_views": m.stats.get("partner_views", 0),
        "landmarks": m.stats["landmarks"],
        "inliers": m.stats["inliers"],
        "outliers": m.stats["outliers"],
        "funnel": m.stats.get("funnel"),
        # reprojection error of the inlier points in every view that saw them (px, after the final BA)
        "reprojection": m.stats.get("reprojection"),
        # how far the image moved between frames (median track displacement per frame, px)
        "image_motion_px": m.stats.get("image_motion_px"),
        "observations": m.observations,
        "inlier_observations": m.inlier_observations,
        "mesh": {"points": int(mesh.n_points), "triangles": int(mesh.n_cells)},
        "surface": "dense" if dense is not None else "alpha",
        "surface_note": surface_note,
        "dense": dense.stats if dense is not None else None,
        "bundle_adjustment": {k: m.stats[k] for k in ("local_ba_runs", "local_ba_mean_s", "final_ba_s")},
        "picture": picture,
    }
    if accuracy is not None:
        report["accuracy"] = accuracy
    write_report(out_dir / "report.json", report)
    return report


def _fov_fields(fov) -> dict:
    return {f.name: getattr(fov, f.name) for f in dataclasses.fields(fov) if not f.name.startswith("_")}


def _surface_accuracy(m, camera: CameraModel, truth: GroundTruth, points: np.ndarray, dense) -> dict | None:
    """The sparse points and the dense surface side by side against the true surface the reference keyframes
    saw (their refined poses; what the real camera sees, its distortion and field of view: ``camera_view``)."""
    from lapreco_hil.evaluation.coverage import camera_view

    poses = np.array([k.T_world_camera for k in m.keyframes if k.reference is None]).reshape(-1, 4, 4)
    if not len(poses):
        return None
    K, size, mask = camera_view(camera)
    return surface_report(truth.surface, poses, K, size, sparse=points,
                          dense=dense.points if dense is not None else None, mask=mask)


def _render_picture(path: Path, mesh, points, colors, cams, camera: CameraModel, config: PipelineConfig) -> str | None:
    """reconstruction.png, or None with one warning when this machine has no renderer: the picture is the one
    output that needs one, and every other output is written regardless."""
    why = offscreen_unavailable()
    if why is None:
        try:
            render_reconstruction(str(path), mesh, points, colors, cams, (camera.width, camera.height),
                                  (config.surface.render_width, config.surface.render_height), camera.fx)
            return path.name
        except Exception as exc:  # VTK reports a window it cannot make in several ways
            why = f"VTK could not render ({exc})"
    log.warning("%s not written: %s; to enable rendering, %s", path.name, why, ENABLE_RENDERING)
    return None
