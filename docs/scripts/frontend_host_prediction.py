"""The Warp front-end's host prediction for a frame with a motion, before and after session 24
(docs/benchmarks.md, "Session 24"): ``start_depths`` (the host borrows every depth) against ``own_start_depths``
(the device borrows), each followed by ``prediction_plan``, on session 15's scenes ("spread": 80% of the tracks
with a landmark at random; "band": all but a 200 px band at the left edge), 1920 x 1080, K 1100 px. Prints the
median ms of 100 calls and the plan (budget, LK levels) each gives.

    python docs/scripts/frontend_host_prediction.py

(Session 25: "after" passes the small-motion test's projections on to the plan, as the front-end does; with
``PYTHONPATH=`` a checkout of an earlier tree, the same script times that tree's functions.)
"""
import time, numpy as np, dataclasses
from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend import epipolar as ep
from lapreco_hil.types import FrameMotion
SIZE = (1920, 1080); K = np.array([[1100.0, 0, 960], [0, 1100.0, 540], [0, 0, 1]])
def rot(axis, a):
    axis = np.asarray(axis, float); axis /= np.linalg.norm(axis)
    c = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * c + (1 - np.cos(a)) * c @ c
def scene(n, kind, scale, rng):
    uv = rng.uniform([0, 0], SIZE, (n, 2)); ids = np.arange(n, dtype=np.int64)
    own = rng.random(n) < 0.8 if kind == "spread" else uv[:, 0] > 200
    T = np.eye(4); T[:3, :3] = rot([0.3, 1, 0.2], np.radians(0.6) * scale); T[:3, 3] = np.array([1.2, 0.6, 1.5]) * 1e-3 * scale
    return uv, ids, FrameMotion(T, ids[own], rng.uniform(0.04, 0.12, own.sum()), (0.03, 0.3))
rng = np.random.default_rng(0)
for cfg_name, cfg in (("default", TrackerConfig()), ("reduced levels", dataclasses.replace(TrackerConfig(), reduced_predicted_levels=True))):
    for n in (2000, 8000):
        for kind in ("spread", "band"):
            uv, ids, m = scene(n, kind, 1.0, rng)
            def before():
                d = ep.start_depths(uv, ids, m, K, SIZE); return ep.prediction_plan(cfg, 5, SIZE, uv, ids, d, m, K)
            def after():
                r = ep.own_start_depths(uv, ids, m, K, SIZE)
                shared = (r.moved_sq, r.terms) if hasattr(r, "moved_sq") else ()  # (session 25 on: reused)
                return ep.prediction_plan(cfg, 5, SIZE, uv, ids, r[1], m, K, *shared)
            res = {}
            for name, f in (("before", before), ("after", after)) * 2:
                for _ in range(5): f()
                ts = []
                for _ in range(100):
                    t = time.perf_counter(); out = f(); ts.append(time.perf_counter() - t)
                res[name] = (np.median(ts) * 1e3, out)
            print(f"{cfg_name:15s} {n:5d} {kind:6s} before {res['before'][0]:.2f} ms {res['before'][1]}  after {res['after'][0]:.2f} ms {res['after'][1]}")
