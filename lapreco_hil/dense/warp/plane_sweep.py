"""Kernels of the plane-sweep stereo (private; the host side is lapreco_hil.dense.depth).

Images are grey in [-0.5, 0.5] (centred, so the windowed sums keep their float32 precision); a pixel that may not
be used (outside the field of view, on a dilated highlight) holds ``EXCLUDED``. Every view's grey lives in a slot
of the estimator's per-keyframe cache; ``slots[s]`` names source s's. A sweep samples every source view on a set
of fronto-parallel planes in inverse depth rho, ``rho = base[y, x] + rho0 + plane * drho`` (base is 0 for the
coarse sweep, the coarse estimate for the fine one), and scores each plane by ZNCC over a square window: one
thread per (source, pixel) samples the source on every plane (source pixel = A @ (x, y, 1) + rho * b, with
A = K_s R_s_r K_r^-1 and b = K_s t_s_r: the plane homography written for inverse depth). The window sums then
come one of two ways, with the same sums up to float rounding:

- sliding (``sweep_rows`` then ``sweep_cols``): one thread per (source, plane, row) adding the entering column and
  dropping the leaving one, then per (source, plane, column) down the column: O(1) per pixel whatever the window,
  the cheapest on a CPU, whose threads run long serial loops well;
- windowed (``sweep_window``, ``sweep_window_ring`` for a 7x7 window): one thread per (source, plane, band of
  rows, column) sums each window row from its taps and slides the rows down its band (the ring kernel keeps
  the window's rows in registers). Neighbouring threads are neighbouring columns (coalesced on a GPU), nothing
  but the samples goes through memory (the sliding way writes 24 bytes of row sums per source, plane and
  pixel), and there are millions of short threads instead of a few hundred thousand long ones.
"""

from __future__ import annotations

import warp as wp

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

vec6 = wp.types.vector(length=6, dtype=wp.float32)  # window sums: w, w^2, w*g, g, g^2, usable count

EXCLUDED = -10.0  # a grey value that may not be used (any value below -1 reads as excluded)
NO_SCORE = -2.0  # a ZNCC that is undefined (window out of view, excluded or textureless)

# funnel codes per reference pixel: the first check it failed, or KEPT
CODE_OUT_OF_VIEW = 0
CODE_HIGHLIGHT = 1
CODE_LOW_TEXTURE = 2
CODE_NO_MATCH = 3
CODE_OUT_OF_RANGE = 4
CODE_DEPTH_EDGE = 5
CODE_NOT_REFINED = 6
CODE_VIEWS_DISAGREE = 7
CODE_UNSUPPORTED = 8
CODE_GEOMETRY_DISAGREES = 9
CODE_KEPT = 10

# why a view's pixel may not be used (kept per cached view: the funnel's first two checks of a reference)
STATE_USABLE = 0
STATE_OUT_OF_VIEW = 1
STATE_HIGHLIGHT = 2


@wp.kernel
def prepare_view(colour: wp.array3d(dtype=wp.uint8), mask: wp.array2d(dtype=wp.uint8), min_value: float,
                 max_saturation: float, grey: wp.array2d(dtype=float), highlight: wp.array2d(dtype=wp.uint8)):
    """RGB -> centred grey (EXCLUDED outside the mask); a saturated specular highlight: bright and nearly white."""
    y, x = wp.tid()
    r = float(colour[y, x, 0])
    g = float(colour[y, x, 1])
    b = float(colour[y, x, 2])
    hi = wp.max(r, wp.max(g, b))
    lo = wp.min(r, wp.min(g, b))
    flag = wp.uint8(0)
    if hi >= min_value * 255.0 and (hi - lo) <= max_saturation * hi:
        flag = wp.uint8(1)
    highlight[y, x] = flag
    if mask[y, x] == wp.uint8(0):
        grey[y, x] = EXCLUDED
    else:
        grey[y, x] = (0.299 * r + 0.587 * g + 0.114 * b) / 255.0 - 0.5


@wp.kernel
def dilate_scatter(flags: wp.array2d(dtype=wp.uint8), r: int, dilated: wp.array2d(dtype=wp.uint8)):
    """Dilation by a (2r+1)^2 square, written outwards from each flagged pixel into a zeroed ``dilated``
    (highlights are a few per cent of a frame: this costs a test per pixel, not a window). Threads that write the
    same pixel write the same value."""
    y, x = wp.tid()
    if flags[y, x] == wp.uint8(0):
        return
    h = flags.shape[0]
    w = flags.shape[1]
    for yy in range(wp.max(y - r, 0), wp.min(y + r + 1, h)):
        for xx in range(wp.max(x - r, 0), wp.min(x + r + 1, w)):
            dilated[yy, xx] = wp.uint8(1)


