"""The coarse level's texture threshold (``lapreco_hil.dense.coarse.coarse_config``, docs/dense.md "Session 25"):
``min_texture`` is the contrast below which a window's ZNCC is noise; the reduced views' area mean averages the
noise down by the level, so the coarse maps' threshold is divided by it. Rendered views of a plane whose texture is
fainter still in a patch (tests/test_dense_coarse.py's scene). Warp's CPU device by default
(LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.geometry import make_T

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
PLANE_Z_M = 0.05
TEXEL_M = 5e-5
PATCH_M = (0.009, 0.006)
OFFSETS = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
FAINT = 2.5  # the patch's grey-level std over 1.5 mm (test_dense_coarse.py's: 5)


def _texture() -> np.ndarray:
    rng = np.random.default_rng(0)
    n = 1024
    fine = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 1.5)
    smooth = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 30.0)
    xs = (np.arange(n) - n / 2) * TEXEL_M
    patch = (np.abs(xs)[None, :] < PATCH_M[0]) & (np.abs(xs)[:, None] < PATCH_M[1])
    return np.where(patch, 128 + FAINT * smooth / smooth.std(), 128 + 40 * fine / fine.std()).astype(np.float32)


def _image(texture: np.ndarray, camera_xy: tuple[float, float]) -> np.ndarray:
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float32)
    x = camera_xy[0] + (u - CAMERA.cx) / CAMERA.fx * PLANE_Z_M
    y = camera_xy[1] + (v - CAMERA.cy) / CAMERA.fy * PLANE_Z_M
    n = texture.shape[0]
    grey = cv2.remap(texture, (x / TEXEL_M + n / 2).astype(np.float32), (y / TEXEL_M + n / 2).astype(np.float32),
                     cv2.INTER_LINEAR)
    return np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _in_patch(scaled: bool) -> tuple[int, int]:
    """The final build of five keyframes (hole filling off: what covers the patch is the coarse level alone), its
    coarse maps' threshold scaled (the package) or not (as before): (fused points well inside the patch, of them
    more than 1 mm off the plane)."""
    import lapreco_hil.dense.coarse as coarse
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    depth = dataclasses.replace(base.depth, consistency_fill_px=0)
    dense = DenseSurface(CAMERA, dataclasses.replace(base, depth=depth), DEVICE, sources_fn=nearest_views)
    texture = _texture()
    poses = {i: make_T(np.eye(3), [0.002 * dx, 0.002 * dy, 0.0]) for i, (dx, dy) in enumerate(OFFSETS)}
    for i, T in poses.items():
        dense.add_view(i, _image(texture, (T[0, 3], T[1, 3])), T)
    package = coarse.coarse_config
    if not scaled:
        coarse.coarse_config = lambda config: config
    try:
        points = dense.build_at(poses, {i: (0.8 * PLANE_Z_M, 1.25 * PLANE_Z_M) for i in poses}).points
    finally:
        coarse.coarse_config = package
    x, y, z = points.T
    inside = (np.abs(x) < PATCH_M[0] - 0.001) & (np.abs(y) < PATCH_M[1] - 0.001)
    return int(np.count_nonzero(inside)), int(np.count_nonzero(inside & (np.abs(z - PLANE_Z_M) > 0.001)))


def test_the_coarse_levels_texture_threshold_is_divided_by_the_level():
    config = PipelineConfig().depth
    from lapreco_hil.dense.coarse import coarse_config

    assert config.coarse_level == 2
    assert coarse_config(config).min_texture == config.min_texture / 2
    assert dataclasses.replace(coarse_config(config), min_texture=config.min_texture) == config


def test_the_coarse_level_covers_a_patch_too_faint_for_the_full_resolution_threshold(warp_cpu):
    """A patch of std 2.5 grey levels over 1.5 mm: with the full-resolution threshold at the half level too (before)
    nothing is fused inside it; with the threshold halved the half-resolution maps give depths there, the
    neighbours' maps confirm them, and they are fused on the plane (measured: 0 -> 65 points, none off)."""
    before, _ = _in_patch(scaled=False)
    inside, off = _in_patch(scaled=True)
    assert before == 0
    assert inside > 20
    assert off == 0
