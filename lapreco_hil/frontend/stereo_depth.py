"""Where along its epipolar line a track's stereo partner is searched: near the depth the map already gives it.

The left-right sweep (``epipolar.match_across``) searches the whole depth range the map spans, widened (x0.5 to
x2): at a 5 mm baseline that is a line of some 40 px, and on smooth tissue a second place along it scores within
the sweep's margin of the best, so a quarter of the tracks went unmatched (docs/results.md, session 15). Such a
track is searched again near its depth: one whose depth is known (its landmark's, carried from the previous
frame into this one by the camera motion) over STEREO_OWN_SPREAD around it; one without, over
STEREO_BORROWED_SPREAD around the median of its neighbours' (tissue is smooth at the scale of a few tracks);
the others not at all. A match that was clear over the whole range stays as it was.
"""

from __future__ import annotations

import numpy as np

from lapreco_hil.frontend import epipolar

# relative spreads of a prior depth: a landmark's (seen at two instants at least, its depth within a few per
# cent) and a neighbour's (tissue is not flat); each search covers depth / (1 + s) to depth x (1 + s)
STEREO_OWN_SPREAD = 0.1
STEREO_BORROWED_SPREAD = 0.25


def carried_depths(ids: np.ndarray, prev_ids: np.ndarray, prev_uv: np.ndarray, prev_depth: np.ndarray,
                   T_cur_prev: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The depth (z) in the current camera of each track of ``ids`` whose depth in the previous frame is known
    (``prev_depth`` at ``prev_uv``, NaN where unknown): its point moved by ``T_cur_prev``; NaN for the others."""
    ids = np.asarray(ids, np.int64)
    known = np.isfinite(prev_depth) & (np.asarray(prev_depth) > 0)
    if not len(ids) or not known.any():
        return np.full(len(ids), np.nan)
    kid, kuv, kz = (np.asarray(prev_ids, np.int64)[known], np.asarray(prev_uv, np.float64)[known],
                    np.asarray(prev_depth, np.float64)[known])
    rays = np.column_stack([(kuv[:, 0] - K[0, 2]) / K[0, 0], (kuv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(kuv))])
    T = np.asarray(T_cur_prev, np.float64)
    return epipolar.own_depths(ids, kid, (rays * kz[:, None]) @ T[2, :3] + T[2, 3])


def search_ranges(uv: np.ndarray, depth: np.ndarray, image_size: tuple[int, int],
                  depth_range_m: tuple[float, float]) -> np.ndarray:
    """(N, 2) depth ranges (near, far) for the stereo sweep of tracks at ``uv`` with their own ``depth`` (NaN:
    none): STEREO_OWN_SPREAD around their own, else STEREO_BORROWED_SPREAD around their neighbours' median
    (``epipolar.borrow_depths``), else ``depth_range_m``. Each range stays within ``depth_range_m``'s far end
    and its near end (a prior outside the map's range is searched where the map is)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    depth = np.asarray(depth, np.float64)
    n = len(uv)
    ranges = np.tile(np.asarray(depth_range_m, np.float64), (n, 1))
    if n == 0:
        return ranges
    own = np.isfinite(depth)
    if not own.any():
        return ranges
    borrowed = epipolar.borrow_depths(uv, depth, image_size)
    z = np.where(own, depth, borrowed)
    spread = np.where(own, STEREO_OWN_SPREAD, STEREO_BORROWED_SPREAD)
    prior = np.isfinite(z)
    near, far = float(depth_range_m[0]), float(depth_range_m[1])
    ranges[prior, 0] = np.clip(z[prior] / (1.0 + spread[prior]), near, far)
    ranges[prior, 1] = np.clip(z[prior] * (1.0 + spread[prior]), near, far)
    collapsed = prior & ~(ranges[:, 1] > ranges[:, 0])  # a prior wholly outside the map's range: all of it
    ranges[collapsed] = (near, far)
    return ranges


def known_depths(ids: np.ndarray, uv: np.ndarray, motion) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What a front-end keeps of a frame's ``motion`` (a FrameMotion, or None) for its stereo matches: the
    previous frame's tracks (``ids``, ``uv``), their own depths there (NaN: none) and the motion T_cur_prev;
    ``carried_depths`` takes them (after ``ids``) into the new frame."""
    ids = np.asarray(ids, np.int64).copy()
    uv = np.asarray(uv, np.float64).reshape(-1, 2).copy()
    if motion is None:
        return ids, uv, np.full(len(ids), np.nan), np.eye(4)
    return ids, uv, epipolar.own_depths(ids, motion.track_ids, motion.depth_m), np.asarray(motion.T_cur_prev,
                                                                                         np.float64)
