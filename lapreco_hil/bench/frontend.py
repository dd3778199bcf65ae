"""``lapreco bench frontend``: the Warp front-end and the OpenCV baseline on the same simulated frames.

Each stage is timed per frame with the device synchronised at its end (the front-end reads its per-track
results back at stage boundaries), median over the frames after a warm-up. OpenCV uses all CPU threads.
"""

from __future__ import annotations

import os
import platform
import time

import cv2
import numpy as np

from lapreco_hil.config import TrackerConfig


def _frames(scene: str, width: int, height: int, n: int, device: str):
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    world = SimWorld(SimSettings(scene=scene, width=width, height=height, device=device))
    from lapreco_hil.types import Frame

    out = []
    for k in range(n):
        t = world.now_ns() + int(k * 1e9 / 25)
        out.append(Frame(world.render(t, k)[0], t, k))
    return world.camera, out


def _pass(frontend, frames, warmup: int):
    stages: dict[str, list[float]] = {}
    totals, tracks = [], []
    for k, frame in enumerate(frames):
        t0 = time.perf_counter()
        obs = frontend.process(frame)
        dt = time.perf_counter() - t0
        if k < warmup:
            continue
        totals.append(dt)
        tracks.append(len(obs))
        for name, v in obs.timings_s.items():
            stages.setdefault(name, []).append(v)
    return totals, tracks, {name: float(np.median(v)) * 1e3 for name, v in stages.items()}


def _run(make, frames, warmup: int) -> dict:
    """Totals from a steady-state pass; per-stage times from a second pass that synchronises at stage ends
    (where the front-end can: the Warp one has a ``profile`` switch, OpenCV's stages are synchronous)."""
    frontend = make()
    totals, tracks, stages = _pass(frontend, frames, warmup)
    if hasattr(frontend, "profile"):
        profiled = make()
        profiled.profile = True
        _, _, stages = _pass(profiled, frames, warmup)
    return {"total_ms": float(np.median(totals)) * 1e3, "total_p95_ms": float(np.percentile(totals, 95)) * 1e3,
            "stages_ms": stages, "tracks_median": float(np.median(tracks))}


def run(device: str, resolutions: list[tuple[int, int]], features: list[int], frames: int = 40,
        warmup: int = 8, scene: str = "skull") -> dict:
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd
    from lapreco_hil.frontend.warp import WarpFrontEnd

    cv2.setNumThreads(os.cpu_count() or 1)
    rows = []
    for width, height in resolutions:
        camera, seq = _frames(scene, width, height, frames, device)
        for n in features:
            # enough room for n corners inside the field of view
            min_distance = float(np.clip(0.5 * np.sqrt(width * height / n), 3.0, 10.0))
            cfg = TrackerConfig(max_features=n, min_distance_px=min_distance, quality_level=0.001)
            warp_row = _run(lambda: WarpFrontEnd(camera, cfg, device), seq, warmup)
            cv_row = _run(lambda: OpenCVFrontEnd(camera, cfg), seq, warmup)
            rows.append({
                "resolution": f"{width}x{height}", "features": n, "min_distance_px": min_distance,
                "warp": warp_row, "opencv": cv_row,
                "ratio_total": cv_row["total_ms"] / max(warp_row["total_ms"], 1e-9),
                "ratio_lk": cv_row["stages_ms"].get("track", 0.0) / max(warp_row["stages_ms"].get("lk", 0.0), 1e-9),
            })
    return {"benchmark": "frontend", "device": device, "frames": frames, "warmup": warmup, "scene": scene,
            "cpu_threads": os.cpu_count(), "machine": platform.node(), "processor": platform.processor(),
            "rows": rows}


def format_table(result: dict) -> str:
    lines = [f"front-end on {result['device']} ({result['frames']} frames, {result['warmup']} warm-up, medians; "
             f"OpenCV on {result['cpu_threads']} threads)",
             f"{'resolution':>10s} {'N':>5s} | {'warp total':>10s} {'upload':>7s} {'prepare':>8s} {'lk':>7s} {'drift':>7s} {'detect':>7s}"
             f" {'tracks':>6s} | {'cv total':>9s} {'cv lk':>7s} {'cv drift':>8s} | {'x total':>7s} {'x LK':>6s}"]
    for r in result["rows"]:
        w, c = r["warp"], r["opencv"]
        ws, cs = w["stages_ms"], c["stages_ms"]
        lines.append(f"{r['resolution']:>10s} {r['features']:>5d} | {w['total_ms']:10.2f} {ws.get('upload', 0):7.2f} {ws.get('prepare', 0):8.2f} "
                     f"{ws.get('lk', 0):7.2f} {ws.get('drift_check', 0):7.2f} {ws.get('detect', 0):7.2f} "
                     f"{w['tracks_median']:6.0f} | {c['total_ms']:9.2f} {cs.get('track', 0):7.2f} "
                     f"{cs.get('drift_check', 0):8.2f} | {r['ratio_total']:7.1f} {r['ratio_lk']:6.1f}")
    return "\n".join(lines)
