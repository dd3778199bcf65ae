"""Zinsser's drift check, one tiled block per feature: each track's first patch is registered against the
current image under an affine warp with gain and bias (8 parameters, Gauss-Newton), which gives the track's
drift-free position and drops tracks whose patch no longer matches. Also the first patches of new tracks."""

from __future__ import annotations

import warp as wp

from lapreco_hil.frontend.warp.block_sum import block_sum1, block_sum4, block_sum44, vec44
from lapreco_hil.frontend.warp.sampling import bilinear, in_view

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

PATCH = 13  # drift-check patch side (pixels)
HALF_PATCH = 6
# lanes (threads) per feature; 32 ran as fast (docs/benchmarks.md, "Front-end and mapper notes")
DRIFT_LANES = 64
vec8 = wp.types.vector(length=8, dtype=wp.float32)
mat88 = wp.types.matrix(shape=(8, 8), dtype=wp.float32)


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


@wp.func
def _sample_new(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                count: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32), patches: wp.array2d(dtype=float),
                t: int, k: int) -> int:
    """Pixel k of new track t's first patch on ``img`` (slots count .. count + taken[0] - 1): its slot, or -1
    past the new tracks."""
    if t >= taken[0]:
        return -1
    s = count[0] + t
    q = pts[s] + _patch_offset(k)
    patches[s, k] = bilinear(img, 0, w, h, q[0], q[1])
    return s


@wp.kernel
def _sample_patches(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                    count: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32),
                    patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22), steps: wp.array(dtype=wp.vec2)):
    """The first patch of each new track, an identity warp, no step."""
    t, k = wp.tid()
    s = _sample_new(img, w, h, pts, count, taken, patches, t, k)
    if s >= 0 and k == 0:
        A[s] = wp.identity(n=2, dtype=float)
        steps[s] = wp.vec2(0.0, 0.0)


def _make_drift_check(per_lane: int, min_blocks: int | None = None):
    """The drift check for lanes that each take ``per_lane`` patch pixels per pass (unrolled, loads in
    flight together); ``min_blocks``: the blocks of DRIFT_LANES an SM must hold at once (CUDA's launch bounds;
    None: no bound)."""
    bounds = None if min_blocks is None else (DRIFT_LANES, min_blocks)

    @wp.kernel(module="unique", enable_backward=False, launch_bounds=bounds)
    def _drift_check(img: wp.array(dtype=float), gx: wp.array(dtype=float), gy: wp.array(dtype=float), w: int,
                     h: int, patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22),
                     pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
                     count: wp.array(dtype=wp.int32), iterations: int, max_residual: float,
                     max_stretch: float, max_correction: float, keep: wp.array(dtype=wp.int32),
                     residual_out: wp.array(dtype=float), only: wp.array(dtype=wp.int32)):
        """Fit alpha I(x) + beta ~ J(A x + b) to each track's first patch I by Gauss-Newton (8 parameters), from the
        tracker's position b; the fitted b is the drift-free position and replaces b in ``pts``. Dropped: large
        normalised residual, too much stretch or a flip of A, a correction larger than max_correction, an absurd
        gain. ``only`` (non-empty): just the slots where it is non-zero (the others' outputs left as they were)."""
        f, lane = wp.tid()
        if f >= count[0]:
            if lane == 0:
                keep[f] = 0  # slots past the live tracks are not kept (the compaction scans every slot)
            return
        if only.shape[0] > 0:
            if only[f] == 0:
                return  # the same slot for every lane: the whole block leaves
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
        S = block_sum4(st, 0)
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
            tot = block_sum44(acc, _it + 1)
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
        rss = block_sum1(racc, 0)
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
            good = good and status[f] == 1 and in_view(mask, b)
            pts[f] = b
            A[f] = Am
            keep[f] = wp.where(good, 1, 0)
            residual_out[f] = res

    return _drift_check


DRIFT_PER_LANE = (PATCH * PATCH + DRIFT_LANES - 1) // DRIFT_LANES
_drift_check = _make_drift_check(DRIFT_PER_LANE)


