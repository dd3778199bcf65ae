"""Pyramidal Lucas-Kanade (Bouguet), one tiled block per feature: the lanes of a block share the feature's
window and combine their partial sums by block sums."""

from __future__ import annotations

import warp as wp

from lapreco_hil.frontend.warp.block_sum import block_sum3

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

# Lanes (threads) per feature. More lanes mean fewer window pixels per lane and shorter iterations, but wider
# block sums; 128 was the fastest on whole frames (docs/benchmarks.md, "Front-end and mapper notes").
LK_LANES = 128


@wp.func
def _window_origin(x: float, y: float) -> wp.vec4:
    """(floor x, floor y, fraction x, fraction y) of a window's top-left sample. The floors are clamped to a
    range that converts to int safely: a diverging step can put a window anywhere, NaN included."""
    fx = wp.floor(x)
    fy = wp.floor(y)
    return wp.vec4(wp.clamp(fx, -1.0e6, 1.0e6), wp.clamp(fy, -1.0e6, 1.0e6), x - fx, y - fy)


@wp.func
def _reflect(x: int, n: int) -> int:
    """x mirrored into [0, n) about the border pixels (OpenCV's BORDER_REFLECT_101, as its LK pads its levels),
    then clamped (a window far outside)."""
    return wp.clamp((n - 1) - wp.abs((n - 1) - wp.abs(x)), 0, n - 1)


@wp.func
def _window_px(img: wp.array(dtype=float), off: int, w: int, h: int, o: wp.vec4, k: int, win: int,
               inv_win: float) -> float:
    """Pixel k (row-major) of a win x win window with origin o (``_window_origin``), bilinear, the border
    reflected as OpenCV's LK samples it (a coarse level's window often reaches past it). Every pixel of a
    translated window shares the same sub-pixel fractions. There is no branch: the four addresses are clamped
    into the image, so the loads of all of a lane's pixels can be in flight at once (an iteration waits for
    memory once, not once per pixel)."""
    row = int((float(k) + 0.5) * inv_win)  # k // win without an integer division
    col = k - row * win
    x0 = int(o[0]) + col
    y0 = int(o[1]) + row
    xa = _reflect(x0, w)
    xb = _reflect(x0 + 1, w)
    ra = off + _reflect(y0, h) * w
    rb = off + _reflect(y0 + 1, h) * w
    a = img[ra + xa]
    b = img[ra + xb]
    c = img[rb + xa]
    d = img[rb + xb]
    top = a + o[2] * (b - a)
    return top + o[3] * (c + o[2] * (d - c) - top)


@wp.func
def _window_grad(img: wp.array(dtype=float), off: int, w: int, h: int, o: wp.vec4, k: int, win: int,
                 inv_win: float, inside: bool) -> float:
    """Pixel k of a window of a gradient level as ``_window_px``, but zero past the level's border: OpenCV's LK
    pads its derivative levels with zeros (a mirrored image's x or y gradient changes sign, so reflecting the
    gradients as the images are put wrong-signed terms into G and b). ``inside``: the window and its bilinear
    neighbours lie inside the level (the same for every pixel of it), so no pixel needs the border."""
    row = int((float(k) + 0.5) * inv_win)
    col = k - row * win
    x0 = int(o[0]) + col
    y0 = int(o[1]) + row
    a = float(0.0)
    b = float(0.0)
    c = float(0.0)
    d = float(0.0)
    if inside:
        i = off + y0 * w + x0
        a = img[i]
        b = img[i + 1]
        c = img[i + w]
        d = img[i + w + 1]
    else:
        ra = off + wp.clamp(y0, 0, h - 1) * w
        rb = off + wp.clamp(y0 + 1, 0, h - 1) * w
        xa = wp.clamp(x0, 0, w - 1)
        xb = wp.clamp(x0 + 1, 0, w - 1)
        mxa = wp.where(x0 >= 0 and x0 < w, 1.0, 0.0)
        mxb = wp.where(x0 + 1 >= 0 and x0 + 1 < w, 1.0, 0.0)
        mya = wp.where(y0 >= 0 and y0 < h, 1.0, 0.0)
        myb = wp.where(y0 + 1 >= 0 and y0 + 1 < h, 1.0, 0.0)
        a = img[ra + xa] * mxa * mya
        b = img[ra + xb] * mxb * mya
        c = img[rb + xa] * mxa * myb
        d = img[rb + xb] * mxb * myb
    top = a + o[2] * (b - a)
    return top + o[3] * (c + o[2] * (d - c) - top)


