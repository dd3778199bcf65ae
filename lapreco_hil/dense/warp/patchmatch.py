"""Kernels of the slanted-window refinement (PatchMatch stereo; private: the host side is lapreco_hil.dense.depth).

Each pixel of the half-resolution reference holds a plane, written as its inverse depth and the inverse depth's
gradient in the image: a plane's inverse depth is affine in the pixel coordinates (rho(q) = rho + gx dx + gy dy),
so a window tap q samples source s at ``A @ q + rho(q) * b``, the plane sweep's own homography terms, with the
slant costing two multiply-adds per tap. A plane is scored as the sweep scores one (ZNCC per source on the taps
usable in both views, the mean of the ``best_k`` best sources: plane_sweep's ``_zncc`` and ``_bilinear``) on a
window of (2r+1)^2 pixels sampled every ``step`` pixels (Gipuma's sparse window: the window's extent at a
quarter of the taps).

Red-black checkerboard (Gipuma/ACMH): a launch updates the pixels of one colour, reading only the other colour's
planes (no thread reads a plane another writes), each pixel trying its 4 adjacent and 4 far neighbours' planes
(5 px away: ACMH's far neighbours carry a plane across a small textureless patch), then random perturbations of
its depth and slant in a range that halves each iteration, and one random plane. Planes stay inside the sweep's
inverse-depth range. The slant is bounded as ``slope`` = |gradient| x f / rho (the tangent of the surface's angle
to the image plane for a ray along the axis) <= ``max_slope``.

Geometric consistency (ACMM's second pass, ``Geometry``; off where its weight is 0): with the sources' own depth
maps from a first pass, each source's score of a plane loses ``weight`` x its forward-backward reprojection error
(the plane's point seen in the source, read back with the source's depth there and re-projected into the
reference, in full-resolution pixels, at most ``tau``; ``tau`` where the source has no depth there), so that a pixel
whose windows barely tell its planes apart takes the one its neighbours' maps agree on.
"""

from __future__ import annotations

import warp as wp

from lapreco_hil.dense.warp.plane_sweep import (CODE_DEPTH_EDGE, CODE_HIGHLIGHT, CODE_KEPT, CODE_LOW_TEXTURE,
                                                CODE_NO_MATCH, CODE_OUT_OF_RANGE, CODE_OUT_OF_VIEW, CODE_UNSUPPORTED,
                                                CODE_VIEWS_DISAGREE, NO_SCORE, STATE_HIGHLIGHT, STATE_OUT_OF_VIEW,
                                                _bilinear, _zncc, vec6)

wp.set_module_options({"enable_backward": False})

MAX_SOURCES = 8  # sources scored per plane (per-view scores live in registers: a fixed-size vector)
vec8 = wp.types.vector(length=MAX_SOURCES, dtype=wp.float32)


@wp.struct
class Geometry:
    """The sources' first-pass depth maps and what maps the reference into them and back: source full-resolution
    pixel ~ A @ (xf, yf, 1) + rho b (the full-resolution homography terms), reference pixel ~ d_s C @ (u, v, 1) + c;
    a level's pixel x is the full-resolution scale x + offset."""
    weight: float
    tau: float
    scale: float
    offset: float
    depth: wp.array3d(dtype=float)
    A: wp.array(dtype=wp.mat33)
    b: wp.array(dtype=wp.vec3)
    C: wp.array(dtype=wp.mat33)
    c: wp.array(dtype=wp.vec3)


@wp.func
def _map_depth(depth: wp.array3d(dtype=float), s: int, u: float, v: float) -> float:
    """Map ``s``'s depth at (u, v): bilinear where the four pixels about it all have one (a surface), the nearest
    pixel's otherwise (0 where it has none or (u, v) lies outside)."""
    h = depth.shape[1]
    w = depth.shape[2]
    if u < -0.5 or v < -0.5 or u > float(w) - 0.5 or v > float(h) - 0.5:
        return 0.0
    x0 = wp.clamp(int(wp.floor(u)), 0, w - 2)
    y0 = wp.clamp(int(wp.floor(v)), 0, h - 2)
    fx = wp.clamp(u - float(x0), 0.0, 1.0)
    fy = wp.clamp(v - float(y0), 0.0, 1.0)
    d00 = depth[s, y0, x0]
    d01 = depth[s, y0, x0 + 1]
    d10 = depth[s, y0 + 1, x0]
    d11 = depth[s, y0 + 1, x0 + 1]
    if d00 > 0.0 and d01 > 0.0 and d10 > 0.0 and d11 > 0.0:
        return (1.0 - fy) * ((1.0 - fx) * d00 + fx * d01) + fy * ((1.0 - fx) * d10 + fx * d11)
    return depth[s, wp.clamp(int(wp.round(v)), 0, h - 1), wp.clamp(int(wp.round(u)), 0, w - 1)]


