"""New corners on the device: the Shi-Tomasi response (the structure tensor's smaller eigenvalue) and its best
value where corners may start, the occupancy discs around live tracks, local maxima kept per grid cell, the
greedy minimum-distance selection (strongest first, as cv2.goodFeaturesToTrack) and the choice of the strongest
selected corners for the free track slots through a histogram of their scores (no sort)."""

from __future__ import annotations

import numpy as np
import warp as wp

from lapreco_hil.frontend.warp.block_sum import block_exclusive_scan

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

# new corners are chosen strongest first through a histogram of their scores (no sort): 32 bins per halving of
# the response below the frame's best cover 16 halvings (a quality level down to 1.5e-5)
SCORE_BINS_PER_OCTAVE = 32
SCORE_BINS = 512
PIXEL_KEY_MAX = 2147483647  # the low half of a cell key: ties between equal scores go to the lower pixel index
PIXEL_KEY_MASK = wp.constant(wp.uint64(PIXEL_KEY_MAX))
KEY_SHIFT = wp.constant(wp.uint64(32))
ZERO_KEY = wp.constant(wp.uint64(0))
ROW_LANES = 256  # lanes of the response's best value, one block per image row


@wp.func
def _allowed(mask: wp.array2d(dtype=wp.uint8), lit: wp.array2d(dtype=float), lit_min: float,
             occ: wp.array2d(dtype=wp.int32), stamp: int, x: int, y: int) -> bool:
    return mask[y, x] != wp.uint8(0) and occ[y, x] != stamp and lit[y, x] >= lit_min


