"""Private Warp kernels of the front-end. Images are float32; a pyramid is one flat array with per-level
offsets, widths and heights (kernels cannot take a list of arrays).

Tiled kernels (one block per feature) stride their lane loops by ``wp.block_dim()``: Warp's CPU device runs a
tiled launch with one lane per block, so a constant stride would silently use a fraction of the window there.
"""

from __future__ import annotations

import warp as wp

PATCH = 13  # drift-check patch side (pixels)
HIGHPASS_RANGE = 128.0 / 96.0  # what frontend.opencv.to_u8 keeps of the log high-pass
HALF_PATCH = 6
# new corners are chosen strongest first through a histogram of their scores (no sort): 32 bins per halving of
# the response below the frame's best cover 16 halvings (a quality level down to 1.5e-5)
SCORE_BINS_PER_OCTAVE = 32
SCORE_BINS = 512

LK_CACHE = 8  # window pixels a lane keeps in registers: 8 x 64 lanes covers windows up to 22 x 22
vec8 = wp.types.vector(length=8, dtype=wp.float32)
vec44 = wp.types.vector(length=44, dtype=wp.float32)  # upper triangle of an 8x8 normal matrix (36) + gradient (8)
mat88 = wp.types.matrix(shape=(8, 8), dtype=wp.float32)


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
def undistort_gray(frame: wp.array2d(dtype=wp.uint8), remap: wp.array2d(dtype=wp.vec2),
                   gray: wp.array2d(dtype=float)):
    """One resampling pass: undistorted pixel <- bilinear sample of the distorted grey frame (0-255) at the
    precomputed map. Outside the frame: 0, as cv2.remap's constant border."""
    y, x = wp.tid()
    m = remap[y, x]
    if m[0] < -1.0 or m[1] < -1.0 or m[0] > float(frame.shape[1]) or m[1] > float(frame.shape[0]):
        gray[y, x] = 0.0
        return
    x0f = wp.floor(m[0])
    y0f = wp.floor(m[1])
    fx = m[0] - x0f
    fy = m[1] - y0f
    x0 = int(x0f)
    y0 = int(y0f)
    top = _grey(frame, x0, y0) * (1.0 - fx) + _grey(frame, x0 + 1, y0) * fx
    bot = _grey(frame, x0, y0 + 1) * (1.0 - fx) + _grey(frame, x0 + 1, y0 + 1) * fx
    gray[y, x] = top * (1.0 - fy) + bot * fy


@wp.kernel
def log_image(gray: wp.array2d(dtype=float), out: wp.array2d(dtype=float)):
    y, x = wp.tid()
    out[y, x] = wp.log(1.0 + gray[y, x])


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
def to_level0(a: wp.array2d(dtype=float), b: wp.array2d(dtype=float), scale: float, subtract: int,
              pyr: wp.array(dtype=float)):
    """Level 0 of the pyramid: (a - b) for the shading-free log image, clamped to the range the OpenCV
    baseline keeps in 8 bits (so silhouettes against black do not dominate the corner threshold), or
    a * scale for plain intensity."""
    y, x = wp.tid()
    v = a[y, x] * scale
    if subtract != 0:
        v = wp.clamp(a[y, x] - b[y, x], -HIGHPASS_RANGE, HIGHPASS_RANGE)
    pyr[y * a.shape[1] + x] = v


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
def sobel(pyr: wp.array(dtype=float), off: int, w: int, h: int, gx: wp.array(dtype=float),
          gy: wp.array(dtype=float)):
    """3x3 Sobel / 8: the derivative per pixel (cv2.Sobel ksize=3, scale 1/8)."""
    y, x = wp.tid()
    if x >= w or y >= h:
        return
    a = _px(pyr, off, w, h, x - 1, y - 1)
    b = _px(pyr, off, w, h, x, y - 1)
    c = _px(pyr, off, w, h, x + 1, y - 1)
    d = _px(pyr, off, w, h, x - 1, y)
    f = _px(pyr, off, w, h, x + 1, y)
    g = _px(pyr, off, w, h, x - 1, y + 1)
    hh = _px(pyr, off, w, h, x, y + 1)
    i = _px(pyr, off, w, h, x + 1, y + 1)
    gx[off + y * w + x] = ((c + 2.0 * f + i) - (a + 2.0 * d + g)) / 8.0
    gy[off + y * w + x] = ((g + 2.0 * hh + i) - (a + 2.0 * b + c)) / 8.0


