"""Lens calibration with OpenCV: board detection, the distortion model chosen by how well each model predicts
views it was not fitted to, parameter uncertainties, rejection of bad views, a picture of where the corners
fell, and a check image.

Models (OpenCV's coefficient order k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4):
- ``k1k2p1p2``: k1 k2 p1 p2, k3 held at 0 (4 coefficients: Bouguet's toolbox default);
- ``standard``: k1 k2 p1 p2 k3 (OpenCV's default, 5 coefficients);
- ``paper``: the seed's model: radial k1..k3, tangential p1 p2, thin prism. The seed's prism terms p_x, p_y
  are OpenCV's s1, s3; OpenCV's thin-prism model adds the second-order s2, s4 and can hold the four prism
  terms only together, so the paper model is fitted as OpenCV's k1 k2 p1 p2 k3 + s1..s4;
- ``rational``: k1..k6 p1 p2 (8);
- ``full``: rational + thin prism (12);
- ``auto`` (the default): standard, rational and full, and cv2.fisheye (k1..k4 on the angle), each scored by
  k-fold cross-validation over views (each view's corners predicted by a model fitted to the other folds, the
  view's own pose fitted by PnP); the SIMPLEST model whose held-out RMS is within 5% of the best is taken.
  A model whose principal point has a standard deviation over 5 px (fitted to all views) competes only when
  all do: on the Viking laparoscope the thin-prism model predicted held-out views 6% better than the standard
  one while its principal point (std 6.3 px) sat 180 px from the owner's.
  Tangential and thin-prism terms trade off against the principal point; a model that lowers the fitted RMS
  by absorbing noise does not predict new views better, and this choice does not take it.
  The app's camera model is OpenCV's pinhole model: when fisheye predicts held-out views clearly (>5%) better
  than every pinhole model, the best pinhole model is kept and a warning says so.

Views: a view whose RMS is over ``max(3 x the median view RMS, 1 px)`` is dropped (the worst first, one at a
time, refitting in between, never below ``min_views``) and named in ``rejected`` with its RMS.
Warnings: principal point standard deviation over 5 px; under 1% of the corners in a part (of a 3x3 split) of
the image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import N_DIST, CameraModel
from lapreco_hil.errors import CalibrationError
from lapreco_hil.calib.boards import Board

log = logging.getLogger(__name__)

MODELS = {
    # radial k1 k2 and tangential p1 p2 (k3 held at 0): Bouguet's toolbox default, what many scopes' owners ship;
    # it cannot bend in the corners a board rarely reaches, as a fitted k3 can
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "standard": 0,
    "paper": cv2.CALIB_THIN_PRISM_MODEL,
    "rational": cv2.CALIB_RATIONAL_MODEL,
    "full": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL,
}
# simplest first; k1k2p1p2 is offered by name only: on the Viking scope it was within 5% of the standard model's
# held-out RMS and moved fx 6 px away from the owner's (docs/calibration.md)
AUTO_CANDIDATES = ("standard", "rational", "full", "fisheye")
N_COEFFS = {"k1k2p1p2": 4, "standard": 5, "paper": 9, "rational": 8, "full": 12, "fisheye": 4}
AUTO_TOLERANCE = 0.05  # a simpler model within 5% of the best held-out RMS is taken
PP_STD_WARN_PX = 5.0
COVERAGE_MIN_SHARE = 0.01  # a part of the image (of a 3x3 split) with fewer corners than this share is named
COEFF_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
CELL_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
              ("bottom-left", "bottom", "bottom-right"))


@dataclass(frozen=True)
class ModelScore:
    model: str
    coefficients: int
    fit_rms_px: float | None
    held_out_rms_px: float | None
    error: str | None = None  # why the model could not be fitted
    pp_std_px: float | None = None  # the larger of the principal point's standard deviations (all views)


@dataclass
class LensResult:
    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict[str, float]
    rejected: dict[str, str]  # view -> why
    model: str
    detections: dict = field(default_factory=dict)  # view -> (image points, ids)
    std: dict[str, float] = field(default_factory=dict)  # parameter -> standard deviation (px or unitless)
    scores: list[ModelScore] = field(default_factory=list)  # the candidates of --model auto
    warnings: list[str] = field(default_factory=list)
    coverage: dict[str, int] = field(default_factory=dict)  # image part -> corners there

    def summary(self) -> dict:
        return {"model": self.model, "rms_px": self.rms_px, "views_used": len(self.per_view_rms_px),
                "per_view_rms_px": self.per_view_rms_px, "rejected": self.rejected,
                "K": self.camera.K.tolist(), "dist": list(self.camera.dist), "std": self.std,
                "model_choice": [s.__dict__ for s in self.scores], "warnings": self.warnings,
                "coverage": self.coverage}


def load_images(paths: list[str]) -> dict[str, np.ndarray]:
    images = {}
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_COLOR)
        if img is None:
            raise CalibrationError(f"{p}: cannot read the image (missing, or not an image file)")
        images[p] = img
    if not images:
        raise CalibrationError("no calibration images given")
    first: dict[tuple[int, int], str] = {}  # (height, width) -> the first image of that size
    for p, im in images.items():
        first.setdefault(im.shape[:2], p)
    if len(first) > 1:
        sizes = ", ".join(f"{p} is {w}x{h}" for (h, w), p in first.items())
        raise CalibrationError(f"calibration images have different sizes ({sizes}); give images of one camera "
                               f"mode only")
    return images


def detect_views(images: dict[str, np.ndarray], board: Board) -> tuple[dict, dict[str, str]]:
    """(view -> (image points, ids)) for the views where the board was found, and (view -> why not)."""
    detections, rejected = {}, {}
    for name, img in images.items():
        found = board.detect(img)
        if found is None:
            rejected[name] = "board not found"
        elif len(found[0]) < 6:
            rejected[name] = f"only {len(found[0])} corners"
        else:
            detections[name] = found
    return detections, rejected


def _pad(d) -> np.ndarray:
    d = np.asarray(d, np.float64).ravel()
    return np.concatenate([d, np.zeros(max(0, N_DIST - len(d)))])[:N_DIST]  # OpenCV may add tauX, tauY


def _calibrate(obj, img, size, model: str):
    """OpenCV's calibration; the richer models start from the standard model's solution (from OpenCV's own
    start, a rational fit can stall far from the optimum on a strongly distorted lens)."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    flags, K0, d0 = MODELS[model], None, None
    if model not in ("standard", "k1k2p1p2"):
        _, K0, d5, *_ = cv2.calibrateCamera(obj, img, size, None, None, criteria=crit)
        d0 = np.zeros(12 if flags & cv2.CALIB_THIN_PRISM_MODEL else 8)
        d0[:5] = np.ravel(d5)[:5]
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    rms, K, d, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(obj, img, size, K0, d0,
                                                                               flags=flags, criteria=crit)
    return float(rms), K, _pad(d), np.asarray(std_in).ravel(), np.asarray(per_view).ravel()


