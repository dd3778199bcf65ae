"""A coarser level for the holes that weak texture leaves, for the final build's consistency check to vet.

Where a full-resolution map has no depth because its window is too flat (``textured``) or its match too weak
(``matched``) - smooth bone, the blurred far omentum - a map made by the same method from the same views reduced by
``[depth] coarse_level`` (the same window in pixels spans that many times more of the scene) gives the depth,
read bilinearly in inverse depth where its four neighbours agree (warp/coarse.py), at ``coarse_weight`` of its
confidence. Like a filled hole, such a depth is only fused where other keyframes' maps confirm it
(``DenseSurface._fuse_consistent``). docs/dense.md, "Session 24".
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.types import DepthMap, KeyframeView
from lapreco_hil.warp_device import device_lock, init_warp

TAKEN = "coarse_taken"  # a map's stats key: (H, W) bool, where its depth came from the coarse level


def coarse_config(config: DepthConfig) -> DepthConfig:
    """The coarse level's depth settings: ``min_texture`` divided by ``coarse_level``. The threshold is a window's
    contrast below which its ZNCC is noise; the area mean of ``coarse_level`` x ``coarse_level`` pixels averages the
    sensor's noise down by that factor, so a window needs that much less contrast to stand as far above it (a
    vignetted periphery's faint texture, the blurred far surface)."""
    factor = max(int(config.coarse_level), 1)
    return dataclasses.replace(config, min_texture=config.min_texture / factor)


def reduced_view(view: KeyframeView, factor: int) -> KeyframeView:
    """``view`` reduced by ``factor`` (area mean; cropped to a multiple of it first, so that the intrinsics scale
    exactly: x_small = (x + 0.5) / factor - 0.5); a reduced pixel is in view where all its pixels are."""
    w, h = view.size
    ws, hs = w // factor, h // factor
    colour = cv2.resize(np.ascontiguousarray(view.colour[:hs * factor, :ws * factor]), (ws, hs),
                        interpolation=cv2.INTER_AREA)
    mask = None
    if view.mask is not None:
        area = cv2.resize(view.mask[:hs * factor, :ws * factor].astype(np.float32), (ws, hs),
                          interpolation=cv2.INTER_AREA)
        mask = area > 1.0 - 1e-4
    K = np.array(view.K, float)
    K[0, 0] /= factor
    K[1, 1] /= factor
    K[0, 1] /= factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return dataclasses.replace(view, colour=colour, K=K, mask=mask)


def coarse_into_holes(full: DepthMap, codes: np.ndarray, coarse: DepthMap, factor: int, max_rel: float,
                      weight: float, device: str = "cpu") -> DepthMap:
    """``full`` with the holes its checks coded too flat or too weak (``codes``: ``DepthEstimator.
    rejection_codes``) given ``coarse``'s depth (a map of the views reduced by ``factor``), where the four coarse
    depths about the pixel agree within ``max_rel`` (inverse depth), at ``weight`` times their confidence;
    ``stats["coarse_taken"]`` marks them."""
    wp = init_warp()
    from lapreco_hil.dense.warp import coarse as kernels
    from lapreco_hil.dense.warp.plane_sweep import CODE_LOW_TEXTURE, CODE_NO_MATCH

    h, w = full.depth_m.shape
    with device_lock(device):
        def up(a, dtype=float):
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)

        out_depth = wp.empty((h, w), dtype=float, device=device)
        out_confidence = wp.empty((h, w), dtype=float, device=device)
        taken = wp.empty((h, w), dtype=wp.uint8, device=device)
        wp.launch(kernels.coarse_into_holes, dim=(h, w),
                  inputs=[up(full.depth_m.astype(np.float32)), up(full.confidence.astype(np.float32)),
                          up(codes.astype(np.uint8), wp.uint8), CODE_LOW_TEXTURE, CODE_NO_MATCH,
                          up(coarse.depth_m.astype(np.float32)), up(coarse.confidence.astype(np.float32)),
                          float(factor), float(max_rel), float(weight), out_depth, out_confidence, taken],
                  device=device)
        depth, confidence, mask = out_depth.numpy(), out_confidence.numpy(), taken.numpy().astype(bool)
    stats = dict(full.stats or {})
    stats[TAKEN] = mask
    stats["coarse_pixels"] = int(np.count_nonzero(mask))
    return DepthMap(full.kf_id, depth, confidence, full.K, full.T_world_camera, stats)


def without_coarse(depth_map: DepthMap) -> DepthMap:
    """``depth_map`` without the depths the coarse level gave it (for a map no other map can check)."""
    taken = (depth_map.stats or {}).get(TAKEN)
    if taken is None or not taken.any():
        return depth_map
    return DepthMap(depth_map.kf_id, np.where(taken, 0.0, depth_map.depth_m).astype(np.float32),
                    np.where(taken, 0.0, depth_map.confidence).astype(np.float32), depth_map.K,
                    depth_map.T_world_camera, dict(depth_map.stats, **{TAKEN: None}))