@wp.func
def _window_inside(o: wp.vec4, win: int, w: int, h: int) -> bool:
    """Whether a window at origin o (``_window_origin``) and its bilinear neighbours lie inside a w x h level."""
    return o[0] >= 0.0 and o[1] >= 0.0 and o[0] + float(win) <= float(w - 1) and o[1] + float(win) <= float(h - 1)


_WINDOW_SLOT_SNIPPET = """
#if defined(__CUDA_ARCH__)
    __shared__ float4 slots[SLOTS * WP_TILE_BLOCK_DIM];
    float4* s = &slots[slot * WP_TILE_BLOCK_DIM + threadIdx.x];
    if (store)
        *s = make_float4(v[0], v[1], v[2], v[3]);
    const float4 r = *s;
    return wp::vec4(r.x, r.y, r.z, r.w);
#else
    return v;
#endif
"""


@wp.func
def _cache_sample(img: wp.array(dtype=float), gx: wp.array(dtype=float), gy: wp.array(dtype=float), off: int, w: int,
                  h: int, o: wp.vec4, k: int, n: int, win: int, inv_win: float, inside: bool) -> wp.vec4:
    """(pixel, gx, gy, offset from the window's corner) of pixel k of a window with origin o; past the window
    (k >= n) the gradients weigh 0 and the offset is 0 (a lane's unused slot reads the corner)."""
    valid = wp.where(k < n, 1.0, 0.0)
    row = int((float(k) + 0.5) * inv_win)
    at = wp.where(k < n, row * w + k - row * win, 0)
    vx = _window_grad(gx, off, w, h, o, k, win, inv_win, inside and k < n) * valid
    vy = _window_grad(gy, off, w, h, o, k, win, inv_win, inside and k < n) * valid
    return wp.vec4(_window_px(img, off, w, h, o, k, win, inv_win), vx, vy, float(at))


def _window_slots(cache: int):
    """A lane's ``cache`` slots of (pixel, gx, gy, offset) in the block's shared memory: ``f(store, slot, v)``
    writes v into the slot when ``store`` is 1 and returns the slot. Each lane only touches its own slots, so no
    barrier is needed."""

    @wp.func_native(_WINDOW_SLOT_SNIPPET.replace("SLOTS", str(cache)))
    def window_slot(store: int, slot: int, v: wp.vec4) -> wp.vec4: ...

    return window_slot