@wp.kernel
def exclude(mask: wp.array2d(dtype=wp.uint8), dilated: wp.array2d(dtype=wp.uint8), grey: wp.array2d(dtype=float),
            state: wp.array2d(dtype=wp.uint8)):
    """Excludes the dilated highlights; ``state`` keeps why a pixel may not be used (the funnel's first checks)."""
    y, x = wp.tid()
    if mask[y, x] == wp.uint8(0):
        state[y, x] = wp.uint8(STATE_OUT_OF_VIEW)
    elif dilated[y, x] != wp.uint8(0):
        grey[y, x] = EXCLUDED
        state[y, x] = wp.uint8(STATE_HIGHLIGHT)
    else:
        state[y, x] = wp.uint8(STATE_USABLE)


@wp.kernel
def half_mean(src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)):
    """2x2 mean to half resolution; excluded if any of the four is."""
    y, x = wp.tid()
    a = src[2 * y, 2 * x]
    b = src[2 * y, 2 * x + 1]
    c = src[2 * y + 1, 2 * x]
    d = src[2 * y + 1, 2 * x + 1]
    if wp.min(wp.min(a, b), wp.min(c, d)) < -1.0:
        dst[y, x] = EXCLUDED
    else:
        dst[y, x] = 0.25 * (a + b + c + d)


@wp.kernel
def window_rows(grey: wp.array2d(dtype=float), r: int, out: wp.array2d(dtype=wp.vec3)):
    """Row pass of the reference's window statistics: (sum, sum of squares, excluded or outside count)."""
    y, x = wp.tid()
    w = grey.shape[1]
    s = wp.vec3(0.0, 0.0, 0.0)
    for k in range(-r, r + 1):
        xx = x + k
        if xx < 0 or xx >= w:
            s += wp.vec3(0.0, 0.0, 1.0)
        else:
            g = grey[y, xx]
            if g < -1.0:
                s += wp.vec3(0.0, 0.0, 1.0)
            else:
                s += wp.vec3(g, g * g, 0.0)
    out[y, x] = s


@wp.kernel
def window_cols(rows: wp.array2d(dtype=wp.vec3), r: int, min_std: float, min_valid: float,
                std: wp.array2d(dtype=float)):
    """Column pass: the standard deviation of the window's usable pixels; 0 where fewer than ``min_valid`` (a
    fraction) of them are usable or the texture is below ``min_std`` (ZNCC is undefined there)."""
    y, x = wp.tid()
    h = rows.shape[0]
    s = wp.vec3(0.0, 0.0, 0.0)
    for k in range(-r, r + 1):
        yy = y + k
        if yy < 0 or yy >= h:
            s += wp.vec3(0.0, 0.0, 1.0)
        else:
            s += rows[yy, x]
    total = float((2 * r + 1) * (2 * r + 1))
    n = wp.max(total - s[2], 1.0)
    m = s[0] / n
    v = s[1] / n - m * m
    if n < min_valid * total or v <= min_std * min_std:
        std[y, x] = 0.0
    else:
        std[y, x] = wp.sqrt(v)


@wp.func
def _bilinear(src: wp.array3d(dtype=float), i: int, q: wp.vec3) -> float:
    """Source ``i``'s grey (bilinear) at the homogeneous pixel q; EXCLUDED behind the camera, outside the image or
    next to an excluded pixel."""
    if q[2] <= 1.0e-9:
        return EXCLUDED
    u = q[0] / q[2]
    v = q[1] / q[2]
    hs = src.shape[1]
    ws = src.shape[2]
    if u < 0.0 or v < 0.0 or u > float(ws - 1) or v > float(hs - 1):
        return EXCLUDED
    x0 = wp.min(int(u), ws - 2)
    y0 = wp.min(int(v), hs - 2)
    fx = u - float(x0)
    fy = v - float(y0)
    a00 = src[i, y0, x0]
    a01 = src[i, y0, x0 + 1]
    a10 = src[i, y0 + 1, x0]
    a11 = src[i, y0 + 1, x0 + 1]
    if wp.min(wp.min(a00, a01), wp.min(a10, a11)) < -1.0:
        return EXCLUDED
    return (a00 * (1.0 - fx) + a01 * fx) * (1.0 - fy) + (a10 * (1.0 - fx) + a11 * fx) * fy


