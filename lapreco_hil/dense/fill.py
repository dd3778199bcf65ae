"""Holes of a depth map filled from the depths about them, for the final build's consistency check to vet.

A textureless patch, a highlight or a stretch the matching lost, enclosed by one surface, is filled by inverse
depth interpolated between the depths on either side along four lines (warp/fill.py). A filled depth is a guess:
it is only ever fused after other keyframes' maps confirm it (``DenseSurface._fuse_consistent``), and it confirms
their depths in turn where they lie on it.
"""

from __future__ import annotations

import numpy as np

from lapreco_hil.dense.types import DepthMap
from lapreco_hil.warp_device import device_lock, init_warp


def fill_holes(depth_map: DepthMap, max_px: int, max_rel: float, min_lines: int = 2, weight: float = 0.5,
               device: str = "cpu") -> DepthMap:
    """``depth_map`` with its holes of at most ``max_px`` pixels along a row, a column or a diagonal filled where
    at least ``min_lines`` of those lines bridge it between depths within ``max_rel`` of one another (inverse
    depth), at ``weight`` times its ends' confidence. ``max_px`` 0: the map as it is."""
    if max_px <= 0:
        return depth_map
    wp = init_warp()
    from lapreco_hil.dense.warp import fill as kernels

    h, w = depth_map.depth_m.shape
    with device_lock(device):
        depth = wp.array(np.ascontiguousarray(depth_map.depth_m, np.float32), dtype=float, device=device)
        confidence = wp.array(np.ascontiguousarray(depth_map.confidence, np.float32), dtype=float, device=device)
        out_depth = wp.empty((h, w), dtype=float, device=device)
        out_confidence = wp.empty((h, w), dtype=float, device=device)
        wp.launch(kernels.fill_holes, dim=(h, w), inputs=[depth, confidence, int(max_px), float(max_rel),
                                                          int(min_lines), float(weight), out_depth, out_confidence],
                  device=device)
        filled_depth = out_depth.numpy()
        filled_confidence = out_confidence.numpy()
    stats = dict(depth_map.stats or {})
    stats["filled_pixels"] = int(np.count_nonzero(filled_depth > 0) - np.count_nonzero(depth_map.depth_m > 0))
    return DepthMap(depth_map.kf_id, filled_depth, filled_confidence, depth_map.K, depth_map.T_world_camera, stats)
