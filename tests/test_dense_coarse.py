"""The coarse level for weak texture (lapreco_hil.dense.coarse, ``[depth] coarse_level``): in the final build a
map's holes that a flat window left take the depth of a map of the views reduced by 2, vetted by the consistency
check; its texture threshold is divided by the level (the reduced views' noise is that much lower). Rendered
views of a plane whose texture is faint and smooth in a patch. Warp's CPU device by default
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
PLANE_Z_M = 0.05  # the plane z = 50 mm; cameras at z = 0 look along +z, 2 mm apart
TEXEL_M = 5e-5
PATCH_M = (0.009, 0.006)  # half-sizes (x, y) of the faint patch about the axis
OFFSETS = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]


def _texture(faint: float = 5.0) -> np.ndarray:
    """Grey levels on 0.05 mm texels: a strong fine texture, and in the patch a faint smooth one (std ``faint`` grey
    levels over 1.5 mm; at 5 a 7x7 window at full resolution is flat, at half resolution it is not)."""
    rng = np.random.default_rng(0)
    n = 1024
    fine = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 1.5)
    smooth = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 30.0)
    xs = (np.arange(n) - n / 2) * TEXEL_M
    patch = (np.abs(xs)[None, :] < PATCH_M[0]) & (np.abs(xs)[:, None] < PATCH_M[1])
    return np.where(patch, 128 + faint * smooth / smooth.std(), 128 + 40 * fine / fine.std()).astype(np.float32)


def _image(texture: np.ndarray, camera_xy: tuple[float, float]) -> np.ndarray:
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float32)
    x = camera_xy[0] + (u - CAMERA.cx) / CAMERA.fx * PLANE_Z_M
    y = camera_xy[1] + (v - CAMERA.cy) / CAMERA.fy * PLANE_Z_M
    n = texture.shape[0]
    grey = cv2.remap(texture, (x / TEXEL_M + n / 2).astype(np.float32), (y / TEXEL_M + n / 2).astype(np.float32),
                     cv2.INTER_LINEAR)
    return np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _build(coarse_level: int, faint: float = 5.0) -> np.ndarray:
    """The final build of five keyframes (the consistency check on; the hole filling off, so that what covers the
    patch is the coarse level alone), the patch's texture of std ``faint``: the fused points (metres)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    depth = dataclasses.replace(base.depth, coarse_level=coarse_level, consistency_fill_px=0)
    dense = DenseSurface(CAMERA, dataclasses.replace(base, depth=depth), DEVICE, sources_fn=nearest_views)
    texture = _texture(faint)
    poses = {i: make_T(np.eye(3), [0.002 * dx, 0.002 * dy, 0.0]) for i, (dx, dy) in enumerate(OFFSETS)}
    for i, T in poses.items():
        dense.add_view(i, _image(texture, (T[0, 3], T[1, 3])), T)
    result = dense.build_at(poses, {i: (0.8 * PLANE_Z_M, 1.25 * PLANE_Z_M) for i in poses})
    assert dense.fused == 5
    return result.points


def _in_patch(points: np.ndarray) -> tuple[int, int]:
    """(fused points well inside the patch, 1 mm from its border; of them, more than 1 mm off the plane)."""
    x, y, z = points.T
    inside = (np.abs(x) < PATCH_M[0] - 0.001) & (np.abs(y) < PATCH_M[1] - 0.001)
    return int(np.count_nonzero(inside)), int(np.count_nonzero(inside & (np.abs(z - PLANE_Z_M) > 0.001)))


def test_the_coarse_level_covers_a_faint_patch_the_full_resolution_maps_leave(warp_cpu):
    """No map has a depth in the faint patch at full resolution (its windows are flat), so the fused surface has
    a hole there; with ``coarse_level = 2`` the half-resolution maps give depths there, the neighbours' maps confirm
    them, and they are fused on the plane."""
    assert _in_patch(_build(0))[0] == 0
    inside, off = _in_patch(_build(2))
    assert inside > 20
    assert off == 0