def sample_patches(img: wp.array, w: int, h: int, pts: wp.array, count: wp.array, taken: wp.array,
                   patches: wp.array, A: wp.array, steps: wp.array, device) -> None:
    """The first patches of the ``taken[0]`` new tracks (slots from ``count[0]``) into ``patches``, with an
    identity warp in ``A`` and no step in ``steps``."""
    wp.launch(_sample_patches, dim=(pts.shape[0], PATCH * PATCH),
              inputs=[img, w, h, pts, count, taken, patches, A, steps], device=device)


@wp.kernel
def _reanchor(img: wp.array(dtype=float), w: int, h: int, searched: wp.array(dtype=wp.int32),
              at_lk: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
              pts: wp.array(dtype=wp.vec2), patches: wp.array2d(dtype=float), A: wp.array(dtype=wp.mat22),
              keep: wp.array(dtype=wp.int32)):
    """A track matched across a wide baseline (``searched``) that the drift check refused keeps LK's position and
    starts a new reference patch there with an identity warp: the first patch's affine model may not hold
    across such a change. (One the drift check kept keeps its refined position.)"""
    t, k = wp.tid()
    if t >= count[0] or searched[t] == 0:
        return
    q = at_lk[t]
    c = q + _patch_offset(k)
    patches[t, k] = bilinear(img, 0, w, h, c[0], c[1])
    if k == 0:
        pts[t] = q
        A[t] = wp.identity(n=2, dtype=float)
        keep[t] = wp.where(in_view(mask, q), 1, 0)


@wp.kernel
def _refused_only(keep: wp.array(dtype=wp.int32), searched: wp.array(dtype=wp.int32)):
    """Of the searched tracks, only those the drift check refused are anchored anew."""
    t = wp.tid()
    if keep[t] != 0:
        searched[t] = 0


def reanchor(img: wp.array, w: int, h: int, searched: wp.array, at_lk: wp.array, count: wp.array, mask: wp.array,
             pts: wp.array, patches: wp.array, A: wp.array, keep: wp.array, device) -> None:
    """After the drift check: the ``searched`` tracks it refused take their LK positions ``at_lk``, a new first
    patch from ``img`` and an identity warp, and are kept if inside the field of view."""
    wp.launch(_refused_only, dim=pts.shape[0], inputs=[keep, searched], device=device)  # (before keep changes)
    wp.launch(_reanchor, dim=(pts.shape[0], PATCH * PATCH),
              inputs=[img, w, h, searched, at_lk, count, mask, pts, patches, A, keep], device=device)


def drift_check(img: wp.array, gx: wp.array, gy: wp.array, w: int, h: int, patches: wp.array, A: wp.array,
                pts: wp.array, status: wp.array, mask: wp.array, count: wp.array, iterations: int,
                max_residual: float, max_stretch: float, max_correction: float, keep: wp.array,
                residual_out: wp.array, device, only: wp.array | None = None) -> None:
    """Register each live track's first patch (every slot is launched): ``pts`` and ``A`` updated in place,
    ``keep`` (1: kept) and ``residual_out`` (the normalised residual). ``only`` (int32 per slot): register just
    the slots where it is non-zero, leaving the others' outputs as they were (None or empty: every slot)."""
    if only is None:
        only = wp.empty(0, dtype=wp.int32, device=device)
    wp.launch_tiled(_drift_check, dim=[pts.shape[0]], inputs=[
        img, gx, gy, w, h, patches, A, pts, status, mask, count, iterations, max_residual, max_stretch,
        max_correction, keep, residual_out, only], block_dim=DRIFT_LANES, device=device)


# --- the rescue of new tracks with a stereo rig at fast motion (``WarpFrontEnd``; frontend/opencv's _drift_check)
# Each track's rescue state, per slot (double-buffered and compacted with the other per-track arrays): before its
# first step, registered on the drift image since, or registered on the rescue-smoothed image (once rescued).
TRACK_NEW = 0
TRACK_PLAIN = 1
TRACK_SMOOTHED = 2


