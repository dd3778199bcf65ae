"""``lapreco bench frontend``: the Warp front-end and the OpenCV baseline on the same simulated frames.

Each stage is timed per frame with the device synchronised at its end (the front-end reads its per-track
results back at stage boundaries), median over the frames after a warm-up. OpenCV uses all CPU threads.

The Warp front-end is also timed on the live path: every frame with the camera's motion, as a live run's pose
source and map give it (the true relative pose, each track's depth from the renderer where it has one); and with
its frames in page-locked memory, as a live run's capture thread stages them (``PageLockedFrames``: the copy is
the capture thread's, beside tracking, so it is not in the front-end's time).

On CUDA each row also has the GPU time of every kernel and copy per frame (``kernels_ms``: the frames without a
motion, kernels launched one by one under Warp's activity timing), which names what a frame's time goes to.
"""

from __future__ import annotations

import dataclasses
import re
from collections import defaultdict

import os
import platform
import time

import cv2
import numpy as np

from lapreco_hil.config import TrackerConfig

# the depth range a track without a depth is searched over (the live run's before its map has points)
SCENE_DEPTH_M = (0.03, 0.3)


def _frames(scene: str, width: int, height: int, n: int, device: str):
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    world = SimWorld(SimSettings(scene=scene, width=width, height=height, device=device))
    from lapreco_hil.types import Frame

    out, truth = [], []
    for k in range(n):
        t = world.now_ns() + int(k * 1e9 / 25)
        image, depth = world.render(t, k)
        out.append(Frame(image, t, k))
        truth.append((depth, world.true_camera_pose(t)))
    return world.camera, out, truth


def _live_motion(truth: list, scene_depth_m: tuple[float, float]):
    """``motion(prev, k)``: the motion into frame k as a live run gives it (None for the first): the true relative
    pose, and each of the previous frame's tracks (``prev``, its observations) with the rendered depth at its
    pixel (the map's landmarks' depths)."""
    from lapreco_hil.mapping.prediction import frame_motion

    def motion(prev, k: int):
        if prev is None:
            return None
        depth, T_world_prev = truth[k - 1]
        ids, uv = prev.track_ids, prev.uv
        h, w = depth.shape
        x = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
        y = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
        z = depth[y, x]
        seen = z > 0
        return frame_motion(T_world_prev, truth[k][1], ids[seen], z[seen], scene_depth_m)

    return motion


def _pass(frontend, frames, warmup: int, motion=None, page_locked=None):
    stages: dict[str, list[float]] = {}
    totals, tracks = [], []
    obs = None
    for k, frame in enumerate(frames):
        frame_motion = motion(obs, k) if motion is not None else None
        if page_locked is not None:
            frame = page_locked.stage(frame)  # (the capture thread's work in a live run)
        t0 = time.perf_counter()
        obs = frontend.process(frame, frame_motion)
        dt = time.perf_counter() - t0
        if k < warmup:
            continue
        totals.append(dt)
        tracks.append(len(obs))
        for name, v in obs.timings_s.items():
            stages.setdefault(name, []).append(v)
    return totals, tracks, {name: float(np.median(v)) * 1e3 for name, v in stages.items()}


KERNEL_ROWS = 12  # kernels listed per row, costliest first


def kernel_times(activities, frames: int) -> dict[str, float]:
    """GPU ms per frame of each kernel or copy (Warp's ``TimingResult`` list over ``frames`` frames), costliest
    first; a kernel's name without Warp's prefix and module hash."""
    per: dict[str, float] = defaultdict(float)
    for a in activities:
        name = re.sub(r"^(forward|builtin) kernel ", "", a.name)
        name = re.sub(r"_[0-9a-f]{8}$", "", name).replace("_make_lk_track__locals___lk_track", "lk_track")
        name = name.replace("_make_drift_check__locals___drift_check", "drift_check")
        per[name] += a.elapsed / max(frames, 1)
    return dict(sorted(per.items(), key=lambda kv: -kv[1]))


