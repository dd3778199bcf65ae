"""Where a track should be in another view of the scene, given the camera motion between the views: its
projection where its depth is known, else a search along its epipolar line (a depth sweep with ZNCC of a patch).
Vectorised numpy/cv2, shared by the OpenCV front-end, both front-ends' ``match_view`` and the mapper; the Warp
front-end runs the same steps in its kernels (``warp/predict.py``).

All pixels are undistorted (ideal pinhole) pixels of the given K; ``T_dst_src`` maps points from the source
camera to the destination camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from lapreco_hil.frontend.drift import AffineDriftCheck, gradients
from lapreco_hil.lookup import positions

# the sweep: an 11 x 11 patch on pyramid level 1 (22 x 22 pixels of the full image), 32 to 96 inverse-depth
# samples (about one per level pixel of the line), a match where ZNCC is above MIN_SCORE and the best score
# away from it (beyond SECOND_RADIUS level pixels) is at least MARGIN lower
SWEEP_PATCH_PX = 11
SWEEP_LEVEL = 1
MIN_SAMPLES, MAX_SAMPLES = 32, 96
MIN_SCORE = 0.7
MARGIN = 0.1
SECOND_RADIUS = 2.5
# tracks without a depth borrow the median depth of up to this many nearest tracks that have one, within
# NEIGHBOUR_RADIUS of the image's larger side
NEIGHBOURS = 6
NEIGHBOUR_RADIUS = 0.15
# a track whose whole epipolar segment (over the depth range) stays within this many pixels of its middle needs
# no search: LK starts at the middle (a slow frame: the robot's small motion is no reason to re-match a track)
SHORT_LINE_PX = 20.0


@dataclass(frozen=True)
class SweepResult:
    uv: np.ndarray  # (N, 2) best position in the destination image (full-resolution pixels), NaN where not found
    found: np.ndarray  # (N,) bool: clear best score
    score: np.ndarray  # (N,) best ZNCC


def _homography_terms(uv: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray,
                      T_dst_src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What every projection of pixels ``uv`` (N, 2) under ``T_dst_src`` shares, whatever their depths: (3, N)
    ``K_dst R K_src^-1 [u, v, 1]`` and ``K_dst t``; a pixel at depth z is then ``z * a + b`` dehomogenised
    (``_pixels_at``), so the several depths one track is projected at cost a few array operations each."""
    T = np.asarray(T_dst_src, np.float64)
    fx, fy, cx, cy = float(K_src[0, 0]), float(K_src[1, 1]), float(K_src[0, 2]), float(K_src[1, 2])
    K_src_inv = np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])
    K_d = np.array([[float(K_dst[0, 0]), 0.0, float(K_dst[0, 2])], [0.0, float(K_dst[1, 1]), float(K_dst[1, 2])],
                    [0.0, 0.0, 1.0]])  # (as project always did: no skew)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    homogeneous = np.ones((3, len(uv)))
    homogeneous[:2] = uv.T
    return (K_d @ T[:3, :3] @ K_src_inv) @ homogeneous, K_d @ T[:3, 3]


def _pixels_at(terms: tuple[np.ndarray, np.ndarray], depth) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the pixels of ``_homography_terms`` at depth z ``depth`` (N,) or scalar: NaN behind the camera
    (and where the depth is NaN)."""
    a, b = terms
    z = depth * a[2] + b[2]
    behind = ~(z > 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (depth * a[0] + b[0]) / z
        y = (depth * a[1] + b[1]) / z
    x[behind] = np.nan
    y[behind] = np.nan
    return x, y


def project(uv: np.ndarray, depth: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray,
            T_dst_src: np.ndarray) -> np.ndarray:
    """Pixels ``uv`` (N, 2) of the source camera at depth z ``depth`` (N,) -> pixels of the destination camera."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    depth = np.asarray(depth, np.float64)
    x, y = _pixels_at(_homography_terms(uv, K_src, K_dst, T_dst_src), depth.reshape(-1) if depth.ndim else depth)
    out = np.empty((len(uv), 2))
    out[:, 0], out[:, 1] = x, y
    return out


def _moved_sq(uv: np.ndarray, terms: tuple[np.ndarray, np.ndarray], depth) -> np.ndarray:
    """Squared distance (px^2) from each pixel ``uv`` to its projection at ``depth`` (same K both sides): NaN
    where the depth is NaN or the point ends behind the camera."""
    x, y = _pixels_at(terms, depth)
    x -= uv[:, 0]
    y -= uv[:, 1]
    x *= x
    y *= y
    x += y
    return x