@wp.kernel
def _sample_rescue_patches(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                           count: wp.array(dtype=wp.int32), taken: wp.array(dtype=wp.int32),
                           patches: wp.array2d(dtype=float), state: wp.array(dtype=wp.int32)):
    """The first patch on the rescue-smoothed image of each new track."""
    t, k = wp.tid()
    s = _sample_new(img, w, h, pts, count, taken, patches, t, k)
    if s >= 0 and k == 0:
        state[s] = TRACK_NEW


@wp.kernel
def _rescue_start(img: wp.array(dtype=float), w: int, h: int, pts: wp.array(dtype=wp.vec2),
                  count: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32),
                  patches: wp.array2d(dtype=float), state: wp.array(dtype=wp.int32)):
    """When the front-end first serves a rig: every live track's first patch on the rescue-smoothed image of
    this frame; the tracks found in this frame (the last ``n_new[0]`` slots) are new, the others plain."""
    t, k = wp.tid()
    c = count[0]
    if t >= c:
        return
    q = pts[t] + _patch_offset(k)
    patches[t, k] = bilinear(img, 0, w, h, q[0], q[1])
    if k == 0:
        state[t] = wp.where(t >= c - n_new[0], TRACK_NEW, TRACK_PLAIN)


@wp.kernel
def _plain_slots(state: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), plain: wp.array(dtype=wp.int32)):
    """1 for the live tracks registered on the drift image (all but the rescued ones)."""
    f = wp.tid()
    plain[f] = wp.where(f < count[0] and state[f] != TRACK_SMOOTHED, 1, 0)


@wp.kernel
def _count_fast(lk_pts: wp.array(dtype=wp.vec2), prev_pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32),
                mask: wp.array2d(dtype=wp.uint8), count: wp.array(dtype=wp.int32), min_px: float,
                counts: wp.array(dtype=wp.int32)):
    """counts <- (tracks LK followed into the view that moved at least min_px, tracks LK followed into the view)."""
    f = wp.tid()
    if f < count[0] and status[f] == 1 and in_view(mask, lk_pts[f]):
        wp.atomic_add(counts, 1, 1)
        if wp.length(lk_pts[f] - prev_pts[f]) >= min_px:
            wp.atomic_add(counts, 0, 1)


@wp.kernel
def _rescue_candidates(state: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32),
                       searched: wp.array(dtype=wp.int32), use_searched: int, counts: wp.array(dtype=wp.int32),
                       count: wp.array(dtype=wp.int32), at_lk: wp.array(dtype=wp.vec2), pts: wp.array(dtype=wp.vec2),
                       A: wp.array(dtype=wp.mat22), again: wp.array(dtype=wp.int32)):
    """The slots registered on the rescue-smoothed image: the rescued tracks, and, on a frame of fast motion (the
    median LK step at least fast_motion_px, read as more than half of the tracked moving that far), the new
    tracks the drift check refused that were not found along their epipolar line. Those start again from LK's
    position with an identity warp."""
    f = wp.tid()
    again[f] = 0
    if f >= count[0]:
        return
    s = state[f]
    swept = int(0)
    if use_searched != 0:
        swept = searched[f]
    fast = 2 * counts[0] > counts[1]
    if s == TRACK_SMOOTHED or (fast and s == TRACK_NEW and keep[f] == 0 and swept == 0):
        again[f] = 1
        if s != TRACK_SMOOTHED:
            pts[f] = at_lk[f]
            A[f] = wp.identity(n=2, dtype=float)


@wp.kernel
def _rescue_back_needed(state: wp.array(dtype=wp.int32), again: wp.array(dtype=wp.int32),
                        keep: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """1 for the new tracks the smoothed check kept: LK from there must track back (``rescue_verdict``)."""
    f = wp.tid()
    out[f] = wp.where(again[f] != 0 and state[f] == TRACK_NEW and keep[f] != 0, 1, 0)


@wp.kernel
def _rescue_verdict(back_needed: wp.array(dtype=wp.int32), back: wp.array(dtype=wp.vec2),
                    back_status: wp.array(dtype=wp.int32), prev_pts: wp.array(dtype=wp.vec2),
                    again: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), max_px: float,
                    keep: wp.array(dtype=wp.int32), state: wp.array(dtype=wp.int32)):
    """A rescued new track stays only if LK back lands within ``max_px`` of where it was; the tracks judged on
    the smoothed image stay registered there, the other new ones have had their first step."""
    f = wp.tid()
    if f >= count[0]:
        return
    if back_needed[f] != 0:
        if back_status[f] == 0 or wp.length(back[f] - prev_pts[f]) >= max_px:
            keep[f] = 0
    if again[f] != 0:
        state[f] = TRACK_SMOOTHED
    elif state[f] == TRACK_NEW:
        state[f] = TRACK_PLAIN


