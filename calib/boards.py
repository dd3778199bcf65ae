"""Calibration boards and their detection, to sub-pixel accuracy, with OpenCV.

Specs (sizes in metres):
- ``chessboard:COLSxROWS:SQUARE``: inner corners;
- ``charuco:COLSxROWS:SQUARE:MARKER[:DICT]``: squares, square and marker side, an ArUco dictionary (default
  DICT_5X5_100);
- ``circles:COLSxROWS:PITCH[:LARGE]``: a symmetric grid of dark dots on white, COLS dots per row; LARGE lists the
  grid positions ``col,row`` of larger fiducial dots, joined by ``+`` (they sit on grid positions);
- ``acircles:COLSxROWS:PITCH``: OpenCV's asymmetric grid (COLS dots per row; PITCH is the distance between
  neighbouring dots of one row, as in OpenCV's ``generate_pattern.py``);
- ``viking``: the UCL/Viking laparoscope board: ``circles:25x18:0.005:8,5+16,5+8,12+16,12``.

A whole circle grid is found with ``cv2.findCirclesGrid``. A symmetric grid seen in part (a laparoscope close to
the board) is found by growing a lattice from the dots themselves; with fiducial dots the lattice is anchored to
the board, so that two cameras label the same dot alike; without them the labels are relative (fine for one
camera's intrinsics, which only need a plane of known pitch).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from lapreco_hil.errors import CalibrationError

PRESETS = {"viking": "circles:25x18:0.005:8,5+16,5+8,12+16,12"}
KINDS = ("chessboard", "charuco", "circles", "acircles")


@dataclass(frozen=True)
class Board:
    kind: str  # one of KINDS
    cols: int
    rows: int
    square_m: float  # square side, or the dot pitch of a circle grid
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"
    large_dots: tuple[tuple[int, int], ...] = ()  # (col, row) of the fiducial dots of a circle grid

    @property
    def object_points(self) -> np.ndarray:
        """(N, 3) point positions in the board frame (z = 0), metres, in OpenCV's order (row by row)."""
        if self.kind == "charuco":  # OpenCV's: origin at the board's outer corner, ids row by row
            return np.asarray(self._charuco()[0].getChessboardCorners(), np.float64).reshape(-1, 3)
        grid = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2).astype(np.float64)
        if self.kind == "acircles":  # OpenCV's layout: odd rows shifted by half a pitch
            grid = np.column_stack([2 * grid[:, 0] + grid[:, 1] % 2, grid[:, 1]]) * 0.5
        return np.column_stack([grid * self.square_m, np.zeros(len(grid))]).astype(np.float64)

    @property
    def point_count(self) -> int:
        return len(self.object_points) if self.kind == "charuco" else self.cols * self.rows

    def _charuco(self):
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)
        return board, cv2.aruco.CharucoDetector(board)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(image points (M, 2), their indices into object_points) or None when the board is not found."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.kind == "chessboard":
            found, corners = cv2.findChessboardCornersSB(gray, (self.cols, self.rows),
                                                         cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
                                                         | cv2.CALIB_CB_ACCURACY)
            if not found:  # the classic detector finds some boards the sector-based one misses
                found, corners = cv2.findChessboardCorners(gray, (self.cols, self.rows),
                                                           cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
                if not found:
                    return None
                corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                                           (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
            return self._canonical_order(corners.reshape(-1, 2).astype(np.float64)), np.arange(self.cols * self.rows)
        if self.kind in ("circles", "acircles"):
            return self._detect_circles(gray)
        _, detector = self._charuco()
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < 6:
            return None
        return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64)

    # --- circle grids ----------------------------------------------------------------------------------------------

    def _detect_circles(self, gray: np.ndarray):
        detector = blob_detector(*gray.shape)
        flags = cv2.CALIB_CB_SYMMETRIC_GRID if self.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        found, centres = cv2.findCirclesGrid(gray, (self.cols, self.rows), flags=flags, blobDetector=detector)
        if found:
            pts = centres.reshape(-1, 2).astype(np.float64)
            if self.kind == "circles":
                pts = self._canonical_order(pts)
            return pts, np.arange(self.cols * self.rows)
        if self.kind == "acircles":
            return None
        return self._detect_partial_grid(detector.detect(gray))

    def _canonical_order(self, pts: np.ndarray) -> np.ndarray:
        """A chessboard's inner corners or a symmetric grid look the same turned by 180 degrees (the detectors
        may start at either end); take the labelling that starts nearer the image's top-left (x + y smaller
        at the first point than at the last), so that two cameras of one rig agree."""
        if pts[0].sum() > pts[-1].sum():
            return pts[::-1].copy()
        return pts

    def _detect_partial_grid(self, keypoints) -> tuple[np.ndarray, np.ndarray] | None:
        if len(keypoints) < 12:
            return None
        xy = np.array([k.pt for k in keypoints], np.float64)
        size = np.array([k.size for k in keypoints], np.float64)
        median = float(np.median(size))
        small = (size > 0.6 * median) & (size < 1.6 * median)
        large = size > 2.0 * median
        labels = grow_lattice(xy[small])
        if labels is None:
            return None
        pts, ij = labels
        # put the labels in the image's sense: first axis to the right, second down (a camera does not see
        # the board mirrored, so this leaves only the grid's own symmetry)
        ij = _orient_labels(pts, ij)
        large_xy, large_ij = _labels_of(xy[large], pts, ij)
        offset = self._anchor(ij, large_ij)
        if offset is None:
            return None
        ij = ij + offset
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < self.cols) & (ij[:, 1] >= 0) & (ij[:, 1] < self.rows)
        if not ok.all():
            return None
        pts, ids = pts, ij[:, 1] * self.cols + ij[:, 0]
        # the fiducials are dots of the grid too: their centres are as good as the small dots'
        if self.large_dots and len(large_ij):
            l_ij = large_ij + offset
            seen: set = set()
            keep = []  # the blob detector can report one large dot twice
            for n, v in enumerate(map(tuple, l_ij.tolist())):
                if v in set(self.large_dots) and v not in seen:
                    seen.add(v)
                    keep.append(n)
            pts = np.vstack([pts, large_xy[keep]])
            ids = np.concatenate([ids, l_ij[keep, 1] * self.cols + l_ij[keep, 0]])
        order = np.argsort(ids)
        if len(np.unique(ids)) != len(ids) or len(ids) < 12:
            return None
        return pts[order], ids[order].astype(np.int64)

    def _anchor(self, ij: np.ndarray, large_ij: np.ndarray) -> np.ndarray | None:
        """The shift from lattice labels to board labels. With fiducials: the one shift that puts the most seen
        fiducials on their places, no small dot on one, and every dot on the board (None when two shifts do
        equally well: the view is not used); without fiducials: labels from the smallest seen (relative)."""
        lo, hi = ij.min(axis=0), ij.max(axis=0)
        if (hi - lo + 1 > [self.cols, self.rows]).any():
            return None
        if not self.large_dots:
            return -lo
        if len(large_ij) == 0:
            return None
        layout = set(self.large_dots)
        best, best_score, tied = None, 0, False
        for dx in range(-lo[0], self.cols - hi[0]):
            for dy in range(-lo[1], self.rows - hi[1]):
                hits = sum((i + dx, j + dy) in layout for i, j in large_ij.tolist())
                if hits < best_score or hits == 0:
                    continue
                if any((i + dx, j + dy) in layout for i, j in ij.tolist()):  # a small dot on a fiducial's place
                    continue
                tied = hits == best_score
                if hits > best_score:
                    best, best_score = np.array([dx, dy]), hits
        return None if tied else best