@wp.func
def _reprojection_errors(geo: Geometry, n_src: int, x: int, y: int, rho: float) -> vec8:
    """Per source: the forward-backward reprojection error (full-resolution pixels, at most ``geo.tau``) of the
    reference pixel (x, y) at inverse depth ``rho`` through the source's depth map."""
    errors = vec8()
    xf = geo.scale * float(x) + geo.offset
    yf = geo.scale * float(y) + geo.offset
    for s in range(MAX_SOURCES):
        e = geo.tau
        if s < n_src:
            p = geo.A[s] * wp.vec3(xf, yf, 1.0) + rho * geo.b[s]
            if p[2] > 1.0e-9:
                u = p[0] / p[2]
                v = p[1] / p[2]
                ds = _map_depth(geo.depth, s, u, v)
                if ds > 0.0:
                    # (the source's depth along the ray through the projected point itself: no rounding, so
                    # that the error changes smoothly with the plane)
                    q = ds * (geo.C[s] * wp.vec3(u, v, 1.0)) + geo.c[s]
                    if q[2] > 1.0e-9:
                        dx = q[0] / q[2] - xf
                        dy = q[1] / q[2] - yf
                        e = wp.min(wp.sqrt(dx * dx + dy * dy), geo.tau)
        errors[s] = e
    return errors


@wp.func
def _with_geometry(scores: vec8, geo: Geometry, n_src: int, x: int, y: int, rho: float) -> vec8:
    """The sources' scores less ``geo.weight`` x their reprojection errors (unchanged where the weight is 0, and
    for a source that did not score)."""
    if geo.weight <= 0.0:
        return scores
    errors = _reprojection_errors(geo, n_src, x, y, rho)
    out = vec8()
    for s in range(MAX_SOURCES):
        out[s] = scores[s]
        if scores[s] > NO_SCORE + 0.5:
            out[s] = scores[s] - geo.weight * errors[s]
    return out


@wp.func
def _view_zncc(ref: wp.array2d(dtype=float), src: wp.array3d(dtype=float), i: int, A: wp.mat33, b: wp.vec3,
               x: int, y: int, rho: float, gx: float, gy: float, r: int, step: int, min_std: float,
               min_valid: float) -> float:
    """ZNCC of the reference window about (x, y) and source ``i`` warped by the plane (rho, gx, gy): the taps
    usable in both views (at least ``min_valid`` of them)."""
    h = ref.shape[0]
    w = ref.shape[1]
    acc = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    taps = float(0.0)
    for dy in range(-r, r + 1, step):
        yy = y + dy
        for dx in range(-r, r + 1, step):
            xx = x + dx
            taps += 1.0
            if yy >= 0 and yy < h and xx >= 0 and xx < w:
                g = ref[yy, xx]
                if g >= -1.0:
                    rq = rho + gx * float(dx) + gy * float(dy)
                    v = _bilinear(src, i, A * wp.vec3(float(xx), float(yy), 1.0) + rq * b)
                    if v >= -1.0:
                        acc += vec6(v, v * v, v * g, g, g * g, 1.0)
    return _zncc(acc, 1.0, taps, min_std, min_valid)


@wp.func
def _view_scores(ref: wp.array2d(dtype=float), src: wp.array3d(dtype=float), slots: wp.array(dtype=int),
                 A: wp.array(dtype=wp.mat33), b: wp.array(dtype=wp.vec3), n_src: int, x: int, y: int, rho: float,
                 gx: float, gy: float, r: int, step: int, min_std: float, min_valid: float) -> vec8:
    scores = vec8()
    for s in range(MAX_SOURCES):
        scores[s] = NO_SCORE
        if s < n_src:
            scores[s] = _view_zncc(ref, src, slots[s], A[s], b[s], x, y, rho, gx, gy, r, step, min_std, min_valid)
    return scores


