"""Where each track starts LK in a new frame when the camera motion is known (``FrameMotion``): its projection
at its depth, or, without one, the best ZNCC match of its patch along its epipolar line (a sweep of inverse
depth on pyramid level SWEEP_LEVEL). The same steps as ``frontend.epipolar`` (numpy), on the device."""

from __future__ import annotations

import numpy as np
import warp as wp

from lapreco_hil.frontend import epipolar
from lapreco_hil.frontend.warp.sampling import bilinear

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

SWEEP_SAMPLES = 64
SWEEP_PATCH = epipolar.SWEEP_PATCH_PX
SWEEP_HALF = (SWEEP_PATCH - 1) // 2
NEIGHBOURS = wp.constant(epipolar.NEIGHBOURS)
_neighbour_vec = wp.types.vector(length=epipolar.NEIGHBOURS, dtype=float)


@wp.func
def _project(K: wp.vec4, R: wp.mat33, t: wp.vec3, uv: wp.vec2, z: float) -> wp.vec2:
    """Pixel uv at depth z of one pinhole camera -> pixel of the other (K: fx, fy, cx, cy); NaN behind it."""
    ray = wp.vec3((uv[0] - K[2]) / K[0], (uv[1] - K[3]) / K[1], 1.0)
    p = R * (ray * z) + t
    if p[2] <= 1.0e-9:
        return wp.vec2(wp.nan, wp.nan)
    return wp.vec2(K[0] * p[0] / p[2] + K[2], K[1] * p[1] / p[2] + K[3])


@wp.func
def _rotation(T: wp.mat44) -> wp.mat33:
    return wp.mat33(T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])


@wp.func
def _translation(T: wp.mat44) -> wp.vec3:
    return wp.vec3(T[0, 3], T[1, 3], T[2, 3])


@wp.kernel
def _predict(pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), depth: wp.array(dtype=float),
             K: wp.vec4, motion: wp.array(dtype=wp.mat44), guess: wp.array(dtype=wp.vec2)):
    """Tracks with a depth: their projection; the others NaN until the sweep finds them."""
    f = wp.tid()
    if f >= count[0]:
        return
    d = depth[f]
    if d > 0.0:
        T = motion[0]
        guess[f] = _project(K, _rotation(T), _translation(T), pts[f], d)
    else:
        guess[f] = wp.vec2(wp.nan, wp.nan)


# The lanes of one warp share a track's search for its nearest tracks with a depth: each lane scans a stride of
# the frame's tracks, then NEIGHBOURS rounds of a warp-wide minimum merge the lanes' lists (shuffles only: no
# shared memory, no barrier). On the CPU a tiled launch has one lane, which scans them all.
BORROW_LANES = 32
_WARP_MIN2_SNIPPET = """
#if defined(__CUDA_ARCH__)
    static_assert(WP_TILE_BLOCK_DIM == 32, "one warp per block");
    auto s = v;
    float* c = reinterpret_cast<float*>(&s);
    float a = c[0], b = c[1];
    #pragma unroll
    for (int o = 16; o > 0; o >>= 1) {
        float oa = __shfl_xor_sync(0xffffffffu, a, o);
        float ob = __shfl_xor_sync(0xffffffffu, b, o);
        if (oa < a || (oa == a && ob < b)) { a = oa; b = ob; }
    }
    c[0] = a;
    c[1] = b;
    return s;
#else
    static_assert(WP_TILE_BLOCK_DIM == 1, "warp minima on the CPU need one lane per block");
    return v;
#endif
"""


@wp.func_native(_WARP_MIN2_SNIPPET)
def _warp_min2(v: wp.vec2) -> wp.vec2: ...


@wp.func
def _settled_depth(p: wp.vec2, K: wp.vec4, T: wp.mat44, inverse_range: wp.vec2, short_px: float) -> float:
    """The range's far depth where pixel p's epipolar segment over the whole range stays within ``short_px`` of
    its middle (``epipolar._settle_short_lines``), else 0."""
    ray = _rotation(T) * wp.vec3((p[0] - K[2]) / K[0], (p[1] - K[3]) / K[1], 1.0)
    a = wp.vec3(K[0] * ray[0] + K[2] * ray[2], K[1] * ray[1] + K[3] * ray[2], ray[2])
    t = _translation(T)
    b = wp.vec3(K[0] * t[0] + K[2] * t[2], K[1] * t[1] + K[3] * t[2], t[2])
    z_near = 1.0 / inverse_range[0]
    z_far = 1.0 / inverse_range[1]
    mid = 2.0 / (inverse_range[0] + inverse_range[1])
    w_mid = mid * a[2] + b[2]
    w_near = z_near * a[2] + b[2]
    w_far = z_far * a[2] + b[2]
    out = float(0.0)
    if w_mid > 1.0e-9 and w_near > 1.0e-9 and w_far > 1.0e-9:
        line = wp.length(wp.vec2(a[0] * b[2] - b[0] * a[2], a[1] * b[2] - b[1] * a[2]))
        worst = wp.max(wp.abs(z_near - mid) / w_near, wp.abs(z_far - mid) / w_far)
        if line * worst / w_mid <= short_px:
            out = z_far
    return out


