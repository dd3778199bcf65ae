"""A/B on a loaded machine: the OpenCV front-end's per-frame time (wall and the thread's CPU time) paced at the
session's rate, with the live dense stage (a) idle, (b) in a thread of this process (as before session 16), (c)
in its own process (DenseProcess). Short blocks, interleaved, so the machine's load drifts over all three alike.
Keyframes (every ``--every`` frames, true poses) go to the dense stage under test; real stereo on Warp's CPU.

usage: python docs/scripts/dense_ab.py SESSION [--rounds R] [--block N] [--every K]"""

import argparse
import threading
import time
from types import SimpleNamespace

import numpy as np

from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense.surface import DenseSurface, stereo_functions
from lapreco_hil.frontend import make_frontend
from lapreco_hil.runtime.dense_process import DenseProcess, DenseSpec
from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.stages import Dense, StageLinks
from lapreco_hil.sessions import format as fmt
from lapreco_hil.sessions.session import Session
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.warp_device import init_warp, preload_kernels


class PlaneDepth:
    """A flat stand-in depth map 10 cm away (the stage's host work and fusion without stereo)."""

    def __call__(self, ref, sources, cfg, device):
        h, w = ref.colour.shape[:2]
        d = (np.full((h, w), 0.1, np.float32) * ref.mask).astype(np.float32)
        return DepthMap(ref.kf_id, d, ref.mask.astype(np.float32), ref.K, ref.T_world_camera)


class NoDepth:
    """No depth map: the stage's host work only (undistortion, JPEG, source choice and decoding)."""

    def __call__(self, ref, sources, cfg, device):
        return None


def main():
    p = argparse.ArgumentParser()
    p.add_argument("session")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--block", type=int, default=75)
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--dense-session", help="keyframes from this session (its camera) instead")
    p.add_argument("--host-only", action="store_true", help="no depth maps: the stage's host work only")
    a = p.parse_args()
    init_warp()
    s = Session(a.session)
    t_ns, poses = fmt.read_pose_table(s.folder / "truth" / "camera_poses.csv", 1.0)
    pose_at = dict(zip(t_ns.tolist(), poses))
    config = PipelineConfig()
    period = 1.0 / s.meta.fps if getattr(s.meta, "fps", None) else 0.04
    n = len(s.frame_t_ns)
    frames = [s.frame(i) for i in range(n)]
    T = [pose_at[int(t)] for t in s.frame_t_ns]
    busy = config.runtime.dense_busy_share
    ds = Session(a.dense_session) if a.dense_session else s
    if a.dense_session:
        dt, dp = fmt.read_pose_table(ds.folder / "truth" / "camera_poses.csv", 1.0)
        dpose = dict(zip(dt.tolist(), dp))
        kf_images = [ds.frame(i).image for i in range(len(ds.frame_t_ns))]
        kf_T = [dpose[int(t)] for t in ds.frame_t_ns]
    else:
        kf_images, kf_T = [f.image for f in frames], T

    def functions():
        if a.host_only:
            from lapreco_hil.dense.surface import nearest_views
            return NoDepth(), nearest_views, None
        return stereo_functions()

    # (b) the stage in a thread here
    preload_kernels("lapreco_hil.dense.warp", "cpu")
    t_links, t_metrics = StageLinks(), LiveMetrics()
    depth_fn, sources_fn, _ = functions()
    thread_stage = Dense(DenseSurface(ds.camera, config, "cpu", None, depth_fn, sources_fn), t_links, t_metrics,
                         period_s=None, device="cpu", busy_share=busy)
    threading.Thread(target=thread_stage.run, daemon=True).start()
    # (c) its own process
    p_links, p_metrics = StageLinks(), LiveMetrics()
    depth_fn, sources_fn, _ = functions()
    proc = DenseProcess(DenseSpec(ds.camera, config, "cpu", None, depth_fn, sources_fn, period_s=None,
                                  busy_share=busy), p_links, p_metrics)
    proc.start()
    assert proc.wait_ready(300)
    threading.Thread(target=proc.run, daemon=True).start()

    results = {"idle": [], "thread": [], "process": []}
    i = 0
    kf = {"thread": 0, "process": 0}
    for r in range(a.rounds):
        for mode in ("idle", "thread", "process"):
            fe = make_frontend("opencv", s.camera, config.tracker)
            next_t = time.perf_counter()
            for j in range(a.block):
                f = frames[i % n]
                if mode != "idle" and j % a.every == 0:
                    target = thread_stage if mode == "thread" else proc
                    k = kf[mode] % len(kf_images)
                    target.keyframe(kf[mode], SimpleNamespace(image=kf_images[k]), kf_T[k])
                    kf[mode] += 1
                w0, c0 = time.perf_counter(), time.thread_time()
                fe.process(f, None)
                results[mode].append((time.perf_counter() - w0, time.thread_time() - c0))
                i += 1
                next_t += period
                time.sleep(max(0.0, next_t - time.perf_counter()))
            # let the dense stage drain a little between blocks so the next block's mode starts clean
            time.sleep(1.0)
    t_links.stop.set()
    p_links.finished.set()
    proc.close()
    print(f"{s.camera.width}x{s.camera.height} front-end, {ds.camera.width}x{ds.camera.height} keyframes"
          f"{' (host work only)' if a.host_only else ''}, {a.rounds} rounds x {a.block} frames per mode, a keyframe every "
          f"{a.every} frames, busy share {busy}")
    print("| dense stage | front-end wall mean / p95 ms | its CPU time mean ms | wall - CPU (waiting) ms | keyframes fused |")
    print("|---|---|---|---|---|")
    fused = {"idle": 0, "thread": t_metrics.get("dense_keyframes"), "process": p_metrics.get("dense_keyframes")}
    for mode, v in results.items():
        w = np.array([x[0] for x in v]) * 1e3
        c = np.array([x[1] for x in v]) * 1e3
        print(f"| {mode} | {w.mean():.1f} / {np.percentile(w, 95):.1f} | {c.mean():.1f} | {(w - c).mean():.1f} | "
              f"{fused[mode]} |")


if __name__ == "__main__":
    main()