def _calibrate_fisheye(obj, img, size):
    flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, D, _, _ = cv2.fisheye.calibrate([o.reshape(-1, 1, 3).astype(np.float64) for o in obj],
                                            [i.reshape(-1, 1, 2).astype(np.float64) for i in img], size,
                                            None, None, flags=flags, criteria=crit)
    return float(rms), K, D


def _held_out_residuals(model: str, fit, obj: np.ndarray, img: np.ndarray) -> np.ndarray:
    """Pixel residuals of one view not used in the fit: its pose by PnP, its corners by the fitted model."""
    img = img.reshape(-1, 2).astype(np.float64)
    obj = obj.reshape(-1, 3).astype(np.float64)
    if model == "fisheye":
        K, D = fit
        norm = cv2.fisheye.undistortPoints(img.reshape(-1, 1, 2), K, D).reshape(-1, 2)
        _, rvec, tvec = cv2.solvePnP(obj, norm, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(obj, norm, np.eye(3), None, rvec, tvec)
        rvec, tvec = _refine_pose_fisheye(obj, img, rvec, tvec, K, D)  # in pixels, as the pinhole models are
        proj = cv2.fisheye.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, D)[0].reshape(-1, 2)
        return proj - img
    K, d = fit
    _, rvec, tvec = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_SQPNP)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, d, rvec, tvec)
    return cv2.projectPoints(obj, rvec, tvec, K, d)[0].reshape(-1, 2) - img


def _refine_pose_fisheye(obj, img, rvec, tvec, K, D):
    """The pose minimising the pixel residuals of the fisheye projection (Levenberg-Marquardt)."""
    from scipy.optimize import least_squares

    def res(x):
        p = cv2.fisheye.projectPoints(obj.reshape(-1, 1, 3), x[:3].reshape(3, 1), x[3:].reshape(3, 1), K, D)[0]
        return (p.reshape(-1, 2) - img).ravel()

    x = least_squares(res, np.concatenate([np.ravel(rvec), np.ravel(tvec)]), method="lm").x
    return x[:3].reshape(3, 1), x[3:].reshape(3, 1)


