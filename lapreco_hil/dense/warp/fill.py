"""Kernel of the hole filling the final build's consistency check vets (private: the host side is
lapreco_hil.dense.fill).

A pixel without a depth takes one interpolated between the nearest depths on either side of it along the row,
the column and both diagonals, where a hole of at most ``max_px`` pixels lies between two depths that agree:
each end's own line (through it and a depth a few steps beyond it) predicts the other's inverse depth within
``max_rel``. Inverse depth is affine in the image along a plane, so a hole in a plane (a textureless patch, a
highlight, a slanted stretch the matching lost) is filled exactly; a gap between two surfaces (a silhouette and
what lies behind it) has ends that disagree and stays a hole. At least ``min_lines`` lines must bridge the hole and agree
with one another: a hole enclosed by one surface, not a strip past its border.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

SLOPE_SPAN = wp.constant(3)  # an end's slope along a line: from the depth this many steps beyond it


@wp.func
def _end(depth: wp.array2d(dtype=float), x: int, y: int, dx: int, dy: int, max_px: int) -> wp.vec2:
    """(distance in steps, depth) of the first depth from (x, y) along (dx, dy) within ``max_px`` steps; (0, 0)
    when there is none."""
    h = depth.shape[0]
    w = depth.shape[1]
    for t in range(1, max_px + 1):
        xx = x + t * dx
        yy = y + t * dy
        if xx < 0 or yy < 0 or xx >= w or yy >= h:
            return wp.vec2(0.0, 0.0)
        d = depth[yy, xx]
        if d > 0.0:
            return wp.vec2(float(t), d)
    return wp.vec2(0.0, 0.0)


@wp.func
def _predicts(depth: wp.array2d(dtype=float), x: int, y: int, dx: int, dy: int, t: float, rho: float,
              rho_other: float, gap: float, max_rel: float) -> int:
    """1 when the line through the end ``t`` steps along (dx, dy) (inverse depth ``rho``) and the depth ``SLOPE_SPAN``
    steps beyond it predicts the other end (``gap`` steps back, ``rho_other``) within ``max_rel``; 1 too where
    there is no depth beyond it to tell the slope and the ends agree within ``max_rel``."""
    h = depth.shape[0]
    w = depth.shape[1]
    xx = x + (int(t) + SLOPE_SPAN) * dx
    yy = y + (int(t) + SLOPE_SPAN) * dy
    predicted = rho
    if xx >= 0 and yy >= 0 and xx < w and yy < h:
        d = depth[yy, xx]
        if d > 0.0:
            predicted = rho - (1.0 / d - rho) * gap / float(SLOPE_SPAN)
    if wp.abs(predicted - rho_other) <= max_rel * wp.min(rho, rho_other):
        return 1
    return 0


@wp.kernel
def fill_holes(depth: wp.array2d(dtype=float), confidence: wp.array2d(dtype=float), max_px: int, max_rel: float,
               min_lines: int, weight: float, out_depth: wp.array2d(dtype=float),
               out_confidence: wp.array2d(dtype=float)):
    """``out_*``: the map with its holes filled (see the module's docstring); a filled depth's confidence is
    ``weight`` times the lower of its ends' (the mean over the lines that bridge it)."""
    y, x = wp.tid()
    d0 = depth[y, x]
    out_depth[y, x] = d0
    out_confidence[y, x] = confidence[y, x]
    if d0 > 0.0:
        return
    n = int(0)
    rho_sum = float(0.0)
    rho_min = float(1.0e30)
    rho_max = float(0.0)
    conf_sum = float(0.0)
    for line in range(4):
        dx = 1
        dy = 0
        if line == 1:
            dx = 0
            dy = 1
        elif line == 2:
            dy = 1
        elif line == 3:
            dy = -1
        a = _end(depth, x, y, dx, dy, max_px)
        if a[0] > 0.0:
            b = _end(depth, x, y, -dx, -dy, max_px)
            gap = a[0] + b[0]
            if b[0] > 0.0 and gap <= float(max_px + 1):
                ra = 1.0 / a[1]
                rb = 1.0 / b[1]
                if (_predicts(depth, x, y, dx, dy, a[0], ra, rb, gap, max_rel) == 1
                        and _predicts(depth, x, y, -dx, -dy, b[0], rb, ra, gap, max_rel) == 1):
                    rho = (ra * b[0] + rb * a[0]) / gap
                    ca = confidence[y + int(a[0]) * dy, x + int(a[0]) * dx]
                    cb = confidence[y - int(b[0]) * dy, x - int(b[0]) * dx]
                    n += 1
                    rho_sum += rho
                    rho_min = wp.min(rho_min, rho)
                    rho_max = wp.max(rho_max, rho)
                    conf_sum += wp.min(ca, cb)
    if n < min_lines or n == 0:
        return
    if rho_max - rho_min > max_rel * rho_min:
        return
    out_depth[y, x] = float(n) / rho_sum
    out_confidence[y, x] = weight * conf_sum / float(n)
