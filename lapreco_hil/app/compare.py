"""``lapreco compare``: the seed paper's comparison on one session: the Warp tracker and the OpenCV tracker,
each with and without the drift check, replayed on identical input; inliers (its Fig 3), tracking time per
frame (Fig 5), the RMS error against the true surface after rigid ICP (Fig 6b; the scale similarity ICP would
need beside it), and camera pose error before and after bundle adjustment."""

from __future__ import annotations

import json
import logging

import numpy as np

from lapreco_hil.evaluation.compare import (VARIANTS, SEED_FIGURES, format_markdown, frame_timings, plot_tracking_times,
                                  read_points_ply, read_report_camera, read_tum, variant_name)
from lapreco_hil.evaluation.coverage import camera_view
from lapreco_hil.evaluation.icp import evaluate_points
from lapreco_hil.outputs import prepare_output_dir
from lapreco_hil.sessions import Session
from lapreco_hil.app.replay import run_replay

log = logging.getLogger(__name__)


def run_comparison(session: str, out: str, device: str = "auto", config_path: str | None = None,
                   variants=VARIANTS, progress: bool = True) -> dict:
    truth = Session(session).ground_truth()  # a session that cannot be read leaves no output folder
    out_dir = prepare_output_dir(out)
    rows = []
    for tracker, drift in variants:
        name = variant_name(tracker, drift)
        log.info("compare: %s", name)
        report = run_replay(session, str(out_dir / name), tracker=tracker, device=device, config_path=config_path,
                            drift_check=drift, progress=progress)
        times = frame_timings(out_dir / name / "frame_timings.csv")
        row = {"variant": name, "tracker": tracker, "drift_check": drift, "inliers": report["inliers"],
               "outliers": report["outliers"], "tracking_ms_mean": float(np.mean(times["frontend_ms"])),
               "tracking_ms_p95": float(np.percentile(times["frontend_ms"], 95)),
               "tracking_ms_per_frame": times["frontend_ms"].tolist(), "device": report["device"]}
        acc = report.get("accuracy", {})
        if "camera_raw_fk" in acc:
            row["camera_raw_mm"] = acc["camera_raw_fk"]["position_rms_mm"]
            row["camera_refined_mm"] = acc["camera_refined"]["position_rms_mm"]
        surface = acc.get("surface") or {}
        row["coverage_1mm_sparse"] = surface.get("sparse", {}).get("coverage")
        row["coverage_1mm_dense"] = surface.get("dense", {}).get("coverage")
        row["dense_rms_mm"] = surface.get("dense", {}).get("rms_mm")
        if truth is not None and truth.surface is not None:
            cam = report["camera"]
            _, poses = read_tum(out_dir / name / "trajectory.tum")
            K, size, mask = camera_view(read_report_camera(cam))  # what the real camera saw
            ev = evaluate_points(read_points_ply(out_dir / name / "points.ply"), truth.surface, poses, K, size,
                                 mask=mask)
            if "error" in ev:  # (a truth in another unit, ...): said, and kept in the row, not blank columns
                log.error("compare: %s: evaluation failed: %s", name, ev["error"])
                row["evaluation_error"] = ev["error"]
            # the headline is rigid ICP (the world frame is metric); the similarity's scale is what the map
            # would need (lapreco_hil.evaluation.icp)
            row["icp_rms_mm"] = ev.get("icp", {}).get("rms_mm")
            row["unaligned_rms_mm"] = ev.get("unaligned", {}).get("rms_mm")
            row["icp_scale"] = ev.get("similarity", {}).get("scale")
            row["similarity_rms_mm"] = ev.get("similarity", {}).get("rms_mm")
            row["coverage"] = ev.get("coverage", {}).get("covered_fraction")
            row["evaluation_warnings"] = ev.get("warnings", [])
            for warning in row["evaluation_warnings"]:
                log.warning("compare: %s: %s", name, warning)
        rows.append(row)
    result = {"session": str(session), "variants": rows,
              "seed": {variant_name(*k): v for k, v in SEED_FIGURES.items()}}
    (out_dir / "comparison.json").write_text(json.dumps(result, indent=2))
    (out_dir / "comparison.md").write_text(format_markdown(result))
    plot_tracking_times(result, out_dir / "tracking_time.png")
    return result
