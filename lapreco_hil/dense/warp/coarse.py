"""Kernel of the coarse level (private: the host side is lapreco_hil.dense.coarse).

A full-resolution pixel that lost its depth because its window is too flat or its match too weak takes the depth
of a map made from the same views reduced by ``factor``: the same window in pixels spans ``factor`` times more of
the scene there, enough texture on smooth or blurred surface. Read bilinearly in inverse depth (affine along a
plane) from the four coarse depths about the pixel, only where all four exist and agree within ``max_rel``: no
depth is blended across an edge.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def coarse_into_holes(depth: wp.array2d(dtype=float), confidence: wp.array2d(dtype=float),
                      code: wp.array2d(dtype=wp.uint8), code_a: int, code_b: int,
                      coarse_depth: wp.array2d(dtype=float), coarse_confidence: wp.array2d(dtype=float),
                      factor: float, max_rel: float, weight: float, out_depth: wp.array2d(dtype=float),
                      out_confidence: wp.array2d(dtype=float), taken: wp.array2d(dtype=wp.uint8)):
    """``out_*``: the map with the coarse depths in its holes coded ``code_a`` or ``code_b``, at ``weight`` times
    their confidence; ``taken`` 1 where a coarse depth went in."""
    y, x = wp.tid()
    d0 = depth[y, x]
    out_depth[y, x] = d0
    out_confidence[y, x] = confidence[y, x]
    taken[y, x] = wp.uint8(0)
    c = int(code[y, x])
    if d0 > 0.0 or (c != code_a and c != code_b):
        return
    hc = coarse_depth.shape[0]
    wc = coarse_depth.shape[1]
    # the coarse image's pixel centres: u = (x + 0.5) / factor - 0.5
    u = wp.clamp((float(x) + 0.5) / factor - 0.5, 0.0, float(wc - 1))
    v = wp.clamp((float(y) + 0.5) / factor - 0.5, 0.0, float(hc - 1))
    x0 = wp.min(int(wp.floor(u)), wc - 2)
    y0 = wp.min(int(wp.floor(v)), hc - 2)
    fx = u - float(x0)
    fy = v - float(y0)
    d00 = coarse_depth[y0, x0]
    d01 = coarse_depth[y0, x0 + 1]
    d10 = coarse_depth[y0 + 1, x0]
    d11 = coarse_depth[y0 + 1, x0 + 1]
    if d00 <= 0.0 or d01 <= 0.0 or d10 <= 0.0 or d11 <= 0.0:
        return
    r00 = 1.0 / d00
    r01 = 1.0 / d01
    r10 = 1.0 / d10
    r11 = 1.0 / d11
    lo = wp.min(wp.min(r00, r01), wp.min(r10, r11))
    hi = wp.max(wp.max(r00, r01), wp.max(r10, r11))
    if hi - lo > max_rel * lo:
        return
    a = (1.0 - fx) * (1.0 - fy)
    b = fx * (1.0 - fy)
    cc = (1.0 - fx) * fy
    e = fx * fy
    rho = a * r00 + b * r01 + cc * r10 + e * r11
    conf = (a * coarse_confidence[y0, x0] + b * coarse_confidence[y0, x0 + 1] + cc * coarse_confidence[y0 + 1, x0]
            + e * coarse_confidence[y0 + 1, x0 + 1])
    out_depth[y, x] = 1.0 / rho
    out_confidence[y, x] = weight * conf
    taken[y, x] = wp.uint8(1)
