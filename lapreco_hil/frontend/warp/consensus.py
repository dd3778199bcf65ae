"""The tracks' consensus on a frame without a pose prediction, on the device (the host's is
``frontend.consensus``): a RANSAC homography of the tracks' LK steps (hypotheses from four tracks each, drawn on
the device, scored in parallel, the best kept), then the tracks off it, or lost, tracked again from where it puts
them, each keeping the position that agrees better with it (``consensus.py`` says why and when).

Coordinates are normalised (centre, half the larger side) so that a four-point homography is well conditioned in
float32. A graph replays every kernel: the hypotheses are drawn from a fixed seed per hypothesis and frame count
on the device."""

from __future__ import annotations

import warp as wp

from lapreco_hil.frontend.warp.block_sum import block_sum3
from lapreco_hil.frontend.consensus import CLOSER_PX, MIN_INLIER_SHARE, MIN_TRACKS, RETRACK_MAX_LEVEL

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

HYPOTHESES = 256
RETRACK_LEVELS = RETRACK_MAX_LEVEL + 1  # LK's levels with full resolution (the Warp kernel's count)
SCORE_LANES = 128  # lanes per hypothesis's block in the scoring kernel
DRAWS = 24  # random slots tried per hypothesis for its four distinct tracked ones
_SEED = 20261125


@wp.func
def _square_to_quad(p0: wp.vec2, p1: wp.vec2, p2: wp.vec2, p3: wp.vec2) -> wp.mat33:
    """The homography taking the unit square's corners (0,0), (1,0), (1,1), (0,1) to p0..p3 (Heckbert's
    closed form)."""
    dx1 = p1[0] - p2[0]
    dx2 = p3[0] - p2[0]
    dx3 = p0[0] - p1[0] + p2[0] - p3[0]
    dy1 = p1[1] - p2[1]
    dy2 = p3[1] - p2[1]
    dy3 = p0[1] - p1[1] + p2[1] - p3[1]
    det = dx1 * dy2 - dx2 * dy1
    g = float(0.0)
    h = float(0.0)
    if wp.abs(det) > 1.0e-12:
        g = (dx3 * dy2 - dx2 * dy3) / det
        h = (dx1 * dy3 - dx3 * dy1) / det
    return wp.mat33(p1[0] - p0[0] + g * p1[0], p3[0] - p0[0] + h * p3[0], p0[0],
                    p1[1] - p0[1] + g * p1[1], p3[1] - p0[1] + h * p3[1], p0[1],
                    g, h, 1.0)


@wp.func
def _apply(H: wp.mat33, p: wp.vec2) -> wp.vec2:
    q = H * wp.vec3(p[0], p[1], 1.0)
    if wp.abs(q[2]) < 1.0e-9:
        return wp.vec2(wp.nan, wp.nan)
    return wp.vec2(q[0] / q[2], q[1] / q[2])


@wp.func
def _normalised(p: wp.vec2, frame: wp.vec3) -> wp.vec2:
    return wp.vec2((p[0] - frame[0]) / frame[2], (p[1] - frame[1]) / frame[2])


@wp.func
def _pixel(p: wp.vec2, frame: wp.vec3) -> wp.vec2:
    return wp.vec2(p[0] * frame[2] + frame[0], p[1] * frame[2] + frame[1])


@wp.func
def _quad_area(a: wp.vec2, b: wp.vec2, c: wp.vec2, d: wp.vec2) -> float:
    """Twice the signed area of the quad a, b, c, d (shoelace)."""
    return (a[0] * b[1] - b[0] * a[1]) + (b[0] * c[1] - c[0] * b[1]) + (c[0] * d[1] - d[0] * c[1]) \
        + (d[0] * a[1] - a[0] * d[1])