# --- Shi-Tomasi ----------------------------------------------------------------------------------------------
@wp.func
def _allowed(mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
             occ: wp.array2d(dtype=wp.int32), x: int, y: int) -> bool:
    return mask[y, x] != wp.uint8(0) and occ[y, x] == 0 and lit[y, x] >= lit_min


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
def min_eigenvalue(rows: wp.array(dtype=wp.vec3), w: int, h: int, block: int,
                   mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
                   occ: wp.array2d(dtype=wp.int32), eig: wp.array2d(dtype=float), max_eig: wp.array(dtype=float)):
    """Smaller eigenvalue of the structure tensor summed over a block x block window (cornerMinEigenVal), from
    the row sums of ``structure_rows``; the maximum that the quality level is relative to is taken where
    corners may start, as OpenCV takes it inside the mask."""
    y, x = wp.tid()
    r = block // 2
    t = wp.vec3(0.0, 0.0, 0.0)
    for k in range(block):
        t += rows[wp.clamp(y + k - r, 0, h - 1) * w + x]
    a = t[0]
    b = t[1]
    c = t[2]
    half = 0.5 * (a + c)
    d = half - wp.sqrt(wp.max(0.25 * (a - c) * (a - c) + b * b, 0.0))
    eig[y, x] = d
    if _allowed(mask, lit, lit_min, occ, x, y):
        wp.atomic_max(max_eig, 0, d)


@wp.kernel
def occupancy(positions: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), radius: float,
              occ: wp.array2d(dtype=wp.int32)):
    """Mark the disc of radius min_distance around each live track: no new corner may start there. The track
    count is read on the device, so the launch has a fixed shape and can live in a CUDA graph."""
    t, j = wp.tid()
    if t >= count[0]:
        return
    r = int(wp.ceil(radius))
    side = 2 * r + 1
    dy = j // side - r
    dx = j % side - r
    if float(dx * dx + dy * dy) > radius * radius:
        return
    p = positions[t]
    x = int(wp.round(p[0])) + dx
    y = int(wp.round(p[1])) + dy
    if x >= 0 and y >= 0 and x < occ.shape[1] and y < occ.shape[0]:
        occ[y, x] = 1


@wp.kernel
def corner_candidates(eig: wp.array2d(dtype=float), max_eig: wp.array(dtype=float), quality: float,
                      mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
                      occ: wp.array2d(dtype=wp.int32), border: int, out_pos: wp.array(dtype=wp.vec2),
                      out_score: wp.array(dtype=float), counter: wp.array(dtype=wp.int32)):
    """Local maxima (3x3) above quality x the frame's best response, inside the field of view, lit, and away
    from live tracks; appended to a compact list."""
    y, x = wp.tid()
    h = eig.shape[0]
    w = eig.shape[1]
    if x < border or y < border or x >= w - border or y >= h - border:
        return
    v = eig[y, x]
    if v < quality * max_eig[0] or v <= 0.0:
        return
    if not _allowed(mask, lit, lit_min, occ, x, y):
        return
    for j in range(3):
        for i in range(3):
            n = eig[y + j - 1, x + i - 1]
            if n > v or (n == v and (j * 3 + i) < 4):
                return
    k = wp.atomic_add(counter, 0, 1)
    if k < out_pos.shape[0]:
        out_pos[k] = wp.vec2(float(x), float(y))
        out_score[k] = v


# --- pyramidal Lucas-Kanade, one block per feature -----------------------------------------------------------
@wp.func
def _window_origin(x: float, y: float) -> wp.vec4:
    """(floor x, floor y, fraction x, fraction y) of a window's top-left sample."""
    fx = wp.floor(x)
    fy = wp.floor(y)
    return wp.vec4(fx, fy, x - fx, y - fy)


@wp.func
def _inside(o: wp.vec4, win: int, w: int, h: int) -> bool:
    """Whether a window with origin o (``_window_origin``) and its bilinear neighbours lie inside the image.
    Tested in floats: a diverging step can put the origin beyond the int range, where the integer test
    would overflow and pass."""
    return o[0] >= 0.0 and o[1] >= 0.0 and o[0] + float(win) <= float(w - 1) and o[1] + float(win) <= float(h - 1)