def _kernel_profile(frontend, frames, warmup: int) -> dict[str, float]:
    """Per-kernel GPU time of the frames after the warm-up, each kernel launched on its own (no graph): where the
    front-end's time goes. Empty off CUDA (no activity timing there)."""
    import warp as wp

    if not frontend.device.is_cuda:
        return {}
    frontend.use_graphs = False
    for frame in frames[:warmup]:
        frontend.process(frame)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for frame in frames[warmup:]:
        frontend.process(frame)
    return kernel_times(wp.timing_end(), len(frames) - warmup)


def _run(make, frames, warmup: int, motion=None, page_locked=None, make_without_prior=None) -> dict:
    """Totals from a steady-state pass; per-stage times from a second pass that synchronises at stage ends
    (where the front-end can: the Warp one has a ``profile`` switch, OpenCV's stages are synchronous). With
    ``motion`` (the Warp front-end), a third pass gives every frame its motion: the live path's totals. With
    ``page_locked`` (a pool), both totals again with the frames staged in page-locked memory. With
    ``make_without_prior``, the frames without a motion once more without the global motion prior (the host's
    alignment that a frame without a motion pays for: ``[tracker] global_motion_prior``)."""
    frontend = make()
    totals, tracks, stages = _pass(frontend, frames, warmup)
    if hasattr(frontend, "profile"):
        profiled = make()
        profiled.profile = True
        _, _, stages = _pass(profiled, frames, warmup)
    row = {"total_ms": float(np.median(totals)) * 1e3, "total_p95_ms": float(np.percentile(totals, 95)) * 1e3,
           "stages_ms": stages, "tracks_median": float(np.median(tracks))}
    if hasattr(frontend, "prior_aligned"):  # the Warp front-end: where each frame's prior was aligned
        row["prior_aligned"] = dict(frontend.prior_aligned)
    if make_without_prior is not None:
        bare, _, _ = _pass(make_without_prior(), frames, warmup)
        row["without_global_prior_ms"] = float(np.median(bare)) * 1e3
        if hasattr(frontend, "use_graphs"):
            kernels = _kernel_profile(make_without_prior(), frames, warmup)
            if kernels:
                row["kernels_ms"] = kernels
    if motion is not None:
        live, live_tracks, _ = _pass(make(), frames, warmup, motion)
        row["with_motion"] = {"total_ms": float(np.median(live)) * 1e3,
                              "total_p95_ms": float(np.percentile(live, 95)) * 1e3,
                              "tracks_median": float(np.median(live_tracks))}
    if page_locked is not None:
        staged, _, _ = _pass(make(), frames, warmup, page_locked=page_locked)
        row["page_locked"] = {"total_ms": float(np.median(staged)) * 1e3,
                              "total_p95_ms": float(np.percentile(staged, 95)) * 1e3}
        if motion is not None:
            staged, _, _ = _pass(make(), frames, warmup, motion, page_locked)
            row["page_locked"]["with_motion_ms"] = float(np.median(staged)) * 1e3
    return row


