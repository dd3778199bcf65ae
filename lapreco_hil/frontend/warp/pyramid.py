"""The image stages of the front-end: undistortion into the log domain, shading removal (a wide blur at reduced
resolution), the pyramid and its gradients. Images are float32; a pyramid is one flat array with per-level
offsets, widths and heights (kernels cannot take a list of arrays)."""

from __future__ import annotations

from typing import Any

import warp as wp

from lapreco_hil.frontend.image import HIGHPASS_RANGE, LOG_OFFSET
from lapreco_hil.frontend.warp.sampling import bilinear

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})


@wp.func
def _grey(frame: wp.array2d(dtype=wp.uint8), x: int, y: int) -> float:
    return float(frame[wp.clamp(y, 0, frame.shape[0] - 1), wp.clamp(x, 0, frame.shape[1] - 1)])


@wp.kernel
def _undistort_log(frame: wp.array2d(dtype=wp.uint8), remap: wp.array2d(dtype=wp.vec2),
                   log_out: wp.array2d(dtype=float)):
    """One resampling pass: undistorted pixel <- bilinear sample of the distorted grey frame (0-255) at the
    precomputed map (outside the frame: 0, as cv2.remap's constant border), stored as log(LOG_OFFSET + grey). The log
    is what the shading removal works on; plain intensity is recovered from it exactly enough (``level0``)."""
    y, x = wp.tid()
    m = remap[y, x]
    g = float(0.0)
    if m[0] >= -1.0 and m[1] >= -1.0 and m[0] <= float(frame.shape[1]) and m[1] <= float(frame.shape[0]):
        x0f = wp.floor(m[0])
        y0f = wp.floor(m[1])
        fx = m[0] - x0f
        fy = m[1] - y0f
        x0 = int(x0f)
        y0 = int(y0f)
        top = _grey(frame, x0, y0) * (1.0 - fx) + _grey(frame, x0 + 1, y0) * fx
        bot = _grey(frame, x0, y0 + 1) * (1.0 - fx) + _grey(frame, x0 + 1, y0 + 1) * fx
        g = top * (1.0 - fy) + bot * fy
    log_out[y, x] = wp.log(LOG_OFFSET + g)


@wp.func
def block_mean(src: wp.array2d(dtype=Any), x: int, y: int, factor: int) -> float:
    """The mean of ``src``'s factor x factor block (x, y) (a block past the border: its pixels inside)."""
    h = src.shape[0]
    w = src.shape[1]
    s = float(0.0)
    n = int(0)
    for j in range(factor):
        yy = y * factor + j
        if yy < h:
            for i in range(factor):
                xx = x * factor + i
                if xx < w:
                    s += float(src[yy, xx])
                    n += 1
    return s / float(wp.max(n, 1))


@wp.func
def border_index(x: int, n: int, reflect: bool) -> int:
    """x inside [0, n): mirrored about the border pixel (BORDER_REFLECT_101) or replicated."""
    r = wp.clamp((n - 1) - wp.abs((n - 1) - wp.abs(x)), 0, n - 1)
    return wp.where(reflect, r, wp.clamp(x, 0, n - 1))


@wp.kernel
def _box_mean(src: wp.array2d(dtype=float), dst: wp.array(dtype=float), dw: int, factor: int):
    """factor x factor mean into a reduced flat image (a block past the border: its pixels inside). The shading
    estimate is a wide blur, so it is taken at a resolution where its sigma is a few pixels: factor^2 fewer
    pixels and factor times fewer taps, and the block's own blur is small beside the Gaussian's."""
    y, x = wp.tid()
    dst[y * dw + x] = block_mean(src, x, y, factor)


