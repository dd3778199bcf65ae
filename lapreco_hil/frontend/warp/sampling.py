"""Device functions shared by the front-end's kernels: clamped and bilinear samples of flat images (a pyramid
is one flat array with per-level offsets, widths and heights: kernels cannot take a list of arrays), and the
field-of-view test of a track position."""

from __future__ import annotations

import warp as wp

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})


@wp.func
def clamped_px(img: wp.array(dtype=float), off: int, w: int, h: int, x: int, y: int) -> float:
    xc = wp.clamp(x, 0, w - 1)
    yc = wp.clamp(y, 0, h - 1)
    return img[off + yc * w + xc]


@wp.func
def bilinear(img: wp.array(dtype=float), off: int, w: int, h: int, x: float, y: float) -> float:
    """Bilinear sample, border replicated; integer coordinates are pixel centres (OpenCV's convention)."""
    x0f = wp.floor(x)
    y0f = wp.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = int(x0f)
    y0 = int(y0f)
    a = clamped_px(img, off, w, h, x0, y0)
    b = clamped_px(img, off, w, h, x0 + 1, y0)
    c = clamped_px(img, off, w, h, x0, y0 + 1)
    d = clamped_px(img, off, w, h, x0 + 1, y0 + 1)
    return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy


@wp.func
def in_view(mask: wp.array2d(dtype=wp.uint8), p: wp.vec2) -> bool:
    if wp.isnan(p[0]) or wp.isnan(p[1]):
        return False
    x = int(wp.round(p[0]))
    y = int(wp.round(p[1]))
    if x < 0 or y < 0 or x >= mask.shape[1] or y >= mask.shape[0]:
        return False
    return mask[y, x] != wp.uint8(0)
