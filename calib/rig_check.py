"""Whether a stereo rig's extrinsics fit its images: the usual mistakes in a hand-written rig (the inverse of
``T_cam0_cam[k]``, a length in the wrong unit, the wrong calibration) leave a run with almost no points and no
word why. Features matched between camera 0 and camera k of one frame say which it is:

- the matches' epipolar distances to the rig's essential matrix and to its inverse's, each judged on its own
  (most within a few pixels when it fits; a free essential matrix fitted to the same matches shows whether the
  matches themselves are good): a rig rotated by a fraction of a degree, given inverted, fits only its inverse;
- where they triangulate: in front of both cameras (an inverse rig puts them behind: with a rotation near the
  identity the inverse has nearly the same epipolar lines, so only the depths' sign tells), at a working distance
  a scope can have (a baseline in millimetres read as metres puts the scene a thousand times too far).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lapreco_hil.calib.time_offset import signed_sampson_of_pairs, skew_matrices
from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.geometry import inv_T

MIN_MATCHES = 25  # fewer, and the rig is not judged
# a match fits an essential matrix within this Sampson distance (camera 0's pixels) per EPIPOLAR_PER_PX of the
# image's longer side, and never less: a good calibration's residual grows with the resolution (a tracked 1080p
# scope's own hand-eye rig: 38% of matches within 2 px, 75% within 4 px)
EPIPOLAR_PX = 2.0
EPIPOLAR_PER_PX = 960
FITS = 0.5  # the share of matches within the epipolar distance for an essential matrix to fit them
IN_FRONT = 0.8  # the share of fitting matches in front of both cameras for a rig the right way round
# working distances a laparoscope sees tissue at (m): a median depth outside this is a unit mistake
DEPTH_RANGE_M = (0.002, 1.0)


@dataclass(frozen=True)
class RigFit:
    camera: int  # k: camera 0 against camera k
    matches: int
    fitting_share: float  # of the matches within epipolar_distance_px of the rig's epipolar lines
    free_fitting_share: float  # ... of a free essential matrix's (what the matches allow at best)
    in_front_share: float  # of the fitting matches, triangulated in front of both cameras with the rig
    inverse_fitting_share: float  # of the matches within epipolar_distance_px of the inverse's epipolar lines
    inverse_in_front_share: float  # of the matches fitting the inverse, in front of both cameras with it
    median_depth_m: float  # of the fitting matches in front, in camera 0
    problem: str | None  # a one-line statement of what is wrong and what to do; None: the rig fits

    def summary(self) -> dict:
        return {"camera": self.camera, "matches": self.matches, "fitting_share": round(self.fitting_share, 3),
                "free_fitting_share": round(self.free_fitting_share, 3),
                "in_front_share": round(self.in_front_share, 3),
                "inverse_fitting_share": round(self.inverse_fitting_share, 3),
                "inverse_in_front_share": round(self.inverse_in_front_share, 3),
                # None: no fitting match in front of both cameras (report.json keeps to strict JSON)
                "median_depth_m": self.median_depth_m if np.isfinite(self.median_depth_m) else None,
                "problem": self.problem}


def _matches(image0: np.ndarray, image_k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matches between camera 0's and camera k's images, distorted pixels, assuming nothing of the rig: corners
    followed by pyramidal LK with a forward-backward check (smooth, specular tissue has few blobs but many
    corners), and SIFT matches (Lowe's ratio, mutual) for what LK cannot reach."""
    grey = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im for im in (image0, image_k)]
    found0, found_k = [], []
    p0 = cv2.goodFeaturesToTrack(grey[0], 2000, 0.001, 5)
    if p0 is not None:
        lk = dict(winSize=(21, 21), maxLevel=4)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(grey[0], grey[1], p0, None, **lk)
        back, st_back, _ = cv2.calcOpticalFlowPyrLK(grey[1], grey[0], p1, None, **lk)
        ok = (st[:, 0] == 1) & (st_back[:, 0] == 1) & (np.linalg.norm(back - p0, axis=2)[:, 0] < 0.5)
        found0.append(p0[ok, 0])
        found_k.append(p1[ok, 0])
    sift = cv2.SIFT_create(nfeatures=4000, contrastThreshold=0.01)
    (kp0, d0), (kp1, d1) = (sift.detectAndCompute(g, None) for g in grey)
    if d0 is not None and d1 is not None and len(kp0) >= 2 and len(kp1) >= 2:
        matcher = cv2.BFMatcher(cv2.NORM_L2)
        backward = {m.queryIdx: m.trainIdx for m in matcher.match(d1, d0)}
        pairs = [(m.queryIdx, m.trainIdx) for m, n in (p for p in matcher.knnMatch(d0, d1, k=2) if len(p) == 2)
                 if m.distance < 0.8 * n.distance and backward.get(m.trainIdx) == m.queryIdx]
        if pairs:
            i0, i1 = np.array(pairs).T
            found0.append(np.array([kp0[i].pt for i in i0], float))
            found_k.append(np.array([kp1[i].pt for i in i1], float))
    if not found0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(found0).astype(float), np.concatenate(found_k).astype(float)


def _normalised(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.dist_array).reshape(-1, 2)


def _sampson_px(E: np.ndarray, x0: np.ndarray, xk: np.ndarray, f: float) -> np.ndarray:
    """Sampson distances (pixels at focal length f) of normalised matches to E, with x0^T E xk = 0."""
    return np.abs(signed_sampson_of_pairs(E[None], np.zeros(len(x0), np.int64), xk, x0, f))