@wp.func
def _window_px(img: wp.array(dtype=float), off: int, w: int, h: int, o: wp.vec4, inside: bool, k: int, win: int,
               inv_win: float) -> float:
    """Pixel k (row-major) of a win x win window with origin o (``_window_origin``). Every pixel of a translated
    window shares the same sub-pixel fractions, so inside the image a sample is four loads and three lerps;
    windows that touch the border (``inside`` false) take the clamped path."""
    row = int((float(k) + 0.5) * inv_win)  # k // win without an integer division
    col = k - row * win
    ix = int(o[0])
    iy = int(o[1])
    if inside:
        i = off + (iy + row) * w + ix + col
        top = img[i] + o[2] * (img[i + 1] - img[i])
        bot = img[i + w] + o[2] * (img[i + w + 1] - img[i + w])
        return top + o[3] * (bot - top)
    return bilinear(img, off, w, h, float(ix + col) + o[2], float(iy + row) + o[3])


@wp.kernel
def lk_track(prev: wp.array(dtype=float), prev_gx: wp.array(dtype=float), prev_gy: wp.array(dtype=float),
             cur: wp.array(dtype=float), offs: wp.array(dtype=int), ws: wp.array(dtype=int),
             hs: wp.array(dtype=int), levels: int, win: int, iterations: int, eps: float, min_eig: float,
             pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), out_pts: wp.array(dtype=wp.vec2),
             status: wp.array(dtype=wp.int32), error: wp.array(dtype=float)):
    """Bouguet's pyramidal LK: per level, the window's spatial gradient matrix from the previous image, then
    Newton steps on the temporal difference; the lanes of a block share the window, tile sums combine them.

    The time goes into the iterations of the slowest features (30 per level at most, as OpenCV), so each
    iteration is kept short: the window's sub-pixel fractions are computed once per iteration, not per pixel,
    and each lane keeps its pixels of the previous window and their gradients in registers (with enough lanes,
    i.e. on CUDA; with one lane, on the CPU device, it re-samples them instead)."""
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
    residual = float(0.0)
    cached = n <= LK_CACHE * nl
    for li in range(levels):
        lvl = levels - 1 - li
        off = offs[lvl]
        w = ws[lvl]
        h = hs[lvl]
        p = p0 * (1.0 / float(1 << lvl))
        o = _window_origin(p[0] - r, p[1] - r)
        inside = _inside(o, win, w, h)
        # spatial gradient matrix over the window in the previous image (its pixels cached on the way)
        acc = wp.vec3(0.0, 0.0, 0.0)
        c_i = vec8()
        c_x = vec8()
        c_y = vec8()
        if cached:
            for j in range(LK_CACHE):
                k = lane + j * nl
                if k < n:
                    vx = _window_px(prev_gx, off, w, h, o, inside, k, win, inv_win)
                    vy = _window_px(prev_gy, off, w, h, o, inside, k, win, inv_win)
                    c_i[j] = _window_px(prev, off, w, h, o, inside, k, win, inv_win)
                    c_x[j] = vx
                    c_y[j] = vy
                    acc += wp.vec3(vx * vx, vx * vy, vy * vy)
        else:
            k = lane
            while k < n:
                vx = _window_px(prev_gx, off, w, h, o, inside, k, win, inv_win)
                vy = _window_px(prev_gy, off, w, h, o, inside, k, win, inv_win)
                acc += wp.vec3(vx * vx, vx * vy, vy * vy)
                k += nl
        G = wp.tile_sum(wp.tile(acc, preserve_type=True))[0]
        det = G[0] * G[2] - G[1] * G[1]
        lam = 0.5 * (G[0] + G[2]) - wp.sqrt(wp.max(0.25 * (G[0] - G[2]) * (G[0] - G[2]) + G[1] * G[1], 0.0))
        if lam / float(n) < min_eig or wp.abs(det) < 1.0e-12:
            ok = 0
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
            q_inside = _inside(oq, win, w, h)
            bacc = wp.vec3(0.0, 0.0, 0.0)
            if cached:
                for j in range(LK_CACHE):
                    k = lane + j * nl
                    if k < n:
                        diff = c_i[j] - _window_px(cur, off, w, h, oq, q_inside, k, win, inv_win)
                        bacc += wp.vec3(diff * c_x[j], diff * c_y[j], wp.abs(diff))
            else:
                k = lane
                while k < n:
                    diff = (_window_px(prev, off, w, h, o, inside, k, win, inv_win)
                            - _window_px(cur, off, w, h, oq, q_inside, k, win, inv_win))
                    vx = _window_px(prev_gx, off, w, h, o, inside, k, win, inv_win)
                    vy = _window_px(prev_gy, off, w, h, o, inside, k, win, inv_win)
                    bacc += wp.vec3(diff * vx, diff * vy, wp.abs(diff))
                    k += nl
            b = wp.tile_sum(wp.tile(bacc, preserve_type=True))[0]
            residual = b[2] / float(n)
            step = wp.vec2((G[2] * b[0] - G[1] * b[1]) / det, (G[0] * b[1] - G[1] * b[0]) / det)
            nu = nu + step
            if wp.length(step) < eps:
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
        out_pts[f] = q
        status[f] = wp.where(ok == 1 and in_image, 1, 0)
        error[f] = residual


