"""The final build's depth range past the landmarks (``[depth] final_far_factor``): surface beyond the far end of
a keyframe's landmark depths (the liver's far omentum) gets depths from a range widened by the factor, vetted by
the consistency check. Rendered views of a textured plane that slopes away past the landmarks' range. Warp's CPU
device by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import math
import os

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.geometry import make_T

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
Z0_M = 0.05  # the plane's depth on the axis; it slopes away to the right: z = Z0 + x tan(SLOPE)
SLOPE = math.radians(20.0)  # 42 mm at the image's left edge, 62 mm at its right
LANDMARKS_M = (0.040, 0.052)  # the keyframes' landmark range: the plane's right third lies beyond it
TEXEL_M = 5e-5
OFFSETS = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]


def _image(texture: np.ndarray, camera_xy: tuple[float, float]) -> np.ndarray:
    """The plane seen from a camera at (x, y, 0) looking along +z: each ray's hit, textured by its (x, y)."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float64)
    dx, dy = (u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy
    t = (Z0_M + math.tan(SLOPE) * camera_xy[0]) / (1.0 - math.tan(SLOPE) * dx)
    x, y = camera_xy[0] + t * dx, camera_xy[1] + t * dy
    n = texture.shape[0]
    grey = cv2.remap(texture, (x / TEXEL_M + n / 2).astype(np.float32), (y / TEXEL_M + n / 2).astype(np.float32),
                     cv2.INTER_LINEAR)
    return np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _build(far_factor: float) -> np.ndarray:
    """The final build of five keyframes 2 mm apart (the consistency check on): the fused points (metres)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    depth = dataclasses.replace(base.depth, final_far_factor=far_factor, coarse_level=0)
    dense = DenseSurface(CAMERA, dataclasses.replace(base, depth=depth), DEVICE, sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.standard_normal((2048, 2048)), (0, 0), 1.5)
    texture = (128 + 40 * texture / texture.std()).astype(np.float32)
    poses = {i: make_T(np.eye(3), [0.002 * dx, 0.002 * dy, 0.0]) for i, (dx, dy) in enumerate(OFFSETS)}
    for i, T in poses.items():
        dense.add_view(i, _image(texture, (T[0, 3], T[1, 3])), T)
    result = dense.build_at(poses, {i: LANDMARKS_M for i in poses})
    assert dense.fused == 5
    return result.points


def test_the_final_build_reaches_past_the_landmarks_far_end(warp_cpu):
    """With the landmarks' range alone no depth lies beyond its far end, so the plane's far third is a hole; with
    the range's far end widened by 1.25 the maps find it, the neighbours' maps confirm it, and it is fused on the
    plane."""
    def beyond(points: np.ndarray) -> tuple[int, int]:
        x, _, z = points.T
        off = np.abs(z - (Z0_M + math.tan(SLOPE) * x)) * math.cos(SLOPE)
        far = z > LANDMARKS_M[1] + 0.002
        return int(np.count_nonzero(far)), int(np.count_nonzero(far & (off > 0.001)))

    assert beyond(_build(1.0))[0] == 0
    far, off = beyond(_build(1.25))
    assert far > 1000
    assert off <= 0.001 * far  # (2 confirming maps let a rare point just past 1 mm through)