def score_model(model: str, obj: list, img: list, size: tuple[int, int], folds: int = 10) -> ModelScore:
    """Fitted RMS over all views and held-out RMS by k-fold cross-validation over views (view i in fold
    i mod k, k = min(views, folds))."""
    n = len(obj)
    k = min(n, folds)
    residuals = []
    try:
        pp_std = None
        if model == "fisheye":
            fit_rms = _calibrate_fisheye(obj, img, size)[0]
        else:
            fit_rms, _, _, std_in, _ = _calibrate(obj, img, size, model)
            pp_std = float(max(std_in[2], std_in[3]))
        for f in range(k):
            train = [i for i in range(n) if i % k != f]
            test = [i for i in range(n) if i % k == f]
            if model == "fisheye":
                _, K, D = _calibrate_fisheye([obj[i] for i in train], [img[i] for i in train], size)
                fit = (K, D)
            else:
                _, K, d, _, _ = _calibrate([obj[i] for i in train], [img[i] for i in train], size, model)
                fit = (K, d)
            residuals += [_held_out_residuals(model, fit, obj[i], img[i]) for i in test]
    except cv2.error as exc:
        return ModelScore(model, N_COEFFS[model], None, None, (exc.err or str(exc)).strip())
    e = np.concatenate(residuals)
    held = float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
    if not np.isfinite(held):
        return ModelScore(model, N_COEFFS[model], fit_rms, None, "held-out error is not finite", pp_std)
    return ModelScore(model, N_COEFFS[model], fit_rms, held, None, pp_std)


def choose_model(scores: list[ModelScore], tolerance: float = AUTO_TOLERANCE) -> tuple[str, list[str]]:
    """The simplest pinhole model within ``tolerance`` of the best held-out RMS, and warnings. A model whose
    principal point is uncertain (std over PP_STD_WARN_PX) competes only when every model's is."""
    ok = [s for s in scores if s.held_out_rms_px is not None]
    determined = [s for s in ok if s.pp_std_px is None or s.pp_std_px <= PP_STD_WARN_PX]
    if any(s.model != "fisheye" for s in determined):
        ok = determined
    pinhole = [s for s in ok if s.model != "fisheye"]
    if not pinhole:
        raise CalibrationError("no lens model could be fitted to these views (" +
                               "; ".join(f"{s.model}: {s.error}" for s in scores) + "); check the board spec")
    best = min(s.held_out_rms_px for s in ok)
    order = {m: i for i, m in enumerate(AUTO_CANDIDATES)}
    within = sorted((s for s in ok if s.held_out_rms_px <= best * (1 + tolerance)), key=lambda s: order[s.model])
    warnings = []
    if within[0].model == "fisheye":
        best_pin = min(pinhole, key=lambda s: s.held_out_rms_px)
        warnings.append(f"the fisheye model predicts held-out views better ({within[0].held_out_rms_px:.3f} px "
                        f"against {best_pin.held_out_rms_px:.3f} px for {best_pin.model}); the app takes pinhole "
                        f"models, so {best_pin.model} was kept")
        return best_pin.model, warnings
    return within[0].model, warnings


