"""One finite source through the sequential pipeline into the outputs contract (lapreco_hil.outputs), with
accuracy when the source carries ground truth. ``lapreco demo --sequential`` and ``lapreco replay`` are both
this."""

from __future__ import annotations

import logging
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.outputs import write_outputs
from lapreco_hil.pipeline import run_sequence
from lapreco_hil.runtime.time_offset_watch import RecordingTimeOffsetWatch

log = logging.getLogger(__name__)


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
                label: str = "frames", report_fields: dict | None = None, rig=None) -> dict:
    """Run ``grabber`` (opened) with pose source ``poses`` to its end, write the outputs into ``out_dir``
    (already prepared) and return the report."""
    from tqdm import tqdm

    tracker_config = config.tracker.for_frames(total)
    if tracker_config is not config.tracker:
        log.info("%d frames: few views, corners detected denser (up to %d, %.1f px apart)", total,
                 tracker_config.max_features, tracker_config.min_distance_px)
        config = replace(config, tracker=tracker_config)
        few = {"frames": total, "max_features": tracker_config.max_features,
               "min_distance_px": tracker_config.min_distance_px}
        report_fields = {**(report_fields or {}), "few_views": few}
    # the pose source's clock against the video's, watched from the run's own tracks as a live run watches it
    # (runtime/time_offset_watch.py): report.json time_offset, for every pose source alike
    watch = RecordingTimeOffsetWatch(camera.K, poses.time_offset_ns) if hasattr(poses, "time_offset_ns") else None
    bar = tqdm(total=total, desc=label, unit="frame", file=sys.stderr, disable=not progress)
    with bar:
        run = run_sequence(grabber, poses, camera, config, tracker=tracker, progress=bar, device=device,
                           rig=rig if rig is not None else grabber.rig, offset_watch=watch)
    if watch is not None:
        report_fields = {**(report_fields or {}), "time_offset": watch.finish()}
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
                         report_fields=report_fields, metrics=metrics, run_wall_s=run.wall_s, dense=run.dense,
                         surface_note=run.surface_note)