@wp.kernel
def _blur_1d(src: wp.array(dtype=float), w: int, h: int, weights: wp.array(dtype=float), step_x: int,
             step_y: int, reflect: int, dst: wp.array(dtype=float)):
    """One pass of a separable filter along (step_x, step_y) over a flat w x h image: run it along rows, then
    along columns; at the border replicated, or reflected (``reflect``: BORDER_REFLECT_101). Away from the
    border the taps walk a flat index with no clamping (the pass is bound by its instruction count, not by
    memory)."""
    y, x = wp.tid()
    r = (weights.shape[0] - 1) // 2
    s = float(0.0)
    if x - r * step_x >= 0 and x + r * step_x < w and y - r * step_y >= 0 and y + r * step_y < h:
        stride = step_x + step_y * w
        i = y * w + x - r * stride
        for k in range(weights.shape[0]):
            s += weights[k] * src[i]
            i += stride
    else:
        for k in range(weights.shape[0]):
            xx = border_index(x + (k - r) * step_x, w, reflect != 0)
            yy = border_index(y + (k - r) * step_y, h, reflect != 0)
            s += weights[k] * src[yy * w + xx]
    dst[y * w + x] = s


@wp.kernel
def _level0(log_img: wp.array2d(dtype=float), low_lit: wp.array(dtype=float), lw: int, lh: int, factor: int,
            subtract: int, pyr: wp.array(dtype=float), lit: wp.array2d(dtype=float)):
    """Level 0 of the pyramid and the full-resolution shading level ``lit`` (the blurred log image, upsampled
    bilinearly from the reduced resolution ``factor``). Level 0 is log - lit, the shading-free log image, clamped to the range
    the OpenCV baseline keeps in 8 bits (so silhouettes against black do not dominate the corner threshold),
    or, with ``subtract`` 0, plain intensity in [0, 1]."""
    y, x = wp.tid()
    # pixel centre x of the full image lies at (x + 0.5) / factor - 0.5 in the reduced image's pixel coordinates
    inv = 1.0 / float(factor)
    s = bilinear(low_lit, 0, lw, lh, (float(x) + 0.5) * inv - 0.5, (float(y) + 0.5) * inv - 0.5)
    lit[y, x] = s
    v = log_img[y, x]
    if subtract != 0:
        v = wp.clamp(v - s, -HIGHPASS_RANGE, HIGHPASS_RANGE)
    else:
        v = (wp.exp(v) - LOG_OFFSET) / 255.0
    pyr[y * log_img.shape[1] + x] = v


@wp.kernel
def _pyr_down(pyr: wp.array(dtype=float), src_off: int, sw: int, sh: int, dst_off: int, dw: int, dh: int):
    """Gaussian 5-tap [1 4 6 4 1]/16 in both directions, then every other pixel, the border reflected
    (cv2.pyrDown's BORDER_REFLECT_101)."""
    y, x = wp.tid()
    if x >= dw or y >= dh:
        return
    s = float(0.0)
    for j in range(5):
        wy = float(1.0)
        if j == 1 or j == 3:
            wy = 4.0
        if j == 2:
            wy = 6.0
        for i in range(5):
            wx = float(1.0)
            if i == 1 or i == 3:
                wx = 4.0
            if i == 2:
                wx = 6.0
            s += wx * wy * pyr[src_off + border_index(2 * y + j - 2, sh, True) * sw
                               + border_index(2 * x + i - 2, sw, True)]
    pyr[dst_off + y * dw + x] = s / 256.0