@wp.kernel
def warp_samples(ref: wp.array2d(dtype=float), src: wp.array3d(dtype=float), slots: wp.array(dtype=int),
                 A: wp.array(dtype=wp.mat33), b: wp.array(dtype=wp.vec3), base: wp.array2d(dtype=float), rho0: float,
                 drho: float, n_planes: int, samples: wp.array4d(dtype=float)):
    """One thread per (source, pixel), looping over the planes: the source's grey (bilinear; source s is
    ``src[slots[s]]``) where the reference pixel's ray meets each plane; EXCLUDED where either view may not be used
    there or the point falls outside the source. The plane-independent part of the homography is computed once
    per pixel, and neighbouring threads write neighbouring pixels of each plane (one coalesced store per
    sample)."""
    s, y, x = wp.tid()
    i = slots[s]
    usable = ref[y, x] >= -1.0
    q0 = A[s] * wp.vec3(float(x), float(y), 1.0)
    bs = b[s]
    rho_base = base[y, x] + rho0
    for p in range(n_planes):
        val = EXCLUDED
        if usable:
            rho = rho_base + float(p) * drho
            val = _bilinear(src, i, q0 + rho * bs)
        samples[s, p, y, x] = val


@wp.func
def _terms(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), s: int, p: int, y: int, x: int) -> vec6:
    """(w, w^2, w g, g, g^2, 1) of the source sample w and the reference grey g at pixel (x, y); zero where the
    pair may not be used (a window scores on its usable pixels only)."""
    if x < 0 or x >= ref.shape[1]:
        return vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    val = samples[s, p, y, x]
    if val < -1.0:
        return vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    g = ref[y, x]
    return vec6(val, val * val, val * g, g, g * g, 1.0)


@wp.kernel
def sweep_rows(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), r: int,
               sums: wp.array4d(dtype=vec6)):
    """One thread per (source, plane, row): the window-row sums of every pixel, sliding along the row."""
    s, p, y = wp.tid()
    w = ref.shape[1]
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for xi in range(-r, r):
        acc += _terms(ref, samples, s, p, y, xi)
    for x in range(w):
        acc += _terms(ref, samples, s, p, y, x + r)
        sums[s, p, y, x] = acc
        acc -= _terms(ref, samples, s, p, y, x - r)


@wp.func
def _row_sum(sums: wp.array4d(dtype=vec6), s: int, p: int, y: int, x: int) -> vec6:
    if y < 0 or y >= sums.shape[2]:
        return vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return sums[s, p, y, x]


@wp.func
def _zncc(acc: vec6, std_ref: float, total: float, min_std: float, min_valid: float) -> float:
    """ZNCC of a window's sums on its usable pixels (at least ``min_valid`` of the window; the reference window
    must be textured); NO_SCORE where undefined."""
    score = NO_SCORE
    n = acc[5]
    if n >= min_valid * total and std_ref > 0.0:
        mw = acc[0] / n
        vw = acc[1] / n - mw * mw
        mg = acc[3] / n
        vg = acc[4] / n - mg * mg
        lim = min_std * min_std
        if vw > lim and vg > lim:
            score = (acc[2] / n - mw * mg) / wp.sqrt(vw * vg)
    return score


@wp.kernel
def sweep_cols(sums: wp.array4d(dtype=vec6), ref_std: wp.array2d(dtype=float), r: int, min_std: float,
               min_valid: float, zncc: wp.array4d(dtype=float)):
    """One thread per (source, plane, column): slide the row sums down the column and score each window on the
    pixels usable in both views (at least ``min_valid`` of it; the reference window must be textured)."""
    s, p, x = wp.tid()
    h = ref_std.shape[0]
    total = float((2 * r + 1) * (2 * r + 1))
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for yi in range(-r, r):
        acc += _row_sum(sums, s, p, yi, x)
    for y in range(h):
        acc += _row_sum(sums, s, p, y + r, x)
        zncc[s, p, y, x] = _zncc(acc, ref_std[y, x], total, min_std, min_valid)
        acc -= _row_sum(sums, s, p, y - r, x)


@wp.func
def _tap(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), s: int, p: int, y: int, x: int,
         inside: float) -> vec6:
    """One tap's (w, w^2, w g, g, g^2, 1) of source sample w and reference grey g, weighing 0 where the sample
    may not be used (EXCLUDED) or ``inside`` is 0 (a clamped column outside the image)."""
    val = samples[s, p, y, x]
    m = wp.where(val >= -1.0, inside, 0.0)
    wv = val * m
    gv = ref[y, x] * m
    return vec6(wv, wv * wv, wv * gv, gv, gv * gv, m)