def blob_detector(height: int, width: int) -> cv2.SimpleBlobDetector:
    """Dark round dots from about 4 px to 13% of the image height across (the large fiducial dots included)."""
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, 0
    p.minThreshold, p.maxThreshold, p.thresholdStep = 10, 230, 10
    p.filterByArea = True
    p.minArea = max(12.0, (0.004 * height) ** 2)
    p.maxArea = (0.13 * height) ** 2
    p.filterByCircularity, p.minCircularity = True, 0.6
    p.filterByConvexity, p.minConvexity = True, 0.85
    p.filterByInertia, p.minInertiaRatio = True, 0.2
    p.minDistBetweenBlobs = max(3.0, 0.004 * height)
    return cv2.SimpleBlobDetector_create(p)


def grow_lattice(xy: np.ndarray, tol: float = 0.3) -> tuple[np.ndarray, np.ndarray] | None:
    """Integer lattice labels for dots of a square grid seen in perspective and with lens distortion: from the dot
    nearest the centre, each labelled dot predicts its four neighbours from the local steps of its labelled
    neighbours; a dot within ``tol`` steps of a prediction takes the label. Returns (points, labels) of the
    labelled dots, or None when fewer than 12 are labelled."""
    tree = cKDTree(xy)
    seed = int(np.argmin(np.linalg.norm(xy - np.median(xy, axis=0), axis=1)))
    _, nn = tree.query(xy[seed], k=min(9, len(xy)))
    steps = xy[nn[1:]] - xy[seed]
    # two basis steps: the nearest neighbour, and the nearest one roughly perpendicular to it
    u = steps[0]
    perp = [s for s in steps[1:] if abs(np.dot(s, u)) < 0.5 * np.linalg.norm(s) * np.linalg.norm(u)]
    if not perp:
        return None
    v = min(perp, key=np.linalg.norm)
    label_of = {seed: (0, 0)}
    at = {(0, 0): seed}
    queue = [seed]
    while queue:
        k = queue.pop(0)
        i, j = label_of[k]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            key = (i + di, j + dj)
            if key in at:
                continue
            back = at.get((i - di, j - dj))  # extrapolate along the row/column where we can
            if back is not None:
                step = xy[k] - xy[back]
            else:
                step = _local_step(xy, at, i, j, di, dj, u, v)
            pred = xy[k] + step
            d, m = tree.query(pred)
            if d < tol * np.linalg.norm(step) and m not in label_of:
                label_of[m] = key
                at[key] = m
                queue.append(m)
    if len(label_of) < 12:
        return None
    idx = np.array(list(label_of), int)
    return xy[idx], np.array([label_of[k] for k in idx.tolist()], int)