@wp.kernel
def _sobel_levels(pyr: wp.array(dtype=float), offs: wp.array(dtype=int), ws: wp.array(dtype=int),
                  hs: wp.array(dtype=int), levels: int, gx: wp.array(dtype=float), gy: wp.array(dtype=float)):
    """The gradients of every pyramid level in one launch over the flat pyramid (a thread finds its level from
    the offsets). Level 0: 3x3 Sobel / 8, border replicated (cv2.Sobel ksize=3, scale 1/8: what the corner
    response and the drift check use, as the OpenCV baseline's). The coarser levels, which only LK reads: 3x3
    Scharr / 32, border reflected, as OpenCV's LK takes them (calcSharrDeriv); Sobel's weaker smoothing across
    the derivative put the coarse levels' steps off OpenCV's on the periodic dot grid (docs/frontend-real-frames.md)."""
    i = wp.tid()
    lvl = int(0)
    for l in range(1, levels):
        if i >= offs[l]:
            lvl = l
    off = offs[lvl]
    w = ws[lvl]
    h = hs[lvl]
    j = i - off
    y = j // w
    x = j - y * w
    if y >= h:
        return
    coarse = lvl > 0
    side = wp.where(coarse, 3.0, 1.0)
    mid = wp.where(coarse, 10.0, 2.0)
    scale = wp.where(coarse, 1.0 / 32.0, 1.0 / 8.0)
    xm = border_index(x - 1, w, coarse)
    xp = border_index(x + 1, w, coarse)
    rm = off + border_index(y - 1, h, coarse) * w
    r0 = off + y * w
    rp = off + border_index(y + 1, h, coarse) * w
    a = pyr[rm + xm]
    b = pyr[rm + x]
    c = pyr[rm + xp]
    d = pyr[r0 + xm]
    f = pyr[r0 + xp]
    g = pyr[rp + xm]
    hh = pyr[rp + x]
    k = pyr[rp + xp]
    gx[i] = (side * (c + k - a - g) + mid * (f - d)) * scale
    gy[i] = (side * (g + k - a - c) + mid * (hh - b)) * scale


# --- host wrappers: a device and preallocated outputs --------------------------------------------------------
def undistort_log(frame: wp.array, remap: wp.array, log_out: wp.array, device) -> None:
    """``log_out`` (H, W) <- log(LOG_OFFSET + grey) of the distorted ``frame`` resampled at ``remap``."""
    wp.launch(_undistort_log, dim=log_out.shape, inputs=[frame, remap, log_out], device=device)


def box_mean(src: wp.array, dst: wp.array, dw: int, dh: int, factor: int, device) -> None:
    """``dst`` (flat dw x dh) <- the factor x factor block means of ``src``."""
    wp.launch(_box_mean, dim=(dh, dw), inputs=[src, dst, dw, factor], device=device)


def blur_1d(src: wp.array, w: int, h: int, weights: wp.array, step_x: int, step_y: int, dst: wp.array,
            device, reflect: bool = False) -> None:
    """``dst`` <- one separable-filter pass of the flat w x h ``src`` along (step_x, step_y), the border
    replicated or ``reflect``-ed."""
    wp.launch(_blur_1d, dim=(h, w), inputs=[src, w, h, weights, step_x, step_y, 1 if reflect else 0, dst],
              device=device)


def level0(log_img: wp.array, low_lit: wp.array, lw: int, lh: int, factor: int, subtract: bool, pyr: wp.array,
           lit: wp.array, device) -> None:
    """Pyramid level 0 into ``pyr`` and the full-resolution shading level (``low_lit`` upsampled) into ``lit``."""
    wp.launch(_level0, dim=log_img.shape,
              inputs=[log_img, low_lit, lw, lh, factor, 1 if subtract else 0, pyr, lit], device=device)


def pyr_down(pyr: wp.array, src_off: int, sw: int, sh: int, dst_off: int, dw: int, dh: int, device) -> None:
    """The level at ``dst_off`` (dw x dh) of the flat pyramid from the one at ``src_off``."""
    wp.launch(_pyr_down, dim=(dh, dw), inputs=[pyr, src_off, sw, sh, dst_off, dw, dh], device=device)


def sobel_levels(pyr: wp.array, offs: wp.array, ws: wp.array, hs: wp.array, levels: int, gx: wp.array,
                 gy: wp.array, device) -> None:
    """``gx``, ``gy`` <- the gradients of every level of the flat pyramid (level 0 Sobel, the others Scharr), in one
    launch."""
    wp.launch(_sobel_levels, dim=pyr.shape[0], inputs=[pyr, offs, ws, hs, levels, gx, gy], device=device)
