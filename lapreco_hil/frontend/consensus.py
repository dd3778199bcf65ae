"""The tracks' consensus on a frame without a pose prediction: pyramidal LK alone takes a neighbouring copy of a
periodic pattern (a dot grid, a chessboard, regular vessels) or loses the track when the view turns or zooms
fast, while most tracks of the same frame agree on one image motion. So a RANSAC homography of the tracks' LK
steps is fitted; a track off it by more than ``TrackerConfig.consensus_px``, or lost, is tracked again from
where it puts it, on the two finest pyramid levels (the coarse ones, where the pattern is blurred away, would
carry it off again), and takes the new position when that agrees better with the homography (a lost one: when
it lands within the tolerance). A homography is only the start: LK settles where the texture is, so a scene in
depth keeps its parallax, and a track the consensus cannot improve keeps LK's answer. With a pose prediction
(``FrameMotion``) the tracks start where the camera motion puts them, and this is not needed.

Host version (numpy + OpenCV) for the OpenCV front-end; the Warp front-end runs it on the device
(``warp/consensus.py``). docs/frontend-real-frames.md, "Without a prediction", has the figures."""

from __future__ import annotations

import cv2
import numpy as np

# no consensus with fewer tracked tracks, or when fewer than this share of them agree with the best homography
MIN_TRACKS = 12
MIN_INLIER_SHARE = 0.25
# a tracked track takes its second position only if it is this much (px) closer to the consensus
CLOSER_PX = 0.5
# LK's levels for the second try: full resolution and the next (OpenCV's maxLevel 1)
RETRACK_MAX_LEVEL = 1


def homography(before: np.ndarray, after: np.ndarray, tracked: np.ndarray, tolerance_px: float) -> np.ndarray | None:
    """The RANSAC homography of the tracked tracks' steps (``before`` -> ``after``, (N, 2)), or None when too few
    tracks agree with one."""
    n = int(tracked.sum())
    if n < MIN_TRACKS:
        return None
    H, inliers = cv2.findHomography(before[tracked].astype(np.float64), after[tracked].astype(np.float64),
                                    cv2.RANSAC, tolerance_px, maxIters=2000, confidence=0.999)
    if H is None or inliers is None or inliers.sum() < max(MIN_TRACKS, MIN_INLIER_SHARE * n):
        return None
    return H


def retrack(before: np.ndarray, after: np.ndarray, tracked: np.ndarray, tolerance_px: float, track_from):
    """``after`` and ``tracked`` with the consensus applied. ``track_from(rows, starts)`` tracks the rows again
    from ``starts`` ((M, 2) float32) and returns (positions (M, 2), tracked (M,) bool)."""
    return retrack_to(homography(before, after, tracked, tolerance_px), before, after, tracked, tolerance_px,
                      track_from)


def retrack_to(H: np.ndarray | None, before: np.ndarray, after: np.ndarray, tracked: np.ndarray,
               tolerance_px: float, track_from):
    """``retrack`` with the consensus homography ``H`` found (None: none, nothing changes)."""
    if H is None:
        return after, tracked
    starts = cv2.perspectiveTransform(before.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    off = np.linalg.norm(after - starts, axis=1)
    again = (~tracked | (off > tolerance_px)) & np.isfinite(starts).all(axis=1)
    if not again.any():
        return after, tracked
    rows = np.flatnonzero(again)
    positions, ok = track_from(rows, starts[rows].astype(np.float32))
    off_new = np.linalg.norm(positions - starts[rows], axis=1)
    take = ok & np.where(tracked[rows], off_new < off[rows] - CLOSER_PX, off_new <= tolerance_px)
    after, tracked = after.copy(), tracked.copy()
    after[rows[take]] = positions[take]
    tracked[rows[take]] = True
    return after, tracked
