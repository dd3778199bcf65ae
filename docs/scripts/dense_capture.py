"""Run the sequential demo once (usage: dense_capture.py SCENE), record each keyframe's stereo inputs (views,
sources, settings) and what the coverage is measured against (the true surface, the keyframes' poses)."""
# Session 17 (docs/dense.md, "Session 17: coverage"): the depth + fusion stage of the sequential demo re-run on saved
# keyframes. Files live in $DENSE_REPLAY_DIR (default /tmp/dense-replay). Not part of the package.
import os
import pickle
import sys
import lapreco_hil.dense.surface as surf
import lapreco_hil.outputs as outputs
from lapreco_hil.app.demo import run_demo

WORK = os.environ.get("DENSE_REPLAY_DIR", "/tmp/dense-replay")

scene = sys.argv[1]
rec = {"views": {}, "jobs": [], "truth": None}

fuse_pending = surf.DenseSurface.fuse_pending
# one keyframe at a time, through _depth_map (no map is made: the capture records its inputs only)
surf.DenseSurface.fuse_pending = lambda self, kf_ids=None, consistent=False: fuse_pending(self, kf_ids)
def _depth_map(self, ref, sources):
    for v in [ref] + list(sources):
        rec["views"][v.kf_id] = v
    rec["jobs"].append((ref.kf_id, [s.kf_id for s in sources]))
    rec["config"] = (self.config.depth, self.config.fusion)
    return None, ref.colour
surf.DenseSurface._depth_map = _depth_map

orig_sr = outputs.surface_report
def sr(surface, poses, K, size, **kw):
    rec["truth"] = (surface, poses, K, size, kw.get("mask"))
    return orig_sr(surface, poses, K, size, **kw)
outputs.surface_report = sr

run_demo(scene=scene, frames=150, runtime="sequential", surface="dense", tracker="opencv", device="cpu",
         out=f"{WORK}/demo-{scene}", progress=False)
surface = rec["truth"][0]
surface.save(f"{WORK}/{scene}-truth.vtp")
rec["truth"] = (None,) + rec["truth"][1:]
with open(f"{WORK}/{scene}.pkl", "wb") as f:
    pickle.dump(rec, f)
print(scene, len(rec["jobs"]), "jobs", len(rec["views"]), "views")
