"""The renderer's true depth at each captured keyframe's refined pose (for dense_diag.py). usage:
dense_true_depth.py SCENE (after dense_capture.py SCENE)."""
# Session 17 (docs/dense.md, "Session 17: coverage"). Files live in $DENSE_REPLAY_DIR (default /tmp/dense-replay).
import os
import pickle
import sys

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.simulators.world import SimSettings, SimWorld

WORK = os.environ.get("DENSE_REPLAY_DIR", "/tmp/dense-replay")
scene = sys.argv[1]
rec = pickle.load(open(f"{WORK}/{scene}.pkl", "rb"))
world = SimWorld(SimSettings(scene=scene, width=640, height=480, device="cpu"))
c = world.camera
cam = CameraModel(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
out = {}
for ref_id, _ in rec["jobs"]:
    v = rec["views"][ref_id]
    # (the view's own pinhole image: since session 23 a canvas larger than the frame holds the whole field of view)
    K = np.asarray(v.K, float)
    view_cam = CameraModel(v.size[0], v.size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    _, depth = world.renderer.render(v.T_world_camera, camera=view_cam)
    out[ref_id] = depth.astype(np.float32)
np.savez_compressed(f"{WORK}/{scene}-truedepth.npz", **{str(k): d for k, d in out.items()})
print("ok", len(out))
