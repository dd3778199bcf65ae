"""Private Warp kernels of the front-end. Images are float32; a pyramid is one flat array with per-level
offsets, widths and heights (kernels cannot take a list of arrays).

Tiled kernels (one block per feature) stride their lane loops by ``wp.block_dim()``: Warp's CPU device runs a
tiled launch with one lane per block, so a constant stride would silently use a fraction of the window there.
"""

from __future__ import annotations

import warp as wp

from ..opencv import HIGHPASS_GAIN

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

PATCH = 13  # drift-check patch side (pixels)
HIGHPASS_RANGE = 128.0 / HIGHPASS_GAIN  # what frontend.opencv.to_u8 keeps of the log high-pass
HALF_PATCH = 6
# new corners are chosen strongest first through a histogram of their scores (no sort): 32 bins per halving of
# the response below the frame's best cover 16 halvings (a quality level down to 1.5e-5)
SCORE_BINS_PER_OCTAVE = 32
SCORE_BINS = 512
PIXEL_KEY_MAX = 2147483647  # the low half of a cell key: ties between equal scores go to the lower pixel index
PIXEL_KEY_MASK = wp.constant(wp.uint64(PIXEL_KEY_MAX))
KEY_SHIFT = wp.constant(wp.uint64(32))
ZERO_KEY = wp.constant(wp.uint64(0))

# Lanes (threads) per feature in LK and in the drift check. More lanes mean fewer window pixels per lane and
# shorter iterations, but wider block sums. Whole 1080p frames with 2000 tracks on an H100 (2026-11-22), LK with
# 32 / 64 / 128 / 256 lanes: 1.29 / 1.13 / 1.09 / 1.18 ms; the drift check with 32 or 64: the same.
LK_LANES = 128
DRIFT_LANES = 64
vec8 = wp.types.vector(length=8, dtype=wp.float32)
vec44 = wp.types.vector(length=44, dtype=wp.float32)  # upper triangle of an 8x8 normal matrix (36) + gradient (8)
mat88 = wp.types.matrix(shape=(8, 8), dtype=wp.float32)


# --- block sums --------------------------------------------------------------------------------------------
# LK and the drift check sum per-lane values over their block once per iteration, and every lane needs the sum.
# wp.tile_sum followed by an extraction takes four barriers and a serial pass by one thread (its result lives in
# lane 0 and is broadcast through shared memory). Here each warp reduces by butterfly shuffles, so every lane
# ends with its warp's sum, and one barrier lets every lane add the warps' sums. Two shared buffers alternate
# with the caller's count of block sums: a lane can only write a buffer again after the next barrier, which
# every lane reaches only once it has read the previous sum. On the CPU a tiled launch has one lane per block,
# whose value is the sum. Every lane of a block must make the same calls (uniform control flow).
_BLOCK_SUM_SNIPPET = """
#if defined(__CUDA_ARCH__)
    static_assert(WP_TILE_BLOCK_DIM % 32 == 0, "block sums need whole warps");
    constexpr int N = sizeof(v) / sizeof(float);
    constexpr int WARPS = WP_TILE_BLOCK_DIM / 32;
    __shared__ float partials[2][WARPS][N];
    auto s = v;
    float* c = reinterpret_cast<float*>(&s);
    #pragma unroll
    for (int i = 0; i < N; ++i) {
        float x = c[i];
        #pragma unroll
        for (int o = 16; o > 0; o >>= 1)
            x += __shfl_xor_sync(0xffffffffu, x, o);
        c[i] = x;
    }
    if (WARPS == 1)
        return s;
    const int buf = parity & 1;
    if ((threadIdx.x & 31) == 0) {
        #pragma unroll
        for (int i = 0; i < N; ++i)
            partials[buf][threadIdx.x >> 5][i] = c[i];
    }
    __syncthreads();
    #pragma unroll
    for (int i = 0; i < N; ++i) {
        float t = partials[buf][0][i];
        #pragma unroll
        for (int w = 1; w < WARPS; ++w)
            t += partials[buf][w][i];
        c[i] = t;
    }
    return s;
#else
    static_assert(WP_TILE_BLOCK_DIM == 1, "block sums on the CPU need one lane per block (enable_cpu_blocks off)");
    return v;
#endif
"""


@wp.func_native(_BLOCK_SUM_SNIPPET)
def _block_sum1(v: float, parity: int) -> float: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def _block_sum3(v: wp.vec3, parity: int) -> wp.vec3: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def _block_sum4(v: wp.vec4, parity: int) -> wp.vec4: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def _block_sum44(v: vec44, parity: int) -> vec44: ...


# --- sampling ----------------------------------------------------------------------------------------------
@wp.func
def _px(img: wp.array(dtype=float), off: int, w: int, h: int, x: int, y: int) -> float:
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
    a = _px(img, off, w, h, x0, y0)
    b = _px(img, off, w, h, x0 + 1, y0)
    c = _px(img, off, w, h, x0, y0 + 1)
    d = _px(img, off, w, h, x0 + 1, y0 + 1)
    return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy


# --- image stages ------------------------------------------------------------------------------------------
@wp.func
def _grey(frame: wp.array2d(dtype=wp.uint8), x: int, y: int) -> float:
    return float(frame[wp.clamp(y, 0, frame.shape[0] - 1), wp.clamp(x, 0, frame.shape[1] - 1)])


