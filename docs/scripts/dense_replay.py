"""Every captured keyframe's depth map made once ([depth] settings as key=value, [fusion] ones as f.key=value;
cached by settings and code), then fused and evaluated per consistency filter: filters=none,MIN:VIEWS,... (MIN
of the maps of the VIEWS nearest keyframes, its sources first, must agree). usage: dense_replay.py SCENE
[key=value ...] [filters=none,2:8]. Prints coverage and accuracy per filter. The final build's hole filling
(``consistency_fill_*`` settings) applies to the cached maps before the check (the maps are not made again), and so
does the coarse level (``coarse_level=2 coarse_weight=W coarse_max_rel=R``: its maps cached apart;
``coarsev=V``: its depths need V maps to agree; ``ctex=1``: its maps' ``min_texture`` divided by the level, as
``coarse.coarse_config`` does since session 25, ``ctex=0``: not).
``fillsrc=0``: the neighbours' maps as made (unfilled) confirm the filled map; ``rounds=2``: the checked maps filled
and checked again (against each other's). Inputs re-derived from the capture (session 24, "the far range and more
views"): ``sources=N``: each keyframe's sources chosen again by ``choose_sources`` (N of them, among the 64 nearest
captured views, as the surface does); ``rnear=F rfar=F``: every view's landmark depth range widened (near / F, far x
F) before its map is made; ``runion=1``: a map's range the union of its own and its sources' ranges; ``checksrc=N``: only the first N sources
lead a map's check's neighbours (the nearest keyframes follow). ``geopass=1``: every map made a second
time with its sources' first-pass maps as PatchMatch's geometric term (``[depth] final_geometric_pass``, session
26; ``geometric_pass_weight=W geometric_pass_tau_px=T`` as settings; its maps cached apart; ``geofirst=checked``: the
first pass's checked maps as the term, instead of its unchecked depths). ``dump=1``: the last filter's maps (as made, with the
coarse level; filled; checked), rejection codes and fused points saved to $DENSE_REPLAY_DIR/SCENE-dump.pkl for
dense_coverage_attribution.py (session 26)."""
# Session 17 (docs/dense.md, "Session 17: coverage"): the depth + fusion stage of the sequential demo re-run on saved
# keyframes. Files live in $DENSE_REPLAY_DIR (default /tmp/dense-replay). Not part of the package.
import dataclasses
import json
import os
import pickle
import sys
import time
import numpy as np
import pyvista as pv
from lapreco_hil.dense.depth import DepthEstimator
from lapreco_hil.dense.fusion import TsdfVolume
from lapreco_hil.dense.surface import KEPT_STEPS
from lapreco_hil.evaluation.accuracy import surface_report
import lapreco_hil.dense.depth as depth_module
import lapreco_hil.dense.warp.patchmatch as pm_module
import lapreco_hil.dense.warp.plane_sweep as sweep_module

WORK = os.environ.get("DENSE_REPLAY_DIR", "/tmp/dense-replay")

scene = sys.argv[1]
sets, fsets, filters, nb, fill_sources, rounds, coarse_views = {}, {}, ["none", "2:8"], 0, True, 1, 0
coarse_texture = None  # ``ctex=0/1``; None: as the package's KeptEstimator does
inputs = {}  # the capture's inputs re-derived: sources, depth ranges
check_sources = None
dump = False
geo_pass = False
geo_first = "unchecked"
for a in sys.argv[2:]:
    k, v = a.split("=")
    if k in ("sources", "rnear", "rfar", "runion"):
        inputs[k] = float(v); continue
    if k == "filters":
        filters = [x for x in v.split(",")]; continue
    if k == "nb":
        nb = int(v); continue
    if k == "checksrc":  # only a map's first N sources lead its check's neighbours (then the nearest keyframes)
        check_sources = int(v); continue
    if k == "ctex":  # session 25: the coarse level's min_texture divided by its factor (1) or not (0)
        coarse_texture = bool(int(v)); continue
    if k == "coarsev":
        coarse_views = int(v); continue
    if k == "rounds":
        rounds = int(v); continue
    if k == "geopass":
        geo_pass = bool(int(v)); continue
    if k == "geofirst":  # the geometric pass's first-pass maps: "unchecked" (the package's) or "checked"
        geo_first = v; continue
    if k == "dump":
        dump = bool(int(v)); continue
    if k == "fillsrc":
        fill_sources = bool(int(v)); continue
    target = fsets if k.startswith("f.") else sets
    k = k[2:] if k.startswith("f.") else k
    try: v = json.loads(v)
    except Exception: pass
    target[k] = v
rec = pickle.load(open(f"{WORK}/{scene}.pkl", "rb"))
if "sources" in inputs:  # chosen again on the landmark ranges, as the surface does (before any widening)
    from lapreco_hil.dense.depth import choose_sources
    from lapreco_hil.dense.surface import CANDIDATE_POSES, same_rig_view

    jobs = []
    for ref_id, _ in rec["jobs"]:
        ref = rec["views"][ref_id]
        c = ref.T_world_camera[:3, 3]
        others = sorted((v for v in rec["views"].values() if v.kf_id != ref_id),
                        key=lambda v: (not same_rig_view(v, ref), np.linalg.norm(v.T_world_camera[:3, 3] - c)))
        jobs.append((ref_id, [v.kf_id for v in choose_sources(ref, others[:CANDIDATE_POSES], int(inputs["sources"]))]))
    print("sources changed for", sum(a != b for a, b in zip(jobs, rec["jobs"])), "of", len(jobs), "keyframes",
          flush=True)
    rec["jobs"] = jobs