@wp.kernel(module="unique", module_options={"block_dim": BORROW_LANES}, enable_backward=False)
def _borrow_and_settle(pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), own: wp.array(dtype=float),
                       reach_sq: float, K: wp.vec4, motion: wp.array(dtype=wp.mat44),
                       inverse_range: wp.array(dtype=wp.vec2), short_px: float, depth: wp.array(dtype=float)):
    """``epipolar.borrow_depths`` then ``settle_short_lines`` per track (a warp each): its own depth (> 0; < 0:
    none, nothing to take: 0); else the median of the own depths of its NEIGHBOURS nearest tracks within reach
    (ties by index); else the range's far depth where its epipolar segment is short; else 0 (swept)."""
    f, lane = wp.tid()
    n = count[0]
    if f >= n:
        return
    d = own[f]
    if d != 0.0:
        if lane == 0:
            depth[f] = wp.max(d, 0.0)  # (< 0: the host found none to take)
        return
    p = pts[f]
    big = float(1.0e30)
    dist = _neighbour_vec()
    index = _neighbour_vec()
    for i in range(NEIGHBOURS):
        dist[i] = big
        index[i] = big
    j = lane
    while j < n:
        z = own[j]
        if z > 0.0:
            q = pts[j] - p
            e = wp.dot(q, q)
            k = float(j)
            if e <= reach_sq and e < dist[NEIGHBOURS - 1]:
                # insert (e, j) into the lane's sorted list (compare-and-swap down it)
                for i in range(NEIGHBOURS):
                    if e < dist[i] or (e == dist[i] and k < index[i]):
                        te = dist[i]
                        tk = index[i]
                        dist[i] = e
                        index[i] = k
                        e = te
                        k = tk
        j += wp.block_dim()
    # the warp's NEIGHBOURS nearest: each round takes the smallest of the lanes' list heads
    near = _neighbour_vec()
    m = int(0)
    head = int(0)
    for r in range(NEIGHBOURS):
        mine = wp.vec2(big, big)
        for i in range(NEIGHBOURS):
            if i == head:
                mine = wp.vec2(dist[i], index[i])
        best = _warp_min2(mine)
        near[r] = big
        if best[0] < big:
            if mine[0] == best[0] and mine[1] == best[1]:
                head += 1
            near[r] = own[int(best[1])]
            m += 1
    if lane != 0:
        return
    if m > 0:
        # the median of the m depths found (sorted; the unused slots stay at the end)
        for r in range(NEIGHBOURS - 1):
            for c in range(NEIGHBOURS - 1 - r):
                if near[c] > near[c + 1]:
                    swap = near[c]
                    near[c] = near[c + 1]
                    near[c + 1] = swap
        lo = (m - 1) // 2
        hi = m // 2
        zl = float(0.0)
        zh = float(0.0)
        for i in range(NEIGHBOURS):
            if i == lo:
                zl = near[i]
            if i == hi:
                zh = near[i]
        depth[f] = 0.5 * (zl + zh)
    else:
        depth[f] = _settled_depth(p, K, motion[0], inverse_range[0], short_px)