# --- Zinsser drift check, one block per feature --------------------------------------------------------------
@wp.func
def _chol_solve8(H: mat88, g: vec8) -> vec8:
    Lm = mat88()
    for j in range(8):
        s = H[j, j]
        for k in range(j):
            s -= Lm[j, k] * Lm[j, k]
        d = wp.sqrt(wp.max(s, 1.0e-12))
        Lm[j, j] = d
        for i in range(j + 1, 8):
            t = H[i, j]
            for k in range(j):
                t -= Lm[i, k] * Lm[j, k]
            Lm[i, j] = t / d
    y = vec8()
    for i in range(8):
        t = g[i]
        for k in range(i):
            t -= Lm[i, k] * y[k]
        y[i] = t / Lm[i, i]
    x = vec8()
    for ii in range(8):
        i = 7 - ii
        t = y[i]
        for k in range(i + 1, 8):
            t -= Lm[k, i] * x[k]
        x[i] = t / Lm[i, i]
    return x


@wp.func
def _patch_offset(k: int) -> wp.vec2:
    """Offset of pixel k of a PATCH x PATCH patch from its centre."""
    return wp.vec2(float(k % PATCH - HALF_PATCH), float(k // PATCH - HALF_PATCH))


@wp.kernel
def sample_patches(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                   count: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32),
                   patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22)):
    """The first patch of each new track (slots count .. count + n_new - 1), and an identity warp."""
    t, k = wp.tid()
    if t >= n_new[0]:
        return
    s = count[0] + t
    q = pts[s] + _patch_offset(k)
    patches[s, k] = bilinear(img, 0, w, h, q[0], q[1])
    if k == 0:
        A[s] = wp.identity(n=2, dtype=float)