@wp.kernel
def undistort_log(frame: wp.array2d(dtype=wp.uint8), remap: wp.array2d(dtype=wp.vec2),
                  log_out: wp.array2d(dtype=float)):
    """One resampling pass: undistorted pixel <- bilinear sample of the distorted grey frame (0-255) at the
    precomputed map (outside the frame: 0, as cv2.remap's constant border), stored as log(1 + grey). The log
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
    log_out[y, x] = wp.log(1.0 + g)


@wp.kernel
def half_mean(src: wp.array2d(dtype=float), dst: wp.array(dtype=float), dw: int):
    """2x2 mean into a half-resolution flat image (odd sizes: the last column/row counts twice). The shading
    estimate is a wide blur, so it is taken at half resolution: a quarter of the pixels and half the taps."""
    y, x = wp.tid()
    h = src.shape[0]
    w = src.shape[1]
    x1 = wp.min(2 * x + 1, w - 1)
    y1 = wp.min(2 * y + 1, h - 1)
    dst[y * dw + x] = 0.25 * (src[2 * y, 2 * x] + src[2 * y, x1] + src[y1, 2 * x] + src[y1, x1])


@wp.kernel
def blur_1d(src: wp.array(dtype=float), w: int, h: int, weights: wp.array(dtype=float), step_x: int,
            step_y: int, dst: wp.array(dtype=float)):
    """One pass of a separable filter along (step_x, step_y) over a flat w x h image: run it along rows, then
    along columns. Away from the border the taps walk a flat index with no clamping (the pass is bound by its
    instruction count, not by memory)."""
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
            xx = wp.clamp(x + (k - r) * step_x, 0, w - 1)
            yy = wp.clamp(y + (k - r) * step_y, 0, h - 1)
            s += weights[k] * src[yy * w + xx]
    dst[y * w + x] = s


@wp.kernel
def level0(log_img: wp.array2d(dtype=float), half_lit: wp.array(dtype=float), hw: int, hh: int, subtract: int,
           pyr: wp.array(dtype=float), lit: wp.array2d(dtype=float)):
    """Level 0 of the pyramid and the full-resolution shading level ``lit`` (the blurred log image, upsampled
    bilinearly from half resolution). Level 0 is log - lit, the shading-free log image, clamped to the range
    the OpenCV baseline keeps in 8 bits (so silhouettes against black do not dominate the corner threshold),
    or, with ``subtract`` 0, plain intensity in [0, 1]."""
    y, x = wp.tid()
    # pixel centre x of the full image lies at (x - 0.5) / 2 in the half image's pixel coordinates
    s = bilinear(half_lit, 0, hw, hh, 0.5 * float(x) - 0.25, 0.5 * float(y) - 0.25)
    lit[y, x] = s
    v = log_img[y, x]
    if subtract != 0:
        v = wp.clamp(v - s, -HIGHPASS_RANGE, HIGHPASS_RANGE)
    else:
        v = (wp.exp(v) - 1.0) / 255.0
    pyr[y * log_img.shape[1] + x] = v


@wp.kernel
def pyr_down(pyr: wp.array(dtype=float), src_off: int, sw: int, sh: int, dst_off: int, dw: int, dh: int):
    """Gaussian 5-tap [1 4 6 4 1]/16 in both directions, then every other pixel (cv2.pyrDown)."""
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
            s += wx * wy * _px(pyr, src_off, sw, sh, 2 * x + i - 2, 2 * y + j - 2)
    pyr[dst_off + y * dw + x] = s / 256.0


@wp.kernel
def sobel_levels(pyr: wp.array(dtype=float), offs: wp.array(dtype=int), ws: wp.array(dtype=int),
                 hs: wp.array(dtype=int), levels: int, gx: wp.array(dtype=float), gy: wp.array(dtype=float)):
    """3x3 Sobel / 8 (cv2.Sobel ksize=3, scale 1/8) of every pyramid level in one launch over the flat
    pyramid: a thread finds its level from the offsets."""
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
    a = _px(pyr, off, w, h, x - 1, y - 1)
    b = _px(pyr, off, w, h, x, y - 1)
    c = _px(pyr, off, w, h, x + 1, y - 1)
    d = _px(pyr, off, w, h, x - 1, y)
    f = _px(pyr, off, w, h, x + 1, y)
    g = _px(pyr, off, w, h, x - 1, y + 1)
    hh = _px(pyr, off, w, h, x, y + 1)
    k = _px(pyr, off, w, h, x + 1, y + 1)
    gx[i] = ((c + 2.0 * f + k) - (a + 2.0 * d + g)) / 8.0
    gy[i] = ((g + 2.0 * hh + k) - (a + 2.0 * b + c)) / 8.0


# --- Shi-Tomasi ----------------------------------------------------------------------------------------------
@wp.func
def _allowed(mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
             occ: wp.array2d(dtype=wp.int32), stamp: int, x: int, y: int) -> bool:
    return mask[y, x] != wp.uint8(0) and occ[y, x] != stamp and lit[y, x] >= lit_min


@wp.kernel
def structure_rows(gx: wp.array(dtype=float), gy: wp.array(dtype=float), w: int, h: int, block: int,
                   rows: wp.array(dtype=wp.vec3)):
    """First, horizontal pass of the structure tensor's box sum: (gx^2, gx gy, gy^2) summed over block columns
    (border replicated). Two separable passes read 3 block values per pixel where one 2D pass reads block^2."""
    y, x = wp.tid()
    r = block // 2
    base = y * w
    acc = wp.vec3(0.0, 0.0, 0.0)
    if x - r >= 0 and x - r + block <= w:
        i = base + x - r
        for k in range(block):
            u = gx[i + k]
            v = gy[i + k]
            acc += wp.vec3(u * u, u * v, v * v)
    else:
        for k in range(block):
            i = base + wp.clamp(x + k - r, 0, w - 1)
            u = gx[i]
            v = gy[i]
            acc += wp.vec3(u * u, u * v, v * v)
    rows[base + x] = acc


@wp.kernel
def min_eigenvalue(rows: wp.array(dtype=wp.vec3), w: int, h: int, block: int, mask: wp.array2d(dtype=wp.uint8),
                   lit: wp.array2d(dtype=float), lit_min: float, occ: wp.array2d(dtype=wp.int32),
                   stamp: wp.array(dtype=wp.int32), eig: wp.array2d(dtype=float), max_eig: wp.array(dtype=float)):
    """Smaller eigenvalue of the structure tensor summed over a block x block window (cornerMinEigenVal), from
    the row sums of ``structure_rows``, and the best of it where corners may start (the quality level is
    relative to it, as OpenCV takes it inside the mask). One block per image row: its lanes stride the row,
    then one block max and one atomic per row. The occupancy must be stamped before."""
    y, lane = wp.tid()
    r = block // 2
    s = stamp[0]
    best = float(0.0)
    x = lane
    while x < w:
        t = wp.vec3(0.0, 0.0, 0.0)
        for k in range(block):
            t += rows[wp.clamp(y + k - r, 0, h - 1) * w + x]
        a = t[0]
        b = t[1]
        c = t[2]
        e = 0.5 * (a + c) - wp.sqrt(wp.max(0.25 * (a - c) * (a - c) + b * b, 0.0))
        eig[y, x] = e
        if e > best and _allowed(mask, lit, lit_min, occ, s, x, y):
            best = e
        x += wp.block_dim()
    row_best = wp.tile_max(wp.tile(best))[0]
    if lane == 0:
        wp.atomic_max(max_eig, 0, row_best)


@wp.kernel
def selection_begin(stamp: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float)):
    """A new detection: two new occupancy stamps (the grid is never cleared: a pixel is occupied when it holds a
    stamp of this detection), one for the selection and one for taking corners, and no best response yet."""
    stamp[0] = stamp[0] + 2
    max_eig[0] = 0.0


@wp.kernel
def occupancy(positions: wp.array(dtype=wp.vec2), steps: wp.array(dtype=wp.vec2), ahead: float,
              count: wp.array(dtype=wp.int32), radius: float, stamp: wp.array(dtype=wp.int32), which: int,
              occ: wp.array2d(dtype=wp.int32)):
    """Mark the disc of radius min_distance around each live track (at its position plus ``ahead`` times its
    last step) with this detection's stamp (plus ``which``: 0 for the selection, 1 for taking corners): no new
    corner may start there. The track count is read on the device, so the launch has a fixed shape and can
    live in a CUDA graph."""
    t, j = wp.tid()
    if t >= count[0]:
        return
    r = int(wp.ceil(radius))
    side = 2 * r + 1
    dy = j // side - r
    dx = j % side - r
    if float(dx * dx + dy * dy) > radius * radius:
        return
    p = positions[t] + ahead * steps[t]
    x = int(wp.round(wp.clamp(p[0], -1.0e6, 1.0e6))) + dx
    y = int(wp.round(wp.clamp(p[1], -1.0e6, 1.0e6))) + dy
    if x >= 0 and y >= 0 and x < occ.shape[1] and y < occ.shape[0]:
        occ[y, x] = stamp[0] + which


@wp.func
def _cell_of(x: float, y: float, cell: float, grid_w: int) -> int:
    return int(y / cell) * grid_w + int(x / cell)


@wp.kernel
def corner_candidates(eig: wp.array2d(dtype=float), max_eig: wp.array(dtype=float), quality: float,
                      mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
                      occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32), border: int, cell: float,
                      grid_w: int,
                      cell_key: wp.array(dtype=wp.uint64)):
    """Local maxima (3x3) above quality x the frame's best response, inside the field of view, lit, and away
    from live tracks. Cells have side min_distance / sqrt(2), so two corners in one cell are always too close:
    each cell keeps its strongest through one 64-bit atomic max of (score relative to the best, pixel) with
    ties to the lower pixel index. No candidate list, so no cap on how many maxima a frame may have."""
    y, x = wp.tid()
    h = eig.shape[0]
    w = eig.shape[1]
    if x < border or y < border or x >= w - border or y >= h - border:
        return
    v = eig[y, x]
    if v < quality * max_eig[0] or v <= 0.0:
        return
    if not _allowed(mask, lit, lit_min, occ, stamp[0], x, y):
        return
    for j in range(3):
        for i in range(3):
            n = eig[y + j - 1, x + i - 1]
            if n > v or (n == v and (j * 3 + i) < 4):
                return
    rel = wp.min(v / max_eig[0], 1.0)
    key = (wp.uint64(int(rel * 2.0e9)) << KEY_SHIFT) | wp.uint64(PIXEL_KEY_MAX - (y * w + x))
    wp.atomic_max(cell_key, _cell_of(float(x), float(y), cell, grid_w), key)


# --- pyramidal Lucas-Kanade, one block per feature -----------------------------------------------------------
@wp.func
def _window_origin(x: float, y: float) -> wp.vec4:
    """(floor x, floor y, fraction x, fraction y) of a window's top-left sample. The floors are clamped to a
    range that converts to int safely: a diverging step can put a window anywhere, NaN included."""
    fx = wp.floor(x)
    fy = wp.floor(y)
    return wp.vec4(wp.clamp(fx, -1.0e6, 1.0e6), wp.clamp(fy, -1.0e6, 1.0e6), x - fx, y - fy)


@wp.func
def _window_px(img: wp.array(dtype=float), off: int, w: int, h: int, o: wp.vec4, k: int, win: int,
               inv_win: float) -> float:
    """Pixel k (row-major) of a win x win window with origin o (``_window_origin``), bilinear, border
    replicated. Every pixel of a translated window shares the same sub-pixel fractions. There is no branch:
    the four addresses are clamped into the image, so the loads of all of a lane's pixels can be in flight at
    once (an iteration waits for memory once, not once per pixel)."""
    row = int((float(k) + 0.5) * inv_win)  # k // win without an integer division
    col = k - row * win
    x0 = int(o[0]) + col
    y0 = int(o[1]) + row
    xa = wp.clamp(x0, 0, w - 1)
    xb = wp.clamp(x0 + 1, 0, w - 1)
    ra = off + wp.clamp(y0, 0, h - 1) * w
    rb = off + wp.clamp(y0 + 1, 0, h - 1) * w
    a = img[ra + xa]
    b = img[ra + xb]
    c = img[rb + xa]
    d = img[rb + xb]
    top = a + o[2] * (b - a)
    return top + o[3] * (c + o[2] * (d - c) - top)


def _make_lk_track(cache: int):
    """The LK kernel for lanes that each keep ``cache`` window pixels (and their gradients) in registers."""
    cache_vec = wp.types.vector(length=cache, dtype=wp.float32)
    cache_ivec = wp.types.vector(length=cache, dtype=wp.int32)

    @wp.kernel(module="unique", enable_backward=False)
    def lk_track(prev: wp.array(dtype=float), prev_gx: wp.array(dtype=float), prev_gy: wp.array(dtype=float),
                 cur: wp.array(dtype=float), offs: wp.array(dtype=int), ws: wp.array(dtype=int),
                 hs: wp.array(dtype=int), levels: int, win: int, iterations: int, eps: float, min_eig: float,
                 max_error: float, pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32),
                 out_pts: wp.array(dtype=wp.vec2),
                 status: wp.array(dtype=wp.int32), error: wp.array(dtype=float)):
        """Bouguet's pyramidal LK: per level, the window's spatial gradient matrix from the previous image, then
        Newton steps on the temporal difference; the lanes of a block share the window, tile sums combine them.

        The time goes into the iterations of the slowest features (30 per level at most, as OpenCV), so each
        iteration is kept short: the window's sub-pixel fractions are computed once per iteration, not per pixel,
        each lane keeps its pixels of the previous window and their gradients in registers (with enough lanes,
        i.e. on CUDA; with one lane, on the CPU device, it re-samples them instead), and its loads of the current
        window carry no branch, so they are all in flight together."""
        f, lane = wp.tid()
        if f >= count[0]:
            return  # the launch covers every slot; the live count is on the device (the whole block leaves)
        nl = wp.block_dim()
        n = win * win
        r = float(win - 1) * 0.5
        inv_win = 1.0 / float(win)
        p0 = pts[f]
        g = wp.vec2(0.0, 0.0)  # guess carried down the pyramid (current level units)
        ok = int(1)
        abs_sum = float(0.0)  # the last iteration's sum of absolute differences over the window
        sums = int(0)  # block sums so far (their shared buffers alternate)
        eps2 = eps * eps
        cached = n <= cache * nl
        for li in range(levels):
            lvl = levels - 1 - li
            off = offs[lvl]
            w = ws[lvl]
            h = hs[lvl]
            p = p0 * (1.0 / float(1 << lvl))
            o = _window_origin(p[0] - r, p[1] - r)
            # spatial gradient matrix over the window in the previous image (its pixels cached on the way)
            acc = wp.vec3(0.0, 0.0, 0.0)
            c_i = cache_vec()
            c_x = cache_vec()
            c_y = cache_vec()
            c_o = cache_ivec()  # each cached pixel's offset in the level (row * w + col); 0 past the window
            if cached:
                for j in range(cache):
                    # unconditional loads, masked: a lane's slots past the window read a clamped pixel, weigh 0
                    k = lane + j * nl
                    valid = wp.where(k < n, 1.0, 0.0)
                    row = int((float(k) + 0.5) * inv_win)
                    c_o[j] = wp.where(k < n, row * w + k - row * win, 0)
                    vx = _window_px(prev_gx, off, w, h, o, k, win, inv_win) * valid
                    vy = _window_px(prev_gy, off, w, h, o, k, win, inv_win) * valid
                    c_i[j] = _window_px(prev, off, w, h, o, k, win, inv_win)
                    c_x[j] = vx
                    c_y[j] = vy
                    acc += wp.vec3(vx * vx, vx * vy, vy * vy)
            else:
                k = lane
                while k < n:
                    vx = _window_px(prev_gx, off, w, h, o, k, win, inv_win)
                    vy = _window_px(prev_gy, off, w, h, o, k, win, inv_win)
                    acc += wp.vec3(vx * vx, vx * vy, vy * vy)
                    k += nl
            G = _block_sum3(acc, sums)
            sums += 1
            det = G[0] * G[2] - G[1] * G[1]
            lam = 0.5 * (G[0] + G[2]) - wp.sqrt(wp.max(0.25 * (G[0] - G[2]) * (G[0] - G[2]) + G[1] * G[1], 0.0))
            if lam / float(n) < min_eig or wp.abs(det) < 1.0e-12:
                ok = 0
            inv_det = 1.0 / wp.where(ok == 1, det, 1.0)
            nu = wp.vec2(0.0, 0.0)
            last_step = wp.vec2(0.0, 0.0)
            done = int(0)
            if ok == 0:
                done = 1
            for _it in range(iterations):
                # every lane holds the same reduced values, so leaving the loop is uniform across the block
                if done == 1:
                    break
                oq = _window_origin(p[0] - r + g[0] + nu[0], p[1] - r + g[1] + nu[1])
                if oq[0] < -float(win) or oq[1] < -float(win) or oq[0] >= float(w) or oq[1] >= float(h):
                    # the window has left the level (OpenCV's test): its samples are the clamped border, so the
                    # steps would not converge and the track would take every iteration of every level. The
                    # track is lost if this happens on the finest level; on a coarser one it keeps its guess.
                    if lvl == 0:
                        ok = 0
                    break
                bacc = wp.vec3(0.0, 0.0, 0.0)
                if cached and oq[0] >= 0.0 and oq[1] >= 0.0 and oq[0] + float(win) <= float(w - 1) and (
                        oq[1] + float(win) <= float(h - 1)):
                    # the window and its bilinear neighbours lie inside the level (the same answer in every lane):
                    # each pixel is its precomputed offset from the window's corner, four loads and three lerps
                    corner = off + int(oq[1]) * w + int(oq[0])
                    for j in range(cache):
                        i = corner + c_o[j]
                        p00 = cur[i]
                        p01 = cur[i + 1]
                        p10 = cur[i + w]
                        p11 = cur[i + w + 1]
                        top = p00 + oq[2] * (p01 - p00)
                        diff = (c_i[j] - top - oq[3] * (p10 + oq[2] * (p11 - p10) - top)) * wp.where(
                            lane + j * nl < n, 1.0, 0.0)
                        bacc += wp.vec3(diff * c_x[j], diff * c_y[j], wp.abs(diff))
                elif cached:
                    for j in range(cache):
                        k = lane + j * nl
                        diff = (c_i[j] - _window_px(cur, off, w, h, oq, k, win, inv_win)) * wp.where(k < n, 1.0, 0.0)
                        bacc += wp.vec3(diff * c_x[j], diff * c_y[j], wp.abs(diff))
                else:
                    k = lane
                    while k < n:
                        diff = (_window_px(prev, off, w, h, o, k, win, inv_win)
                                - _window_px(cur, off, w, h, oq, k, win, inv_win))
                        vx = _window_px(prev_gx, off, w, h, o, k, win, inv_win)
                        vy = _window_px(prev_gy, off, w, h, o, k, win, inv_win)
                        bacc += wp.vec3(diff * vx, diff * vy, wp.abs(diff))
                        k += nl
                b = _block_sum3(bacc, sums)
                sums += 1
                abs_sum = b[2]
                step = wp.vec2(G[2] * b[0] - G[1] * b[1], G[0] * b[1] - G[1] * b[0]) * inv_det
                nu = nu + step
                if wp.dot(step, step) < eps2:
                    done = 1
                elif _it > 0 and wp.abs(step[0] + last_step[0]) < 0.01 and wp.abs(step[1] + last_step[1]) < 0.01:
                    # the step undoes the last one (oscillation around the optimum): take the midpoint and stop,
                    # as OpenCV's calcOpticalFlowPyrLK does, rather than bouncing until the iteration limit
                    nu = nu - 0.5 * step
                    done = 1
                last_step = step
            if lvl > 0:
                g = (g + nu) * 2.0
            else:
                g = g + nu
        if lane == 0:
            q = p0 + g
            finite = not (wp.isnan(q[0]) or wp.isnan(q[1]) or wp.isinf(q[0]) or wp.isinf(q[1]))
            in_image = finite and q[0] >= 0.0 and q[1] >= 0.0 and q[0] <= float(ws[0] - 1) and q[1] <= float(hs[0] - 1)
            err = abs_sum / float(n)
            out_pts[f] = q
            # lost: too little texture, the window left the image, or the window's mean absolute difference
            # above max_error (as the OpenCV baseline filters calcOpticalFlowPyrLK's error)
            status[f] = wp.where(ok == 1 and in_image and err < max_error, 1, 0)
            error[f] = err

    return lk_track


# each lane caches enough pixels that the lanes cover windows up to 22 x 22
lk_track = _make_lk_track((22 * 22 + LK_LANES - 1) // LK_LANES)


# --- Zinsser drift check, one block per feature --------------------------------------------------------------
@wp.func
def _chol_solve8(H: mat88, g: vec8) -> vec8:
    """Solve H x = g for a symmetric positive definite 8x8 H (Cholesky). Every loop has a constant range and
    the triangular structure is in conditions on the loop indices, so Warp unrolls them and every index is a
    compile-time constant: the matrices stay in registers instead of local memory."""
    Lm = mat88()
    for j in range(8):
        s = H[j, j]
        for k in range(8):
            if k < j:
                s -= Lm[j, k] * Lm[j, k]
        d = wp.sqrt(wp.max(s, 1.0e-12))
        Lm[j, j] = d
        inv = 1.0 / d
        for i in range(8):
            if i > j:
                t = H[i, j]
                for k in range(8):
                    if k < j:
                        t -= Lm[i, k] * Lm[j, k]
                Lm[i, j] = t * inv
    y = vec8()
    for i in range(8):
        t = g[i]
        for k in range(8):
            if k < i:
                t -= Lm[i, k] * y[k]
        y[i] = t / Lm[i, i]
    x = vec8()
    for ii in range(8):
        i = 7 - ii
        t = y[i]
        for k in range(8):
            if k > i:
                t -= Lm[k, i] * x[k]
        x[i] = t / Lm[i, i]
    return x


@wp.func
def _normal_equations(row: vec8, r: float, acc: vec44) -> vec44:
    """acc + the upper triangle of row row^T (36, row-major) and row r (8), with constant indices (unrolled)."""
    out = acc
    for a in range(8):
        for c in range(8):
            if c >= a:
                i = a * 8 - (a * (a - 1)) // 2 + (c - a)
                out[i] = out[i] + row[a] * row[c]
        out[36 + a] = out[36 + a] + row[a] * r
    return out


@wp.func
def _patch_offset(k: int) -> wp.vec2:
    """Offset of pixel k of a PATCH x PATCH patch from its centre."""
    return wp.vec2(float(k % PATCH - HALF_PATCH), float(k // PATCH - HALF_PATCH))


@wp.kernel
def sample_patches(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                   count: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32),
                   patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22), steps: wp.array(dtype=wp.vec2)):
    """The first patch of each new track (slots count .. count + taken[0] - 1), an identity warp, no step."""
    t, k = wp.tid()
    if t >= taken[0]:
        return
    s = count[0] + t
    q = pts[s] + _patch_offset(k)
    patches[s, k] = bilinear(img, 0, w, h, q[0], q[1])
    if k == 0:
        A[s] = wp.identity(n=2, dtype=float)
        steps[s] = wp.vec2(0.0, 0.0)


def _make_drift_check(per_lane: int):
    """The drift check for lanes that each take ``per_lane`` patch pixels per pass (unrolled, loads in
    flight together)."""

    @wp.kernel(module="unique", enable_backward=False)
    def drift_check(img: wp.array(dtype=float), gx: wp.array(dtype=float), gy: wp.array(dtype=float), w: int,
                    h: int, patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22),
                    pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
                    count: wp.array(dtype=wp.int32), iterations: int, max_residual: float,
                    max_stretch: float, max_correction: float, keep: wp.array(dtype=wp.int32),
                    residual_out: wp.array(dtype=float)):
        """Fit alpha I(x) + beta ~ J(A x + b) to each track's first patch I by Gauss-Newton (8 parameters), from the
        tracker's position b; the fitted b is the drift-free position and replaces b in ``pts``. Dropped: large
        normalised residual, too much stretch or a flip of A, a correction larger than max_correction, an absurd
        gain."""
        f, lane = wp.tid()
        if f >= count[0]:
            if lane == 0:
                keep[f] = 0  # slots past the live tracks are not kept (the compaction scans every slot)
            return
        nl = wp.block_dim()
        n = PATCH * PATCH
        b = pts[f]
        Am = A[f]
        b0 = b
        # gain and bias from the patch statistics
        st = wp.vec4(0.0, 0.0, 0.0, 0.0)
        base = lane
        while base < n:  # one pass on CUDA, where per_lane x lanes cover the patch; many with one CPU lane
            for jj in range(per_lane):
                k = base + jj * nl
                valid = wp.where(k < n, 1.0, 0.0)
                kc = wp.min(k, n - 1)
                ref = patches[f, kc]
                q = b + Am * _patch_offset(kc)
                j = bilinear(img, 0, w, h, q[0], q[1])
                st += valid * wp.vec4(ref, ref * ref, j, j * j)
            base += per_lane * nl
        S = _block_sum4(st, 0)
        fn = float(n)
        ref_mean = S[0] / fn
        ref_std = wp.sqrt(wp.max(S[1] / fn - ref_mean * ref_mean, 0.0)) + 1.0e-6
        cur_mean = S[2] / fn
        cur_std = wp.sqrt(wp.max(S[3] / fn - cur_mean * cur_mean, 0.0)) + 1.0e-6
        alpha = cur_std / ref_std
        beta = cur_mean - alpha * ref_mean
        for _it in range(iterations):
            acc = vec44()
            base = lane
            while base < n:
                for jj in range(per_lane):
                    k = base + jj * nl
                    valid = wp.where(k < n, 1.0, 0.0)
                    kc = wp.min(k, n - 1)
                    ref = patches[f, kc]
                    o = _patch_offset(kc)
                    q = b + Am * o
                    j = bilinear(img, 0, w, h, q[0], q[1])
                    u = bilinear(gx, 0, w, h, q[0], q[1]) * valid
                    v = bilinear(gy, 0, w, h, q[0], q[1]) * valid
                    r = (j - alpha * ref - beta) * valid
                    row = vec8(u * o[0], u * o[1], v * o[0], v * o[1], u, v, -ref * valid, -valid)
                    acc = _normal_equations(row, r, acc)
                base += per_lane * nl
            tot = _block_sum44(acc, _it + 1)
            H = mat88()
            gvec = vec8()
            for a in range(8):
                for c in range(8):
                    if c >= a:
                        i = a * 8 - (a * (a - 1)) // 2 + (c - a)
                        H[a, c] = tot[i]
                        H[c, a] = tot[i]
                H[a, a] = H[a, a] + 1.0e-6
                gvec[a] = -tot[36 + a]
            d = _chol_solve8(H, gvec)
            Am = Am + wp.mat22(d[0], d[1], d[2], d[3])
            b = b + wp.vec2(d[4], d[5])
            alpha = alpha + d[6]
            beta = beta + d[7]
            # converged when the position moves by less than 0.01 px, as in the OpenCV baseline's drift check;
            # every lane holds the same solution, so leaving is uniform across the block
            if wp.max(wp.abs(d[4]), wp.abs(d[5])) < 0.01:
                break
        # final normalised residual
        racc = float(0.0)
        base = lane
        while base < n:
            for jj in range(per_lane):
                k = base + jj * nl
                kc = wp.min(k, n - 1)
                ref = patches[f, kc]
                q = b + Am * _patch_offset(kc)
                r = bilinear(img, 0, w, h, q[0], q[1]) - alpha * ref - beta
                racc += wp.where(k < n, r * r, 0.0)
            base += per_lane * nl
        rss = _block_sum1(racc, 0)
        if lane == 0:
            res = wp.sqrt(rss / fn) / (wp.abs(alpha) * ref_std)
            # singular values of the 2x2 warp
            a11 = Am[0, 0]
            a12 = Am[0, 1]
            a21 = Am[1, 0]
            a22 = Am[1, 1]
            s1 = a11 * a11 + a12 * a12 + a21 * a21 + a22 * a22
            det = a11 * a22 - a12 * a21
            disc = wp.sqrt(wp.max(s1 * s1 - 4.0 * det * det, 0.0))
            smax = wp.sqrt(0.5 * (s1 + disc))
            smin = wp.sqrt(wp.max(0.5 * (s1 - disc), 0.0))
            moved = wp.length(b - b0)
            good = res <= max_residual and smax <= max_stretch and smin >= 1.0 / max_stretch and det > 0.0
            good = good and moved <= max_correction and alpha > 0.2 and alpha < 5.0 and not wp.isnan(res)
            good = good and status[f] == 1 and _in_view(mask, b)
            pts[f] = b
            A[f] = Am
            keep[f] = wp.where(good, 1, 0)
            residual_out[f] = res

    return drift_check


drift_check = _make_drift_check((PATCH * PATCH + DRIFT_LANES - 1) // DRIFT_LANES)


# --- bookkeeping -------------------------------------------------------------------------------------------
@wp.func
def _in_view(mask: wp.array2d(dtype=wp.uint8), p: wp.vec2) -> bool:
    if wp.isnan(p[0]) or wp.isnan(p[1]):
        return False
    x = int(wp.round(p[0]))
    y = int(wp.round(p[1]))
    if x < 0 or y < 0 or x >= mask.shape[1] or y >= mask.shape[0]:
        return False
    return mask[y, x] != wp.uint8(0)


@wp.kernel
def lk_keep(pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
            count: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    """Without the drift check: keep what LK tracked into the field of view."""
    f = wp.tid()
    if f >= count[0]:
        keep[f] = 0
        return
    keep[f] = wp.where(status[f] == 1 and _in_view(mask, pts[f]), 1, 0)


@wp.kernel
def scatter_tracks(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32),
                   src_pts: wp.array(dtype=wp.vec2), before: wp.array(dtype=wp.vec2), src_A: wp.array(dtype=wp.mat22),
                   src_patches: wp.array2d(dtype=float), src_ids: wp.array(dtype=wp.int32),
                   dst_pts: wp.array(dtype=wp.vec2), dst_steps: wp.array(dtype=wp.vec2),
                   dst_A: wp.array(dtype=wp.mat22), dst_patches: wp.array2d(dtype=float),
                   dst_ids: wp.array(dtype=wp.int32)):
    """Compaction on the device: a kept track moves to its slot (exclusive prefix sum of the keep flags), with
    its step in this frame (from ``before``, its position in the previous frame)."""
    t, k = wp.tid()
    if keep[t] == 0:
        return
    s = slot[t]
    dst_patches[s, k] = src_patches[t, k]
    if k == 0:
        dst_pts[s] = src_pts[t]
        dst_steps[s] = src_pts[t] - before[t]
        dst_A[s] = src_A[t]
        dst_ids[s] = src_ids[t]


@wp.kernel
def count_kept(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
               redetect_below: int, detect: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32)):
    """After the compaction: the live count, whether to look for new corners, and no new tracks yet."""
    last = keep.shape[0] - 1
    c = slot[last] + keep[last]
    count[0] = c
    detect[0] = wp.where(c < redetect_below, 1, 0)
    n_new[0] = 0


# --- corner selection on the device: strongest first, none closer than min_distance -----------------------
@wp.kernel
def cell_init(cell_key: wp.array(dtype=wp.uint64), eig: wp.array2d(dtype=float), cells: wp.array(dtype=wp.vec3),
              state: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    """Each cell's winner as (x, y, score), undecided (state 0); empty cells out (-1). Clears the keys for the
    next detection, and the score histogram (the launch covers at least its bins)."""
    c = wp.tid()
    if c < hist.shape[0]:
        hist[c] = 0
    if c >= cell_key.shape[0]:
        return
    key = cell_key[c]
    cell_key[c] = ZERO_KEY
    if key == ZERO_KEY:
        state[c] = -1
        return
    pixel = PIXEL_KEY_MAX - wp.int32(key & PIXEL_KEY_MASK)
    w = eig.shape[1]
    y = pixel // w
    x = pixel - y * w
    cells[c] = wp.vec3(float(x), float(y), eig[y, x])
    state[c] = 0


@wp.kernel
def selection_round(cells: wp.array(dtype=wp.vec3), grid_w: int, grid_h: int, min_distance: float,
                    state: wp.array(dtype=wp.int32)):
    """One round of greedy selection in parallel, one thread per cell, in place: an undecided corner (0) is
    rejected (-1) next to a selected one, and selected (1) when no stronger undecided corner is within
    min_distance. Both verdicts are final and rest only on final verdicts of others, so reading a neighbour
    before or after its update this round is equally right: the result is OpenCV's greedy (strongest first)
    one, whatever the order, and a verdict reaches its neighbours within the same round when it can.
    Corners within min_distance are at most 2 cells apart (cells have side min_distance / sqrt(2)); the
    neighbours are read unconditionally (clamped at the grid's edge), so their loads overlap."""
    c = wp.tid()
    if state[c] != 0:
        return
    me = cells[c]
    cy = c // grid_w
    cx = c - cy * grid_w
    d2 = min_distance * min_distance
    near_selected = int(0)
    near_stronger = int(0)
    for dy in range(-2, 3):
        yy = wp.clamp(cy + dy, 0, grid_h - 1)
        for dx in range(-2, 3):
            j = yy * grid_w + wp.clamp(cx + dx, 0, grid_w - 1)
            sj = state[j]
            other = cells[j]
            ex = other[0] - me[0]
            ey = other[1] - me[1]
            near = j != c and sj >= 0 and ex * ex + ey * ey < d2
            if near and sj == 1:
                near_selected = 1
            if near and sj == 0 and (other[2] > me[2] or (other[2] == me[2] and j < c)):
                near_stronger = 1
    if near_selected == 1:
        state[c] = -1
    elif near_stronger == 0:
        state[c] = 1


@wp.func
def _score_bin(score: float, max_score: float) -> int:
    """Histogram bin of a corner score: SCORE_BINS_PER_OCTAVE bins per halving below the frame's best."""
    octaves = wp.log2(max_score / wp.max(score, 1.0e-30))
    return wp.clamp(int(octaves * float(SCORE_BINS_PER_OCTAVE)), 0, SCORE_BINS - 1)


@wp.func
def _free_now(me: wp.vec3, occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32)) -> bool:
    """Whether a selected corner is away from every track where the tracks are now. The selection kept its
    distance from where they were predicted to be (it runs beside tracking on CUDA); a corner that a track has
    come near all the same is not taken (the second occupancy stamp, around the tracks that survived the
    frame)."""
    return occ[int(me[1]), int(me[0])] != stamp[0] + 1


