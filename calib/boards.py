"""Calibration boards: ``chessboard:COLSxROWS:SQUARE`` (inner corners, square side in metres) or
``charuco:COLSxROWS:SQUARE:MARKER[:DICT]`` (squares, square and marker side in metres, an OpenCV ArUco
dictionary name, default DICT_5X5_100). Detection is OpenCV's, to sub-pixel accuracy."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import CalibrationError


@dataclass(frozen=True)
class Board:
    kind: str  # "chessboard" | "charuco"
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"

    @property
    def object_points(self) -> np.ndarray:
        """(N, 3) corner positions in the board frame (z = 0), metres, in OpenCV's corner order."""
        if self.kind == "charuco":  # OpenCV's: origin at the board's outer corner, ids row by row
            return np.asarray(self._charuco()[0].getChessboardCorners(), np.float64).reshape(-1, 3)
        grid = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.column_stack([grid * self.square_m, np.zeros(len(grid))]).astype(np.float64)

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
            return corners.reshape(-1, 2).astype(np.float64), np.arange(self.cols * self.rows)
        _, detector = self._charuco()
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < 6:
            return None
        return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64)


def parse_board(spec: str) -> Board:
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
        else:
            raise ValueError
    except (ValueError, IndexError):
        raise CalibrationError(f"board '{spec}' must look like chessboard:9x6:0.025 (inner corners, square in m) "
                               f"or charuco:7x5:0.03:0.022[:DICT_5X5_100]") from None
    if cols < 2 or rows < 2 or square <= 0 or (board.kind == "charuco" and not 0 < board.marker_m < square):
        raise CalibrationError(f"board '{spec}': sizes must be positive (and the marker smaller than the square)")
    return board