@wp.func
def _window_row(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), s: int, p: int, y: int, x: int,
                r: int) -> vec6:
    """The sums (w, w^2, w g, g, g^2, usable count) over the window row of pixel (x, y), from its 2r + 1 taps
    (clipped to the image: outside counts as unusable); zero for a row outside the image. Branch-free per tap:
    an unusable sample (EXCLUDED, also where the reference is) weighs 0."""
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if y < 0 or y >= ref.shape[0]:
        return acc
    for xx in range(wp.max(x - r, 0), wp.min(x + r + 1, ref.shape[1])):
        acc += _tap(ref, samples, s, p, y, xx, 1.0)
    return acc


@wp.kernel
def sweep_window(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), ref_std: wp.array2d(dtype=float),
                 r: int, band: int, min_std: float, min_valid: float, zncc: wp.array4d(dtype=float)):
    """One thread per (source, plane, band of ``band`` rows, column): each window row summed from its taps, the
    rows slid down the band (the leaving row summed again rather than kept: registers, not memory), scored as
    ``sweep_cols`` does. Neighbouring threads are neighbouring columns: every load and store of a warp is one
    contiguous run. ``samples`` and ``zncc`` must be different arrays (other threads still read the samples a
    thread's scores would overwrite)."""
    s, p, c, x = wp.tid()
    h = ref.shape[0]
    y0 = c * band
    y1 = wp.min(y0 + band, h)
    total = float((2 * r + 1) * (2 * r + 1))
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for yi in range(y0 - r, y0 + r):
        acc += _window_row(ref, samples, s, p, yi, x, r)
    for y in range(y0, y1):
        acc += _window_row(ref, samples, s, p, y + r, x, r)
        zncc[s, p, y, x] = _zncc(acc, ref_std[y, x], total, min_std, min_valid)
        acc -= _window_row(ref, samples, s, p, y - r, x, r)


RING_RADIUS = 3  # the window radius (7x7, the default) that sweep_window_ring keeps its window rows for


@wp.func
def _window_row_ring(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), s: int, p: int, y: int,
                     x: int) -> vec6:
    """``_window_row`` for the radius RING_RADIUS as a loop of constant length (unrolled: the row's loads are
    issued together, no loop control); a column outside the image is read at the nearest side and weighs 0
    (adding zeros leaves the sums as they were: the same sums in the same order)."""
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if y < 0 or y >= ref.shape[0]:
        return acc
    w = ref.shape[1]
    for dx in range(wp.static(-RING_RADIUS), wp.static(RING_RADIUS + 1)):
        xx = wp.clamp(x + dx, 0, w - 1)
        acc += _tap(ref, samples, s, p, y, xx, wp.where(xx == x + dx, 1.0, 0.0))
    return acc


@wp.func
def _ring_step(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float), ref_std: wp.array2d(dtype=float),
               s: int, p: int, y: int, y1: int, x: int, total: float, min_std: float, min_valid: float, acc: vec6,
               leaving: vec6, zncc: wp.array4d(dtype=float)):
    """One row of sweep_window_ring: the entering window row (y + RING_RADIUS) summed and added, row y scored
    (rows from y1 on belong to the next band or lie outside the image), the leaving row (kept from when it
    entered) taken off. Returns the sums and the entering row."""
    entering = _window_row_ring(ref, samples, s, p, y + RING_RADIUS, x)
    acc = acc + entering
    if y < y1:
        zncc[s, p, y, x] = _zncc(acc, ref_std[y, x], total, min_std, min_valid)
    return acc - leaving, entering