def _make_lk_track(slots: int, min_blocks: int | None = None):
    """The LK kernel. With ``slots`` > 0 (CUDA): each lane keeps ``slots`` window pixels with their gradients in the
    block's shared memory, for windows of at most ``slots`` x LK_LANES pixels; with 0 (the CPU device's one lane per
    block, or a wider window), every iteration samples the previous window again. ``min_blocks``: the blocks of
    LK_LANES an SM must hold at once (CUDA's launch bounds; None: none). Each build holds only its own path: a kernel
    is given the registers of its heaviest path, and the paths together took 240 per lane, two blocks an SM."""
    cached = slots > 0
    window_slot = _window_slots(max(slots, 1))
    bounds = None if min_blocks is None else (LK_LANES, min_blocks)

    @wp.kernel(module="unique", enable_backward=False, launch_bounds=bounds)
    def _lk_track(prev: wp.array(dtype=float), prev_gx: wp.array(dtype=float), prev_gy: wp.array(dtype=float),
                  cur: wp.array(dtype=float), offs: wp.array(dtype=int), ws: wp.array(dtype=int),
                  hs: wp.array(dtype=int), levels: int, fine_win: int, coarse_win: int, coarse_from: int,
                  iterations: int, eps: float, coarse_eps: float, min_eig: float,
                  max_error: float, pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32),
                  guess: wp.array(dtype=wp.vec2), use_guess: wp.array(dtype=wp.int32),
                  only: wp.array(dtype=wp.int32), out_pts: wp.array(dtype=wp.vec2),
                  status: wp.array(dtype=wp.int32), error: wp.array(dtype=float)):
        """Bouguet's pyramidal LK: per level, the window's spatial gradient matrix from the previous image, then
        Newton steps on the temporal difference; the lanes of a block share the window, block sums combine them.

        The time goes into the iterations of the slowest features (30 per level at most, as OpenCV), so each
        iteration is kept short: the window's sub-pixel fractions are computed once per iteration, not per pixel,
        each lane keeps its pixels of the previous window and their gradients in shared memory (on CUDA), and its
        loads of the current window carry no branch, so they are all in flight together. The gradient pass and a
        window at the level's border take one slot at a time: they are rare, and their loads in flight would cost
        every iteration registers."""
        f, lane = wp.tid()
        if f >= count[0]:
            return  # the launch covers every slot; the live count is on the device (the whole block leaves)
        if only.shape[0] > 0:
            if only[f] == 0:
                return  # a slot whose answer nobody reads (its outputs are left as they were)
        nl = wp.block_dim()
        p0 = pts[f]
        # the guess carried down the pyramid (current level units): from where the camera motion predicts the
        # track when use_guess is set (NaN there: not found, the track is lost), else zero
        q0 = guess[f]
        use = use_guess[0] == 1
        lost = use and (wp.isnan(q0[0]) or wp.isnan(q0[1]))
        g = wp.where(use and not lost, (q0 - p0) / wp.pow(2.0, float(levels - 1)), wp.vec2(0.0, 0.0))
        ok = wp.where(lost, 0, 1)
        abs_sum = float(0.0)  # the last iteration's sum of absolute differences over the window
        sums = int(0)  # block sums so far (their shared buffers alternate)
        eps2 = eps * eps
        coarse_eps2 = coarse_eps * coarse_eps
        n = int(0)
        for li in range(levels):
            lvl = levels - 1 - li
            # the window: coarse_win on the levels from coarse_from up, fine_win below
            win = wp.where(lvl >= coarse_from, coarse_win, fine_win)
            n = win * win
            r = float(win - 1) * 0.5
            inv_win = 1.0 / float(win)
            used = (n + nl - 1) // nl  # the slots a lane's share of the window takes
            off = offs[lvl]
            w = ws[lvl]
            h = hs[lvl]
            p = p0 * (1.0 / float(1 << lvl))
            o = _window_origin(p[0] - r, p[1] - r)
            inside = _window_inside(o, win, w, h)
            # spatial gradient matrix over the window in the previous image (its pixels kept on the way)
            acc = wp.vec3(0.0, 0.0, 0.0)
            if wp.static(cached):
                for j in range(used):
                    c = _cache_sample(prev, prev_gx, prev_gy, off, w, h, o, lane + j * nl, n, win, inv_win, inside)
                    window_slot(1, j, c)
                    acc += wp.vec3(c[1] * c[1], c[1] * c[2], c[2] * c[2])
                for j in range(used, slots):
                    window_slot(1, j, wp.vec4(0.0))  # weighs nothing, reads the window's corner
            else:
                k = lane
                while k < n:
                    vx = _window_grad(prev_gx, off, w, h, o, k, win, inv_win, inside)
                    vy = _window_grad(prev_gy, off, w, h, o, k, win, inv_win, inside)
                    acc += wp.vec3(vx * vx, vx * vy, vy * vy)
                    k += nl
            G = block_sum3(acc, sums)
            sums += 1
            det = G[0] * G[2] - G[1] * G[1]
            lam = 0.5 * (G[0] + G[2]) - wp.sqrt(wp.max(0.25 * (G[0] - G[2]) * (G[0] - G[2]) + G[1] * G[1], 0.0))
            # too little texture in the window: on the finest level the track is lost; on a coarser one (a
            # wide high-pass leaves little there) the guess carries down unchanged, as OpenCV's LK does
            weak = lam / float(n) < min_eig or wp.abs(det) < 1.0e-12
            if weak and lvl == 0:
                ok = 0
            inv_det = 1.0 / wp.where(weak, 1.0, det)
            nu = wp.vec2(0.0, 0.0)
            last_step = wp.vec2(0.0, 0.0)
            done = int(0)
            tol2 = wp.where(lvl > 0, coarse_eps2, eps2)
            if ok == 0 or weak:
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
                if wp.static(cached):
                    if _window_inside(oq, win, w, h):
                        # the window and its bilinear neighbours lie inside the level (the same answer in every
                        # lane): each pixel is its slot's offset from the window's corner, four loads, three lerps;
                        # the slots in groups of four, each group's loads in flight together
                        corner = off + int(oq[1]) * w + int(oq[0])
                        for group in range((used + 3) // 4):
                            for jj in range(4):
                                j = group * 4 + jj
                                c = window_slot(0, j, wp.vec4(0.0))
                                i = corner + int(c[3])
                                p00 = cur[i]
                                p01 = cur[i + 1]
                                p10 = cur[i + w]
                                p11 = cur[i + w + 1]
                                top = p00 + oq[2] * (p01 - p00)
                                diff = (c[0] - top - oq[3] * (p10 + oq[2] * (p11 - p10) - top)) * wp.where(
                                    lane + j * nl < n, 1.0, 0.0)
                                bacc += wp.vec3(diff * c[1], diff * c[2], wp.abs(diff))
                    else:
                        for j in range(used):
                            k = lane + j * nl
                            c = window_slot(0, j, wp.vec4(0.0))
                            diff = (c[0] - _window_px(cur, off, w, h, oq, k, win, inv_win)) * wp.where(
                                k < n, 1.0, 0.0)
                            bacc += wp.vec3(diff * c[1], diff * c[2], wp.abs(diff))
                else:
                    k = lane
                    while k < n:
                        diff = (_window_px(prev, off, w, h, o, k, win, inv_win)
                                - _window_px(cur, off, w, h, oq, k, win, inv_win))
                        vx = _window_grad(prev_gx, off, w, h, o, k, win, inv_win, inside)
                        vy = _window_grad(prev_gy, off, w, h, o, k, win, inv_win, inside)
                        bacc += wp.vec3(diff * vx, diff * vy, wp.abs(diff))
                        k += nl
                b = block_sum3(bacc, sums)
                sums += 1
                abs_sum = b[2]
                step = wp.vec2(G[2] * b[0] - G[1] * b[1], G[0] * b[1] - G[1] * b[0]) * inv_det
                nu = nu + step
                if wp.dot(step, step) < tol2:
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

    return _lk_track


# each lane keeps 8 pixels of a window (a multiple of 4, the slots' groups): with 128 lanes, windows up to 32 x 32
# (the default 21 and 31 px)
LK_SLOTS = 8
_lk_track_slots = _make_lk_track(LK_SLOTS)
_lk_track_resampled = _make_lk_track(0)


def lk_track(prev: wp.array, prev_gx: wp.array, prev_gy: wp.array, cur: wp.array, offs: wp.array, ws: wp.array,
             hs: wp.array, levels: int, win: int, iterations: int, eps: float, min_eig: float, max_error: float,
             pts: wp.array, count: wp.array, guess: wp.array, use_guess: wp.array, out_pts: wp.array,
             status: wp.array, error: wp.array, device, coarse_win: int | None = None,
             coarse_from: int | None = None, coarse_eps: float | None = None, only: wp.array | None = None) -> None:
    """Track ``pts`` (the first ``count[0]`` of them; every slot is launched) from the ``prev`` pyramid into
    ``cur``, from ``guess`` where ``use_guess[0]`` is 1 (NaN: lost), else from where they were: ``out_pts``,
    ``status`` (1: tracked) and ``error`` (the window's mean absolute difference). The window is ``win`` px,
    ``coarse_win`` on the levels from ``coarse_from`` up (None: ``win`` throughout). LK stops on a level when a
    step is shorter than ``eps`` px, on the levels above full resolution ``coarse_eps`` px of that level (None:
    ``eps``): a coarse level only has to start the next one inside its reach, and the finest level's steps
    settle the answer (docs/benchmarks.md, session 16). ``only`` (int32 per slot): track just the slots where it is
    non-zero, leaving the others' outputs as they were (None: every slot)."""
    if only is None:
        only = wp.empty(0, dtype=wp.int32, device=device)
    coarse_win = win if coarse_win is None else coarse_win
    coarse_from = levels if coarse_from is None else coarse_from
    coarse_eps = eps if coarse_eps is None else coarse_eps
    widest = max(win, coarse_win if coarse_win > win and coarse_from < levels else win)
    kernel = _lk_track_slots if wp.get_device(device).is_cuda and widest * widest <= LK_SLOTS * LK_LANES \
        else _lk_track_resampled
    wp.launch_tiled(kernel, dim=[pts.shape[0]], inputs=[
        prev, prev_gx, prev_gy, cur, offs, ws, hs, levels, win, coarse_win, coarse_from, iterations, eps, coarse_eps,
        min_eig, max_error, pts, count,
        guess, use_guess, only, out_pts, status, error], block_dim=LK_LANES, device=device)
