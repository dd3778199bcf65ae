"""Two-view depth maps (a stereo pair, or a two-frame session) against the truth: usage dense_pair.py [key=value ...]
with [depth] settings. Three rendered stereo pairs (720x576, f 700 px, 5.5 mm baseline: liver at 75 and 90 mm,
skull at 80 mm; the renderer's true depth) and the Hamlyn phantom's real pair (tests/data; no truth: agreement
with OpenCV's StereoSGBM on the rectified pair). Per pair: the left map as made (raw), checked left-right against
the right one's (LR), and both filled then checked (fLR: what the final build of two keyframes fuses). Coverage is
the share of the pixels with a true depth that get a depth within 1 mm. The rendered pairs are cached in
$DENSE_PAIR_CACHE (default /tmp/dense-pairs.pkl). Session 19 (docs/dense.md, "Two views"); not part of the package."""
import copy
import dataclasses
import os
import pickle
import sys
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.depth import DepthEstimator
from lapreco_hil.dense.fill import fill_holes
from lapreco_hil.dense.types import KeyframeView

CACHE = os.environ.get("DENSE_PAIR_CACHE", "/tmp/dense-pairs.pkl")
HAMLYN = Path(__file__).resolve().parents[2] / "tests" / "data" / "hamlyn-phantom-stereo"
PAIRS = (("liver", (0.01, 0.03, 0.075)), ("skull", (0.02, -0.01, 0.08)), ("liver", (-0.02, 0.0, 0.09)))

base = DepthConfig()
cfg = dataclasses.replace(base, **{k: type(getattr(base, k))(v) for k, v in (a.split("=") for a in sys.argv[1:])})
estimator = DepthEstimator(cfg, "cpu")


def rendered_pairs():
    if os.path.exists(CACHE):
        return pickle.load(open(CACHE, "rb"))
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.geometry import look_at
    from lapreco_hil.simulators.world.renderer import Renderer
    from lapreco_hil.simulators.world.scenes import build_scene

    w, h, f = 720, 576, 700.0
    camera = CameraModel(w, h, f, f, (w - 1) / 2, (h - 1) / 2)
    out = []
    for name, eye in PAIRS:
        scene = build_scene(name, 0)
        renderer = Renderer(scene.vertices, scene.faces, scene.face_material, list(scene.materials), camera,
                            device="cpu")
        T_left = look_at(np.array(eye), np.zeros(3), np.array([0.0, 1.0, 0.0]))
        T_right = T_left.copy()
        T_right[:3, 3] += T_left[:3, 0] * 0.0055
        left, depth_left = renderer.render(T_left, seed=1)
        right, _ = renderer.render(T_right, seed=2)
        out.append((name, left, right, depth_left, camera.K, T_left, T_right))
    pickle.dump(out, open(CACHE, "wb"))
    return out


def maps(left, right, K, T_left, T_right, near_far):
    ref = KeyframeView(0, left[:, :, ::-1].copy(), K, T_left, None, near_far)
    src = KeyframeView(1, right[:, :, ::-1].copy(), K, T_right, None, near_far)
    m0, m1 = estimator.compute(ref, [src]), estimator.compute(src, [ref])

    def filled(m):
        return fill_holes(copy.deepcopy(m), cfg.consistency_fill_px, cfg.consistency_fill_rel,
                          cfg.consistency_fill_lines, cfg.consistency_fill_weight, "cpu")

    return {"raw": m0, "LR": estimator.check_geometry(m0, [m1]),
            "fLR": estimator.check_geometry(filled(m0), [filled(m1)])}


for name, left, right, truth, K, T_left, T_right in rendered_pairs():
    z = truth[truth > 0]
    for label, m in maps(left, right, K, T_left, T_right, (np.percentile(z, 1) * 0.9, np.percentile(z, 99) * 1.1)).items():
        seen = truth > 0
        err = np.abs(m.depth_m - truth) * 1e3
        kept = m.valid & seen
        print(f"{name:6s} {label:3s} depth {m.valid.mean() * 100:5.1f}% covered<1mm "
              f"{(kept & (err < 1)).sum() / seen.sum() * 100:5.1f}% median {np.median(err[kept]):.2f} mm "
              f">1mm {np.mean(err[kept] > 1) * 100:4.1f}% >5mm {np.mean(err[kept] > 5) * 100:4.2f}%")

# the real pair: the right image resampled to the left intrinsics (both have no distortion)
K = np.loadtxt(HAMLYN / "calib.left.intrinsic.txt")
T_right_left = np.loadtxt(HAMLYN / "calib.l2r.4x4")
left = cv2.imread(str(HAMLYN / "f7_dynamic_deint_L_0100.png"))
right = cv2.imread(str(HAMLYN / "f7_dynamic_deint_R_0100.png"))
h, w = left.shape[:2]
mx, my = cv2.initUndistortRectifyMap(np.loadtxt(HAMLYN / "calib.right.intrinsic.txt"), None, None, K, (w, h),
                                     cv2.CV_32FC1)
right = cv2.remap(right, mx, my, cv2.INTER_LINEAR)
T_world_right = np.linalg.inv(T_right_left)
T_world_right[:3, 3] /= 1000.0
R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K, np.zeros(5), K, np.zeros(5), (w, h), T_right_left[:3, :3],
                                            T_right_left[:3, 3], alpha=0)
rect = [cv2.remap(img, *cv2.initUndistortRectifyMap(K, None, R, P, (w, h), cv2.CV_32FC1), cv2.INTER_LINEAR)
        for img, R, P in ((left, R1, P1), (right, R2, P2))]
sgbm = cv2.StereoSGBM_create(0, 96, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, speckleWindowSize=100,
                             speckleRange=2, disp12MaxDiff=1)
disparity = sgbm.compute(*[cv2.cvtColor(r, cv2.COLOR_BGR2GRAY) for r in rect]).astype(np.float32) / 16
X = cv2.reprojectImageTo3D(disparity, Q)[disparity > 0] @ R1
uv = X @ K.T
u, v = np.round(uv[:, 0] / uv[:, 2]).astype(int), np.round(uv[:, 1] / uv[:, 2]).astype(int)
ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
reference = np.zeros((h, w))
reference[v[ok], u[ok]] = X[ok, 2] / 1000.0
for label, m in maps(left, right, K, np.eye(4), T_world_right, (0.05, 0.09)).items():
    both = m.valid & (reference > 0)
    err = np.abs(m.depth_m - reference)[both] * 1e3
    print(f"hamlyn {label:3s} depth {m.valid.mean() * 100:5.1f}% (SGBM {(reference > 0).mean() * 100:.1f}%) "
          f"within 1 mm of SGBM: {(err < 1).sum() / (reference > 0).sum() * 100:5.1f}% of SGBM's pixels, median "
          f"{np.median(err):.2f} mm >1mm {np.mean(err > 1) * 100:4.1f}% >5mm {np.mean(err > 5) * 100:4.2f}%")
