"""Hand-eye calibration: the camera's pose on the scope tip (T_tip_camera, "X") from stations where the
robot's tip pose A_i = T_base_tip is known from kinematics and the camera sees a board (C_i = T_camera_board
from PnP): A_i X C_i = T_base_board for every station.

1. OpenCV's closed-form solvers of AX = XB (Tsai, Park, Horaud, Andreff, Daniilidis).
2. A joint robust refinement in GTSAM: unknowns X, the board pose B = T_base_board and every station's tip
   pose T_i (with the robot's reading as a prior: the joints are not exact either), one factor per station
   on the board corners' reprojection error under a Cauchy loss, started from the best closed-form X.
3. Consistency per station (the board pose each station implies, against their consensus) and warnings
   for motion that cannot determine X well.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, T, X

from lapreco_hil.camera import CameraModel
from lapreco_hil.errors import CalibrationError
from lapreco_hil.geometry import make_T, rotation_angle
from lapreco_hil.calib.boards import Board

log = logging.getLogger(__name__)

METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


@dataclass
class Station:
    name: str
    T_base_tip: np.ndarray  # robot kinematics
    T_camera_board: np.ndarray  # PnP
    object_points: np.ndarray  # (M, 3) board frame
    uv: np.ndarray  # (M, 2) undistorted pixels (pinhole K)


def board_station(name: str, image: np.ndarray, board: Board, camera: CameraModel,
                  T_base_tip: np.ndarray, min_corners: int = 8) -> Station | None:
    found = board.detect(image)
    if found is None or len(found[0]) < min_corners:
        return None
    pts, ids = found
    obj = board.object_points[ids]
    ok, rvec, tvec = cv2.solvePnP(obj, pts, camera.K, camera.dist_array, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, pts, camera.K, camera.dist_array, rvec, tvec)
    return Station(name, T_base_tip, make_T(cv2.Rodrigues(rvec)[0], tvec), obj, camera.undistort_pixels(pts))


def motion_warnings(stations: list[Station], min_rotation_deg: float = 5.0) -> list[str]:
    """What makes X poorly determined: too little rotation between stations, or rotations about (nearly)
    parallel axes (then the translation along that axis is unobservable)."""
    axes, angles = [], []
    for i in range(len(stations)):
        for j in range(i + 1, len(stations)):
            R = stations[i].T_base_tip[:3, :3].T @ stations[j].T_base_tip[:3, :3]
            rv = cv2.Rodrigues(R)[0].ravel()
            angle = float(np.linalg.norm(rv))
            angles.append(angle)
            if angle > np.deg2rad(1.0):
                axes.append(rv / angle)
    warnings = []
    max_deg = float(np.degrees(max(angles))) if angles else 0.0
    if max_deg < min_rotation_deg:
        warnings.append(f"too little rotation between stations (largest {max_deg:.1f} deg, want >= "
                        f"{min_rotation_deg:.0f} deg): rotate the scope more between views")
    if len(axes) >= 2:
        s = np.linalg.svd(np.array(axes), compute_uv=False)
        if s[1] / s[0] < 0.2:
            warnings.append(f"rotations between stations are about nearly parallel axes (spread {s[1] / s[0]:.2f}): "
                            f"rotate about at least two different axes")
    elif len(stations) >= 2:
        warnings.append("fewer than two rotations between stations: the hand-eye is undetermined")
    return warnings


def solve_closed_form(stations: list[Station], method: str) -> np.ndarray:
    if len(stations) < 3:
        raise CalibrationError(f"hand-eye needs at least 3 stations where the board is seen, got {len(stations)}")
    R, t = cv2.calibrateHandEye([s.T_base_tip[:3, :3] for s in stations], [s.T_base_tip[:3, 3] for s in stations],
                                [s.T_camera_board[:3, :3] for s in stations],
                                [s.T_camera_board[:3, 3] for s in stations], method=METHODS[method])
    return make_T(R, t.ravel())


def board_in_base(stations: list[Station], X_: np.ndarray) -> np.ndarray:
    """(N, 4, 4) the board pose each station implies: A_i X C_i."""
    return np.array([s.T_base_tip @ X_ @ s.T_camera_board for s in stations])


def station_consistency(stations: list[Station], X_: np.ndarray) -> dict:
    """Each station's implied board pose against the consensus (chordal mean rotation, median translation):
    rotation (deg) and translation (mm) residuals per station, with RMS."""
    Bs = board_in_base(stations, X_)
    U, _, Vt = np.linalg.svd(Bs[:, :3, :3].sum(axis=0))
    R_mean = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    t_med = np.median(Bs[:, :3, 3], axis=0)
    rot = np.array([np.degrees(rotation_angle(R_mean.T @ b[:3, :3])) for b in Bs])
    trans = np.linalg.norm(Bs[:, :3, 3] - t_med, axis=1) * 1e3
    return {"rotation_rms_deg": float(np.sqrt(np.mean(rot**2))), "translation_rms_mm": float(np.sqrt(np.mean(trans**2))),
            "per_station": {s.name: {"rotation_deg": float(r), "translation_mm": float(d)}
                            for s, r, d in zip(stations, rot, trans)}}


def _pose3(T_: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(T_[:3, :3]), gtsam.Point3(*T_[:3, 3]))


def _reprojection(K: np.ndarray, tip: gtsam.Pose3, x: gtsam.Pose3, b: gtsam.Pose3, obj: np.ndarray,
                  uv: np.ndarray) -> np.ndarray:
    T_cam_board = (tip.compose(x)).inverse().compose(b).matrix()
    pc = obj @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    proj = pc[:, :2] / pc[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return (proj - uv).ravel()


def _station_factor(K, station: Station, index: int, noise) -> gtsam.CustomFactor:
    obj, uv = station.object_points, station.uv
    eps = 1e-6

    def error(this, values, H):
        poses = [values.atPose3(k) for k in (T(index), X(0), B(0))]
        r0 = _reprojection(K, *poses, obj, uv)
        if H is not None:
            for slot in range(3):
                J = np.empty((len(r0), 6))
                for d in range(6):
                    delta = np.zeros(6)
                    delta[d] = eps
                    moved = list(poses)
                    moved[slot] = poses[slot].retract(delta)
                    plus = _reprojection(K, *moved, obj, uv)
                    moved[slot] = poses[slot].retract(-delta)
                    J[:, d] = (plus - _reprojection(K, *moved, obj, uv)) / (2 * eps)
                H[slot] = J
        return r0

    return gtsam.CustomFactor(noise, [T(index), X(0), B(0)], error)


def refine(stations: list[Station], X0: np.ndarray, camera: CameraModel, sigma_px: float = 0.5,
           robot_rot_sigma: float = 0.003, robot_trans_sigma: float = 0.0005, cauchy_k: float = 2.0
           ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """(X, B, per-station reprojection RMS in px) from the joint robust refinement."""
    K = camera.K
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([robot_rot_sigma] * 3 + [robot_trans_sigma] * 3))
    Bs = board_in_base(stations, X0)
    B0 = Bs[int(np.argmin([np.linalg.norm(b[:3, 3] - np.median(Bs[:, :3, 3], axis=0)) for b in Bs]))]
    values.insert(X(0), _pose3(X0))
    values.insert(B(0), _pose3(B0))
    for i, s in enumerate(stations):
        values.insert(T(i), _pose3(s.T_base_tip))
        graph.add(gtsam.PriorFactorPose3(T(i), _pose3(s.T_base_tip), prior))
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k),
                                               gtsam.noiseModel.Isotropic.Sigma(2 * len(s.uv), sigma_px))
        graph.add(_station_factor(K, s, i, noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    X_ = result.atPose3(X(0)).matrix()
    B_ = result.atPose3(B(0)).matrix()
    per_station = {}
    for i, s in enumerate(stations):
        r = _reprojection(K, result.atPose3(T(i)), result.atPose3(X(0)), result.atPose3(B(0)), s.object_points, s.uv)
        per_station[s.name] = float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2))
    return X_, B_, per_station


def pose_difference(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two transforms."""
    return float(np.degrees(rotation_angle(Ta[:3, :3].T @ Tb[:3, :3]))), \
        float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) * 1e3)