def _essential(T_cam0_camk: np.ndarray) -> np.ndarray:
    return skew_matrices(T_cam0_camk[None, :3, 3])[0] @ T_cam0_camk[:3, :3]


def _depths(T_cam0_camk: np.ndarray, x0: np.ndarray, xk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths of the triangulated matches in camera 0 and in camera k."""
    T_k0 = inv_T(T_cam0_camk)
    X = cv2.triangulatePoints(np.eye(3, 4), T_k0[:3], x0.T, xk.T)
    X = (X[:3] / X[3]).T
    return X[:, 2], (X @ T_k0[:3, :3].T + T_k0[:3, 3])[:, 2]


def _judged(T_cam0_camk: np.ndarray, x0: np.ndarray, xk: np.ndarray, f: float,
            epipolar_px: float) -> tuple[float, float, float]:
    """(the share of the matches within ``epipolar_px`` of the transform's epipolar lines, the share of those
    triangulated in front of both cameras, their median depth in camera 0: NaN when none)."""
    fitting = _sampson_px(_essential(T_cam0_camk), x0, xk, f) <= epipolar_px
    if fitting.sum() < MIN_MATCHES // 2:
        return float(np.mean(fitting)), 0.0, float("nan")
    z0, zk = _depths(T_cam0_camk, x0[fitting], xk[fitting])
    front = (z0 > 0) & (zk > 0)
    median_depth = float(np.median(z0[front])) if front.any() else float("nan")
    return float(np.mean(fitting)), float(np.mean(front)), median_depth


def epipolar_distance_px(camera: CameraModel) -> float:
    """The Sampson distance within which a match fits an essential matrix, for a camera of this size."""
    return EPIPOLAR_PX * max(1.0, max(camera.width, camera.height) / EPIPOLAR_PER_PX)


def check_rig_pair(rig: Rig, k: int, image0: np.ndarray, image_k: np.ndarray) -> RigFit | None:
    """How well ``rig.T_cam0_cam[k]`` fits one frame's images of camera 0 and camera k; None when too few
    features match to judge."""
    uv0, uvk = _matches(image0, image_k)
    if len(uv0) < MIN_MATCHES:
        return None
    cam0, camk = rig.cameras[0], rig.cameras[k]
    x0, xk = _normalised(cam0, uv0), _normalised(camk, uvk)
    f = float(cam0.K[0, 0])
    T = np.asarray(rig.T_cam0_cam[k], float)
    epipolar_px = epipolar_distance_px(cam0)
    E_free, _ = cv2.findEssentialMat(xk, x0, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=epipolar_px / f)
    free_share = 0.0
    if E_free is not None and E_free.shape == (3, 3):
        # findEssentialMat(points1=xk, points2=x0) gives x0^T E xk = 0, as the rig's
        free_share = float(np.mean(_sampson_px(E_free, x0, xk, f) <= epipolar_px))
    # the given transform and its inverse, each judged on the matches that fit it: with a rotation near the
    # identity both fit the same matches and only the depths' sign tells; with a rotation of a fraction of a
    # degree (a real rig) the inverse's epipolar lines are already pixels off, so only its own matches fit it
    fit_share, in_front, median_depth = _judged(T, x0, xk, f, epipolar_px)
    inverse_fit_share, inverse_in_front, _ = _judged(inv_T(T), x0, xk, f, epipolar_px)
    field = f"rig.T_cam0_cam[{k}]"
    problem = None
    right_way = fit_share >= FITS and in_front >= IN_FRONT
    if inverse_fit_share >= FITS and inverse_in_front >= IN_FRONT and not right_way:
        problem = (f"{field} looks inverted: {fit_share:.0%} of {len(uv0)} matches between camera 0 and camera {k} "
                   f"lie within {epipolar_px:g} px of its epipolar lines ({in_front:.0%} of those in front of both "
                   f"cameras), {inverse_fit_share:.0%} of its inverse's ({inverse_in_front:.0%} in front); "
                   f"T_cam0_cam[{k}] maps points from camera {k} to camera 0 (a stereo calibration's R, T map camera "
                   f"0 to camera {k}: give their inverse)")
    elif fit_share < FITS and free_share >= FITS:
        problem = (f"{field} does not fit the images: {fit_share:.0%} of {len(uv0)} matches between camera 0 and "
                   f"camera {k} lie within {epipolar_px:g} px of its epipolar lines, {free_share:.0%} of a free fit's "
                   f"({inverse_fit_share:.0%} of its inverse's); check the extrinsics and each camera's K and "
                   "distortion against the calibration")
    elif right_way and not (DEPTH_RANGE_M[0] <= median_depth <= DEPTH_RANGE_M[1]):
        problem = (f"{field}: the matched points lie at a median depth of {median_depth:.4g} m with a baseline of "
                   f"{rig.baseline_m(k):.4g} m; a scope sees tissue at {DEPTH_RANGE_M[0]:g}-{DEPTH_RANGE_M[1]:g} m: "
                   "is units.length right (the rig's translations are in it)?")
    return RigFit(k, len(uv0), fit_share, free_share, in_front, inverse_fit_share, inverse_in_front, median_depth,
                  problem)


def check_rig(rig: Rig, images: tuple[np.ndarray, ...]) -> list[RigFit]:
    """``check_rig_pair`` for every camera k >= 1 of a stereo rig, on one frame's images (camera 0's first);
    the pairs too poor in features to judge are left out."""
    fits = [check_rig_pair(rig, k, images[0], images[k]) for k in range(1, len(rig))]
    return [f for f in fits if f is not None]