@wp.kernel
def _hypotheses(before: wp.array(dtype=wp.vec2), after: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32),
                count: wp.array(dtype=wp.int32), frame_no: wp.array(dtype=wp.int32), frame: wp.vec3,
                H_out: wp.array(dtype=wp.mat33), valid: wp.array(dtype=wp.int32), inliers: wp.array(dtype=wp.int32)):
    """Hypothesis h: four distinct tracked slots drawn at random, the homography of their steps (normalised
    coordinates); invalid when four were not found or their quads are degenerate or folded."""
    h = wp.tid()
    inliers[h] = 0
    valid[h] = 0
    n = count[0]
    if n < MIN_TRACKS:
        return
    state = wp.rand_init(_SEED + (frame_no[0] % 65536) * HYPOTHESES, h)
    s0 = int(-1)
    s1 = int(-1)
    s2 = int(-1)
    s3 = int(-1)
    found = int(0)
    for _ in range(DRAWS):
        if found < 4:
            s = wp.randi(state, 0, n)
            if status[s] == 1 and s != s0 and s != s1 and s != s2:
                if found == 0:
                    s0 = s
                elif found == 1:
                    s1 = s
                elif found == 2:
                    s2 = s
                else:
                    s3 = s
                found += 1
    if found < 4:
        return
    a0 = _normalised(before[s0], frame)
    a1 = _normalised(before[s1], frame)
    a2 = _normalised(before[s2], frame)
    a3 = _normalised(before[s3], frame)
    b0 = _normalised(after[s0], frame)
    b1 = _normalised(after[s1], frame)
    b2 = _normalised(after[s2], frame)
    b3 = _normalised(after[s3], frame)
    area_a = _quad_area(a0, a1, a2, a3)
    area_b = _quad_area(b0, b1, b2, b3)
    # nearly collinear picks, or a step that folds the quad over: no homography of a scope's view
    if wp.abs(area_a) < 1.0e-3 or area_a * area_b <= 0.0:
        return
    A = _square_to_quad(a0, a1, a2, a3)
    if wp.abs(wp.determinant(A)) < 1.0e-9:
        return
    H_out[h] = _square_to_quad(b0, b1, b2, b3) * wp.inverse(A)
    valid[h] = 1


@wp.kernel
def _score(before: wp.array(dtype=wp.vec2), after: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32),
           count: wp.array(dtype=wp.int32), frame: wp.vec3, tolerance_px: float, H: wp.array(dtype=wp.mat33),
           valid: wp.array(dtype=wp.int32), inliers: wp.array(dtype=wp.int32), tracked: wp.array(dtype=wp.int32)):
    """Hypothesis h's inliers (tracked slots whose step agrees within ``tolerance_px``), one block per hypothesis:
    each lane counts a stride of slots and a block sum adds them (an atomic per inlier on 256 counters made this
    the front-end's second-costliest kernel, docs/benchmarks.md, session 21). Block 0 also counts the tracked
    slots."""
    h, lane = wp.tid()
    if h != 0 and valid[h] == 0:
        return  # the whole block leaves: no block sum is left waiting
    nl = wp.block_dim()
    n = count[0]
    use = valid[h] == 1
    Hh = H[h]
    agree = float(0.0)
    live = float(0.0)
    t = lane
    while t < n:
        if status[t] == 1:
            live += 1.0
            if use:
                q = _apply(Hh, _normalised(before[t], frame))
                if wp.length(_pixel(q, frame) - after[t]) <= tolerance_px:
                    agree += 1.0
        t += nl
    sums = block_sum3(wp.vec3(agree, live, 0.0), 0)
    if lane == 0:
        inliers[h] = int(sums[0] + 0.5)
        if h == 0:
            tracked[0] = int(sums[1] + 0.5)


@wp.kernel
def _rank(valid: wp.array(dtype=wp.int32), inliers: wp.array(dtype=wp.int32), ranked: wp.array(dtype=wp.int32)):
    """Each valid hypothesis's key, the largest for the most inliers (the first of equals): one atomic max picks
    the best (a single thread reading every count would wait on each load in turn)."""
    h = wp.tid()
    if valid[h] == 1 and inliers[h] > 0:
        wp.atomic_max(ranked, 0, inliers[h] * HYPOTHESES + (HYPOTHESES - 1 - h))


@wp.kernel
def _best(ranked: wp.array(dtype=wp.int32), tracked: wp.array(dtype=wp.int32), H: wp.array(dtype=wp.mat33),
          best: wp.array(dtype=wp.mat33), agreed: wp.array(dtype=wp.int32), frame_no: wp.array(dtype=wp.int32)):
    """The best hypothesis, if enough tracks agree with it; the frame count moves on."""
    key = ranked[0]
    agreed[0] = 0
    if key >= 0:
        most = key // HYPOTHESES
        if most >= MIN_TRACKS and float(most) >= MIN_INLIER_SHARE * float(tracked[0]):
            best[0] = H[HYPOTHESES - 1 - key % HYPOTHESES]
            agreed[0] = most
    frame_no[0] = frame_no[0] + 1