@wp.kernel(launch_bounds=(256, 2))
def sweep_window_ring(ref: wp.array2d(dtype=float), samples: wp.array4d(dtype=float),
                      ref_std: wp.array2d(dtype=float), band: int, min_std: float, min_valid: float,
                      zncc: wp.array4d(dtype=float)):
    """sweep_window for the radius RING_RADIUS (3: a 7x7 window): the window's 7 row sums stay in registers (a
    ring, unrolled over 7 rows), so each window row is summed from its taps once instead of twice. ``band``
    should be a multiple of 7 (the rows past a band's end up to the next multiple are summed for nothing)."""
    s, p, c, x = wp.tid()
    h = ref.shape[0]
    r = RING_RADIUS
    y0 = c * band
    y1 = wp.min(y0 + band, h)
    total = float((2 * r + 1) * (2 * r + 1))
    # rows y0 - 3 .. y0 + 2 in slots 0 .. 5; row y enters slot (y - y0 + 6) % 7 and leaves slot (y - y0) % 7
    h0 = _window_row_ring(ref, samples, s, p, y0 - 3, x)
    h1 = _window_row_ring(ref, samples, s, p, y0 - 2, x)
    h2 = _window_row_ring(ref, samples, s, p, y0 - 1, x)
    h3 = _window_row_ring(ref, samples, s, p, y0, x)
    h4 = _window_row_ring(ref, samples, s, p, y0 + 1, x)
    h5 = _window_row_ring(ref, samples, s, p, y0 + 2, x)
    h6 = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    acc = h0 + h1 + h2 + h3 + h4 + h5
    for y in range(y0, y1, 7):
        acc, h6 = _ring_step(ref, samples, ref_std, s, p, y, y1, x, total, min_std, min_valid, acc, h0, zncc)
        acc, h0 = _ring_step(ref, samples, ref_std, s, p, y + 1, y1, x, total, min_std, min_valid, acc, h1, zncc)
        acc, h1 = _ring_step(ref, samples, ref_std, s, p, y + 2, y1, x, total, min_std, min_valid, acc, h2, zncc)
        acc, h2 = _ring_step(ref, samples, ref_std, s, p, y + 3, y1, x, total, min_std, min_valid, acc, h3, zncc)
        acc, h3 = _ring_step(ref, samples, ref_std, s, p, y + 4, y1, x, total, min_std, min_valid, acc, h4, zncc)
        acc, h4 = _ring_step(ref, samples, ref_std, s, p, y + 5, y1, x, total, min_std, min_valid, acc, h5, zncc)
        acc, h5 = _ring_step(ref, samples, ref_std, s, p, y + 6, y1, x, total, min_std, min_valid, acc, h6, zncc)


@wp.func
def _best_k_mean(zncc: wp.array4d(dtype=float), n_src: int, k: int, p: int, y: int, x: int) -> float:
    """Mean of the k best scores of the sources at one plane (an occluded view does not spoil it); NO_SCORE
    when fewer than k sources have one."""
    taken = int(0)
    total = float(0.0)
    for i in range(k):
        best = float(NO_SCORE)
        arg = int(-1)
        for s in range(n_src):
            if (taken >> s) & 1 == 0:
                z = zncc[s, p, y, x]
                if z > best:
                    best = z
                    arg = s
        if arg < 0 or best <= NO_SCORE + 0.5:
            return NO_SCORE
        taken = taken | (1 << arg)
        total += best
    return total / float(k)


@wp.func
def _plane_score(zncc: wp.array4d(dtype=float), n_src: int, k: int, p: int, y: int, x: int) -> float:
    """``_best_k_mean`` reading each source's score once: the best two in one pass (k of 1 or 2, the default; the
    same sums in the same order), the general selection for a larger k."""
    if k > 2:
        return _best_k_mean(zncc, n_src, k, p, y, x)
    b1 = float(NO_SCORE)
    b2 = float(NO_SCORE)
    for s in range(n_src):
        z = zncc[s, p, y, x]
        if z > b1:
            b2 = b1
            b1 = z
        elif z > b2:
            b2 = z
    if b1 <= NO_SCORE + 0.5:
        return NO_SCORE
    if k == 1:
        return b1
    if b2 <= NO_SCORE + 0.5:
        return NO_SCORE
    return (b1 + b2) / 2.0


@wp.func
def _apart(i: int, b: int) -> bool:
    """Plane i is a local maximum (i >= 0) other than the best plane b and its neighbours."""
    return i >= 0 and (i < b - 1 or i > b + 1)