if {"rnear", "rfar", "runion"} & set(inputs):
    landmark = {i: v.depth_range_m for i, v in rec["views"].items()}
    for ref_id, src_ids in rec["jobs"]:
        rs = [landmark[i] for i in [ref_id] + (src_ids if inputs.get("runion") else []) if landmark[i] is not None]
        if rs:
            near, far = min(r[0] for r in rs), max(r[1] for r in rs)
            rec["views"][ref_id] = dataclasses.replace(rec["views"][ref_id], depth_range_m=(
                near / inputs.get("rnear", 1.0), far * inputs.get("rfar", 1.0)))
dcfg, fcfg = rec["config"]
dcfg = dataclasses.replace(dcfg, **sets)
fcfg = dataclasses.replace(fcfg, **fsets)
est = DepthEstimator(dcfg, "cpu", host_buffers=0)
t0 = time.time()
import hashlib
# (the settings applied after the maps are made leave them as cached)
after = ("consistency_fill", "coarse_", "geometric_pass_")
key = hashlib.md5(repr((scene, sorted((k, v) for k, v in sets.items() if not k.startswith(after)), open(pm_module.__file__).read(), open(depth_module.__file__).read(), open(sweep_module.__file__).read()) + ((tuple(sorted(inputs.items())),) if inputs else ())).encode()).hexdigest()[:10]
cache = f"{WORK}/maps-{key}.pkl"
codes_cache = f"{WORK}/codes-{key}.pkl"  # each map's rejection codes (for the coarse level)
unchecked_cache = f"{WORK}/unchecked-{key}.pkl"  # each map's depths before the checks (the geometric pass's input)
if os.path.exists(cache) and os.path.exists(codes_cache) and (os.path.exists(unchecked_cache) or not geo_pass):
    maps = pickle.load(open(cache, "rb"))
    codes = pickle.load(open(codes_cache, "rb"))
else:
    maps, codes, unchecked = {}, {}, {}
    cpu0 = time.process_time()
    for ref_id, src_ids in rec["jobs"]:
        maps[ref_id] = est.compute(rec["views"][ref_id], [rec["views"][s] for s in src_ids])
        codes[ref_id] = est.rejection_codes()
        if dcfg.method == "patchmatch":
            unchecked[ref_id] = est.unchecked_depth()
    print(f"full-resolution maps: {time.time() - t0:.0f} s wall, {time.process_time() - cpu0:.0f} s CPU", flush=True)
    pickle.dump(maps, open(cache, "wb"))
    pickle.dump(codes, open(codes_cache, "wb"))
    pickle.dump(unchecked, open(unchecked_cache, "wb"))
if geo_pass:  # session 26: the second pass, each map against its sources' first-pass maps (ACMM)
    gkey = f"{WORK}/geo-{key}-w{dcfg.geometric_pass_weight:g}-t{dcfg.geometric_pass_tau_px:g}-{geo_first}"
    if os.path.exists(gkey + ".pkl"):
        maps, codes = pickle.load(open(gkey + ".pkl", "rb"))
    else:
        # the first pass as the geometric term sees it: every scored pixel's depth, unchecked (as ACMM's maps)
        unc = pickle.load(open(unchecked_cache, "rb"))
        first = {i: dataclasses.replace(m, depth_m=unc[i], confidence=(unc[i] > 0).astype(np.float32))
                 for i, m in maps.items()}
        if geo_first == "checked":  # (the first try: the checked maps, with their holes)
            first = maps
        maps, codes = {}, {}
        cpu0, t00 = time.process_time(), time.time()
        for ref_id, src_ids in rec["jobs"]:
            maps[ref_id] = est.compute(rec["views"][ref_id], [rec["views"][s] for s in src_ids], geometry=first)
            codes[ref_id] = est.rejection_codes()
        print(f"second pass: {time.time() - t00:.0f} s wall, {time.process_time() - cpu0:.0f} s CPU", flush=True)
        pickle.dump((maps, codes), open(gkey + ".pkl", "wb"))