def coverage_cells(points: np.ndarray, width: int, height: int) -> dict[str, int]:
    """Corners in each of the 3x3 parts of the image."""
    cells = {}
    col = np.clip((points[:, 0] * 3 // width).astype(int), 0, 2)
    row = np.clip((points[:, 1] * 3 // height).astype(int), 0, 2)
    for r in range(3):
        for c in range(3):
            cells[CELL_NAMES[r][c]] = int(np.sum((row == r) & (col == c)))
    return cells


def calibrate_lens(images: dict[str, np.ndarray], board: Board, model: str = "auto",
                   reject_factor: float = 3.0, min_views: int = 4) -> LensResult:
    h, w = next(iter(images.values())).shape[:2]
    detections, rejected = detect_views(images, board)
    if len(detections) < min_views:
        raise CalibrationError(f"the board ({board.kind} {board.cols}x{board.rows}) was found in {len(detections)} "
                               f"of {len(images)} images; at least {min_views} are needed (check --board: inner "
                               f"corners for a chessboard, dots per row x rows for a circle grid)")
    return calibrate_detections(detections, (w, h), board, model, reject_factor, min_views, rejected)


def calibrate_detections(detections: dict, size: tuple[int, int], board: Board, model: str = "auto",
                         reject_factor: float = 3.0, min_views: int = 4,
                         rejected: dict[str, str] | None = None) -> LensResult:
    """Calibrate from detected points (view -> (image points (M, 2), ids into board.object_points))."""
    if model != "auto" and model not in MODELS:
        raise CalibrationError(f"unknown lens model '{model}' (known: auto, {', '.join(MODELS)})")
    if len(detections) < min_views:
        raise CalibrationError(f"{len(detections)} views with the board; at least {min_views} are needed")
    w, h = size
    rejected = dict(rejected or {})
    objp = board.object_points
    names = list(detections)

    def arrays(views):
        return ([objp[detections[n][1]].astype(np.float32) for n in views],
                [detections[n][0].astype(np.float32).reshape(-1, 1, 2) for n in views])

    reject_model = "standard" if model == "auto" else model
    while True:
        obj, img = arrays(names)
        per_view = _calibrate(obj, img, size, reject_model)[4]
        # views far worse than the others (a blurred frame, a mis-ordered detection) are dropped, once each
        limit = max(reject_factor * float(np.median(per_view)), 1.0)
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit or len(names) <= min_views:
            break
        rejected[names[worst]] = f"reprojection RMS {per_view[worst]:.2f} px > {limit:.2f} px"
        log.info("rejecting %s (RMS %.2f px)", names[worst], per_view[worst])
        names.pop(worst)

    warnings: list[str] = []
    scores: list[ModelScore] = []
    if model == "auto":
        scores = [score_model(m, obj, img, size) for m in AUTO_CANDIDATES]
        for s in scores:
            log.info("model %s: fitted %s px, held out %s px%s", s.model, s.fit_rms_px, s.held_out_rms_px,
                     f" ({s.error})" if s.error else "")
        model, warnings = choose_model(scores)
    rms, K, d, std_in, per_view = _calibrate(obj, img, size, model)
    std = {"fx": float(std_in[0]), "fy": float(std_in[1]), "cx": float(std_in[2]), "cy": float(std_in[3])}
    std.update({c: float(v) for c, v in zip(COEFF_NAMES, std_in[4:4 + N_DIST]) if v > 0})
    if max(std["cx"], std["cy"]) > PP_STD_WARN_PX:
        warnings.append(f"the principal point is uncertain (std cx {std['cx']:.1f} px, cy {std['cy']:.1f} px > "
                        f"{PP_STD_WARN_PX:.0f} px): add views with the board tilted and near the image corners")
    all_pts = np.concatenate([detections[n][0] for n in names])
    coverage = coverage_cells(all_pts, w, h)
    empty = [c for c, k in coverage.items() if k < COVERAGE_MIN_SHARE * len(all_pts)]
    if empty:
        warnings.append(f"few or no corners (under {COVERAGE_MIN_SHARE:.0%} of them) in the {', '.join(empty)} of "
                        f"the image: the distortion there is extrapolated; add views with the board there")
    for msg in warnings:
        log.warning(msg)
    camera = CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d.tolist()))
    return LensResult(camera, rms, {n: float(e) for n, e in zip(names, per_view)}, rejected, model,
                      {n: detections[n] for n in names}, std, scores, warnings, coverage)


def save_coverage_image(path: str | Path, result: LensResult, max_width: int = 960) -> None:
    """Where the corners fell over the image (one colour per view), with the 3x3 parts; nearly empty ones in red."""
    cam = result.camera
    s = min(1.0, max_width / cam.width)
    W, H = int(round(cam.width * s)), int(round(cam.height * s))
    canvas = np.full((H, W, 3), 255, np.uint8)
    total = sum(result.coverage.values())
    for r in range(3):
        for c in range(3):
            if result.coverage.get(CELL_NAMES[r][c], 1) < COVERAGE_MIN_SHARE * total:
                canvas[r * H // 3:(r + 1) * H // 3, c * W // 3:(c + 1) * W // 3] = (200, 200, 255)
    for k in (1, 2):
        cv2.line(canvas, (k * W // 3, 0), (k * W // 3, H), (160, 160, 160), 1)
        cv2.line(canvas, (0, k * H // 3), (W, k * H // 3), (160, 160, 160), 1)
    for n, (name, (pts, _)) in enumerate(result.detections.items()):
        hue = np.uint8(int(180 * n / max(1, len(result.detections))))
        colour = tuple(int(v) for v in cv2.cvtColor(np.array([[[hue, 255, 200]]], np.uint8), cv2.COLOR_HSV2BGR)[0, 0])
        for u, v in pts * s:
            cv2.circle(canvas, (int(round(u)), int(round(v))), 2, colour, -1, cv2.LINE_AA)
    cv2.putText(canvas, f"{len(result.detections)} views, {sum(len(p) for p, _ in result.detections.values())} "
                f"points ({cam.width}x{cam.height})", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1)
    if not cv2.imwrite(str(path), canvas):
        raise CalibrationError(f"cannot write the coverage image '{path}'")


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