@wp.kernel
def select_plane(zncc: wp.array4d(dtype=float), n_src: int, n_planes: int, k: int, min_scored: int,
                 plane: wp.array2d(dtype=float), best: wp.array2d(dtype=float), second: wp.array2d(dtype=float)):
    """Per pixel: the plane of the best combined score, refined by a parabola through its neighbours, the best
    score, and the second-best local maximum (the margin measures uniqueness). -1 where fewer than
    ``min_scored`` planes have a score: near the edge of the sources' views only a few planes land inside them,
    and the best of a few is no match. One pass over the planes, nothing written but the results: each plane's
    score is known once the next is (a local maximum), and the four highest local maxima are kept, enough to
    find the highest apart from the best plane and its two neighbours."""
    y, x = wp.tid()
    b_val = float(NO_SCORE)
    b_idx = int(-1)
    b_lo = float(NO_SCORE)
    b_hi = float(NO_SCORE)
    scored = int(0)
    before = float(NO_SCORE)  # the score of plane p - 2
    last = float(NO_SCORE)  # of plane p - 1
    m0 = float(NO_SCORE)  # the highest local maxima, highest first, and their planes
    m1 = float(NO_SCORE)
    m2 = float(NO_SCORE)
    m3 = float(NO_SCORE)
    i0 = int(-1)
    i1 = int(-1)
    i2 = int(-1)
    i3 = int(-1)
    for p in range(n_planes + 1):
        c = float(NO_SCORE)
        if p < n_planes:
            c = _plane_score(zncc, n_src, k, p, y, x)
            if c > NO_SCORE + 0.5:
                scored += 1
            if c > b_val:
                b_val = c
                b_idx = p
                b_lo = last
            elif p == b_idx + 1:
                b_hi = c
        # plane p - 1 is a local maximum if it is at least both neighbours (NO_SCORE beyond the ends)
        if p >= 1 and last > NO_SCORE and last >= before and last >= c and last > m3:
            q = p - 1
            if last > m2:
                m3 = m2
                i3 = i2
                if last > m1:
                    m2 = m1
                    i2 = i1
                    if last > m0:
                        m1 = m0
                        i1 = i0
                        m0 = last
                        i0 = q
                    else:
                        m1 = last
                        i1 = q
                else:
                    m2 = last
                    i2 = q
            else:
                m3 = last
                i3 = q
        before = last
        last = c
    if scored < min_scored:
        b_idx = -1
    sec = float(NO_SCORE)
    if _apart(i0, b_idx):
        sec = m0
    elif _apart(i1, b_idx):
        sec = m1
    elif _apart(i2, b_idx):
        sec = m2
    elif _apart(i3, b_idx):
        sec = m3
    best[y, x] = b_val
    second[y, x] = sec
    if b_idx < 0:
        plane[y, x] = -1.0
        return
    f = float(b_idx)
    if b_idx > 0 and b_idx < n_planes - 1:
        lo = b_lo
        hi = b_hi
        if lo > NO_SCORE + 0.5 and hi > NO_SCORE + 0.5:
            den = lo - 2.0 * b_val + hi
            if den < -1.0e-6:
                f += wp.clamp(0.5 * (lo - hi) / den, -0.5, 0.5)
    plane[y, x] = f


@wp.kernel
def upsample_rho(plane: wp.array2d(dtype=float), rho0: float, drho: float, rho_fill: float,
                 base: wp.array2d(dtype=float)):
    """The coarse inverse depth, bilinear at full resolution: the fine sweep's base (a pixel with no coarse plane
    takes ``rho_fill``, the middle of the range; it is dropped anyway by the coarse checks)."""
    y, x = wp.tid()
    hc = plane.shape[0]
    wc = plane.shape[1]
    xc = wp.clamp((float(x) + 0.5) * 0.5 - 0.5, 0.0, float(wc - 1))
    yc = wp.clamp((float(y) + 0.5) * 0.5 - 0.5, 0.0, float(hc - 1))
    x0 = wp.min(int(xc), wc - 1)
    y0 = wp.min(int(yc), hc - 1)
    x1 = wp.min(x0 + 1, wc - 1)
    y1 = wp.min(y0 + 1, hc - 1)
    fx = xc - float(x0)
    fy = yc - float(y0)
    total = float(0.0)
    weight = float(0.0)
    for j in range(4):
        xx = x0
        yy = y0
        wgt = (1.0 - fx) * (1.0 - fy)
        if j == 1:
            xx = x1
            wgt = fx * (1.0 - fy)
        elif j == 2:
            yy = y1
            wgt = (1.0 - fx) * fy
        elif j == 3:
            xx = x1
            yy = y1
            wgt = fx * fy
        pl = plane[yy, xx]
        if pl >= 0.0:
            total += wgt * (rho0 + pl * drho)
            weight += wgt
    if weight > 1.0e-6:
        base[y, x] = total / weight
    else:
        base[y, x] = rho_fill


