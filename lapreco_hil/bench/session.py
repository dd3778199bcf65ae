"""``lapreco bench session``: how fast a session is written (crash-safe PNG + CSV rows) and read back,
at given resolutions, with textured synthetic frames (noise compresses like real video, not like a flat
image). Recording must keep up with the grabber; these figures say up to which frame rate it does."""

from __future__ import annotations

import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.sessions import Session, SessionMeta
from lapreco_hil.sessions.writer import SessionWriter
from lapreco_hil.types import Frame


def _frames(width: int, height: int, n: int, seed: int = 0) -> list[np.ndarray]:
    import cv2

    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 255, (height, width, 3), dtype=np.uint8), (0, 0), 3)
    return [np.clip(base.astype(np.int16) + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8)
            for _ in range(n)]


def run(resolutions, frames: int = 60, compression: int = 1) -> dict:
    rows = []
    for w, h in resolutions:
        images = _frames(w, h, min(frames, 8))
        cam = CameraModel(w, h, w, w, w / 2, h / 2)
        meta = SessionMeta(camera=cam, pose_source="camera_poses")
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "s"
            t0 = time.perf_counter()
            with SessionWriter(folder, meta, png_compression=compression) as writer:
                workers = writer.workers
                for i in range(frames):
                    writer.add_frame(Frame(images[i % len(images)], 1_000 + i * 16_666_667, i))
                    writer.add_camera_pose(1_000 + i * 16_666_667, np.eye(4))
            write_s = time.perf_counter() - t0
            size = sum(p.stat().st_size for p in folder.rglob("*"))
            t1 = time.perf_counter()
            s = Session(folder)
            for i in range(len(s)):
                s.frame(i)
            read_s = time.perf_counter() - t1
        rows.append({"resolution": f"{w}x{h}", "frames": frames, "write_fps": frames / write_s,
                     "read_fps": frames / read_s, "mb_per_frame": size / frames / 1e6, "encoder_threads": workers})
    return {"machine": platform.processor() or platform.machine(), "png_compression": compression, "rows": rows}


def format_table(result: dict) -> str:
    lines = [f"session write/read (PNG compression {result['png_compression']}, {result['machine']})",
             "| resolution | write fps | encoder threads | read fps | MB/frame |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['resolution']} | {r['write_fps']:.1f} | {r['encoder_threads']} | {r['read_fps']:.1f} | "
                     f"{r['mb_per_frame']:.2f} |")
    return "\n".join(lines)
