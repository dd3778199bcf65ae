"""Pinhole camera with OpenCV's distortion coefficients.

The coefficient vector is always OpenCV's 12-element order (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4).
The seed paper's model (radial k1..k3, tangential t1 t2, thin prism p) is the subset with k4..k6 = 0,
p1 = t1, p2 = t2, s1 = p_x, s3 = p_y and s2 = s4 = 0 (its equations 1-4 written out match OpenCV's).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

N_DIST = 12


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0,) * N_DIST
    # the scope's circular field of view: radius in pixels about (cx, cy); 0 = none
    fov_radius_px: float = 0.0

    def __post_init__(self) -> None:
        if len(self.dist) != N_DIST:
            object.__setattr__(self, "dist", tuple(self.dist) + (0.0,) * (N_DIST - len(self.dist)))

    @staticmethod
    def from_paper_model(width, height, fx, fy, cx, cy, k=(0.0, 0.0, 0.0), t=(0.0, 0.0), p=(0.0, 0.0),
                         fov_radius_px: float = 0.0) -> "CameraModel":
        """The seed paper's model: radial k1..k3, tangential t1 t2, thin prism p = (px, py)."""
        dist = (k[0], k[1], t[0], t[1], k[2], 0.0, 0.0, 0.0, p[0], 0.0, p[1], 0.0)
        return CameraModel(width, height, fx, fy, cx, cy, dist, fov_radius_px)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N, 2) of camera-frame points (N, 3) (z > 0)."""
        pts = np.asarray(points_camera, dtype=np.float64).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return uv.reshape(-1, 2)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> pixels of the ideal pinhole camera with the same K."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPointsIter(
            pts, self.K, self.dist_array, None, self.K,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10),
        ).reshape(-1, 2)

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps from the distorted frame to the undistorted image with the same K."""
        return cv2.initUndistortRectifyMap(self.K, self.dist_array, None, self.K, (self.width, self.height),
                                           cv2.CV_32FC1)

    def fov_mask(self, margin_px: float = 0.0) -> np.ndarray:
        """uint8 mask (255 inside) of the circular field of view in the distorted image."""
        mask = np.zeros((self.height, self.width), np.uint8)
        if self.fov_radius_px <= 0:
            mask[:] = 255
            return mask
        r = int(round(self.fov_radius_px - margin_px))
        cv2.circle(mask, (int(round(self.cx)), int(round(self.cy))), max(r, 0), 255, -1)
        return mask


@dataclass(frozen=True)
class Rig:
    """The cameras of a scope, rigidly mounted together: camera 0 is the reference (its pose is the rig's
    pose, T_world_camera everywhere else); ``T_cam0_cam[k]`` maps points from camera k to camera 0 (identity
    for k = 0). A stereo scope is a rig of two; its extrinsics are held by bundle adjustment within their
    calibrated 1-sigma uncertainty (``sigma_rotation_rad``, ``sigma_translation_m``)."""

    cameras: tuple[CameraModel, ...]
    T_cam0_cam: tuple[np.ndarray, ...]
    sigma_rotation_rad: float = 0.0005
    sigma_translation_m: float = 0.0001

    def __post_init__(self) -> None:
        if len(self.cameras) != len(self.T_cam0_cam) or not self.cameras:
            raise ValueError("a rig needs one T_cam0_cam per camera")
        if not np.allclose(self.T_cam0_cam[0], np.eye(4)):
            raise ValueError("T_cam0_cam of camera 0 must be the identity")

    @staticmethod
    def mono(camera: CameraModel) -> "Rig":
        return Rig((camera,), (np.eye(4),))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def is_stereo(self) -> bool:
        return len(self.cameras) >= 2

    def baseline_m(self, k: int = 1) -> float:
        return float(np.linalg.norm(self.T_cam0_cam[k][:3, 3]))
