"""Stereo calibration with OpenCV: board views seen by both cameras of a rig, cv2.stereoCalibrate with each
camera's own lens calibration (held fixed, or refined together with the rig), and the rectified epipolar error:
after cv2.stereoRectify, the mean |y_left - y_right| of the board points seen in both images, in pixels
(zero for a perfect rig; it measures what a stereo matcher searching along rows will suffer)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.errors import CalibrationError
from lapreco_hil.calib.boards import Board

log = logging.getLogger(__name__)


@dataclass
class StereoResult:
    cam0: CameraModel
    cam1: CameraModel
    R: np.ndarray  # x1 = R x0 + T (OpenCV's)
    T: np.ndarray
    E: np.ndarray
    F: np.ndarray
    rms_px: float
    rectified_epipolar_error_px: float  # mean |y0 - y1| after rectification
    pairs: list[str] = field(default_factory=list)
    refined_intrinsics: bool = False

    @property
    def T_cam0_cam1(self) -> np.ndarray:
        T_cam1_cam0 = np.eye(4)
        T_cam1_cam0[:3, :3], T_cam1_cam0[:3, 3] = self.R, np.ravel(self.T)
        return np.linalg.inv(T_cam1_cam0)

    def summary(self) -> dict:
        return {"pairs": len(self.pairs), "rms_px": self.rms_px,
                "rectified_epipolar_error_px": self.rectified_epipolar_error_px,
                "baseline_mm": float(np.linalg.norm(self.T) * 1e3), "T_cam0_cam1": self.T_cam0_cam1.tolist(),
                "refined_intrinsics": self.refined_intrinsics,
                "cam0": {"K": self.cam0.K.tolist(), "dist": list(self.cam0.dist)},
                "cam1": {"K": self.cam1.K.tolist(), "dist": list(self.cam1.dist)}}


def common_points(board: Board, det0, det1) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(object points, image points in camera 0, in camera 1) of the board points both cameras saw.

    A whole chessboard or symmetric dot grid reads alike turned by 180 degrees; the two cameras of a rig see
    the board turned alike, so camera 1's labelling is turned when its first-to-last point runs against
    camera 0's. A dot grid without fiducials seen in part is labelled relative to what each camera saw: such
    pairs are not used."""
    n = board.cols * board.rows
    if board.kind == "circles" and not board.large_dots and min(len(det0[1]), len(det1[1])) < n:
        return None  # a dot grid seen in part without fiducials has relative labels: the cameras cannot agree
    if board.kind in ("chessboard", "circles") and len(det0[1]) == len(det1[1]) == n:
        a, b = det0[0][-1] - det0[0][0], det1[0][-1] - det1[0][0]
        if float(np.dot(a, b)) < 0:
            det1 = (det1[0][::-1].copy(), det1[1])
    ids, i0, i1 = np.intersect1d(det0[1], det1[1], return_indices=True)
    if len(ids) < 6:
        return None
    return board.object_points[ids], det0[0][i0], det1[0][i1]


def rectified_epipolar_error(cam0: CameraModel, cam1: CameraModel, R, T, pts0: list, pts1: list) -> float:
    """Mean |y0 - y1| (px) of matching points after cv2.stereoRectify, the points undistorted and rectified
    (as remapping the images would put them)."""
    size = (cam0.width, cam0.height)
    R0, R1, P0, P1, *_ = cv2.stereoRectify(cam0.K, cam0.dist_array, cam1.K, cam1.dist_array, size, R, T,
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    dy = []
    for a, b in zip(pts0, pts1):
        r0 = cv2.undistortPoints(a.reshape(-1, 1, 2), cam0.K, cam0.dist_array, R=R0, P=P0).reshape(-1, 2)
        r1 = cv2.undistortPoints(b.reshape(-1, 1, 2), cam1.K, cam1.dist_array, R=R1, P=P1).reshape(-1, 2)
        dy.append(np.abs(r0[:, 1] - r1[:, 1]))
    return float(np.mean(np.concatenate(dy)))


def calibrate_stereo(detections0: dict, detections1: dict, pairs: list[tuple[str, str]], board: Board,
                     cam0: CameraModel, cam1: CameraModel, refine_intrinsics: bool = False,
                     min_pairs: int = 3) -> StereoResult:
    """Rig from views taken together (``pairs``: (camera 0 view, camera 1 view)), each view's detection as
    :meth:`Board.detect` gives it, and each camera's lens calibration."""
    obj, p0, p1, used = [], [], [], []
    for a, b in pairs:
        if a not in detections0 or b not in detections1:
            continue
        common = common_points(board, detections0[a], detections1[b])
        if common is None:
            continue
        obj.append(common[0].astype(np.float32))
        p0.append(common[1].astype(np.float32).reshape(-1, 1, 2))
        p1.append(common[2].astype(np.float32).reshape(-1, 1, 2))
        used.append(f"{a} + {b}")
    if len(used) < min_pairs:
        raise CalibrationError(f"the board was seen by both cameras in {len(used)} of {len(pairs)} pairs; at "
                               f"least {min_pairs} are needed (check --board and that --left/--right are in step)")
    if (cam0.width, cam0.height) != (cam1.width, cam1.height):
        raise CalibrationError(f"the cameras' images differ in size ({cam0.width}x{cam0.height} and "
                               f"{cam1.width}x{cam1.height}); stereo calibration needs one mode")
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if refine_intrinsics else cv2.CALIB_FIX_INTRINSIC
    # OpenCV reads only the coefficients its model flags name, even for fixed intrinsics
    d = np.vstack([cam0.dist_array, cam1.dist_array])
    if np.any(d[:, 8:]):
        flags |= cv2.CALIB_THIN_PRISM_MODEL | cv2.CALIB_RATIONAL_MODEL
    elif np.any(d[:, 5:8]):
        flags |= cv2.CALIB_RATIONAL_MODEL
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms, K0, d0, K1, d1, R, T, E, F = cv2.stereoCalibrate(obj, p0, p1, cam0.K, cam0.dist_array, cam1.K,
                                                          cam1.dist_array, (cam0.width, cam0.height),
                                                          flags=flags, criteria=crit)
    if refine_intrinsics:
        cam0 = CameraModel(cam0.width, cam0.height, K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2],
                           tuple(np.ravel(d0)[:12].tolist()))
        cam1 = CameraModel(cam1.width, cam1.height, K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2],
                           tuple(np.ravel(d1)[:12].tolist()))
    err = rectified_epipolar_error(cam0, cam1, R, T, p0, p1)
    return StereoResult(cam0, cam1, R, T.reshape(3, 1), E, F, float(rms), err, used, refine_intrinsics)
