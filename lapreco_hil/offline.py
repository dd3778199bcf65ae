"""One finite source through the pipeline into the outputs contract (DESIGN.md): points.ply, mesh.ply,
trajectory.tum, reconstruction.png and report.json, with accuracy when the source carries ground truth.
``lapreco demo`` (simulated devices) and ``lapreco replay`` (a session) are both this."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from .camera import CameraModel
from .config import PipelineConfig
from .evaluation.accuracy import distance_stats_mm, pose_error_stats, surface_distances
from .evaluation.truth import GroundTruth
from .outputs import write_mesh_ply, write_points_ply, write_report, write_tum
from .pipeline import run_sequence
from .surface.mesh import alpha_shape
from .surface.render import render_reconstruction


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


def write_frame_timings(path: Path, frames, stage_s: dict) -> None:
    """Per-frame stage times (ms), for plots of tracking time over a sequence (the seed's Fig 5)."""
    names = [k for k in ("capture", "pose", "frontend", "mapper") if len(stage_s.get(k, [])) == len(frames)]
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(",".join(["seq", "t_ns", *(f"{n}_ms" for n in names)]) + "\n")
        for i, f in enumerate(frames):
            fh.write(",".join([str(f.seq), str(f.t_ns), *(f"{stage_s[n][i] * 1e3:.3f}" for n in names)]) + "\n")


def _percentiles_ms(values_s) -> dict:
    ms = np.asarray(values_s) * 1e3
    return {"mean": float(np.mean(ms)), "p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)),
            "p99": float(np.percentile(ms, 99))}


def reconstruct(grabber, poses, camera: CameraModel, config: PipelineConfig, out_dir: Path, *, tracker: str,
                device: str, truth: GroundTruth | None = None, progress: bool = True, total: int | None = None,
                label: str = "frames", report_fields: dict | None = None) -> dict:
    """Run ``grabber`` (opened) with pose source ``poses`` to its end, write the outputs into ``out_dir``
    (already prepared) and return the report."""
    from tqdm import tqdm

    bar = tqdm(total=total, desc=label, unit="frame", file=sys.stderr, disable=not progress)
    with bar:
        run = run_sequence(grabber, poses, camera, config, tracker=tracker, progress=bar, device=device)
    write_frame_timings(out_dir / "frame_timings.csv", run.map.frames, run.stage_s)
    metrics = {
        "frames": {"in": run.frames_in, "processed": run.frames_processed,
                   "dropped": run.frames_in - run.frames_processed - run.frames_without_pose,
                   "without_pose": run.frames_without_pose,
                   "without_pose_by_cause": run.without_pose_by_cause},
        "throughput_fps": run.frames_processed / run.wall_s,
        "latency_ms": {**_percentiles_ms(run.latency_s),
                       "note": "frame received -> pose and points updated (sequential runner)"},
        "stage_ms": {k: _percentiles_ms(v) for k, v in run.stage_s.items() if v},
    }
    return write_outputs(run.map, camera, config, out_dir, tracker=tracker, device=device, truth=truth,
                         report_fields=report_fields, metrics=metrics, run_wall_s=run.wall_s)


def write_outputs(m, camera: CameraModel, config: PipelineConfig, out_dir: Path, *, tracker: str, device: str,
                  truth: GroundTruth | None, report_fields: dict | None, metrics: dict, run_wall_s: float) -> dict:
    """The outputs contract from a finished map: mesh, PLYs, TUM trajectory, picture, report.json."""
    t0 = time.perf_counter()
    points, colors = m.points[m.inlier], m.colors[m.inlier]
    mesh = alpha_shape(points, colors, config.surface.alpha_factor)
    surface_s = time.perf_counter() - t0
    accuracy = accuracy_report(m, truth) if truth is not None else None

    t1 = time.perf_counter()
    write_points_ply(out_dir / "points.ply", points, colors)
    write_mesh_ply(out_dir / "mesh.ply", mesh)
    write_tum(out_dir / "trajectory.tum", np.array([f.t_ns for f in m.frames]), m.frame_poses)
    cams = [(k.T_world_camera, k.refined) for k in m.keyframes]
    render_reconstruction(str(out_dir / "reconstruction.png"), mesh, points, colors, cams,
                          (camera.width, camera.height),
                          (config.surface.render_width, config.surface.render_height), camera.fx)
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
        "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), "dist": list(camera.dist)},
        "out": str(out_dir),
        **metrics,
        "wall_s": run_wall_s + surface_s + output_s,
        "stage_ms": stage_ms,
        "tracks": m.stats["tracks"],
        "keyframes": m.stats["keyframes"],
        "landmarks": m.stats["landmarks"],
        "inliers": m.stats["inliers"],
        "outliers": m.stats["outliers"],
        "observations": m.observations,
        "inlier_observations": m.inlier_observations,
        "mesh": {"points": int(mesh.n_points), "triangles": int(mesh.n_cells)},
        "bundle_adjustment": {k: m.stats[k] for k in ("local_ba_runs", "local_ba_mean_s", "final_ba_s")},
    }
    if accuracy is not None:
        report["accuracy"] = accuracy
    write_report(out_dir / "report.json", report)
    return report
