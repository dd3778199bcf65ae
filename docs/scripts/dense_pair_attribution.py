"""Where a rendered stereo pair's uncovered footprint goes (session 25, docs/dense.md): the pair's version-2
session replayed in-process with hooks on the final build's stages (each map's raw depths and rejection codes, the
coarse level, the hole filling, SGBM, the left-right check), then every footprint pixel of the left image the fused
surface misses (no point within 1 mm: the reviewer's measure.py) given to the first stage that lost it, in either
view's map. Needs the outside reviewer's folder (pairs/P/truth.npz, sessions/P/v2, measure.py, rl.py).
usage: dense_pair_attribution.py REVIEW_DIR PAIR OUT_DIR [lapreco replay options]. Not part of the package."""
import os
import subprocess
import sys

import numpy as np

review, pair, out = sys.argv[1:4]
sys.path.insert(0, review)
import lapreco_hil.dense.depth as D  # noqa: E402
import lapreco_hil.dense.surface as S  # noqa: E402

rec = {}
_compute, _coarse, _fill, _sgbm, _fill_from, _check = (D.DepthEstimator.compute, D.KeptEstimator.with_coarse_level,
                                                        S.fill_holes, S.sgbm_depth, S.fill_from,
                                                        D.KeptEstimator.check_geometry)


def compute(self, ref, sources, source_depths=None, on_device=False):
    r = _compute(self, ref, sources, source_depths, on_device)
    if ref.K[0, 0] == rec.setdefault("fx", ref.K[0, 0]):  # (the full-resolution map: the first made; not the coarse)
        rec.setdefault(ref.kf_id, {}).update(raw=(r.depth_m.copy(), self.rejection_codes()), K=np.array(ref.K),
                                             T=np.array(ref.T_world_camera))
    return r


D.DepthEstimator.compute = compute
D.KeptEstimator.with_coarse_level = lambda self, ref, *a: _keep(ref.kf_id, "coarse", _coarse(self, ref, *a))
S.fill_holes = lambda m, *a, **k: _keep(m.kf_id, "filled", _fill(m, *a, **k))
S.fill_from = lambda d, o: _keep(d.kf_id, "sgbm", _fill_from(d, o))
D.KeptEstimator.check_geometry = lambda self, dm, *a: _keep(dm.kf_id, "checked", _check(self, dm, *a))


def _keep(kf_id, stage, m):
    rec.setdefault(kf_id, {})[stage] = m.depth_m.copy()
    return m


from lapreco_hil.cli.main import main  # noqa: E402

try:
    main(["replay", f"{review}/sessions/{pair}/v2", "--out", out, "--no-progress"] + sys.argv[4:])
except SystemExit:
    pass
subprocess.run([sys.executable, "measure.py", f"pairs/{pair}", os.path.abspath(f"{out}/dense.ply")], cwd=review,
               check=True, capture_output=True)
import rl  # noqa: E402  (the reviewer's exact mesh distances and ray casts)

FUNNEL = D.FUNNEL[1:] + ("kept",)
t = np.load(f"{review}/pairs/{pair}/truth.npz")
foot, both, P = t["foot"], t["both"], t["P_L"].astype(float)
mesh = rl.MeshTruth(t["V"], t["F"])
covered = np.load(f"{out}/dense.ply.covered.npy")
ys, xs = np.nonzero(foot)
X = P[ys, xs]
per_view = []
for kf_id in sorted(k for k in rec if isinstance(k, int)):
    m = rec[kf_id]
    K, T = m["K"], m["T"]
    h, w = m["raw"][0].shape
    v, u = np.mgrid[0:h, 0:w]
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    rays /= np.linalg.norm(rays, axis=0)
    hit = mesh.cast(T[:3, 3], (T[:3, :3] @ rays).T)
    z_true = np.where(hit > 0, hit * rays[2], 0).reshape(h, w)
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    p = Xc @ K.T
    pu, pv = np.round(p[:, 0] / p[:, 2]).astype(int), np.round(p[:, 1] / p[:, 2]).astype(int)
    inside = (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h) & (Xc[:, 2] > 0)
    pu, pv = np.clip(pu, 0, w - 1), np.clip(pv, 0, h - 1)
    seen = inside & (np.abs(z_true[pv, pu] - Xc[:, 2]) < 1e-3)
    m.setdefault("sgbm", m.get("filled", m.get("coarse", m["raw"][0])))  # (the last stage before the check)
    good = {s: seen & (m[s][pv, pu] > 0) & (np.abs(m[s][pv, pu] - z_true[pv, pu]) < 1e-3)
            for s in ("sgbm", "checked")}
    has = {s: m[s][pv, pu] > 0 for s in ("sgbm", "checked")}
    per_view.append(dict(code=np.where(seen, m["raw"][1][pv, pu], 255), good=good, has=has))
L, R = per_view[0], per_view[1]
miss = ~covered[ys, xs]
seen_by_both = both[ys, xs]
made_good = L["good"]["sgbm"] | R["good"]["sgbm"]  # a right depth before the check (raw, coarse, filled, SGBM)
groups = {"one camera only": miss & ~seen_by_both}
miss &= seen_by_both
groups["confirmed, not meshed"] = miss & (L["good"]["checked"] | R["good"]["checked"])
miss &= ~groups["confirmed, not meshed"]
groups["check dropped a good depth"] = miss & made_good
miss &= ~made_good
groups["wrong depth only"] = miss & (L["has"]["sgbm"] | R["has"]["sgbm"])
miss &= ~groups["wrong depth only"]
code = np.where(L["code"] != 255, L["code"], R["code"])
for name, checks in (("highlight", ("not_highlight",)), ("flat window / weak match", ("textured", "matched")),
                     ("depth edge", ("off_edges",)), ("out of range", ("in_range",))):
    groups[name] = miss & np.isin(code, [FUNNEL.index(c) for c in checks])
    miss &= ~groups[name]
groups["other"] = miss
print(f"{pair}: covered {covered[foot].mean() * 100:.1f}% of the footprint; uncovered, by cause (% of the footprint): "
      + " | ".join(f"{k} {v.mean() * 100:.1f}" for k, v in groups.items()))