def _shift_px(terms: tuple[np.ndarray, np.ndarray], depth, ends) -> np.ndarray:
    """How far (px) a pixel's projection (``_homography_terms``) at ``depth`` moves at most when its depth is
    each of ``ends`` instead (arrays or scalars): NaN where one of them is behind the camera or NaN. Along a
    track's epipolar line its projection at z moves from that at d by (z - d) e / (w_z w_d), with
    e = a_xy b_w - b_xy a_w and w the depth in the destination camera: one line direction per track."""
    a, b = terms
    e = np.hypot(a[0] * b[2] - b[0] * a[2], a[1] * b[2] - b[1] * a[2])
    w_at = depth * a[2] + b[2]
    valid = w_at > 1e-9
    worst = None
    for end in ends:
        w_end = end * a[2] + b[2]
        valid &= w_end > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            shift = np.abs(end - depth) / w_end
        worst = shift if worst is None else np.maximum(worst, shift)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = e * worst / w_at
    out[~valid] = np.nan
    return out


def _median_below(values_sq: np.ndarray, threshold: float) -> bool:
    """Whether the median of the square roots of ``values_sq`` (finite, non-negative, at least one) is below
    ``threshold``: counted, not sorted (more than half of the values below it; for an even count with exactly
    half below, the mean of the two middle values, which straddle it)."""
    n = len(values_sq)
    below = values_sq < threshold * threshold
    count = int(np.count_nonzero(below))
    if 2 * count > n:  # the middle value (both, for an even count) below
        return True
    if n % 2 or 2 * count < n:  # the middle value (or the upper one of two) at or above
        return False
    # an even count split evenly: the mean of the largest value below and the smallest one at or above
    lower, upper = np.sqrt(values_sq[below].max()), np.sqrt(values_sq[~below].min())
    return bool((lower + upper) / 2 < threshold)


def _median_motion_below(moved_sq: np.ndarray, px: float) -> bool | None:
    """Whether the tracks' median motion (``_moved_sq``, NaN where unknown) is below ``px``; None where no track has
    a motion."""
    moved_sq = moved_sq[np.isfinite(moved_sq)]
    return _median_below(moved_sq, px) if len(moved_sq) else None


def depths_for_tracks(uv: np.ndarray, ids: np.ndarray, known_ids: np.ndarray, known_depth: np.ndarray,
                      image_size: tuple[int, int]) -> np.ndarray:
    """Each track's depth: its own where ``known_ids`` has it, else the median of its nearest tracks' that have
    one (the map's depth nearby), else NaN (to be searched along its epipolar line)."""
    return borrow_depths(uv, own_depths(ids, known_ids, known_depth), image_size)


def own_depths(ids: np.ndarray, known_ids: np.ndarray, known_depth: np.ndarray) -> np.ndarray:
    """Each track's own depth where ``known_ids`` has it (and it is positive), else NaN."""
    n = len(ids)
    depth = np.full(n, np.nan)
    if n == 0 or len(known_ids) == 0:
        return depth
    at, found = positions(known_ids, ids)
    depth[found] = np.asarray(known_depth, np.float64)[at[found]]
    depth[~(depth > 0)] = np.nan
    return depth