@wp.kernel
def _sweep_scores(prev: wp.array(dtype=float), cur: wp.array(dtype=float), off: int, w: int, h: int, scale: float,
                  pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32), depth: wp.array(dtype=float),
                  K: wp.vec4, motion: wp.array(dtype=wp.mat44), inverse_range: wp.array(dtype=wp.vec2),
                  scores: wp.array2d(dtype=float), cand: wp.array2d(dtype=wp.vec2)):
    """One thread per (track without depth, inverse-depth sample): ZNCC of the track's patch in the previous
    level image against the current one at the sample's projection (-1 where the patch leaves the level)."""
    f, s = wp.tid()
    if f >= count[0] or depth[f] > 0.0:
        return
    inv_near = inverse_range[0][0]
    inv_far = inverse_range[0][1]
    inv = inv_near + (inv_far - inv_near) * float(s) / float(SWEEP_SAMPLES - 1)
    T = motion[0]
    c = _project(K, _rotation(T), _translation(T), pts[f], 1.0 / inv)
    cand[f, s] = c
    q = c * scale
    r = float(SWEEP_HALF)
    if not (q[0] >= r and q[1] >= r and q[0] <= float(w - 1) - r and q[1] <= float(h - 1) - r):
        scores[f, s] = -1.0
        return
    p = pts[f] * scale
    sa = float(0.0)
    sb = float(0.0)
    saa = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    for j in range(SWEEP_PATCH):
        for i in range(SWEEP_PATCH):
            dx = float(i - SWEEP_HALF)
            dy = float(j - SWEEP_HALF)
            a = bilinear(prev, off, w, h, p[0] + dx, p[1] + dy)
            b = bilinear(cur, off, w, h, q[0] + dx, q[1] + dy)
            sa += a
            sb += b
            saa += a * a
            sbb += b * b
            sab += a * b
    n = float(SWEEP_PATCH * SWEEP_PATCH)
    va = saa - sa * sa / n
    vb = sbb - sb * sb / n
    scores[f, s] = (sab - sa * sb / n) / (wp.sqrt(wp.max(va * vb, 0.0)) + 1.0e-6)


@wp.kernel
def _sweep_pick(scores: wp.array2d(dtype=float), cand: wp.array2d(dtype=wp.vec2), count: wp.array(dtype=wp.int32),
                depth: wp.array(dtype=float), scale: float, min_score: float, margin: float, radius: float,
                guess: wp.array(dtype=wp.vec2), found: wp.array(dtype=wp.int32)):
    """Per track without depth: the best sample where it is clear (above min_score, and the best score more
    than ``radius`` level pixels from it at least ``margin`` lower; ``found`` 1); else the line's far end
    (``epipolar.unclear_start``; ``found`` 0)."""
    f = wp.tid()
    if f >= count[0] or depth[f] > 0.0:
        return
    best = int(0)
    for s in range(SWEEP_SAMPLES):
        if scores[f, s] > scores[f, best]:
            best = s
    cb = cand[f, best]
    second = float(-1.0)
    for s in range(SWEEP_SAMPLES):
        if wp.length(cand[f, s] - cb) * scale > radius:
            second = wp.max(second, scores[f, s])
    short = wp.length(cand[f, 0] - cand[f, SWEEP_SAMPLES - 1]) * scale < radius
    b = scores[f, best]
    if b > min_score and (b - second > margin or short):
        guess[f] = cb
        found[f] = 1
    else:
        guess[f] = cand[f, SWEEP_SAMPLES - 1]
        found[f] = 0


@wp.kernel
def _forward_backward(depth: wp.array(dtype=float), prev_pts: wp.array(dtype=wp.vec2), back: wp.array(dtype=wp.vec2),
                      back_status: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), max_px: float,
                      status: wp.array(dtype=wp.int32), searched: wp.array(dtype=wp.int32)):
    """A track found along its epipolar line (no depth) stays only if LK back from where it landed returns
    within ``max_px`` of where it was; ``searched`` marks those that stay (their drift reference starts anew)."""
    f = wp.tid()
    searched[f] = 0
    if f >= count[0] or depth[f] > 0.0 or status[f] == 0:
        return
    if back_status[f] == 0 or wp.length(back[f] - prev_pts[f]) >= max_px:
        status[f] = 0
    else:
        searched[f] = 1


@wp.kernel
def _swept_and_tracked(depth: wp.array(dtype=float), status: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                       out: wp.array(dtype=wp.int32)):
    """1 for the tracks the forward-backward check reads (swept: no depth; tracked by LK), else 0."""
    f = wp.tid()
    out[f] = wp.where(f < count[0] and depth[f] <= 0.0 and status[f] != 0, 1, 0)


# --- host wrappers: a device and preallocated outputs --------------------------------------------------------
def forward_backward(depth: wp.array, prev_pts: wp.array, back: wp.array, back_status: wp.array, count: wp.array,
                     status: wp.array, searched: wp.array, device) -> None:
    """``status`` <- 0 for swept tracks that fail the forward-backward check; ``searched`` <- 1 for those kept."""
    wp.launch(_forward_backward, dim=depth.shape[0], inputs=[depth, prev_pts, back, back_status, count,
                                                              float(epipolar.FORWARD_BACKWARD_PX), status, searched],
              device=device)