@wp.func
def _best_k(scores: vec8, n_src: int, k: int) -> float:
    """Mean of the k best views' scores (an occluded view or one with a highlight drops out); NO_SCORE when
    fewer than k views score."""
    taken = int(0)
    total = float(0.0)
    for i in range(k):
        best = float(NO_SCORE)
        arg = int(-1)
        for s in range(n_src):
            if (taken >> s) & 1 == 0 and scores[s] > best:
                best = scores[s]
                arg = s
        if arg < 0 or best <= NO_SCORE + 0.5:
            return NO_SCORE
        taken = taken | (1 << arg)
        total += best
    return total / float(k)


@wp.func
def _score(ref: wp.array2d(dtype=float), src: wp.array3d(dtype=float), slots: wp.array(dtype=int),
           A: wp.array(dtype=wp.mat33), b: wp.array(dtype=wp.vec3), n_src: int, k: int, x: int, y: int, rho: float,
           gx: float, gy: float, r: int, step: int, min_std: float, min_valid: float, geo: Geometry) -> float:
    scores = _view_scores(ref, src, slots, A, b, n_src, x, y, rho, gx, gy, r, step, min_std, min_valid)
    return _best_k(_with_geometry(scores, geo, n_src, x, y, rho), n_src, k)


@wp.func
def _clip_slope(g: wp.vec2, rho: float, focal: float, max_slope: float) -> wp.vec2:
    """The gradient with its slope (|g| f / rho) at most ``max_slope``."""
    limit = max_slope * rho / focal
    n = wp.length(g)
    if n > limit:
        return g * (limit / n)
    return g


@wp.kernel
def init_planes(coarse_plane: wp.array2d(dtype=float), rho0: float, drho: float, rho_lo: float, rho_hi: float,
                focal: float, max_slope: float, init_slope: float, seed: int, ref: wp.array2d(dtype=float),
                ref_std: wp.array2d(dtype=float), src: wp.array3d(dtype=float), slots: wp.array(dtype=int),
                A: wp.array(dtype=wp.mat33), b: wp.array(dtype=wp.vec3), n_src: int, k: int, r: int, step: int,
                min_std: float, min_valid: float, plane: wp.array2d(dtype=wp.vec3), score: wp.array2d(dtype=float),
                geo: Geometry):
    """Each pixel's first plane: the plane sweep's depth where it has one, slanted as the sweep's depths about it
    (central differences, where both neighbours have one), a random plane elsewhere; and its score."""
    y, x = wp.tid()
    h = coarse_plane.shape[0]
    w = coarse_plane.shape[1]
    state = wp.rand_init(seed, y * w + x)
    p = coarse_plane[y, x]
    rho = float(0.0)
    g = wp.vec2(0.0, 0.0)
    if p >= 0.0:
        rho = rho0 + p * drho
        pl = coarse_plane[y, wp.max(x - 1, 0)]
        pr = coarse_plane[y, wp.min(x + 1, w - 1)]
        pu = coarse_plane[wp.max(y - 1, 0), x]
        pd = coarse_plane[wp.min(y + 1, h - 1), x]
        if pl >= 0.0 and pr >= 0.0 and x > 0 and x < w - 1:
            g[0] = 0.5 * (pr - pl) * drho
        if pu >= 0.0 and pd >= 0.0 and y > 0 and y < h - 1:
            g[1] = 0.5 * (pd - pu) * drho
    else:
        rho = rho_lo + wp.randf(state) * (rho_hi - rho_lo)
        g = wp.vec2(wp.randf(state) - 0.5, wp.randf(state) - 0.5) * (2.0 * init_slope * rho / focal)
    rho = wp.clamp(rho, rho_lo, rho_hi)
    g = _clip_slope(g, rho, focal, max_slope)
    plane[y, x] = wp.vec3(rho, g[0], g[1])
    sc = float(NO_SCORE)
    if ref_std[y, x] > 0.0:
        sc = _score(ref, src, slots, A, b, n_src, k, x, y, rho, g[0], g[1], r, step, min_std, min_valid, geo)
    score[y, x] = sc