def _local_step(xy, at, i, j, di, dj, u, v):
    """The step to the (di, dj) neighbour from a labelled neighbour across, else the seed's basis."""
    for oi, oj in ((dj, di), (-dj, -di)):  # a neighbour on the other axis whose own step is known
        a, b = at.get((i + oi, j + oj)), at.get((i + oi + di, j + oj + dj))
        if a is not None and b is not None:
            return xy[b] - xy[a]
    return di * u + dj * v


def _orient_labels(pts: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """Relabel so that the first label axis points right in the image and the second down (the lattice's axes
    were taken from the seed's neighbours, in any of the square's orientations)."""
    A, *_ = np.linalg.lstsq(np.column_stack([ij, np.ones(len(ij))]), pts, rcond=None)
    ax_i, ax_j = A[0], A[1]  # image steps of +1 in each label
    if abs(ax_j[0]) > abs(ax_i[0]):  # swap so the first axis is the more horizontal one
        ij, ax_i, ax_j = ij[:, ::-1], ax_j, ax_i
    if ax_i[0] < 0:
        ij = ij * [-1, 1]
    if ax_j[1] < 0:
        ij = ij * [1, -1]
    return ij - ij.min(axis=0)


def _labels_of(xy_large: np.ndarray, pts: np.ndarray, ij: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fiducial dots that fall on a lattice position, and their labels (from the labelled dots around each
    one, through a local affine map)."""
    if len(xy_large) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2), int)
    tree = cKDTree(pts)
    out, kept = [], []
    for p in xy_large:
        _, nn = tree.query(p, k=min(8, len(pts)))
        A, *_ = np.linalg.lstsq(np.column_stack([pts[nn], np.ones(len(nn))]), ij[nn].astype(float), rcond=None)
        lab = np.append(p, 1.0) @ A
        if np.all(np.abs(lab - np.round(lab)) < 0.3):
            out.append(np.round(lab).astype(int))
            kept.append(p)
    return np.array(kept, np.float64).reshape(-1, 2), np.array(out, int).reshape(-1, 2)


MAX_SQUARE_M = 1.0  # no printed calibration board has squares this large


def parse_board(spec: str) -> Board:
    spec = PRESETS.get(spec, spec)
    parts = spec.split(":")
    try:
        kind = parts[0]
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square = float(parts[2])
        if kind == "chessboard" and len(parts) == 3:
            board = Board("chessboard", cols, rows, square)
        elif kind == "charuco" and len(parts) in (4, 5):
            board = Board("charuco", cols, rows, square, float(parts[3]), parts[4] if len(parts) == 5 else
                          "DICT_5X5_100")
            if not hasattr(cv2.aruco, board.dictionary):
                raise CalibrationError(f"board '{spec}': unknown ArUco dictionary '{board.dictionary}'")
        elif kind == "circles" and len(parts) in (3, 4):
            large = tuple(tuple(int(v) for v in p.split(",")) for p in parts[3].split("+")) if len(parts) == 4 \
                else ()
            if any(len(p) != 2 or not (0 <= p[0] < cols and 0 <= p[1] < rows) for p in large):
                raise CalibrationError(f"board '{spec}': each large dot is col,row inside the {cols}x{rows} grid")
            board = Board("circles", cols, rows, square, large_dots=large)
        elif kind == "acircles" and len(parts) == 3:
            board = Board("acircles", cols, rows, square)
        else:
            raise ValueError
    except (ValueError, IndexError):
        raise CalibrationError(f"board '{spec}' must look like chessboard:9x6:0.025 (inner corners, square in m), "
                               f"charuco:7x5:0.03:0.022[:DICT_5X5_100], circles:25x18:0.005[:8,5+16,5] (dots, "
                               f"pitch in m, large dots), acircles:4x11:0.02 or viking") from None
    if cols < 2 or rows < 2 or square <= 0 or (board.kind == "charuco" and not 0 < board.marker_m < square):
        raise CalibrationError(f"board '{spec}': sizes must be positive (and the marker smaller than the square)")
    if square >= MAX_SQUARE_M:
        # a size in millimetres read as metres scales every translation (a stereo baseline of 83 m)
        raise CalibrationError(f"board '{spec}': a square (or pitch) of {square:g} m? sizes are in metres, e.g. "
                               f"{square / 1000:g} for {square:g} mm")
    return board