@wp.kernel
def finalise(state: wp.array2d(dtype=wp.uint8), grey: wp.array2d(dtype=float), fine_std: wp.array2d(dtype=float),
             coarse_plane: wp.array2d(dtype=float), coarse_best: wp.array2d(dtype=float),
             coarse_second: wp.array2d(dtype=float), n_coarse: int, edge_radius: int, max_jump: float,
             edge_zncc: float,
             base: wp.array2d(dtype=float), fine_zncc: wp.array4d(dtype=float), n_src: int,
             fine_plane: wp.array2d(dtype=float), fine_best: wp.array2d(dtype=float), n_fine: int,
             rho0: float, drho: float, min_zncc: float, min_margin: float, margin_scale: float,
             view_min_zncc: float, min_views: int,
             depth: wp.array2d(dtype=float), confidence: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8)):
    """Depth, confidence and the funnel code of each full-resolution pixel: the first check it failed."""
    y, x = wp.tid()
    depth[y, x] = 0.0
    confidence[y, x] = 0.0
    hc = coarse_plane.shape[0]
    wc = coarse_plane.shape[1]
    yc = wp.min(y / 2, hc - 1)
    xc = wp.min(x / 2, wc - 1)
    if state[y, x] == wp.uint8(STATE_OUT_OF_VIEW):
        code[y, x] = wp.uint8(CODE_OUT_OF_VIEW)
        return
    if state[y, x] == wp.uint8(STATE_HIGHLIGHT) or grey[y, x] < -1.0:
        code[y, x] = wp.uint8(CODE_HIGHLIGHT)
        return
    if fine_std[y, x] <= 0.0:
        code[y, x] = wp.uint8(CODE_LOW_TEXTURE)
        return
    cp = coarse_plane[yc, xc]
    cb = coarse_best[yc, xc]
    margin = cb - coarse_second[yc, xc]
    if cp < 0.0 or cb < min_zncc or margin < min_margin:
        code[y, x] = wp.uint8(CODE_NO_MATCH)
        return
    if cp < 0.5 or cp > float(n_coarse) - 1.5:
        code[y, x] = wp.uint8(CODE_OUT_OF_RANGE)
        return
    # a window across a depth edge matches the nearer surface on both sides (it fattens foreground): drop the
    # pixels where the coarse planes a window away on opposite sides bend by more than max_jump planes (a slanted
    # surface is a straight line in inverse depth, and passes)
    for j in range(8):
        step = edge_radius
        if j >= 4:
            step = (edge_radius + 1) / 2
        m = j % 4
        dx = step
        dy = int(0)
        if m == 1:
            dx = 0
            dy = step
        elif m == 2:
            dy = step
        elif m == 3:
            dy = -step
        ya = wp.clamp(yc + dy, 0, hc - 1)
        xa = wp.clamp(xc + dx, 0, wc - 1)
        yb = wp.clamp(yc - dy, 0, hc - 1)
        xb = wp.clamp(xc - dx, 0, wc - 1)
        na = coarse_plane[ya, xa]
        nb = coarse_plane[yb, xb]
        if na >= 0.0 and nb >= 0.0 and coarse_best[ya, xa] >= edge_zncc and coarse_best[yb, xb] >= edge_zncc:
            if wp.abs(na + nb - 2.0 * cp) > max_jump:
                code[y, x] = wp.uint8(CODE_DEPTH_EDGE)
                return
    fp = fine_plane[y, x]
    fb = fine_best[y, x]
    if fp < 0.0 or fb < min_zncc:
        code[y, x] = wp.uint8(CODE_NO_MATCH)
        return
    if fp < 0.5 or fp > float(n_fine) - 1.5:
        code[y, x] = wp.uint8(CODE_NOT_REFINED)
        return
    pi = int(wp.round(fp))
    agree = int(0)
    for s in range(n_src):
        if fine_zncc[s, pi, y, x] >= view_min_zncc:
            agree += 1
    if agree < wp.min(min_views, n_src):
        code[y, x] = wp.uint8(CODE_VIEWS_DISAGREE)
        return
    rho = base[y, x] + rho0 + fp * drho
    if rho <= 0.0:
        code[y, x] = wp.uint8(CODE_OUT_OF_RANGE)
        return
    depth[y, x] = 1.0 / rho
    c_match = wp.clamp((fb - min_zncc) / (1.0 - min_zncc), 0.0, 1.0)
    c_unique = wp.clamp(margin / margin_scale, 0.0, 1.0)
    confidence[y, x] = c_match * c_unique
    code[y, x] = wp.uint8(CODE_KEPT)


