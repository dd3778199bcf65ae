"""Where the multi-view build's uncovered seen surface goes (session 26, docs/dense.md). usage:
dense_coverage_attribution.py SCENE, after dense_capture.py SCENE, dense_true_depth.py SCENE and
dense_replay.py SCENE ... dump=1 (its last filter's maps). Every seen true-surface sample (as ``surface_report``
samples and sees it) without a fused point within 1 mm is followed into every keyframe that sees it (in the image
and its mask, within 2 mm + 1% of the renderer's depth at the keyframe's refined pose) and assigned to the first
of: seen by no / one keyframe; a checked depth within 1 mm (then fusion lost it); a depth within 1 mm that the check
dropped (as made or filled); only depths more than 1 mm off; no depth, named by the furthest check any keyframe's
map reached. Uncovered samples are also split by how many of a seeing keyframe's own sources see them (the map
scores a plane on its ``best_k`` 2 best sources) and by their best viewing angle. Not part of the package."""
import os
import pickle
import sys

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from lapreco_hil.dense.depth import FUNNEL
from lapreco_hil.evaluation.coverage import sample_surface, visible_samples

WORK = os.environ.get("DENSE_REPLAY_DIR", "/tmp/dense-replay")
scene = sys.argv[1]
rec = pickle.load(open(f"{WORK}/{scene}.pkl", "rb"))
dump = pickle.load(open(f"{WORK}/{scene}-dump.pkl", "rb"))
true = np.load(f"{WORK}/{scene}-truedepth.npz")
surface = pv.read(f"{WORK}/{scene}-truth.vtp")
_, poses, K_eval, size, mask_eval = rec["truth"]

samples = sample_surface(surface, 0.0005)
spacing = float(np.sqrt(surface.area / max(len(samples), 1)))
seen = samples[visible_samples(samples, poses, K_eval, size, mask=mask_eval, occlusion_m=0.001, spacing_m=spacing)]
normals_mesh = surface.compute_normals(cell_normals=True, point_normals=False)
normals = normals_mesh.cell_data["Normals"][normals_mesh.find_closest_cell(seen)]
covered = cKDTree(dump["points"]).query(seen, distance_upper_bound=1e-3)[0] <= 1e-3
n = len(seen)
jobs = dict(dump["jobs"])
ids = [i for i, _ in dump["jobs"]]

# per keyframe: sees the sample (u, v pixel), and the best outcome of its maps there
RANK_FINAL, RANK_DROPPED, RANK_WRONG = 30, 20, 15  # above every funnel code (< 11)
n_vis = np.zeros(n, int)
best = np.full(n, -1, int)  # the best outcome over the keyframes that see the sample
best_cos = np.zeros(n)
vis_of = {}
for kf in ids:
    v = rec["views"][kf]
    T = np.asarray(v.T_world_camera, float)
    K = np.asarray(v.K, float)
    w, h = v.size
    pc = (seen - T[:3, 3]) @ T[:3, :3]
    z = pc[:, 2]
    ok = z > 1e-3
    uv = np.zeros((n, 2))
    uv[ok] = pc[ok, :2] / z[ok, None] @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= 0) & (uv[:, 1] < h - 0.5)
    px = np.clip(np.rint(uv).astype(int), 0, [w - 1, h - 1])
    if v.mask is not None:
        ok &= np.asarray(v.mask)[px[:, 1], px[:, 0]] > 0
    td = true[str(kf)][px[:, 1], px[:, 0]]
    ok &= (td > 0) & (np.abs(td - z) < 0.002 + 0.01 * z)
    vis_of[kf] = (ok, px, z)
    n_vis += ok
    ray = seen - T[:3, 3]
    cos = np.abs(np.sum(ray * normals, 1)) / np.linalg.norm(ray, axis=1)
    best_cos = np.where(ok, np.maximum(best_cos, cos), best_cos)
    ray_px = np.linalg.inv(K) @ np.c_[uv, np.ones(n)].T  # the depth map's point on the sample's ray

    def good(depth):
        d = depth[px[:, 1], px[:, 0]]
        err = np.abs(d - z) * np.linalg.norm(ray_px, axis=0)
        return (d > 0) & (err <= 1e-3), d > 0

    g_final, _ = good(dump["final"][kf])
    g_filled, h_filled = good(dump["filled"][kf])
    g_raw, h_raw = good(dump["raw"][kf])
    code = dump["codes"][kf][px[:, 1], px[:, 0]].astype(int)
    outcome = np.where(g_final, RANK_FINAL, np.where(g_raw | g_filled, RANK_DROPPED,
                                                      np.where(h_raw | h_filled, RANK_WRONG, code)))
    best = np.where(ok, np.maximum(best, outcome), best)

# how many of a seeing keyframe's own sources see the sample: the most over the keyframes that see it
src_vis = np.zeros(n, int)
for kf in ids:
    ok = vis_of[kf][0]
    c = sum(vis_of[s][0].astype(int) for s in jobs[kf] if s in vis_of)
    src_vis = np.where(ok, np.maximum(src_vis, c), src_vis)

un = ~covered
pct = lambda m: f"{100 * np.count_nonzero(m) / n:5.1f}%"
print(f"{scene}: {n} seen samples, covered {pct(covered)} (fused points within 1 mm), filter {dump['filter']}")
rows = [("uncovered", un),
        ("  seen by no keyframe (per-keyframe test)", un & (n_vis == 0)),
        ("  seen by one keyframe only", un & (n_vis == 1)),
        ("  a checked depth within 1 mm, not fused within 1 mm", un & (n_vis > 1) & (best == RANK_FINAL)),
        ("  a depth within 1 mm the check dropped", un & (n_vis > 1) & (best == RANK_DROPPED)),
        ("  only depths > 1 mm off", un & (n_vis > 1) & (best == RANK_WRONG))]
for c in range(len(FUNNEL) - 1):
    rows.append((f"  no depth, furthest check failed: {FUNNEL[c + 1]}", un & (n_vis > 1) & (best == c)))
for name, m in rows:
    print(f"{name:60s} {pct(m)}")
nodepth = un & (n_vis > 1) & (best < RANK_WRONG)
print("no-depth samples (2+ keyframes see them), by the most sources of one seeing keyframe that see them too:")
for lo, hi in ((0, 0), (1, 1), (2, 3), (4, 8)):
    print(f"  {lo}-{hi} sources {pct(nodepth & (src_vis >= lo) & (src_vis <= hi))}")
ang = np.degrees(np.arccos(np.clip(best_cos, 0, 1)))
print("best viewing angle (degrees from the normal), uncovered (2+ keyframes) / covered:")
for lo, hi in ((0, 45), (45, 60), (60, 70), (70, 80), (80, 91)):
    b = (ang >= lo) & (ang < hi)
    print(f"  {lo}-{hi}: uncovered {pct(un & (n_vis > 1) & b)}  no depth {pct(nodepth & b)}  covered {pct(covered & b)}")
print("keyframes that see the samples: median uncovered", np.median(n_vis[un]), "covered", np.median(n_vis[covered]))