@wp.kernel
def drift_check(img: wp.array(dtype=float), gx: wp.array(dtype=float), gy: wp.array(dtype=float), w: int,
                h: int, patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22),
                pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
                count: wp.array(dtype=wp.int32), iterations: int, max_residual: float,
                max_stretch: float, max_correction: float, out_pts: wp.array(dtype=wp.vec2),
                keep: wp.array(dtype=wp.int32), residual_out: wp.array(dtype=float)):
    """Fit alpha I(x) + beta ~ J(A x + b) to each track's first patch I by Gauss-Newton (8 parameters), from the
    tracker's position b; the fitted b is the drift-free position. Dropped: large normalised residual, too
    much stretch or a flip of A, a correction larger than max_correction, an absurd gain."""
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
    k = lane
    while k < n:
        ref = patches[f, k]
        q = b + Am * _patch_offset(k)
        j = bilinear(img, 0, w, h, q[0], q[1])
        st += wp.vec4(ref, ref * ref, j, j * j)
        k += nl
    S = wp.tile_sum(wp.tile(st, preserve_type=True))[0]
    fn = float(n)
    ref_mean = S[0] / fn
    ref_std = wp.sqrt(wp.max(S[1] / fn - ref_mean * ref_mean, 0.0)) + 1.0e-6
    cur_mean = S[2] / fn
    cur_std = wp.sqrt(wp.max(S[3] / fn - cur_mean * cur_mean, 0.0)) + 1.0e-6
    alpha = cur_std / ref_std
    beta = cur_mean - alpha * ref_mean
    for _it in range(iterations):
        acc = vec44()
        k = lane
        while k < n:
            ref = patches[f, k]
            o = _patch_offset(k)
            q = b + Am * o
            j = bilinear(img, 0, w, h, q[0], q[1])
            u = bilinear(gx, 0, w, h, q[0], q[1])
            v = bilinear(gy, 0, w, h, q[0], q[1])
            r = j - alpha * ref - beta
            row = vec8(u * o[0], u * o[1], v * o[0], v * o[1], u, v, -ref, -1.0)
            idx = int(0)
            for a in range(8):
                for c in range(a, 8):
                    acc[idx] += row[a] * row[c]
                    idx += 1
                acc[36 + a] += row[a] * r
            k += nl
        tot = wp.tile_sum(wp.tile(acc, preserve_type=True))[0]
        H = mat88()
        gvec = vec8()
        idx = int(0)
        for a in range(8):
            for c in range(a, 8):
                H[a, c] = tot[idx]
                H[c, a] = tot[idx]
                idx += 1
            H[a, a] = H[a, a] + 1.0e-6
            gvec[a] = -tot[36 + a]
        d = _chol_solve8(H, gvec)
        Am = Am + wp.mat22(d[0], d[1], d[2], d[3])
        b = b + wp.vec2(d[4], d[5])
        alpha = alpha + d[6]
        beta = beta + d[7]
    # final normalised residual
    racc = float(0.0)
    k = lane
    while k < n:
        ref = patches[f, k]
        q = b + Am * _patch_offset(k)
        r = bilinear(img, 0, w, h, q[0], q[1]) - alpha * ref - beta
        racc += r * r
        k += nl
    rss = wp.tile_sum(wp.tile(racc))[0]
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
        out_pts[f] = b
        A[f] = Am
        keep[f] = wp.where(good, 1, 0)
        residual_out[f] = res


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
            count: wp.array(dtype=wp.int32), out_pts: wp.array(dtype=wp.vec2), keep: wp.array(dtype=wp.int32)):
    """Without the drift check: keep what LK tracked into the field of view."""
    f = wp.tid()
    if f >= count[0]:
        keep[f] = 0
        return
    out_pts[f] = pts[f]
    keep[f] = wp.where(status[f] == 1 and _in_view(mask, pts[f]), 1, 0)


@wp.kernel
def scatter_tracks(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32),
                   src_pts: wp.array(dtype=wp.vec2), src_A: wp.array(dtype=wp.mat22),
                   src_patches: wp.array2d(dtype=float), src_ids: wp.array(dtype=wp.int32),
                   dst_pts: wp.array(dtype=wp.vec2), dst_A: wp.array(dtype=wp.mat22),
                   dst_patches: wp.array2d(dtype=float), dst_ids: wp.array(dtype=wp.int32)):
    """Compaction on the device: a kept track moves to its slot (exclusive prefix sum of the keep flags)."""
    t, k = wp.tid()
    if keep[t] == 0:
        return
    s = slot[t]
    dst_patches[s, k] = src_patches[t, k]
    if k == 0:
        dst_pts[s] = src_pts[t]
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
def cell_best(pos: wp.array(dtype=wp.vec2), score: wp.array(dtype=float), count: wp.array(dtype=wp.int32),
              cell: float, grid_w: int, best: wp.array(dtype=float)):
    """Cells of side min_distance / sqrt(2): two corners in one cell are always too close, keep the best."""
    i = wp.tid()
    if i >= wp.min(count[0], pos.shape[0]):
        return
    p = pos[i]
    c = int(p[1] / cell) * grid_w + int(p[0] / cell)
    wp.atomic_max(best, c, score[i])


@wp.kernel
def cell_winner(pos: wp.array(dtype=wp.vec2), score: wp.array(dtype=float), count: wp.array(dtype=wp.int32),
                cell: float, grid_w: int, best: wp.array(dtype=float), winner: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if i >= wp.min(count[0], pos.shape[0]):
        return
    p = pos[i]
    c = int(p[1] / cell) * grid_w + int(p[0] / cell)
    if score[i] == best[c]:
        wp.atomic_max(winner, c, i)


@wp.kernel
def selection_init(pos: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), cell: float, grid_w: int,
                   winner: wp.array(dtype=wp.int32), state: wp.array(dtype=wp.int32)):
    """0 = undecided (its cell's best), -1 = out."""
    i = wp.tid()
    state[i] = -1
    if i < wp.min(count[0], pos.shape[0]):
        p = pos[i]
        if winner[int(p[1] / cell) * grid_w + int(p[0] / cell)] == i:
            state[i] = 0