@wp.kernel
def support(depth: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8), r: int, max_rel: float,
            min_fraction: float, supported: wp.array2d(dtype=wp.uint8)):
    """A depth is supported where at least ``min_fraction`` of its (2r+1)^2 neighbours have a depth within
    ``max_rel`` of it: wrong matches come as specks and thin slivers (along silhouettes and folds), surfaces as
    regions."""
    y, x = wp.tid()
    supported[y, x] = wp.uint8(0)
    d = depth[y, x]
    if d <= 0.0:
        return
    h = depth.shape[0]
    w = depth.shape[1]
    n = int(0)
    for dy in range(-r, r + 1):
        yy = y + dy
        if yy >= 0 and yy < h:
            for dx in range(-r, r + 1):
                xx = x + dx
                if xx >= 0 and xx < w:
                    dn = depth[yy, xx]
                    if dn > 0.0 and wp.abs(dn - d) <= max_rel * d:
                        n += 1
    if float(n) >= min_fraction * float((2 * r + 1) * (2 * r + 1)):
        supported[y, x] = wp.uint8(1)


@wp.kernel
def apply_support(supported: wp.array2d(dtype=wp.uint8), depth: wp.array2d(dtype=float),
                  confidence: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8)):
    y, x = wp.tid()
    if depth[y, x] > 0.0 and supported[y, x] == wp.uint8(0):
        depth[y, x] = 0.0
        confidence[y, x] = 0.0
        code[y, x] = wp.uint8(CODE_UNSUPPORTED)


@wp.kernel
def geometric_agreement(depth: wp.array2d(dtype=float), K_ref_inv: wp.mat33, K_ref: wp.mat33,
                        R_src_ref: wp.mat33, t_src_ref: wp.vec3, K_src: wp.mat33, K_src_inv: wp.mat33,
                        src_depth: wp.array2d(dtype=float), max_px: float, max_rel: float,
                        agree: wp.array2d(dtype=int)):
    """Forward-backward through one source's own depth map: the reference point, seen in the source, read back
    with the source's depth there and re-projected into the reference, must land within ``max_px`` at a depth
    within ``max_rel``. Counts the sources that agree."""
    y, x = wp.tid()
    d = depth[y, x]
    if d <= 0.0:
        return
    X = d * (K_ref_inv * wp.vec3(float(x), float(y), 1.0))
    Xs = R_src_ref * X + t_src_ref
    if Xs[2] <= 1.0e-6:
        return
    q = K_src * Xs
    u = int(wp.round(q[0] / q[2]))
    v = int(wp.round(q[1] / q[2]))
    if u < 0 or v < 0 or u >= src_depth.shape[1] or v >= src_depth.shape[0]:
        return
    ds = src_depth[v, u]
    if ds <= 0.0:
        return
    Ys = ds * (K_src_inv * wp.vec3(float(u), float(v), 1.0))
    Y = wp.transpose(R_src_ref) * (Ys - t_src_ref)
    if Y[2] <= 1.0e-6:
        return
    pr = K_ref * Y
    dx = pr[0] / pr[2] - float(x)
    dy = pr[1] / pr[2] - float(y)
    if dx * dx + dy * dy <= max_px * max_px and wp.abs(Y[2] - d) <= max_rel * d:
        agree[y, x] = agree[y, x] + 1


@wp.kernel
def apply_agreement(agree: wp.array2d(dtype=int), min_agree: int, depth: wp.array2d(dtype=float),
                    confidence: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8)):
    y, x = wp.tid()
    if depth[y, x] > 0.0 and agree[y, x] < min_agree:
        depth[y, x] = 0.0
        confidence[y, x] = 0.0
        code[y, x] = wp.uint8(CODE_GEOMETRY_DISAGREES)


@wp.kernel
def count_codes(code: wp.array2d(dtype=wp.uint8), span: int, counts: wp.array(dtype=int)):
    """A histogram of the funnel codes (into a zeroed ``counts``): the funnel without downloading the codes. One
    thread per ``span`` pixels of a row adds each run of one code at once: codes come in regions, so a few atomic
    adds per thread instead of one per pixel on 11 addresses (which a GPU would serialise)."""
    y, c = wp.tid()
    x0 = c * span
    x1 = wp.min(x0 + span, code.shape[1])
    run = int(0)
    current = int(-1)
    for x in range(x0, x1):
        value = int(code[y, x])
        if value != current:
            if run > 0:
                wp.atomic_add(counts, current, run)
            current = value
            run = 0
        run += 1
    if run > 0:
        wp.atomic_add(counts, current, run)