@wp.kernel
def score_histogram(cells: wp.array(dtype=wp.vec3), state: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float),
                    occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    """How many selected corners, still free of tracks, fall in each score bin (bin 0 = strongest)."""
    c = wp.tid()
    if state[c] == 1 and _free_now(cells[c], occ, stamp):
        wp.atomic_add(hist, _score_bin(cells[c][2], max_eig[0]), 1)


@wp.kernel
def score_threshold(hist: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), max_features: int,
                    cut: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32)):
    """One thread per bin: the strongest selected corners that fill the free slots. Every corner in a bin above
    the cut bin is offered; from the cut bin only as many as fit (cut[1]). Each bin sums the bins before it
    (independent loads; a single thread walking the bins waited on one per bin)."""
    b = wp.tid()
    if b < 2:
        taken[b] = 0  # take_corners' counters
    want = max_features - count[0]
    start = int(0)
    for i in range(b):
        start += hist[i]
    if start <= want and start + hist[b] > want:  # the cumulative count passes the free slots in this bin
        cut[0] = b
        cut[1] = want - start
    if b == SCORE_BINS - 1:
        if start + hist[b] <= want:  # every selected corner fits
            cut[0] = SCORE_BINS
            cut[1] = 0


@wp.kernel
def take_corners(cells: wp.array(dtype=wp.vec3), state: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float),
                 cut: wp.array(dtype=wp.int32), occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32),
                 count: wp.array(dtype=wp.int32), next_id: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32),
                 pts: wp.array(dtype=wp.vec2), ids: wp.array(dtype=wp.int32)):
    """The chosen corners (selected, free of tracks now, strong enough) become tracks after the live ones (slots
    count .. count + taken[0] - 1)."""
    c = wp.tid()
    if state[c] != 1:
        return
    me = cells[c]
    b = _score_bin(me[2], max_eig[0])
    if b > cut[0] or not _free_now(me, occ, stamp):
        return
    if b == cut[0]:
        if wp.atomic_add(taken, 1, 1) >= cut[1]:
            return
    k = wp.atomic_add(taken, 0, 1)
    pts[count[0] + k] = wp.vec2(me[0], me[1])
    ids[count[0] + k] = next_id[0] + k