@wp.kernel
def _reanchored_plain(searched: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                      state: wp.array(dtype=wp.int32)):
    """A track anchored anew (``reanchor``) registers on the drift image again."""
    f = wp.tid()
    if f < count[0] and searched[f] != 0:
        state[f] = TRACK_PLAIN


def sample_rescue_patches(img: wp.array, w: int, h: int, pts: wp.array, count: wp.array, taken: wp.array,
                          patches: wp.array, state: wp.array, device) -> None:
    """The new tracks' first patches on the rescue-smoothed ``img`` and their state (new)."""
    wp.launch(_sample_rescue_patches, dim=(pts.shape[0], PATCH * PATCH),
              inputs=[img, w, h, pts, count, taken, patches, state], device=device)


def rescue_start(img: wp.array, w: int, h: int, pts: wp.array, count: wp.array, n_new: wp.array,
                 patches: wp.array, state: wp.array, device) -> None:
    """Every live track's first patch on the rescue-smoothed ``img`` and its state (``_rescue_start``)."""
    wp.launch(_rescue_start, dim=(pts.shape[0], PATCH * PATCH),
              inputs=[img, w, h, pts, count, n_new, patches, state], device=device)


def plain_slots(state: wp.array, count: wp.array, plain: wp.array, device) -> None:
    """``plain`` <- 1 for the live tracks not registered on the rescue-smoothed image."""
    wp.launch(_plain_slots, dim=state.shape[0], inputs=[state, count, plain], device=device)


def count_fast(lk_pts: wp.array, prev_pts: wp.array, status: wp.array, mask: wp.array, count: wp.array,
               min_px: float, counts: wp.array, device) -> None:
    """``counts`` <- (tracked that moved at least ``min_px``, tracked) after LK and its checks."""
    counts.zero_()
    wp.launch(_count_fast, dim=lk_pts.shape[0], inputs=[lk_pts, prev_pts, status, mask, count, float(min_px),
                                                         counts], device=device)


def rescue_candidates(state: wp.array, keep: wp.array, searched: wp.array | None, counts: wp.array,
                      count: wp.array, at_lk: wp.array, pts: wp.array, A: wp.array, again: wp.array, device) -> None:
    """``again`` <- the slots the smoothed drift check registers (``_rescue_candidates``); ``searched``: the
    tracks found along their epipolar line this frame (None: a frame without a motion, none)."""
    use = 0 if searched is None else 1
    searched = keep if searched is None else searched  # (not read)
    wp.launch(_rescue_candidates, dim=state.shape[0],
              inputs=[state, keep, searched, use, counts, count, at_lk, pts, A, again], device=device)


def rescue_back_needed(state: wp.array, again: wp.array, keep: wp.array, out: wp.array, device) -> None:
    """``out`` <- 1 for the new tracks the smoothed check kept (LK back checks them)."""
    wp.launch(_rescue_back_needed, dim=state.shape[0], inputs=[state, again, keep, out], device=device)


def rescue_verdict(back_needed: wp.array, back: wp.array, back_status: wp.array, prev_pts: wp.array,
                   again: wp.array, count: wp.array, max_px: float, keep: wp.array, state: wp.array,
                   device) -> None:
    """The forward-backward verdict on the rescued new tracks, and every live track's next state."""
    wp.launch(_rescue_verdict, dim=state.shape[0], inputs=[back_needed, back, back_status, prev_pts, again, count,
                                                            float(max_px), keep, state], device=device)


def reanchored_plain(searched: wp.array, count: wp.array, state: wp.array, device) -> None:
    """The tracks ``reanchor`` anchored anew register on the drift image again."""
    wp.launch(_reanchored_plain, dim=state.shape[0], inputs=[searched, count, state], device=device)