@wp.func
def _from_neighbour(plane: wp.array2d(dtype=wp.vec3), x: int, y: int, xn: int, yn: int) -> wp.vec3:
    """The neighbour's plane carried to (x, y): its inverse depth there, the same gradient."""
    q = plane[yn, xn]
    return wp.vec3(q[0] + q[1] * float(x - xn) + q[2] * float(y - yn), q[1], q[2])


@wp.kernel
def propagate(parity: int, iteration: int, seed: int, far: int, rho_lo: float, rho_hi: float, focal: float,
              max_slope: float, perturb_rho: float, perturb_slope: float, ref: wp.array2d(dtype=float),
              ref_std: wp.array2d(dtype=float), src: wp.array3d(dtype=float), slots: wp.array(dtype=int),
              A: wp.array(dtype=wp.mat33), b: wp.array(dtype=wp.vec3), n_src: int, k: int, r: int, step: int,
              min_std: float, min_valid: float, plane: wp.array2d(dtype=wp.vec3), score: wp.array2d(dtype=float),
              geo: Geometry):
    """One colour of the checkerboard: thread (y, j) updates pixel (2 j + (y + parity) % 2, y). Its 4 adjacent
    and 4 far (``far`` px, odd: the other colour) neighbours' planes, then its own perturbed by at most
    ``perturb_rho`` in inverse depth and ``perturb_slope`` in slope (each alone, then both), then a random
    plane; the best scoring is kept."""
    y, j = wp.tid()
    h = plane.shape[0]
    w = plane.shape[1]
    x = 2 * j + (y + parity) % 2
    if x >= w or ref_std[y, x] <= 0.0:
        return
    state = wp.rand_init(seed, (iteration * 2 + parity) * h * w + y * w + x)
    best = plane[y, x]
    best_score = score[y, x]
    for c in range(13):
        cand = best
        if c < 8:
            d = 1
            if c >= 4:
                d = far
            m = c % 4
            xn = x
            yn = y
            if m == 0:
                xn = x - d
            elif m == 1:
                xn = x + d
            elif m == 2:
                yn = y - d
            else:
                yn = y + d
            if xn < 0 or xn >= w or yn < 0 or yn >= h:
                continue
            cand = _from_neighbour(plane, x, y, xn, yn)
        elif c < 12:
            # the best so far, its inverse depth and/or its slant perturbed (a slope step in gradient units)
            unit = best[0] / focal
            drho = float(0.0)
            dg = wp.vec2(0.0, 0.0)
            if c != 9:
                drho = (2.0 * wp.randf(state) - 1.0) * perturb_rho
            if c != 8:
                dg = wp.vec2(2.0 * wp.randf(state) - 1.0, 2.0 * wp.randf(state) - 1.0) * (perturb_slope * unit)
            if c == 11:
                drho = drho * 0.25
                dg = dg * 0.25
            cand = wp.vec3(best[0] + drho, best[1] + dg[0], best[2] + dg[1])
        else:
            rr = rho_lo + wp.randf(state) * (rho_hi - rho_lo)
            cand = wp.vec3(rr, 0.0, 0.0)
        if cand[0] < rho_lo or cand[0] > rho_hi:
            continue
        g = _clip_slope(wp.vec2(cand[1], cand[2]), cand[0], focal, max_slope)
        cand = wp.vec3(cand[0], g[0], g[1])
        sc = _score(ref, src, slots, A, b, n_src, k, x, y, cand[0], cand[1], cand[2], r, step, min_std, min_valid,
                    geo)
        if sc > best_score:
            best_score = sc
            best = cand
    plane[y, x] = best
    score[y, x] = best_score