@wp.kernel
def _starts(before: wp.array(dtype=wp.vec2), after: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32),
            count: wp.array(dtype=wp.int32), frame: wp.vec3, tolerance_px: float, best: wp.array(dtype=wp.mat33),
            agreed: wp.array(dtype=wp.int32), guess: wp.array(dtype=wp.vec2), again: wp.array(dtype=wp.int32)):
    """Where the consensus puts each slot, and whether it is tracked again from there: lost, or off it."""
    t = wp.tid()
    again[t] = 0
    if t >= count[0] or agreed[0] == 0:
        return
    p = _pixel(_apply(best[0], _normalised(before[t], frame)), frame)
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1])):
        return
    guess[t] = p
    if status[t] != 1 or wp.length(after[t] - p) > tolerance_px:
        again[t] = 1


@wp.kernel
def _merge(again: wp.array(dtype=wp.int32), guess: wp.array(dtype=wp.vec2), tolerance_px: float,
           re_pts: wp.array(dtype=wp.vec2), re_status: wp.array(dtype=wp.int32), re_error: wp.array(dtype=float),
           pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), error: wp.array(dtype=float)):
    """A slot tracked again takes its new position where it agrees better with the consensus (a lost one: where
    it lands within ``tolerance_px`` of it)."""
    t = wp.tid()
    if again[t] == 0 or re_status[t] != 1:
        return
    d_new = wp.length(re_pts[t] - guess[t])
    take = bool(False)
    if status[t] == 1:
        take = d_new < wp.length(pts[t] - guess[t]) - CLOSER_PX
    else:
        take = d_new <= tolerance_px
    if take:
        pts[t] = re_pts[t]
        status[t] = 1
        error[t] = re_error[t]


class ConsensusBuffers:
    """The device state of the consensus for ``slots`` track slots."""

    def __init__(self, slots: int, width: int, height: int, device) -> None:
        self.frame = wp.vec3(0.5 * width, 0.5 * height, 0.5 * max(width, height))
        with wp.ScopedDevice(device):
            self.H = wp.zeros(HYPOTHESES, dtype=wp.mat33)
            self.valid = wp.zeros(HYPOTHESES, dtype=wp.int32)
            self.inliers = wp.zeros(HYPOTHESES, dtype=wp.int32)
            self.tracked = wp.zeros(1, dtype=wp.int32)
            self.best = wp.zeros(1, dtype=wp.mat33)
            self.ranked = wp.zeros(1, dtype=wp.int32)  # the best hypothesis's key (_rank; -1: none)
            self.agreed = wp.zeros(1, dtype=wp.int32)  # the best hypothesis's inliers (0: no consensus)
            self.frame_no = wp.zeros(1, dtype=wp.int32)
            self.guess = wp.zeros(slots, dtype=wp.vec2)
            self.again = wp.zeros(slots, dtype=wp.int32)
            self.re_pts = wp.zeros(slots, dtype=wp.vec2)
            self.re_status = wp.zeros(slots, dtype=wp.int32)
            self.re_error = wp.zeros(slots, dtype=float)


def find_consensus(b: ConsensusBuffers, before: wp.array, after: wp.array, status: wp.array, count: wp.array,
                   tolerance_px: float, device) -> None:
    """The best homography of the tracks' steps and each slot's start from it (``b.guess``), and which slots to
    track again (``b.again``)."""
    slots = before.shape[0]
    b.ranked.fill_(-1)
    wp.launch(_hypotheses, dim=HYPOTHESES, inputs=[before, after, status, count, b.frame_no, b.frame, b.H, b.valid,
                                                   b.inliers], device=device)
    wp.launch_tiled(_score, dim=[HYPOTHESES], inputs=[before, after, status, count, b.frame, tolerance_px, b.H,
                                                       b.valid, b.inliers, b.tracked], block_dim=SCORE_LANES,
                    device=device)
    wp.launch(_rank, dim=HYPOTHESES, inputs=[b.valid, b.inliers, b.ranked], device=device)
    wp.launch(_best, dim=1, inputs=[b.ranked, b.tracked, b.H, b.best, b.agreed, b.frame_no], device=device)
    wp.launch(_starts, dim=slots, inputs=[before, after, status, count, b.frame, tolerance_px, b.best, b.agreed,
                                          b.guess, b.again], device=device)


def take_closer(b: ConsensusBuffers, tolerance_px: float, pts: wp.array, status: wp.array, error: wp.array,
                device) -> None:
    """The slots tracked again (into ``b.re_*``) take their new positions where they agree better."""
    wp.launch(_merge, dim=pts.shape[0], inputs=[b.again, b.guess, tolerance_px, b.re_pts, b.re_status, b.re_error,
                                                pts, status, error], device=device)