@wp.kernel
def selection_round(pos: wp.array(dtype=wp.vec2), score: wp.array(dtype=float), count: wp.array(dtype=wp.int32),
                    cell: float, grid_w: int, grid_h: int, winner: wp.array(dtype=wp.int32), min_distance: float,
                    state_in: wp.array(dtype=wp.int32), state_out: wp.array(dtype=wp.int32)):
    """One round of greedy selection in parallel: an undecided corner is rejected next to a selected one, and
    selected when no stronger undecided corner is within min_distance. Its fixed point is OpenCV's greedy
    (strongest first) result."""
    i = wp.tid()
    st = state_in[i]
    state_out[i] = st
    if st != 0:
        return
    p = pos[i]
    s = score[i]
    cx = int(p[0] / cell)
    cy = int(p[1] / cell)
    reach = int(wp.ceil(min_distance / cell))
    blocked = int(0)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            x = cx + dx
            y = cy + dy
            if x >= 0 and y >= 0 and x < grid_w and y < grid_h and (dx != 0 or dy != 0):
                j = winner[y * grid_w + x]
                if j >= 0:
                    if wp.length(pos[j] - p) < min_distance:
                        if state_in[j] == 1:
                            state_out[i] = -1
                            return
                        if state_in[j] == 0 and (score[j] > s or (score[j] == s and j < i)):
                            blocked = 1
    if blocked == 0:
        state_out[i] = 1


@wp.func
def _score_bin(score: float, max_score: float) -> int:
    """Histogram bin of a corner score: SCORE_BINS_PER_OCTAVE bins per halving below the frame's best."""
    octaves = wp.log2(max_score / wp.max(score, 1.0e-30))
    return wp.clamp(int(octaves * float(SCORE_BINS_PER_OCTAVE)), 0, SCORE_BINS - 1)


@wp.kernel
def score_histogram(score: wp.array(dtype=float), state: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float),
                    hist: wp.array(dtype=wp.int32)):
    """How many selected corners fall in each score bin (bin 0 = strongest)."""
    i = wp.tid()
    if state[i] == 1:
        wp.atomic_add(hist, _score_bin(score[i], max_eig[0]), 1)


@wp.kernel
def score_threshold(hist: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), max_features: int,
                    cut: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32)):
    """One thread: the strongest selected corners that fill the free slots. Every corner in a bin above the cut
    bin is taken; from the cut bin only as many as fit (cut[1]). n_new = how many are taken."""
    want = max_features - count[0]
    taken = int(0)
    b = int(0)
    while b < SCORE_BINS and taken + hist[b] <= want:
        taken += hist[b]
        b += 1
    cut[0] = b
    room = int(0)
    if b < SCORE_BINS:
        room = want - taken
    cut[1] = room
    n_new[0] = taken + room


@wp.kernel
def take_corners(pos: wp.array(dtype=wp.vec2), score: wp.array(dtype=float), state: wp.array(dtype=wp.int32),
                 max_eig: wp.array(dtype=float), cut: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                 next_id: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32), pts: wp.array(dtype=wp.vec2),
                 ids: wp.array(dtype=wp.int32)):
    """The chosen corners become tracks after the live ones (slots count .. count + n_new - 1)."""
    i = wp.tid()
    if state[i] != 1:
        return
    b = _score_bin(score[i], max_eig[0])
    if b > cut[0]:
        return
    if b == cut[0]:
        if wp.atomic_add(taken, 1, 1) >= cut[1]:
            return
    k = wp.atomic_add(taken, 0, 1)
    pts[count[0] + k] = pos[i]
    ids[count[0] + k] = next_id[0] + k


@wp.kernel
def commit_new_tracks(count: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32),
                      next_id: wp.array(dtype=wp.int32)):
    count[0] = count[0] + n_new[0]
    next_id[0] = next_id[0] + n_new[0]