@wp.kernel
def pack_results(pts: wp.array(dtype=wp.vec2), ids: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                 n_new: wp.array(dtype=wp.int32), remap: wp.array2d(dtype=wp.vec2), out_f: wp.array(dtype=wp.vec4),
                 out_i: wp.array(dtype=wp.int32)):
    """The frame's results in two buffers, so two copies bring them to the host: per track (x, y, source x,
    source y) and [count, n_new, ids...]. The source is where the track lies in the distorted frame (the
    undistortion map, sampled bilinearly at its position): the host reads the track's colour there."""
    t = wp.tid()
    if t == 0:
        out_i[0] = count[0]
        out_i[1] = n_new[0]
    if t >= count[0]:
        return
    h = remap.shape[0]
    w = remap.shape[1]
    p = pts[t]
    x = wp.clamp(p[0], 0.0, float(w - 1))
    y = wp.clamp(p[1], 0.0, float(h - 1))
    x0 = wp.min(int(x), w - 2)
    y0 = wp.min(int(y), h - 2)
    fx = x - float(x0)
    fy = y - float(y0)
    top = remap[y0, x0] * (1.0 - fx) + remap[y0, x0 + 1] * fx
    bot = remap[y0 + 1, x0] * (1.0 - fx) + remap[y0 + 1, x0 + 1] * fx
    src = top * (1.0 - fy) + bot * fy
    out_f[t] = wp.vec4(p[0], p[1], src[0], src[1])
    out_i[2 + t] = ids[t]


@wp.kernel
def commit_new_tracks(taken: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                      n_new: wp.array(dtype=wp.int32), next_id: wp.array(dtype=wp.int32)):
    n = taken[0]
    count[0] = count[0] + n
    next_id[0] = next_id[0] + n
    n_new[0] = n