def swept_and_tracked(depth: wp.array, status: wp.array, count: wp.array, out: wp.array, device) -> None:
    """``out`` <- 1 for the slots ``forward_backward`` will judge (LK back runs for those only), else 0."""
    wp.launch(_swept_and_tracked, dim=depth.shape[0], inputs=[depth, status, count, out], device=device)


def borrow_and_settle(pts: wp.array, count: wp.array, own: wp.array, K, motion: wp.array, inverse_range: wp.array,
                      image_size: tuple[int, int], depth: wp.array, device) -> None:
    """``depth`` <- each of the first ``count[0]`` tracks' start depth from ``own`` (its landmark's; 0: none, take
    one; < 0: none, none to take) as
    ``epipolar.start_depths`` makes it after its small-motion test: borrowed from the nearest tracks with one,
    else the far depth where its epipolar segment is short, else 0 (swept along its line)."""
    Kv = wp.vec4(float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2]))
    reach = epipolar.NEIGHBOUR_RADIUS * max(image_size)
    wp.launch_tiled(_borrow_and_settle, dim=[pts.shape[0]], inputs=[
        pts, count, own, float(reach * reach), Kv, motion, inverse_range, float(epipolar.SHORT_LINE_PX), depth],
        block_dim=BORROW_LANES, device=device)


def motion_params(T_cur_prev, depth_range_m) -> tuple[np.ndarray, np.ndarray]:
    """A frame's motion as ``predict_starts`` reads it from the device: (T_cur_prev as one float32 4x4, the
    inverse depth range (1 / near, 1 / far) as one float32 pair)."""
    near, far = depth_range_m
    return (np.asarray(T_cur_prev, np.float32).reshape(1, 4, 4),
            np.array([[1.0 / near, 1.0 / far]], np.float32))


def predict_starts(prev_pyr: wp.array, cur_pyr: wp.array, level_off: int, level_w: int, level_h: int, level: int,
                   pts: wp.array, count: wp.array, depth: wp.array, K, motion: wp.array, inverse_range: wp.array,
                   scores: wp.array, cand: wp.array, guess: wp.array, found: wp.array, device) -> None:
    """``guess`` <- where each of the first ``count[0]`` tracks starts LK: projected at ``depth`` (> 0), else
    swept along its epipolar line on pyramid ``level`` (``scores``, ``cand``: (n, SWEEP_SAMPLES) scratch);
    where the sweep finds no clear match, the line's far end (``found`` 0). K is the 3x3 intrinsics of both
    frames (one camera); the motion is read from the device (``motion``: T_cur_prev, ``inverse_range``: 1 / near,
    1 / far; ``motion_params``), so a captured graph replays these launches for any frame's motion."""
    Kv = wp.vec4(float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2]))
    n = pts.shape[0]
    wp.launch(_predict, dim=n, inputs=[pts, count, depth, Kv, motion, guess], device=device)
    scale = 1.0 / (1 << level)
    wp.launch(_sweep_scores, dim=(n, SWEEP_SAMPLES), inputs=[
        prev_pyr, cur_pyr, level_off, level_w, level_h, scale, pts, count, depth, Kv, motion, inverse_range,
        scores, cand], device=device)
    wp.launch(_sweep_pick, dim=n, inputs=[scores, cand, count, depth, scale, epipolar.MIN_SCORE, epipolar.MARGIN,
                                           epipolar.SECOND_RADIUS, guess, found], device=device)


@wp.kernel
def _prior_starts(H: wp.array(dtype=wp.mat33), pts: wp.array(dtype=wp.vec2), count: wp.array(dtype=wp.int32),
                  guess: wp.array(dtype=wp.vec2)):
    t = wp.tid()
    if t >= count[0]:
        return
    p = pts[t]
    q = H[0] * wp.vec3(p[0], p[1], 1.0)
    if wp.abs(q[2]) < 1.0e-9:
        guess[t] = p  # (a point the motion sends to infinity starts where it was)
    else:
        guess[t] = wp.vec2(q[0] / q[2], q[1] / q[2])


def prior_starts(H: wp.array, pts: wp.array, count: wp.array, guess: wp.array, device) -> None:
    """``guess`` <- where the frame's image motion ``H[0]`` (a homography in pixels, from the host's dense
    alignment: ``frontend.global_motion``) puts each of the first ``count[0]`` tracks, on a frame without a pose
    prediction. H is read from the device, so a captured graph replays this launch for any frame's motion."""
    wp.launch(_prior_starts, dim=pts.shape[0], inputs=[H, pts, count, guess], device=device)