@wp.kernel
def finalise_planes(state: wp.array2d(dtype=wp.uint8), grey: wp.array2d(dtype=float),
                    fine_std: wp.array2d(dtype=float), half_plane: wp.array2d(dtype=wp.vec3),
                    src: wp.array3d(dtype=float), slots: wp.array(dtype=int), A: wp.array(dtype=wp.mat33),
                    b: wp.array(dtype=wp.vec3), n_src: int, k: int, r: int, step: int, min_std: float,
                    min_valid: float, rho_lo: float, rho_hi: float, edge_rho: float, refine_rho: float,
                    min_zncc: float, view_min_zncc: float, min_views: int, depth: wp.array2d(dtype=float),
                    confidence: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8),
                    plane: wp.array2d(dtype=wp.vec3), K: wp.mat33, K_inv: wp.mat33, angle_weight: float,
                    geo: Geometry, unchecked: wp.array2d(dtype=float)):
    """Full resolution: the half-resolution plane of the pixel carried to it, scored at full resolution at its
    inverse depth and ``refine_rho`` either side (a parabola through the three where the middle is best, else the
    better side): the depth, the funnel code (in view, not a highlight, textured, matched, in range: not within
    ``edge_rho`` of the range's ends, views agree), a confidence (the score's, times the cosine between the ray and
    the plane's normal to the power ``angle_weight``: a depth seen at a grazing angle is the least certain, and
    fusion weighs it less), the pixel's plane (inverse depth and its gradient per pixel) for the support check;
    ``unchecked``: every scored pixel's depth before the checks (the geometric term's first-pass map: ACMM's maps
    have no holes, and a hole would weigh against the planes that see it)."""
    y, x = wp.tid()
    depth[y, x] = 0.0
    confidence[y, x] = 0.0
    unchecked[y, x] = 0.0
    if state[y, x] == wp.uint8(STATE_OUT_OF_VIEW):
        code[y, x] = wp.uint8(CODE_OUT_OF_VIEW)
        return
    if state[y, x] == wp.uint8(STATE_HIGHLIGHT) or grey[y, x] < -1.0:
        code[y, x] = wp.uint8(CODE_HIGHLIGHT)
        return
    if fine_std[y, x] <= 0.0:
        code[y, x] = wp.uint8(CODE_LOW_TEXTURE)
        return
    hc = half_plane.shape[0]
    wc = half_plane.shape[1]
    xc = wp.min(x / 2, wc - 1)
    yc = wp.min(y / 2, hc - 1)
    q = half_plane[yc, xc]
    # half-resolution coordinates of this pixel's centre, and the gradient per full-resolution pixel
    u = (float(x) + 0.5) * 0.5 - 0.5
    v = (float(y) + 0.5) * 0.5 - 0.5
    rho = q[0] + q[1] * (u - float(xc)) + q[2] * (v - float(yc))
    gx = 0.5 * q[1]
    gy = 0.5 * q[2]
    s0 = _view_scores(grey, src, slots, A, b, n_src, x, y, rho, gx, gy, r, step, min_std, min_valid)
    c0 = _best_k(_with_geometry(s0, geo, n_src, x, y, rho), n_src, k)
    cm = _score(grey, src, slots, A, b, n_src, k, x, y, rho - refine_rho, gx, gy, r, step, min_std, min_valid, geo)
    cp = _score(grey, src, slots, A, b, n_src, k, x, y, rho + refine_rho, gx, gy, r, step, min_std, min_valid, geo)
    best = c0
    scores = s0
    # a parabola through the best of the three and its two neighbours: where a side scored best, one more score a
    # step beyond it (else the depth would move by a whole step, up to half a step off)
    lo = cm
    hi = cp
    if cm > c0 and cm >= cp:
        rho = rho - refine_rho
        best = cm
        hi = c0
        lo = _score(grey, src, slots, A, b, n_src, k, x, y, rho - refine_rho, gx, gy, r, step, min_std, min_valid,
                    geo)
        scores = _view_scores(grey, src, slots, A, b, n_src, x, y, rho, gx, gy, r, step, min_std, min_valid)
    elif cp > c0:
        rho = rho + refine_rho
        best = cp
        lo = c0
        hi = _score(grey, src, slots, A, b, n_src, k, x, y, rho + refine_rho, gx, gy, r, step, min_std, min_valid,
                    geo)
        scores = _view_scores(grey, src, slots, A, b, n_src, x, y, rho, gx, gy, r, step, min_std, min_valid)
    if lo > NO_SCORE + 0.5 and hi > NO_SCORE + 0.5:
        den = lo - 2.0 * best + hi
        if den < -1.0e-6:
            rho = rho + refine_rho * wp.clamp(0.5 * (lo - hi) / den, -0.5, 0.5)
    # the match itself is judged on the windows alone (with geometry, ``best`` includes the reprojection errors)
    if geo.weight > 0.0:
        best = _best_k(scores, n_src, k)
    if best > NO_SCORE + 0.5 and rho > 0.0:
        unchecked[y, x] = 1.0 / rho
    if best < min_zncc:
        code[y, x] = wp.uint8(CODE_NO_MATCH)
        return
    if rho < rho_lo + edge_rho or rho > rho_hi - edge_rho:
        code[y, x] = wp.uint8(CODE_OUT_OF_RANGE)
        return
    agree = int(0)
    for s in range(n_src):
        if scores[s] >= view_min_zncc:
            agree += 1
    if agree < wp.min(min_views, n_src):
        code[y, x] = wp.uint8(CODE_VIEWS_DISAGREE)
        return
    depth[y, x] = 1.0 / rho
    plane[y, x] = wp.vec3(rho, gx, gy)
    # rho(q) = c . (x, y, 1): the plane's normal is K^T c, and its dot product with the ray K^-1 (x, y, 1) is rho
    c = wp.vec3(gx, gy, rho - gx * float(x) - gy * float(y))
    cos_view = rho / (wp.length(wp.transpose(K) * c) * wp.length(K_inv * wp.vec3(float(x), float(y), 1.0)))
    c_match = wp.clamp((best - min_zncc) / (1.0 - min_zncc), 0.0, 1.0)
    confidence[y, x] = c_match * wp.pow(wp.clamp(cos_view, 1.0e-6, 1.0), angle_weight)
    code[y, x] = wp.uint8(CODE_KEPT)