def borrow_depths(uv: np.ndarray, depth: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """``depth`` with each NaN replaced by the median of its nearest tracks' depths (within reach), else left NaN."""
    depth = np.array(depth, np.float64)
    has = np.isfinite(depth)
    n_has = int(np.count_nonzero(has))
    if n_has == 0 or n_has == len(depth):
        return depth
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    k = min(NEIGHBOURS, n_has)
    reach = NEIGHBOUR_RADIUS * max(image_size)
    candidate = _neighbour_candidates(uv, has, k, reach)
    known = has if candidate is None else candidate
    known_uv, known_depth, query_uv = uv[known], depth[known], uv[~has]
    if len(known_uv) == 0:
        return depth
    # (an unbalanced tree with loose nodes: half the build, the same nearest neighbours)
    tree = cKDTree(known_uv, balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(query_uv, k=k, distance_upper_bound=reach)
    dist, idx = dist.reshape(len(dist), k), idx.reshape(len(idx), k)
    near = known_depth[np.minimum(idx, len(known_uv) - 1)]
    near[~np.isfinite(dist)] = np.nan
    # each row's median over its neighbours in reach (NaN: none, searched); sorting puts the NaNs last
    near.sort(axis=1)
    count = np.count_nonzero(np.isfinite(near), axis=1)
    rows = np.arange(len(near))
    borrowed = (near[rows, np.maximum(count - 1, 0) // 2] + near[rows, count // 2]) / 2
    borrowed[count == 0] = np.nan
    depth[~has] = borrowed
    return depth


# _neighbour_candidates' grid holds about this many known tracks per cell
CELL_TRACKS = 2.0


def _neighbour_candidates(uv: np.ndarray, known: np.ndarray, k: int, reach: float) -> np.ndarray | None:
    """Which of the ``known`` tracks (a mask over ``uv``) can be among the others' (the queries') ``k`` nearest
    within ``reach``: a mask over ``uv`` (None: any known one may be), so that the tree is built on those only:
    where the tracks without a depth gather (a band the motion uncovers, a region without landmarks) the rest
    of the image is left out. On a grid of cells: a query whose 3 x 3 block of cells holds k known tracks has its
    k nearest within 2 sqrt(2) cells, so within its 7 x 7 block (the rest of 3 cells covers the cells'
    rounding); another has its within ``reach`` of its cell."""
    xy = uv[:, 0], uv[:, 1]  # (numpy reduces a column by itself faster than an (N, 2) array along axis 0)
    low = np.array([xy[0].min(), xy[1].min()])
    extent = np.maximum(np.array([xy[0].max(), xy[1].max()]) - low, 1.0)
    if not np.isfinite(extent).all():
        return None
    n_known = int(np.count_nonzero(known))
    per_cell = float(np.sqrt(n_known / (extent[0] * extent[1] * CELL_TRACKS)))  # (1 / the cell's side)
    nx, ny = int(extent[0] * per_cell) + 1, int(extent[1] * per_cell) + 1
    reach_cells = int(np.ceil(reach * per_cell)) + 1  # (+1: the cells' rounding)
    cells = ((xy[1] - low[1]) * per_cell).astype(np.int64) * nx + ((xy[0] - low[0]) * per_cell).astype(np.int64)
    known_cells, query_cells = cells[known], cells[~known]
    counts = np.zeros((ny + 2, nx + 2), np.int32)  # (a border of empty cells: every 3 x 3 block is inside)
    counts[1:-1, 1:-1] = np.bincount(known_cells, minlength=nx * ny).reshape(ny, nx)
    block = sum(counts[1 + dy:ny + 1 + dy, 1 + dx:nx + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    dense = block.reshape(-1)[query_cells] >= k
    marks = np.zeros(nx * ny, np.uint8)
    marks[query_cells[dense]] = 1
    needed = cv2.dilate(marks.reshape(ny, nx), np.ones((7, 7), np.uint8))
    if not dense.all():
        if reach_cells >= max(nx, ny):
            return None
        marks[:] = 0
        marks[query_cells[~dense]] = 1
        needed |= cv2.dilate(marks.reshape(ny, nx), np.ones((2 * reach_cells + 1,) * 2, np.uint8))
    if needed.all():
        return None
    return known & (needed.reshape(-1)[cells] > 0)


# a frame whose tracks the motion moves less than this (median) is tracked as without one: LK's own reach covers
# it, and the robot's noise in a small motion only moves the starts about (docs/frontend-real-frames.md)
SMALL_MOTION_PX = 8.0


def start_depths(uv: np.ndarray, ids: np.ndarray, motion, K: np.ndarray,
                 image_size: tuple[int, int]) -> np.ndarray | None:
    """Each track's depth for its start in the new frame: its own or its neighbours' (``depths_for_tracks``), the
    far end of a short epipolar segment (``settle_short_lines``), else NaN (searched along its line). None when
    the motion moves the tracks with a depth by less than SMALL_MOTION_PX (median, at least 10 of them): the
    frame is then tracked as without a motion. That test is made on the tracks' own depths where at least 10
    have one, else on their own and borrowed depths."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return None
    T = np.asarray(motion.T_cur_prev, np.float64)
    terms = _homography_terms(uv, K, K, T)  # (shared by every projection below)
    # the small-motion test on the tracks' own depths first: most frames of a live run end here, and borrowing
    # depths for the others (a nearest-neighbour search) costs more than the rest of this together
    depth = own_depths(ids, motion.track_ids, motion.depth_m)
    if _small_motion(uv, terms, depth):
        return None
    settled = np.count_nonzero(np.isfinite(depth)) >= 10  # (enough own depths said it: borrowed ones only echo)
    if not np.isfinite(depth).all():
        depth = borrow_depths(uv, depth, image_size)
        if not settled and _small_motion(uv, terms, depth):
            return None
    return _settle_short_lines(terms, depth, motion.depth_range_m)


class OwnStartDepths(NamedTuple):
    """``own_start_depths``' answer: what the device starts from, what the plan is made from, and what the plan can
    reuse of the small-motion test's work (None where the host borrowed)."""

    depth: np.ndarray  # each track's own depth, NaN where it has none, -1 where it has none to take either
    plan: np.ndarray  # the depths ``prediction_plan`` is made from
    moved_sq: np.ndarray | None = None  # each track's squared predicted motion (px^2) at its plan depth
    terms: tuple[np.ndarray, np.ndarray] | None = None  # ``_homography_terms`` of the tracks under the motion


def own_start_depths(uv: np.ndarray, ids: np.ndarray, motion, K: np.ndarray,
                     image_size: tuple[int, int]) -> OwnStartDepths | None:
    """``start_depths`` for a front-end that borrows and settles the depths itself (the Warp one, on the device:
    ``warp.predict.borrow_and_settle``): the depths it starts from (NaN where a track has none of its own and -1
    where it has none to take either) and the depths its ``prediction_plan`` is made from (the others at the own
    depths' median, a borrowed depth's stand-in), or None for a small motion. The small-motion test's projections
    serve the plan too (``OwnStartDepths.moved_sq``: an own depth's motion is the same for both). Where fewer than
    10 tracks have a depth of their own, the small-motion test needs the borrowed ones: the host then makes them
    (``start_depths``, few to borrow from), the tracks left without one are sent as -1, and the plan is made from
    ``start_depths``' answer."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return None
    depth = own_depths(ids, motion.track_ids, motion.depth_m)
    known = np.isfinite(depth)
    if np.count_nonzero(known) < 10:
        full = start_depths(uv, ids, motion, K, image_size)
        return None if full is None else OwnStartDepths(np.where(np.isfinite(full), full, -1.0), full)
    plan = depth.copy()
    plan[~known] = np.median(depth[known])
    terms = _homography_terms(uv, K, K, np.asarray(motion.T_cur_prev, np.float64))
    moved_sq = _moved_sq(uv, terms, plan)
    if _median_motion_below(moved_sq[known], SMALL_MOTION_PX):  # (``_small_motion`` on the own depths)
        return None
    return OwnStartDepths(depth, plan, moved_sq, terms)


def _small_motion(uv: np.ndarray, terms: tuple[np.ndarray, np.ndarray], depth: np.ndarray) -> bool:
    """Whether the motion (``_homography_terms``) moves the tracks with a depth by less than SMALL_MOTION_PX
    (median, at least 10)."""
    if np.count_nonzero(np.isfinite(depth)) < 10:
        return False
    return bool(_median_motion_below(_moved_sq(uv, terms, depth), SMALL_MOTION_PX))


def start_motion_px(uv: np.ndarray, depth: np.ndarray, K: np.ndarray, T_cur_prev: np.ndarray) -> float | None:
    """The median distance (px) from each track to its predicted start, over the tracks with a start depth
    (``start_depths``); None when none has one."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    return _start_motion_px(uv, _homography_terms(uv, K, K, T_cur_prev), np.asarray(depth, np.float64))


def _start_motion_px(uv: np.ndarray, terms: tuple[np.ndarray, np.ndarray], depth: np.ndarray) -> float | None:
    moved_sq = _moved_sq(uv, terms, depth)
    moved_sq = moved_sq[np.isfinite(moved_sq)]
    return float(np.median(np.sqrt(moved_sq))) if len(moved_sq) else None


def settle_short_lines(uv: np.ndarray, depth: np.ndarray, K: np.ndarray, T_cur_prev: np.ndarray,
                       depth_range_m: tuple[float, float]) -> np.ndarray:
    """``depth`` with the tracks that have none but whose epipolar segment is short (SHORT_LINE_PX) given the
    range's far depth: they start LK at the segment's far end, unsearched (where the map knows no depth yet the
    range runs from a centimetre, so its middle is far nearer than tissue usually is; LK's reach covers the
    segment)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    unknown = ~np.isfinite(np.asarray(depth, np.float64))
    if not unknown.any():
        return np.array(depth, np.float64)
    return _settle_short_lines(_homography_terms(uv[unknown], K, K, T_cur_prev), depth, depth_range_m,
                               terms_of_unknown=True)


def _settle_short_lines(terms: tuple[np.ndarray, np.ndarray], depth: np.ndarray, depth_range_m: tuple[float, float],
                        terms_of_unknown: bool = False) -> np.ndarray:
    """``settle_short_lines`` from ``_homography_terms`` of every track (or, ``terms_of_unknown``, of only those
    without a depth)."""
    depth = np.array(depth, np.float64)
    unknown = ~np.isfinite(depth)
    if not unknown.any():
        return depth
    if not terms_of_unknown:
        terms = (terms[0][:, unknown], terms[1])
    near, far = depth_range_m
    reach = _shift_px(terms, 2.0 / (1.0 / near + 1.0 / far), (near, far))
    short = reach <= SHORT_LINE_PX  # (False where NaN)
    depth[np.flatnonzero(unknown)[short]] = far
    return depth


# How far off a pose-predicted start may be, which sets LK's pyramid for a predicted frame (``start_uncertainty_px``):
# a landmark's depth within OWN_DEPTH_SPREAD (relative), a depth borrowed from neighbouring tracks within
# BORROWED_DEPTH_SPREAD (tissue is not flat), the sweep's best within its SECOND_RADIUS on SWEEP_LEVEL; at least
# POSE_UNCERTAINTY_PX everywhere (the robot's relative pose between two frames: in the simulated fast run, 50 px a
# frame on a compliant ECM, LK lands a median 5 px and 90 % within 8 px from the start its own landmark predicts),
# and the frame's figure is the START_QUANTILE of its tracks'
OWN_DEPTH_SPREAD = 0.05
BORROWED_DEPTH_SPREAD = 0.15
POSE_UNCERTAINTY_PX = 8.0
START_QUANTILE = 90.0


def start_uncertainty_px(uv: np.ndarray, ids: np.ndarray, depth: np.ndarray, motion, K: np.ndarray) -> float:
    """How far (px) the predicted starts of a frame's tracks may lie from where the tracks truly are, given their
    start ``depth`` (``start_depths``): each start moved by its depth's spread (its landmark's, a borrowed one's,
    or for a short line settled at the range's far end the whole range), the sweep's resolution for the
    tracks searched along their line (NaN depth), the pose's floor; the START_QUANTILE over the tracks."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return POSE_UNCERTAINTY_PX
    return _start_uncertainty_px(_homography_terms(uv, K, K, motion.T_cur_prev), ids, np.asarray(depth, np.float64),
                                 motion)


def _start_uncertainty_px(terms: tuple[np.ndarray, np.ndarray], ids: np.ndarray, depth: np.ndarray,
                          motion) -> float:
    own = np.isin(ids, np.asarray(motion.track_ids)[np.asarray(motion.depth_m) > 0])
    near, far = (float(d) for d in motion.depth_range_m)
    settled = ~own & (depth == far)
    relative = np.where(own, OWN_DEPTH_SPREAD, BORROWED_DEPTH_SPREAD)
    spread = _shift_px(terms, depth, (np.where(settled, near, depth * (1.0 - relative)),
                                      np.where(settled, far, depth * (1.0 + relative))))
    spread[~np.isfinite(depth)] = SECOND_RADIUS * 2.0 ** SWEEP_LEVEL
    spread = np.nan_to_num(spread, nan=1e6, posinf=1e6)  # behind the camera at one end: unbounded
    return float(max(POSE_UNCERTAINTY_PX, np.percentile(spread, START_QUANTILE)))


def prediction_plan(config, levels: int, size: tuple[int, int], uv: np.ndarray, ids: np.ndarray, depth: np.ndarray,
                    motion, K: np.ndarray, moved_sq: np.ndarray | None = None,
                    terms: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[int, int]:
    """For a frame tracked from ``motion``'s prediction (``depth``: its tracks' start depths, ``start_depths``):
    (the tracks it keeps, ``track_budget``; LK's pyramid levels above full resolution of the front-end's
    ``levels``, ``image.predicted_levels``). Each is measured only where its option is on
    (``fast_features_scale`` above 1, ``reduced_predicted_levels``): both front-ends run this every frame.
    ``moved_sq`` and ``terms``: the tracks' squared motion at ``depth`` and their ``_homography_terms``, where the
    caller has them (``OwnStartDepths``)."""
    from lapreco_hil.frontend import track_capacity
    from lapreco_hil.frontend.image import predicted_levels

    budget, lk_levels = config.max_features, levels
    if config.fast_features_scale <= 1.0 and not config.reduced_predicted_levels:
        return budget, lk_levels
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    depth = np.asarray(depth, np.float64)
    if terms is None:
        terms = _homography_terms(uv, K, K, motion.T_cur_prev)  # (shared by both measures)
    if config.fast_features_scale > 1.0:
        # ``track_budget``'s rule (the median motion at least fast_motion_px), counted rather than sorted
        moved_sq = _moved_sq(uv, terms, depth) if moved_sq is None else moved_sq
        if _median_motion_below(moved_sq, config.fast_motion_px) is False:  # (None: no motion known)
            budget = track_capacity(config)
    if config.reduced_predicted_levels:
        uncertainty = _start_uncertainty_px(terms, ids, depth, motion) if len(uv) else POSE_UNCERTAINTY_PX
        lk_levels = predicted_levels(config, levels, size[0], size[1], uncertainty)
    return budget, lk_levels


def _patch_offsets(patch_px: int) -> np.ndarray:
    r = (patch_px - 1) / 2
    g = np.arange(patch_px, dtype=np.float32) - r
    X, Y = np.meshgrid(g, g)
    return np.column_stack([X.ravel(), Y.ravel()])


def _level(image: np.ndarray, level: int) -> np.ndarray:
    out = image.astype(np.float32)
    for _ in range(level):
        out = cv2.pyrDown(out)
    return out


def _zscore(patches: np.ndarray) -> np.ndarray:
    z = patches - patches.mean(-1, keepdims=True)
    return z / (np.sqrt((z * z).sum(-1, keepdims=True)) + 1e-6)


def sweep(src_image: np.ndarray, dst_image: np.ndarray, uv: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray,
          T_dst_src: np.ndarray, depth_range_m: tuple[float, float], level: int = SWEEP_LEVEL,
          patch_px: int = SWEEP_PATCH_PX, min_score: float = MIN_SCORE, margin: float = MARGIN) -> SweepResult:
    """Each source pixel searched along its epipolar line in the destination image: inverse depth sampled
    uniformly over ``depth_range_m`` (as many samples as the line's length in level pixels needs, 32 to 96),
    ZNCC of a patch of the tracker images on pyramid ``level``, the best taken where it is clear. The result is
    a starting point for LK, not a refined position."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return SweepResult(np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0))
    ranges = np.broadcast_to(np.asarray(depth_range_m, np.float64).reshape(-1, 2), (n, 2))
    near, far = ranges[:, 0], ranges[:, 1]
    scale = 1.0 / (1 << level)
    src, dst = _level(src_image, level), _level(dst_image, level)
    ends = np.stack([project(uv, near, K_src, K_dst, T_dst_src), project(uv, far, K_src, K_dst, T_dst_src)])
    length = np.nan_to_num(np.linalg.norm(ends[0] - ends[1], axis=1) * scale, nan=np.inf)
    s = int(np.clip(np.ceil(np.max(np.where(np.isfinite(length), length, 0.0))) + 1, MIN_SAMPLES, MAX_SAMPLES))
    if np.ndim(depth_range_m) == 1:  # one range for all
        inv = np.tile(np.linspace(1.0 / near[0], 1.0 / far[0], s), (n, 1))
    else:
        inv = np.linspace(1.0 / near, 1.0 / far, s, axis=1)
    cand = project(np.repeat(uv, s, 0), (1.0 / inv).ravel(), K_src, K_dst, T_dst_src).reshape(n, s, 2)
    off = _patch_offsets(patch_px)
    # the source patches, then every candidate's: (n, P) and (n, s, P), bilinear, the border a constant
    # outside the level (a patch off the image cannot match)
    p0 = (uv * scale)[:, None, :]  # cv2.pyrDown's level pixel x sits on full-resolution pixel x / scale
    ref = cv2.remap(src, (p0[..., 0] + off[None, :, 0]).astype(np.float32),
                    (p0[..., 1] + off[None, :, 1]).astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    c = cand * scale
    cx = np.nan_to_num(c[..., 0], nan=-1e4).astype(np.float32)[..., None] + off[None, None, :, 0]
    cy = np.nan_to_num(c[..., 1], nan=-1e4).astype(np.float32)[..., None] + off[None, None, :, 1]
    h, w = dst.shape
    patches = cv2.remap(dst, cx.reshape(n, -1), cy.reshape(n, -1),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0).reshape(n, s, -1)
    r = (patch_px - 1) / 2
    inside = (c[..., 0] >= r) & (c[..., 1] >= r) & (c[..., 0] <= w - 1 - r) & (c[..., 1] <= h - 1 - r)
    score = np.einsum("np,nsp->ns", _zscore(ref), _zscore(patches))
    score[~inside] = -1.0
    best = np.argmax(score, axis=1)
    rows = np.arange(n)
    best_score = score[rows, best]
    best_c = c[rows, best]
    apart = np.linalg.norm(c - best_c[:, None, :], axis=2) > SECOND_RADIUS
    second = np.where(apart, score, -1.0).max(axis=1)
    # a line shorter than the patch's reach has no second place to compare with: the best alone decides
    short = length < SECOND_RADIUS
    found = (best_score > min_score) & ((best_score - second > margin) | short)
    out = cand[rows, best].copy()
    out[~found] = np.nan
    return SweepResult(out, found, best_score)


def predict(uv: np.ndarray, depth: np.ndarray, prev_image: np.ndarray, cur_image: np.ndarray, K: np.ndarray,
            T_cur_prev: np.ndarray, depth_range_m: tuple[float, float]) -> np.ndarray:
    """Where each previous-frame track starts in the current frame: projected at its depth, or found by the
    sweep where it has none; where the sweep finds no clear match, the far end of its line (``unclear_start``)."""
    guess = project(uv, np.nan_to_num(depth, nan=1.0), K, K, T_cur_prev)
    unknown = ~np.isfinite(depth)
    guess[unknown] = np.nan
    if unknown.any():
        found = sweep(prev_image, cur_image, uv[unknown], K, K, T_cur_prev, depth_range_m)
        guess[unknown] = np.where(found.found[:, None], found.uv,
                                  unclear_start(uv[unknown], K, T_cur_prev, depth_range_m))
    return guess


def unclear_start(uv: np.ndarray, K: np.ndarray, T_cur_prev: np.ndarray,
                  depth_range_m: tuple[float, float]) -> np.ndarray:
    """Where a track without depth whose sweep found no clear match starts LK: its line's far end (the rotation's
    part of the motion, which tissue at any depth shares). Dropping it instead lost most tracks of every frame
    before the map had depths (smooth tissue, 1080p: docs/frontend-real-frames.md); a wrong start fails the
    forward-backward check that every swept track must pass."""
    return project(uv, np.full(len(uv), float(depth_range_m[1])), K, K, T_cur_prev)


# a match in another view must track back into this view within this many pixels
FORWARD_BACKWARD_PX = 1.0


def lk_params(window_px: int, levels: int) -> dict:
    """cv2.calcOpticalFlowPyrLK's settings as the front-ends use them (OpenCV's default stopping criteria)."""
    return dict(winSize=(window_px, window_px), maxLevel=levels,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))


def tracks_back(cur_u8: np.ndarray, prev_u8: np.ndarray, cur_uv: np.ndarray, prev_uv: np.ndarray,
                lk: dict) -> np.ndarray:
    """Whether LK from ``cur_uv`` in the current image lands back within FORWARD_BACKWARD_PX of ``prev_uv`` in
    the previous one (the forward-backward check of a match found across a wide baseline)."""
    p = np.asarray(cur_uv, np.float32).reshape(-1, 1, 2)
    q = np.asarray(prev_uv, np.float32).reshape(-1, 1, 2)
    back, st, _ = cv2.calcOpticalFlowPyrLK(cur_u8, prev_u8, p, q.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    return (st.ravel() == 1) & (np.linalg.norm((back - q).reshape(-1, 2), axis=1) < FORWARD_BACKWARD_PX)


def match_across(this_u8: np.ndarray, this_float: np.ndarray, other_u8: np.ndarray, other_float: np.ndarray,
                 uv: np.ndarray, K_this: np.ndarray, K_other: np.ndarray, T_other_this: np.ndarray,
                 depth_range_m: tuple[float, float], lk: dict, max_residual: float,
                 search_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``uv`` of this view found in another view of the same instant (a stereo partner): the epipolar
    sweep, LK from its best, and LK back into this view, which must land within FORWARD_BACKWARD_PX of where
    the track is; then LK's window in this view registered affinely (with gain and bias) in the other, as the
    drift check registers a temporal track: the fit moves the match along its epipolar line where it passes the
    drift check's bounds (``max_residual``: its residual bound, the tracker's ``drift_max_residual``), LK's match
    stands where it does not, and a fit that disagrees with LK by more than FORWARD_BACKWARD_PX, passed or not,
    drops the match (``register_along``). A match must end on the part of its line that was searched
    (``on_segment``, within FORWARD_BACKWARD_PX: the whole range, or a re-searched track's own one). Tracker
    images of both views (8-bit for LK, float
    for the sweep and the registration). ``search_m``: each track's own (near, far), (N, 2)
    (``stereo_depth.search_ranges``: around the depth the map gives it), where a track whose sweep over
    ``depth_range_m`` was unclear is searched again; None: no second search. -> (uv in the other view, found).

    Why the registration: a short baseline turns a fraction of a pixel into millimetres of depth (5 mm at 12 cm:
    0.1 px is 0.7 mm), and LK's translation-only window is off by 0.2 px (median) where the surface is seen
    slanted, foreshortened differently by the two views (docs/results.md, session 14)."""
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    res = sweep(this_float, other_float, uv, K_this, K_other, T_other_this, depth_range_m)
    own = None if search_m is None else np.asarray(search_m, np.float64).reshape(-1, 2)
    again = np.zeros(0, np.int64) if own is None else \
        np.flatnonzero(~res.found & np.any(own != np.asarray(depth_range_m, np.float64), axis=1))
    searched = np.tile(np.asarray(depth_range_m, np.float64), (n, 1))  # the range each match was found over
    if len(again):
        # unclear over the whole range (a second place along the line scores nearly as well): searched again
        # over the track's own range, where one of them may stand clear
        near = sweep(this_float, other_float, uv[again], K_this, K_other, T_other_this, own[again])
        res = SweepResult(res.uv.copy(), res.found.copy(), res.score.copy())
        res.uv[again], res.found[again], res.score[again] = near.uv, near.found, near.score
        searched[again] = own[again]
    found = res.found.copy()
    out = np.full((n, 2), np.nan)
    if not found.any():
        return out, found
    p = uv[found].astype(np.float32).reshape(-1, 1, 2)
    guess = res.uv[found].astype(np.float32).reshape(-1, 1, 2)
    # the sweep placed each match within a pixel of its level: LK refines it on that level and finer only (on
    # coarser levels the window holds what lies around the track, as the field of view's edge, and goes there)
    lk = dict(lk, maxLevel=min(int(lk.get("maxLevel", SWEEP_LEVEL)), SWEEP_LEVEL))
    fwd, st, _ = cv2.calcOpticalFlowPyrLK(this_u8, other_u8, p, guess.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                          **lk)
    h, w = other_u8.shape[:2]
    q = fwd.reshape(-1, 2)
    ok = ((st.ravel() == 1) & tracks_back(other_u8, this_u8, q, p.reshape(-1, 2), lk) & (q[:, 0] >= 0)
          & (q[:, 1] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] <= h - 1))
    idx = np.flatnonzero(found)
    found[idx[~ok]] = False
    idx = idx[ok]
    out[idx] = q[ok]
    if len(idx):
        near, far = depth_range_m
        line = project(uv[idx], np.full(len(idx), float(far)), K_this, K_other, T_other_this) \
            - project(uv[idx], np.full(len(idx), float(near)), K_this, K_other, T_other_this)
        out[idx], agree = register_along(this_float, other_float, uv[idx], out[idx], line, lk["winSize"][0],
                                         max_residual)
        # LK and the fit may leave the part of the line that was searched: a match the sweep never scored (a
        # window that holds the field of view's static edge locks onto it at no disparity; a re-searched match
        # that leaves its prior's range had only the prior to go by, and the prior does not hold there)
        agree &= on_segment(uv[idx], out[idx], K_this, K_other, T_other_this, searched[idx], FORWARD_BACKWARD_PX)
        found[idx[~agree]] = False
        out[idx[~agree]] = np.nan
    return out, found


def on_segment(uv: np.ndarray, matched: np.ndarray, K_this: np.ndarray, K_other: np.ndarray,
               T_other_this: np.ndarray, ranges: np.ndarray, tolerance_px: float) -> np.ndarray:
    """Whether each ``matched`` (the other view's position of this view's ``uv``) lies along its epipolar line
    between the projections of its depth range ``ranges`` (N, 2: near, far), within ``tolerance_px`` of either
    end (only the position along the line is judged)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    ranges = np.asarray(ranges, np.float64).reshape(-1, 2)
    near = project(uv, ranges[:, 0], K_this, K_other, T_other_this)
    line = project(uv, ranges[:, 1], K_this, K_other, T_other_this) - near
    length = np.linalg.norm(line, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.sum((np.asarray(matched, np.float64) - near) * line, axis=1) / length
    along = np.where(length > 0, along, 0.0)
    return (along >= -tolerance_px) & (along <= length + tolerance_px)


def register_along(this_float: np.ndarray, other_float: np.ndarray, uv: np.ndarray, matched: np.ndarray,
                   line: np.ndarray, window_px: int, max_residual: float) -> tuple[np.ndarray, np.ndarray]:
    """``matched`` (the other view's positions of this view's ``uv``) refined along its epipolar ``line`` (a
    direction in the other view, per match) by an affine fit: each ``window_px`` patch of this view registered
    in the other with the drift check's model (gain and bias too). -> (positions, agree). A fit within the drift
    check's bounds moves its match by its correction along the line; only that part carries depth, and across
    the line the match keeps LK's position (a real pair's calibration is off by more than the fit would correct
    there: 0.5 px on the Hamlyn pair). A fit whose correction exceeds FORWARD_BACKWARD_PX disagrees with LK by
    more than a match may (one of them is wrong, and which is unknown), whether or not the fit passed: ``agree``
    is False there. ``max_residual``: the drift check's bound (``[tracker] drift_max_residual``)."""
    check = AffineDriftCheck(int(window_px), max_residual=max_residual)
    gx, gy = gradients(other_float)
    matched = np.asarray(matched, np.float64)
    ref = check.reference_patches(this_float, np.asarray(uv, np.float64))
    fit = check.register(other_float, gx, gy, ref, np.repeat(np.eye(2)[None], len(uv), 0), matched)
    direction = line / np.maximum(np.linalg.norm(line, axis=1, keepdims=True), 1e-12)
    correction = np.sum((fit.positions - matched) * direction, axis=1)
    moved = matched + correction[:, None] * direction
    h, w = other_float.shape[:2]
    x, y = moved[:, 0], moved[:, 1]
    better = fit.keep & np.isfinite(moved).all(axis=1) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    agree = ~(np.abs(correction) > FORWARD_BACKWARD_PX)  # (a fit gone NaN is no evidence against LK)
    return np.where(better[:, None], moved, matched), agree