def run(device: str, resolutions: list[tuple[int, int]], features: list[int], frames: int = 40,
        warmup: int = 8, scene: str = "skull", baseline: bool = True) -> dict:
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd
    from lapreco_hil.frontend.warp import WarpFrontEnd
    from lapreco_hil.frontend.warp.page_locked import PageLockedFrames

    cv2.setNumThreads(os.cpu_count() or 1)
    rows = []
    for width, height in resolutions:
        camera, seq, truth = _frames(scene, width, height, frames, device)
        for n in features:
            # enough room for n corners inside the field of view
            min_distance = float(np.clip(0.5 * np.sqrt(width * height / n), 3.0, 10.0))
            cfg = TrackerConfig(max_features=n, min_distance_px=min_distance, quality_level=0.001)
            bare = dataclasses.replace(cfg, global_motion_prior=False)
            warp_row = _run(lambda: WarpFrontEnd(camera, cfg, device), seq, warmup,
                            motion=_live_motion(truth, SCENE_DEPTH_M),
                            page_locked=PageLockedFrames((height, width, 3), 4, device),
                            make_without_prior=lambda: WarpFrontEnd(camera, bare, device))
            row = {"resolution": f"{width}x{height}", "features": n, "min_distance_px": min_distance, "warp": warp_row}
            if baseline:
                cv_row = _run(lambda: OpenCVFrontEnd(camera, cfg), seq, warmup,
                              make_without_prior=lambda: OpenCVFrontEnd(camera, bare))
                row.update({"opencv": cv_row, "ratio_total": cv_row["total_ms"] / max(warp_row["total_ms"], 1e-9),
                            "ratio_lk": cv_row["stages_ms"].get("track", 0.0)
                            / max(warp_row["stages_ms"].get("lk", 0.0), 1e-9)})
            rows.append(row)
    return {"benchmark": "frontend", "device": device, "frames": frames, "warmup": warmup, "scene": scene,
            "cpu_threads": os.cpu_count(), "machine": platform.node(), "processor": platform.processor(),
            "rows": rows}


def format_table(result: dict) -> str:
    lines = [f"front-end on {result['device']} ({result['frames']} frames, {result['warmup']} warm-up, medians; "
             f"OpenCV on {result['cpu_threads']} threads)",
             f"{'resolution':>10s} {'N':>5s} | {'warp total':>10s} {'upload':>7s} {'prepare':>8s} {'lk':>7s} "
             f"{'drift':>7s} {'detect':>7s} {'tracks':>6s} {'-prior':>7s} {'+motion':>8s} {'locked':>7s} "
             f"{'+motion':>8s} | {'cv total':>9s} {'-prior':>7s} {'cv lk':>7s} "
             f"{'cv drift':>8s} | {'x total':>7s} {'x LK':>6s}"]
    nan = float("nan")
    for r in result["rows"]:
        w = r["warp"]
        c = r.get("opencv", {"total_ms": nan, "stages_ms": {"track": nan, "drift_check": nan}})  # (--warp-only)
        ws, cs = w["stages_ms"], c["stages_ms"]
        live = w.get("with_motion", {}).get("total_ms", float("nan"))
        locked = w.get("page_locked", {})
        lines.append(f"{r['resolution']:>10s} {r['features']:>5d} | {w['total_ms']:10.2f} {ws.get('upload', 0):7.2f} "
                     f"{ws.get('prepare', 0):8.2f} {ws.get('lk', 0):7.2f} {ws.get('drift_check', 0):7.2f} "
                     f"{ws.get('detect', 0):7.2f} {w['tracks_median']:6.0f} "
                     f"{w.get('without_global_prior_ms', float('nan')):7.2f} {live:8.2f} "
                     f"{locked.get('total_ms', float('nan')):7.2f} {locked.get('with_motion_ms', float('nan')):8.2f} | "
                     f"{c['total_ms']:9.2f} {c.get('without_global_prior_ms', float('nan')):7.2f} "
                     f"{cs.get('track', 0):7.2f} {cs.get('drift_check', 0):8.2f} | {r.get('ratio_total', nan):7.1f} "
                     f"{r.get('ratio_lk', nan):6.1f}")
    for r in result["rows"]:
        kernels = r["warp"].get("kernels_ms")
        if kernels:
            top = ", ".join(f"{name} {ms:.3f}" for name, ms in list(kernels.items())[:KERNEL_ROWS])
            lines.append(f"{r['resolution']} / {r['features']}: GPU ms per frame (-prior, {sum(kernels.values()):.2f} "
                         f"in all): {top}")
    lines.append("-prior: the frames without a motion, without the global motion prior's host alignment; +motion: "
                 "the Warp front-end's total with every frame's motion given, as in a live run (no alignment); "
                 "locked: the frames in page-locked memory, as the live run's capture thread stages them on CUDA")
    return "\n".join(lines)
