"""The live dense stage's host work per keyframe, by step, and the share of it that holds the GIL.

Replays a session's frames with their TRUE poses through DenseSurface as the live stage does (a keyframe every
``--every`` frames: add_view, then fuse_pending of the one before). cv2's imdecode / imencode / remap / cvtColor
are timed apart (they release the GIL); the rest of each step is Python / numpy glue, counted as GIL-held.
A probe thread counting in pure Python measures the GIL's availability a second way.

usage: python docs/scripts/dense_host_steps.py SESSION [--every N] [--keyframes K] [--stub-depth]"""

import argparse
import collections
import statistics
import threading
import time

import cv2
import numpy as np

from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense import surface as ds
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.sessions import format as fmt
from lapreco_hil.sessions.session import Session
from lapreco_hil.warp_device import init_warp

CV2_TIMED = ("imdecode", "imencode", "remap", "cvtColor")
tls = threading.local()


class TimedCv2:
    def __getattr__(self, name):
        f = getattr(cv2, name)
        if name not in CV2_TIMED:
            return f

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                acc = getattr(tls, "acc", None)
                if acc is not None:
                    acc[name] += time.perf_counter() - t0
        return timed


def main():
    p = argparse.ArgumentParser()
    p.add_argument("session")
    p.add_argument("--every", type=int, default=5)
    p.add_argument("--keyframes", type=int, default=20)
    p.add_argument("--stub-depth", action="store_true", help="a plane for depth (host steps only)")
    p.add_argument("--probe", action="store_true")
    a = p.parse_args()
    init_warp()
    s = Session(a.session)
    t_ns, poses = fmt.read_pose_table(s.folder / "truth" / "camera_poses.csv", 1.0)
    pose_at = dict(zip(t_ns.tolist(), poses))
    config = PipelineConfig()
    ds.cv2 = TimedCv2()
    if a.stub_depth:
        def depth_fn(ref, sources, cfg, device):
            h, w = ref.colour.shape[:2]
            d = np.full((h, w), 0.1, np.float32) * ref.mask
            return DepthMap(ref.kf_id, d.astype(np.float32), ref.mask.astype(np.float32), ref.K, ref.T_world_camera)
        surf = ds.DenseSurface(s.camera, config, "cpu", depth_fn=depth_fn, sources_fn=ds.nearest_views)
    else:
        surf = ds.DenseSurface(s.camera, config, "cpu")
    steps = collections.defaultdict(list)  # name -> [(total, cv2)]

    def timed(name, f, *args):
        outer = getattr(tls, "acc", None)
        tls.acc = collections.Counter()
        t0 = time.perf_counter()
        out = f(*args)
        total = time.perf_counter() - t0
        steps[name].append((total, sum(tls.acc.values())))
        if outer is not None:
            outer.update(tls.acc)
        tls.acc = outer
        return out

    # fuse_pending's parts, timed apart
    orig_sources, orig_depth, orig_fuse = surf._sources, surf._depth_map, surf._fuse_and_keep
    orig_view = surf.keyframe_view
    surf._sources = lambda ref: timed("sources (choose + decode)", orig_sources, ref)
    surf._depth_map = lambda ref, src: timed("depth map (device)", orig_depth, ref, src)
    surf._fuse_and_keep = lambda v, d, c: timed("integrate + read back + reach (device)", orig_fuse, v, d, c)

    probe_n = [0]
    stop = threading.Event()

    def probe():
        n = 0
        while not stop.is_set():
            n += 1
            if n & 0xFFFF == 0:
                probe_n[0] = n
        probe_n[0] = n

    png = []
    orig_png = ds._encode_pngs

    def enc(d16, c8):
        t0 = time.perf_counter()
        out = orig_png(d16, c8)
        png.append(time.perf_counter() - t0)
        return out
    ds._encode_pngs = enc
    frames = list(range(0, len(s.frame_t_ns), a.every))[:a.keyframes + 1]
    images = {i: s.frame(i).image for i in frames}
    walls = []
    if a.probe:
        th = threading.Thread(target=probe, daemon=True)
        # baseline rate alone
        th.start(); time.sleep(1.0); base0 = probe_n[0]; time.sleep(1.0); base_rate = probe_n[0] - base0
    n0 = probe_n[0]
    t_all = time.perf_counter()
    for k, i in enumerate(frames):
        T = pose_at[int(s.frame_t_ns[i])]
        t0 = time.perf_counter()
        timed("add_view (undistort + JPEG)", surf.add_view, k, images[i], T)
        if k >= 1:
            timed("reference decode", orig_view, k - 1)
            surf._decoded.pop(k - 1, None)  # (fuse_pending decodes it again, as live)
            timed("fuse_pending (all)", surf.fuse_pending, {k - 1})
        walls.append(time.perf_counter() - t0)
    # the encoder thread's PNGs: wait for them
    t0 = time.perf_counter()
    for v in surf.views.values():
        surf._encoded(v)
    wall = time.perf_counter() - t_all
    if a.probe:
        got = probe_n[0] - n0
        stop.set()
        print(f"probe: {got / wall:.0f}/s during vs {base_rate:.0f}/s alone: GIL free ~{got / wall / base_rate:.0%}")
    # a re-fusion's host part: the stored map and colour decoded
    for v in list(surf.views.values())[1:6]:
        if v.T_fused is not None:
            timed("refuse: map PNG decode", surf._stored_map, v)
    print(f"{s.camera.width}x{s.camera.height}, {len(frames) - 1} keyframes fused, fused={surf.fused}, "
          f"without sources={len(surf.without_sources)}")
    print("| step | ms mean | in cv2 (GIL released) ms | Python/numpy glue (GIL held) ms |")
    print("|---|---:|---:|---:|")
    for name, v in steps.items():
        tot = statistics.mean(x[0] for x in v) * 1e3
        c = statistics.mean(x[1] for x in v) * 1e3
        print(f"| {name} | {tot:.2f} | {c:.2f} | {tot - c:.2f} |")
    print(f"| PNG encode of the kept map (encoder thread, cv2) | {statistics.mean(png) * 1e3:.2f} | all | 0 |")
    print(f"per keyframe wall (add_view + ref decode + fuse_pending): {statistics.mean(walls[1:]) * 1e3:.1f} ms")
    print("timings", {k: round(v, 3) for k, v in surf.timings.items()})


if __name__ == "__main__":
    main()