def test_the_coarse_levels_texture_threshold_is_divided_by_the_level():
    """``min_texture`` is the contrast below which a window's ZNCC is noise; the reduced views' area mean averages
    the noise down by the level, so the coarse maps' threshold is divided by it (``coarse.coarse_config``)."""
    from lapreco_hil.dense.coarse import coarse_config

    config = PipelineConfig().depth
    assert config.coarse_level == 2
    assert coarse_config(config).min_texture == config.min_texture / 2
    assert dataclasses.replace(coarse_config(config), min_texture=config.min_texture) == config


def test_the_coarse_level_covers_a_patch_too_faint_for_the_full_resolution_threshold(warp_cpu, monkeypatch):
    """A patch of std 2.5 grey levels over 1.5 mm: with the full-resolution threshold at the half level too (before)
    nothing is fused inside it; with the threshold halved the half-resolution maps give depths there, the
    neighbours' maps confirm them, and they are fused on the plane (measured: 0 -> 65 points, none off)."""
    import lapreco_hil.dense.coarse as coarse

    inside, off = _in_patch(_build(2, faint=2.5))
    assert inside > 20
    assert off == 0
    monkeypatch.setattr(coarse, "coarse_config", lambda config: config)
    assert _in_patch(_build(2, faint=2.5))[0] == 0


def test_coarse_depths_go_only_into_flat_or_unmatched_holes_and_agree_across_an_edge_only_when_close(warp_cpu):
    """The merge itself: a coarse depth enters a hole coded too flat or too weak, not one the depth-edge check
    made, nor a pixel with a depth; it is read bilinearly in inverse depth where the four coarse depths agree, at
    the configured share of their confidence; a coarse step between surfaces 10% apart gives nothing near it."""
    from lapreco_hil.dense.coarse import TAKEN, coarse_into_holes, without_coarse
    from lapreco_hil.dense.types import DepthMap
    from lapreco_hil.dense.warp.plane_sweep import CODE_DEPTH_EDGE, CODE_KEPT, CODE_LOW_TEXTURE, CODE_NO_MATCH

    h, w = 40, 48
    full = DepthMap(0, np.zeros((h, w), np.float32), np.zeros((h, w), np.float32), np.eye(3), np.eye(4))
    full.depth_m[:, :8] = 0.05
    full.confidence[:, :8] = 0.9
    codes = np.full((h, w), CODE_LOW_TEXTURE, np.uint8)
    codes[:, :8] = CODE_KEPT
    codes[:, 8:16] = CODE_NO_MATCH
    codes[:, 16:24] = CODE_DEPTH_EDGE
    coarse_depth = np.full((h // 2, w // 2), 0.05, np.float32)
    coarse_depth[:, 18:] = 0.055  # a step between coarse columns 17 and 18 (read by full columns 35 and 36)
    coarse = DepthMap(0, coarse_depth, np.full((h // 2, w // 2), 0.8, np.float32), np.eye(3), np.eye(4))
    merged = coarse_into_holes(full, codes, coarse, 2, 0.02, 0.5, DEVICE)
    taken = merged.stats[TAKEN]
    assert not taken[:, :8].any() and np.all(merged.depth_m[:, :8] == 0.05)  # a depth stays
    assert taken[:, 8:16].all() and taken[:, 24:34].all()  # weak match, flat window
    assert not taken[:, 16:24].any()  # a depth edge stays a hole
    assert not taken[:, 35:37].any()  # the coarse step (its four depths disagree) ...
    assert taken[:, 37:].all()  # ... and beyond it
    np.testing.assert_allclose(merged.depth_m[:, 24:34], 0.05, rtol=1e-6)
    np.testing.assert_allclose(merged.depth_m[:, 37:], 0.055, rtol=1e-6)
    np.testing.assert_allclose(merged.confidence[taken], 0.4, rtol=1e-6)
    assert not without_coarse(merged).depth_m[taken].any()


def test_the_coarse_kernel_compiles_for_cuda(sm90_ptx):
    """CI has no GPU: the coarse level's kernel still compiles for an H100 (sm_90)."""
    from lapreco_hil.dense.warp import coarse

    assert "coarse_into_holes" in sm90_ptx(coarse)