@wp.kernel
def _structure_rows(gx: wp.array(dtype=float), gy: wp.array(dtype=float), w: int, h: int, block: int,
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
def _min_eigenvalue(rows: wp.array(dtype=wp.vec3), w: int, h: int, block: int, mask: wp.array2d(dtype=wp.uint8),
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
def _selection_begin(stamp: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float)):
    """A new detection: two new occupancy stamps (the grid is never cleared: a pixel is occupied when it holds a
    stamp of this detection), one for the selection and one for taking corners, and no best response yet."""
    stamp[0] = stamp[0] + 2
    max_eig[0] = 0.0


@wp.kernel
def _occupancy(positions: wp.array(dtype=wp.vec2), steps: wp.array(dtype=wp.vec2), ahead: float,
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
def _corner_candidates(eig: wp.array2d(dtype=float), max_eig: wp.array(dtype=float), quality: float,
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


@wp.kernel
def _cell_init(cell_key: wp.array(dtype=wp.uint64), eig: wp.array2d(dtype=float), cells: wp.array(dtype=wp.vec3),
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
def _selection_round(cells: wp.array(dtype=wp.vec3), grid_w: int, grid_h: int, min_distance: float,
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
def _score_histogram(cells: wp.array(dtype=wp.vec3), state: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float),
                     occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    """How many selected corners, still free of tracks, fall in each score bin (bin 0 = strongest)."""
    c = wp.tid()
    if state[c] == 1 and _free_now(cells[c], occ, stamp):
        wp.atomic_add(hist, _score_bin(cells[c][2], max_eig[0]), 1)


@wp.kernel
def _score_threshold(hist: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), max_features: int,
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
def _corner_offers(cells: wp.array(dtype=wp.vec3), state: wp.array(dtype=wp.int32), max_eig: wp.array(dtype=float),
                   cut: wp.array(dtype=wp.int32), occ: wp.array2d(dtype=wp.int32), stamp: wp.array(dtype=wp.int32),
                   offer: wp.array(dtype=wp.int32), in_cut: wp.array(dtype=wp.int32)):
    """Per cell: whether its corner (selected, free of tracks now) is offered for sure (above the cut bin: 1) or
    only if there is room in the cut bin (``in_cut`` 1; which of those are taken is decided in cell order)."""
    c = wp.tid()
    offer[c] = 0
    in_cut[c] = 0
    if state[c] != 1:
        return
    me = cells[c]
    b = _score_bin(me[2], max_eig[0])
    if b > cut[0] or not _free_now(me, occ, stamp):
        return
    if b == cut[0]:
        in_cut[c] = 1
    else:
        offer[c] = 1


TAKE_LANES = 1024  # one block ranks every cell: each lane a contiguous run of them


@wp.kernel
def _take_corners(cells: wp.array(dtype=wp.vec3), offer: wp.array(dtype=wp.int32), in_cut: wp.array(dtype=wp.int32),
                  cut: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), next_id: wp.array(dtype=wp.int32),
                  taken: wp.array(dtype=wp.int32), pts: wp.array(dtype=wp.vec2), ids: wp.array(dtype=wp.int32)):
    """One block: the cut bin's first cut[1] corners in cell order join the offered ones, and the offered corners
    become tracks after the live ones in cell order (slot count + their rank): the same frame gives the same
    tracks in the same slots on every run (an atomic counter's order did not). Each lane ranks a contiguous run of
    cells; two block scans order the runs."""
    _b, lane = wp.tid()
    nl = wp.block_dim()
    n = offer.shape[0]
    run = (n + nl - 1) // nl
    start = wp.min(lane * run, n)
    end = wp.min(start + run, n)
    mine = int(0)
    for c in range(start, end):
        mine += in_cut[c]
    rank = block_exclusive_scan(mine)
    offered = int(0)
    for c in range(start, end):
        if in_cut[c] == 1:
            if rank < cut[1]:
                offer[c] = 1
            rank += 1
        offered += offer[c]
    slot = block_exclusive_scan(offered)
    base = count[0]
    first = next_id[0]
    for c in range(start, end):
        if offer[c] == 1:
            me = cells[c]
            pts[base + slot] = wp.vec2(me[0], me[1])
            ids[base + slot] = first + slot
            slot += 1
    if lane == nl - 1:
        taken[0] = slot


class TakeScratch:
    """Per-cell scratch of ``take_corners`` (which cells offer a corner, which are in the cut bin)."""

    def __init__(self, n_cells: int, device) -> None:
        with wp.ScopedDevice(device):
            self.offer = wp.zeros(n_cells, dtype=wp.int32)
            self.in_cut = wp.zeros(n_cells, dtype=wp.int32)


# --- host wrappers: a device and preallocated outputs --------------------------------------------------------
def selection_begin(stamp: wp.array, max_eig: wp.array, device) -> None:
    """A new detection: its occupancy stamps, no best response yet."""
    wp.launch(_selection_begin, dim=1, inputs=[stamp, max_eig], device=device)


def occupancy(positions: wp.array, steps: wp.array, ahead: float, count: wp.array, radius: float, stamp: wp.array,
              which: int, occ: wp.array, device) -> None:
    """Stamp into ``occ`` the discs of ``radius`` around the live tracks (every slot of ``positions`` is
    launched; the live count is read on the device)."""
    r = int(np.ceil(radius))
    wp.launch(_occupancy, dim=(positions.shape[0], (2 * r + 1) ** 2),
              inputs=[positions, steps, ahead, count, radius, stamp, which, occ], device=device)


def structure_rows(gx: wp.array, gy: wp.array, w: int, h: int, block: int, rows: wp.array, device) -> None:
    """``rows`` <- the structure tensor's horizontal box sums over ``block`` columns."""
    wp.launch(_structure_rows, dim=(h, w), inputs=[gx, gy, w, h, block, rows], device=device)


def min_eigenvalue(rows: wp.array, w: int, h: int, block: int, mask: wp.array, lit: wp.array, lit_min: float,
                   occ: wp.array, stamp: wp.array, eig: wp.array, max_eig: wp.array, device) -> None:
    """``eig`` <- the Shi-Tomasi response, ``max_eig`` <- its best where corners may start."""
    wp.launch_tiled(_min_eigenvalue, dim=[h], inputs=[rows, w, h, block, mask, lit, lit_min, occ, stamp, eig,
                                                      max_eig], block_dim=ROW_LANES, device=device)


def corner_candidates(eig: wp.array, max_eig: wp.array, quality: float, mask: wp.array, lit: wp.array,
                      lit_min: float, occ: wp.array, stamp: wp.array, border: int, cell: float, grid_w: int,
                      cell_key: wp.array, device) -> None:
    """``cell_key`` <- each grid cell's strongest local maximum (keys are zero before, see ``cell_init``)."""
    wp.launch(_corner_candidates, dim=eig.shape, inputs=[eig, max_eig, quality, mask, lit, lit_min, occ, stamp,
                                                         border, cell, grid_w, cell_key], device=device)


def cell_init(cell_key: wp.array, eig: wp.array, cells: wp.array, state: wp.array, hist: wp.array, device) -> None:
    """``cells``, ``state`` <- each cell's candidate, undecided; clears ``cell_key`` and ``hist``."""
    wp.launch(_cell_init, dim=max(cell_key.shape[0], hist.shape[0]), inputs=[cell_key, eig, cells, state, hist],
              device=device)


def selection_round(cells: wp.array, grid_w: int, grid_h: int, min_distance: float, state: wp.array,
                    device) -> None:
    """One round of the parallel greedy selection, in place on ``state``."""
    wp.launch(_selection_round, dim=grid_w * grid_h, inputs=[cells, grid_w, grid_h, min_distance, state],
              device=device)


def score_histogram(cells: wp.array, state: wp.array, max_eig: wp.array, occ: wp.array, stamp: wp.array,
                    hist: wp.array, device) -> None:
    """``hist`` <- the selected corners still free of tracks, per score bin."""
    wp.launch(_score_histogram, dim=cells.shape[0], inputs=[cells, state, max_eig, occ, stamp, hist], device=device)


def score_threshold(hist: wp.array, count: wp.array, max_features: int, cut: wp.array, taken: wp.array,
                    device) -> None:
    """``cut`` <- the score bin (and how many of it) that fills the free slots; clears ``taken``."""
    wp.launch(_score_threshold, dim=SCORE_BINS, inputs=[hist, count, max_features, cut, taken], device=device)


def take_corners(cells: wp.array, state: wp.array, max_eig: wp.array, cut: wp.array, occ: wp.array,
                 stamp: wp.array, count: wp.array, next_id: wp.array, taken: wp.array, pts: wp.array,
                 ids: wp.array, scratch: TakeScratch, device) -> None:
    """The chosen corners into ``pts``, ``ids`` after the live tracks, in cell order; ``taken[0]`` says how many.
    Which of the cut bin's corners fit, and each corner's slot, are ranked in cell order (block scans: the launch
    may sit in a conditional graph node, where a scan's temporary allocation is not allowed), so the result does
    not depend on the order the threads run in."""
    n = cells.shape[0]
    wp.launch(_corner_offers, dim=n, inputs=[cells, state, max_eig, cut, occ, stamp, scratch.offer, scratch.in_cut],
              device=device)
    wp.launch_tiled(_take_corners, dim=[1], inputs=[cells, scratch.offer, scratch.in_cut, cut, count, next_id, taken,
                                                    pts, ids], block_dim=TAKE_LANES, device=device)
