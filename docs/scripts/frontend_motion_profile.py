"""Where the Warp front-end's time goes on frames with and without the pose source's motion (docs/benchmarks.md,
session 24): per frame, the total and the host steps before the frame's graph (the start depths, the plan, the
upload), the kinds of frame its graphs were captured for, and with a motion the GPU time of each kernel (launched
one by one under Warp's activity timing, CUDA only).

    python docs/scripts/frontend_motion_profile.py [DEVICE] [small] [motion-only] [host-borrows] [warm] [only=WxH/N,...]

DEVICE: cuda:0 (the default) or cpu; ``small``: 640x360 and 12 frames instead of 1080p and 4K with 40 (a check
that the script runs, on the CPU); ``host-borrows``: the host borrows every start depth, as before session 24
(the device's kernel then has none left to borrow), to compare both on one machine; ``warm``: the front-end's
``warm_up`` first, as a live run does, so that every kind of frame replays a captured graph (session 25 on);
``only``: just these frame sizes and track counts (e.g. ``only=1920x1080/2000,3840x2160/8000``).
"""
import sys
import time
from collections import defaultdict

import numpy as np
import warp as wp

import lapreco_hil.frontend.epipolar as ep
from lapreco_hil.bench.frontend import SCENE_DEPTH_M, _frames, _live_motion, kernel_times
from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend.warp import WarpFrontEnd

args = sys.argv[1:]
device = args[0] if args and args[0] not in ("small", "motion-only", "host-borrows", "warm") and "=" not in args[0] \
    else "cuda:0"
only = next((a[len("only="):].split(",") for a in args if a.startswith("only=")), None)
host_steps = defaultdict(list)


def timed(owner, name):
    f = getattr(owner, name, None)
    if f is None:  # (an earlier version of the front-end, for a comparison)
        return

    def wrapper(*a, **k):
        t = time.perf_counter()
        out = f(*a, **k)
        host_steps[name].append(time.perf_counter() - t)
        return out

    setattr(owner, name, wrapper)


if "host-borrows" in args:
    def _host_borrows(uv, ids, motion, K, size):
        full = ep.start_depths(uv, ids, motion, K, size)
        return None if full is None else (np.where(np.isfinite(full), full, -1.0), full)

    ep.own_start_depths = _host_borrows
for name in ("start_depths", "own_start_depths", "prediction_plan", "borrow_depths"):
    timed(ep, name)
for name in ("_set_motion", "_process_frame", "_to_staging", "_stage_image", "_set_prior"):
    timed(WarpFrontEnd, name)

sizes = [(640, 360)] if "small" in args else [(1920, 1080), (3840, 2160)]
n_frames = 12 if "small" in args else 40
for W, H in sizes:
    camera, seq, truth = _frames("skull", W, H, n_frames, device)
    for N in (2000, 8000):
        if only is not None and f"{W}x{H}/{N}" not in only:
            continue
        min_distance = float(np.clip(0.5 * np.sqrt(W * H / N), 3.0, 10.0))
        cfg = TrackerConfig(max_features=N, min_distance_px=min_distance, quality_level=0.001)
        for with_motion in ((True,) if "motion-only" in args else (False, True)):
            fe = WarpFrontEnd(camera, cfg, device)
            if "warm" in args:
                fe.warm_up()
            motion = _live_motion(truth, SCENE_DEPTH_M)
            obs, totals = None, []
            for k, frame in enumerate(seq):
                m = motion(obs, k) if with_motion else None
                wp.synchronize()
                t = time.perf_counter()
                obs = fe.process(frame, m)
                if k >= 8:
                    totals.append(time.perf_counter() - t)
                if k == 7:
                    host_steps.clear()
            steps = ", ".join(f"{n} {np.median(v) * 1e3:.3f} x{len(v)}" for n, v in host_steps.items())
            print(f"{W}x{H} / {N} motion={with_motion}: total {np.median(totals) * 1e3:.3f} ms; {steps}", flush=True)
            image = getattr(fe, "_image_graphs", None)  # (session 25 on: the image stages' own graphs)
            images = "" if image is None else f"; image stages' kinds {len(image.runs)}, captured {len(image.captured)}"
            print(f"  > kinds of frame: {len(fe._graphs.runs)}, captured {len(fe._graphs.captured)}{images}",
                  flush=True)
            if with_motion and wp.get_device(device).is_cuda:
                fe.use_graphs = False
                obs = None
                wp.timing_begin(cuda_filter=wp.TIMING_ALL)
                for k, frame in enumerate(seq[:16]):
                    obs = fe.process(frame, motion(obs, k))
                per_kernel = kernel_times(wp.timing_end(), 16)
                top = ", ".join(f"{n} {v:.3f}" for n, v in list(per_kernel.items())[:12])
                print(f"  > GPU ms a frame {sum(per_kernel.values()):.3f}: {top}", flush=True)