def calibrate_hand_eye(stations: list[Station], camera: CameraModel, **refine_options) -> dict:
    """Every closed-form method, the refinement from the most consistent one, consistency and warnings."""
    warnings = motion_warnings(stations)
    for w in warnings:
        log.warning("hand-eye: %s", w)
    methods, failed = {}, {}
    for name in METHODS:
        try:
            Xm = solve_closed_form(stations, name)
        except cv2.error as exc:  # a method can break down on some data (e.g. Andreff's normalisation)
            failed[name] = str(exc).strip().splitlines()[-1]
            log.warning("hand-eye method %s failed: %s", name, failed[name])
            continue
        if not np.all(np.isfinite(Xm)):
            failed[name] = "no finite solution (degenerate motion?)"
            continue
        methods[name] = {"T_tip_camera": Xm, **station_consistency(stations, Xm)}
    if not methods:
        raise CalibrationError(f"every hand-eye method failed: {failed}")
    best = min(methods, key=lambda n: methods[n]["translation_rms_mm"] + methods[n]["rotation_rms_deg"])
    X_, B_, reproj = refine(stations, methods[best]["T_tip_camera"], camera, **refine_options)
    return {"methods": methods, "initial_method": best, "T_tip_camera": X_, "T_base_board": B_,
            "refined": {**station_consistency(stations, X_), "reprojection_rms_px": reproj},
            "warnings": warnings, "stations": len(stations), "failed_methods": failed}