coarse = dcfg.coarse_level
if coarse > 1:  # [depth] coarse_level (session 24): the holes of weak texture from a map of the views reduced by it
    from lapreco_hil.dense.coarse import coarse_into_holes, reduced_view

    from lapreco_hil.dense import coarse as coarse_module

    ccfg = coarse_module.coarse_config(dcfg) if hasattr(coarse_module, "coarse_config") else dcfg
    if coarse_texture is not None:  # (session 25: the coarse level's texture threshold by its noise, or as before)
        ccfg = dataclasses.replace(dcfg, min_texture=dcfg.min_texture / (coarse if coarse_texture else 1))
    ckey = f"{WORK}/coarse{coarse}-{key}" + ("" if ccfg == dcfg else f"-t{ccfg.min_texture:g}") + ".pkl"
    if os.path.exists(ckey):
        cmaps = pickle.load(open(ckey, "rb"))
    else:
        cest = DepthEstimator(ccfg, "cpu", host_buffers=0)
        small = {i: reduced_view(v, coarse) for i, v in rec["views"].items()}
        cmaps = {ref_id: cest.compute(small[ref_id], [small[s] for s in src_ids]) for ref_id, src_ids in rec["jobs"]}
        pickle.dump(cmaps, open(ckey, "wb"))
    maps = {i: coarse_into_holes(m, codes[i], cmaps[i], coarse, dcfg.coarse_max_rel, dcfg.coarse_weight)
            for i, m in maps.items()}
    print("coarse level adds", sum(m.stats["coarse_pixels"] for m in maps.values()), "pixels to",
          sum(int((m.depth_m > 0).sum()) for m in maps.values()), flush=True)
t1 = time.time()
from lapreco_hil.dense.fill import fill_holes
raw = maps
filled = {i: fill_holes(m, dcfg.consistency_fill_px, dcfg.consistency_fill_rel, dcfg.consistency_fill_lines,
                        dcfg.consistency_fill_weight) for i, m in maps.items()}
t2 = time.time()
surface = pv.read(f"{WORK}/{scene}-truth.vtp")
_, poses, K, size, mask = rec["truth"]
def fill(m):
    return fill_holes(m, dcfg.consistency_fill_px, dcfg.consistency_fill_rel, dcfg.consistency_fill_lines,
                      dcfg.consistency_fill_weight)


def checked(filt, nb, own, others):
    """Each map of ``own`` checked against ``others``' maps of its neighbours (its sources first, then the nearest)."""
    out = {}
    est.config = dataclasses.replace(dcfg, geometric_min_views=filt)
    for ref_id, src_ids in rec["jobs"]:
        ids = [s for s in src_ids[:check_sources] if s in others]
        if nb > len(ids):
            c = rec["views"][ref_id].T_world_camera[:3, 3]
            near = sorted((np.linalg.norm(rec["views"][o].T_world_camera[:3, 3] - c), o) for o in others
                          if o != ref_id and o not in ids)
            ids += [o for _, o in near[:nb - len(ids)]]
        ids = ids[:nb]  # (as the surface's _neighbours: more sources than VIEWS are cut)
        out[ref_id] = est.check_geometry(own[ref_id], [others[s] for s in ids])
        taken = (own[ref_id].stats or {}).get("coarse_taken")
        if coarse_views and taken is not None and taken.any():  # the coarse level's depths need more maps to agree
            strict = est.check_geometry(own[ref_id], [others[s] for s in ids], coarse_views)
            drop = taken & (strict.depth_m <= 0)
            m = out[ref_id]
            out[ref_id] = dataclasses.replace(m, depth_m=np.where(drop, 0, m.depth_m).astype(np.float32),
                                              confidence=np.where(drop, 0, m.confidence).astype(np.float32))
    return out


for spec in filters:
    filt, nb = (spec.split(":") + ["0"])[:2] if spec != "none" else ("none", "0")
    filt = int(filt) if filt != "none" else filt
    nb = int(nb)
    if filt == "none":
        final = raw
    else:
        final = checked(filt, nb, filled, filled if fill_sources else raw)
        for _ in range(rounds - 1):  # the checked maps' holes filled from confirmed depths, checked again
            refilled = {i: fill(m) for i, m in final.items()}
            final = checked(filt, nb, refilled, refilled)
    vol = TsdfVolume(fcfg, "cpu")
    for ref_id, src_ids in rec["jobs"]:
        vol.integrate(final[ref_id], rec["views"][ref_id].colour, quantise=KEPT_STEPS)
    pts, nrm, col = vol.extract_points()
    d = surface_report(surface, poses, K, size, dense=pts, mask=mask)["dense"]
    from lapreco_hil.evaluation.accuracy import surface_distances
    dd = surface_distances(pts[::3], surface) * 1e3
    extra = f"median {np.median(dd):.3f} p90 {np.percentile(dd, 90):.2f} >1mm {100*np.mean(dd > 1):.1f}% >2mm {100*np.mean(dd > 2):.1f}% rms<2mm {np.sqrt(np.mean(dd[dd<2]**2)):.3f}"
    print(f"{scene} {' '.join(sys.argv[2:])} geo={spec}: {extra} coverage {100*d['coverage']:.1f}% rms {d['rms_mm']:.3f} mm "
          f">5mm {100*d['beyond_5mm']:.2f}% points {d['points']} depth {t1-t0:.0f}s fill {t2-t1:.1f}s", flush=True)
    if dump:
        f32 = lambda ms: {i: np.asarray(m.depth_m, np.float32) for i, m in ms.items()}
        pickle.dump({"jobs": rec["jobs"], "raw": f32(raw), "filled": f32(filled), "final": f32(final), "codes": codes,
                     "points": pts.astype(np.float32), "filter": spec},
                    open(f"{WORK}/{scene}-dump.pkl", "wb"))