@wp.kernel
def plane_support(depth: wp.array2d(dtype=float), plane: wp.array2d(dtype=wp.vec3), r: int, max_rel: float,
                  min_fraction: float, edge_r: int, edge_rel: float, edge_slope: float, focal: float,
                  edge_min: int, supported: wp.array2d(dtype=wp.uint8)):
    """plane_sweep's ``support`` for slanted planes: a neighbour supports a depth where its own depth lies within
    ``max_rel`` of the pixel's plane there (on a surface seen obliquely the depth changes by percents per pixel:
    compared with the pixel's own depth, its neighbours would not support it). 2 (a depth edge) where at least
    ``edge_min`` depths within ``edge_r`` depart from the plane by more than ``edge_rel`` plus what a slope error
    of ``edge_slope`` makes of their distance (d / ``focal``; a plane's slant is the less certain the smaller the
    image): a window across a depth
    edge matches the nearer surface on both sides (fattens the foreground), as far as the window reaches; the
    other surface is a region, a stray wrong depth is not."""
    y, x = wp.tid()
    supported[y, x] = wp.uint8(0)
    if depth[y, x] <= 0.0:
        return
    q = plane[y, x]
    h = depth.shape[0]
    w = depth.shape[1]
    n = int(0)
    off_plane = int(0)
    for dy in range(-edge_r, edge_r + 1):
        yy = y + dy
        if yy >= 0 and yy < h:
            for dx in range(-edge_r, edge_r + 1):
                xx = x + dx
                if xx >= 0 and xx < w:
                    dn = depth[yy, xx]
                    if dn > 0.0:
                        rp = q[0] + q[1] * float(dx) + q[2] * float(dy)
                        off = wp.abs(dn * rp - 1.0)
                        reach = edge_rel + edge_slope * wp.sqrt(float(dx * dx + dy * dy)) / focal
                        if rp <= 0.0 or off > reach:
                            off_plane += 1
                        elif off <= max_rel and wp.abs(dx) <= r and wp.abs(dy) <= r:
                            n += 1
    if off_plane >= edge_min:
        supported[y, x] = wp.uint8(2)
    elif float(n) >= min_fraction * float((2 * r + 1) * (2 * r + 1)):
        supported[y, x] = wp.uint8(1)


@wp.kernel
def apply_plane_support(supported: wp.array2d(dtype=wp.uint8), depth: wp.array2d(dtype=float),
                        confidence: wp.array2d(dtype=float), code: wp.array2d(dtype=wp.uint8)):
    y, x = wp.tid()
    if depth[y, x] > 0.0 and supported[y, x] != wp.uint8(1):
        depth[y, x] = 0.0
        confidence[y, x] = 0.0
        code[y, x] = wp.where(supported[y, x] == wp.uint8(2), wp.uint8(CODE_DEPTH_EDGE), wp.uint8(CODE_UNSUPPORTED))
