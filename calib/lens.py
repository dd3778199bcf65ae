"""Lens calibration with OpenCV: board detection, cv2.calibrateCamera with a chosen distortion model,
rejection of bad views, per-view and overall reprojection error, and a check image.

Models (OpenCV's coefficient order k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4):
- ``standard``: k1 k2 p1 p2 k3 (OpenCV's default);
- ``paper``: the seed's model: radial k1..k3, tangential p1 p2, thin prism. The seed's prism terms p_x, p_y
  are OpenCV's s1, s3; OpenCV's thin-prism model adds the second-order s2, s4 and can hold the four prism
  terms only together, so the paper model is fitted as OpenCV's k1 k2 p1 p2 k3 + s1..s4 (s2, s4 come out
  near zero on a lens the seed's model describes; they are reported, not hidden);
- ``rational``: k1..k6 p1 p2;
- ``full``: rational + thin prism.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..camera import N_DIST, CameraModel
from ..errors import CalibrationError
from .boards import Board

log = logging.getLogger(__name__)

MODELS = {
    "standard": 0,
    "paper": cv2.CALIB_THIN_PRISM_MODEL,
    "rational": cv2.CALIB_RATIONAL_MODEL,
    "full": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL,
}


@dataclass
class LensResult:
    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict[str, float]
    rejected: dict[str, str]  # view -> why
    model: str
    detections: dict = field(default_factory=dict)  # view -> (image points, ids)

    def summary(self) -> dict:
        return {"model": self.model, "rms_px": self.rms_px, "views_used": len(self.per_view_rms_px),
                "per_view_rms_px": self.per_view_rms_px, "rejected": self.rejected,
                "K": self.camera.K.tolist(), "dist": list(self.camera.dist)}


def load_images(paths: list[str]) -> dict[str, np.ndarray]:
    images = {}
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_COLOR)
        if img is None:
            raise CalibrationError(f"{p}: cannot read the image (missing, or not an image file)")
        images[p] = img
    if not images:
        raise CalibrationError("no calibration images given")
    sizes = {im.shape[:2] for im in images.values()}
    if len(sizes) > 1:
        raise CalibrationError(f"calibration images have different sizes: {sorted(sizes)}; use one camera mode")
    return images


def _calibrate(obj, img, size, model: str, K0=None, d0=None):
    flags = MODELS[model]
    K = None if K0 is None else K0.copy()
    d = None if d0 is None else d0.copy()
    if K is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, d, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(obj, img, size, K, d, flags=flags,
                                                                          criteria=crit)
    d = np.asarray(d, np.float64).ravel()
    d = np.concatenate([d, np.zeros(max(0, N_DIST - len(d)))])[:N_DIST]  # OpenCV may add tauX, tauY
    return float(rms), K, d, rvecs, tvecs, np.asarray(per_view).ravel()


def calibrate_lens(images: dict[str, np.ndarray], board: Board, model: str = "paper",
                   reject_factor: float = 3.0, min_views: int = 4) -> LensResult:
    if model not in MODELS:
        raise CalibrationError(f"unknown lens model '{model}' (known: {', '.join(MODELS)})")
    h, w = next(iter(images.values())).shape[:2]
    rejected: dict[str, str] = {}
    detections = {}
    for name, img in images.items():
        found = board.detect(img)
        if found is None:
            rejected[name] = "board not found"
        elif len(found[0]) < 6:
            rejected[name] = f"only {len(found[0])} corners"
        else:
            detections[name] = found
    if len(detections) < min_views:
        raise CalibrationError(f"the board ({board.kind} {board.cols}x{board.rows}) was found in {len(detections)} "
                               f"of {len(images)} images; at least {min_views} are needed (check --board: inner "
                               f"corners for a chessboard)")
    objp = board.object_points
    names = list(detections)
    while True:
        obj = [objp[detections[n][1]].astype(np.float32) for n in names]
        img = [detections[n][0].astype(np.float32).reshape(-1, 1, 2) for n in names]
        rms, K, d, rvecs, tvecs, per_view = _calibrate(obj, img, (w, h), model)
        # views far worse than the others (a blurred frame, a mis-ordered detection) are dropped, once each
        limit = max(reject_factor * float(np.median(per_view)), 1.0)
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit or len(names) <= min_views:
            break
        rejected[names[worst]] = f"reprojection RMS {per_view[worst]:.2f} px > {limit:.2f} px"
        log.info("rejecting %s (RMS %.2f px)", names[worst], per_view[worst])
        names.pop(worst)
    camera = CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d.tolist()))
    return LensResult(camera, rms, {n: float(e) for n, e in zip(names, per_view)}, rejected, model,
                      {n: detections[n] for n in names})


def save_check_image(path: str | Path, result: LensResult, images: dict[str, np.ndarray]) -> None:
    """Detected corners on the best view, next to that view undistorted (straight lines should be straight)."""
    name = min(result.per_view_rms_px, key=result.per_view_rms_px.get)
    image = images[name].copy()
    pts, _ = result.detections[name]
    for u, v in pts:
        cv2.circle(image, (int(round(u)), int(round(v))), 3, (0, 0, 255), 1, cv2.LINE_AA)
    cam = result.camera
    und = cv2.undistort(images[name], cam.K, cam.dist_array)
    canvas = np.hstack([image, und])
    cv2.putText(canvas, f"{Path(name).name}: corners", (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 255, 0), 2)
    cv2.putText(canvas, f"undistorted ({result.model}, RMS {result.rms_px:.3f} px)", (image.shape[1] + 10, 24),
                cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 255, 0), 2)
    if not cv2.imwrite(str(path), canvas):
        raise CalibrationError(f"cannot write the check image '{path}'")
