"""A two-view pair's semi-global matching (``[depth] two_view_sgbm``) searches the depth range the pair's maps search:
the landmarks' range with its far end widened by ``final_far_factor`` (docs/dense.md, "Session 25"). Before, it
searched the landmarks' range alone, so surface past their far end (a far background) had a disparity below the
search and got no depth from it. Rendered views of a textured plane past the landmarks. Warp's CPU device by
default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import os

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.geometry import make_T

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
PLANE_Z_M = 0.0575  # a fronto-parallel plane 1.1 times past the landmarks' far end (within 1.25 times)
LANDMARKS_M = (0.040, 0.052)
BASELINE_M = 0.005
TEXEL_M = 5e-5


def _image(texture: np.ndarray, camera_x: float) -> np.ndarray:
    """The plane seen from a camera at (x, 0, 0) looking along +z."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float64)
    x = camera_x + PLANE_Z_M * (u - CAMERA.cx) / CAMERA.fx
    y = PLANE_Z_M * (v - CAMERA.cy) / CAMERA.fy
    n = texture.shape[0]
    grey = cv2.remap(texture, (x / TEXEL_M + n / 2).astype(np.float32), (y / TEXEL_M + n / 2).astype(np.float32),
                     cv2.INTER_LINEAR)
    return np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def test_a_pairs_semi_global_matching_reaches_past_the_landmarks_far_end(warp_cpu):
    """The plane lies past the landmarks' far end: SGBM over the landmarks' range gave the left map's holes no depth
    there at all; over the map's own range (far end x 1.25) it fills most of the image (79%), on the plane."""
    from lapreco_hil.dense.surface import DenseSurface

    dense = DenseSurface(CAMERA, PipelineConfig(), DEVICE)
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.standard_normal((2048, 2048)), (0, 0), 1.5)
    texture = (128 + 40 * texture / texture.std()).astype(np.float32)
    poses = {0: make_T(np.eye(3), [0.0, 0.0, 0.0]), 1: make_T(np.eye(3), [BASELINE_M, 0.0, 0.0])}
    for i, T in poses.items():
        dense.add_view(i, _image(texture, T[0, 3]), T)
    dense.set_depth_ranges({0: LANDMARKS_M, 1: LANDMARKS_M})
    assert PLANE_Z_M > LANDMARKS_M[1] and PLANE_Z_M < LANDMARKS_M[1] * PipelineConfig().depth.final_far_factor
    h, w = CAMERA.height, CAMERA.width
    empty = DepthMap(0, np.zeros((h, w), np.float32), np.zeros((h, w), np.float32), dense.K, poses[0])
    filled = dense._sgbm_filled(0, empty, [1])
    depth = filled.depth_m
    assert dense.sgbm_filled == 1
    assert np.count_nonzero(depth > 0) > 0.5 * h * w
    err = np.abs(depth[depth > 0] - PLANE_Z_M)
    assert np.mean(err > 1e-3) < 0.001 and err.max() < 2e-3  # (measured: 1 pixel of 60 930 at 1.16 mm)
