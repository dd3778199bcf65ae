"""Hand-eye calibration: the camera's pose on the scope tip (T_tip_camera, "X") from stations where the
robot's tip pose A_i = T_base_tip is known from kinematics and the camera sees a board (C_i = T_camera_board
from PnP): A_i X C_i = T_base_board for every station.

1. OpenCV's closed-form solvers of AX = XB (Tsai, Park, Horaud, Andreff, Daniilidis).
2. A joint robust refinement in GTSAM: unknowns X, the board pose B = T_base_board and every station's tip
   pose T_i (with the robot's reading as a prior: the joints are not exact either), one factor per station
   on the board corners' reprojection error under a Cauchy loss, started from the best closed-form X. This
   assumes nothing about the arm beyond a tip-pose error of a few mrad / a fraction of a mm (the default).
   On request (``refine="joints"``) the unknowns are the joint errors instead, with the arm's joint-error
   time constant and backlash as the caller states them (``refine_in_joint_space``).
3. Consistency per station (the board pose each station implies, against their consensus) and warnings
   for motion that cannot determine X well.

An optically tracked scope is the same problem with the tracker as the "robot" (the scope marker's pose in the
board marker's frame): ``calibrate_tracked_hand_eye`` (one camera, or a stereo pair as one hand-eye plus the
rig) and its held-out figure ``leave_one_view_out`` (docs/calibration-handeye.md).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, E, L, Q, T, X

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
    q: np.ndarray | None = None  # the joint reading T_base_tip came from (for the refinement in joint space)
    side: np.ndarray | None = None  # per joint, the side its backlash is on (-1..1, from the direction of motion)
    t_s: float | None = None  # when (for the joints' wander, correlated in time between stations)


def board_station(name: str, image: np.ndarray, board: Board, camera: CameraModel,
                  T_base_tip: np.ndarray, min_corners: int = 8, q: np.ndarray | None = None) -> Station | None:
    found = board.detect(image)
    if found is None or len(found[0]) < min_corners:
        return None
    pts, ids = found
    obj = board.object_points[ids]
    ok, rvec, tvec = cv2.solvePnP(obj, pts, camera.K, camera.dist_array, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, pts, camera.K, camera.dist_array, rvec, tvec)
    return Station(name, T_base_tip, make_T(cv2.Rodrigues(rvec)[0], tvec), obj, camera.undistort_pixels(pts), q)


# What makes X poorly determined (Tsai and Lenz 1989; Shah et al. 2012): X's rotation comes from the rotation
# axes of the motions between stations and its translation from how those rotations move the tip, so
# - the largest rotation between two stations must be well above the joints' and PnP's rotation noise
#   (a few mrad): below MIN_ROTATION_DEG the solution is mostly noise;
# - the rotation axes must spread over at least two directions: about one axis only, the translation along
#   it is unobservable. MIN_AXIS_SPREAD is the ratio of the second to the first singular value of the
#   stacked unit axes (0: all parallel, 1: two equally used directions);
# - a handful of stations gives the closed-form methods too little redundancy to expose a bad station.
MIN_ROTATION_DEG = 10.0
MIN_AXIS_SPREAD = 0.3
MIN_STATIONS = 10
# rotations between stations below this angle have no meaningful axis (noise) and are left out of the spread
AXIS_MIN_ANGLE_DEG = 1.0
# the methods' solutions should agree to about the noise; beyond these the data do not pin X down
MAX_METHOD_SPREAD_DEG = 0.5
MAX_METHOD_SPREAD_MM = 1.0
# a method this many times further from the consensus than the median method (and beyond the limits above)
# has broken down on these data rather than disagreeing within the noise
OUTLIER_FACTOR = 5.0


def motion_warnings(stations: list[Station], min_rotation_deg: float = MIN_ROTATION_DEG,
                    min_stations: int = MIN_STATIONS, more_views: str = "record longer or use a smaller --stride",
                    rotate: str = "rotate the scope more between views") -> list[str]:
    """What makes X poorly determined: too few stations, too little rotation between them, or rotations
    about (nearly) parallel axes (then the translation along that axis is unobservable). ``more_views`` and
    ``rotate`` are the advice, in the words of the set-up (a robot's session, a tracked scope)."""
    axes, angles = [], []
    for i in range(len(stations)):
        for j in range(i + 1, len(stations)):
            R = stations[i].T_base_tip[:3, :3].T @ stations[j].T_base_tip[:3, :3]
            rv = cv2.Rodrigues(R)[0].ravel()
            angle = float(np.linalg.norm(rv))
            angles.append(angle)
            if angle > np.deg2rad(AXIS_MIN_ANGLE_DEG):
                axes.append(rv / angle)
    warnings = []
    if len(stations) < min_stations:
        warnings.append(f"only {len(stations)} stations see the board (want >= {min_stations}): {more_views}")
    max_deg = float(np.degrees(max(angles))) if angles else 0.0
    if max_deg < min_rotation_deg:
        warnings.append(f"too little rotation between stations (largest {max_deg:.1f} deg, want >= "
                        f"{min_rotation_deg:.0f} deg): {rotate}")
    if len(axes) >= 2:
        s = np.linalg.svd(np.array(axes), compute_uv=False)
        if s[1] / s[0] < MIN_AXIS_SPREAD:
            warnings.append(f"rotations between stations are about nearly parallel axes (spread {s[1] / s[0]:.2f}, "
                            f"want >= {MIN_AXIS_SPREAD}): rotate about at least two different axes")
    elif len(stations) >= 2:
        warnings.append("fewer than two rotations between stations: the hand-eye is undetermined")
    return warnings


@contextlib.contextmanager
def _captured_stderr():
    """OpenCV's C++ code writes to fd 2 (e.g. "calibrateHandEyeTsai ... failed"); keep it off the console
    and hand it back as text (a list with one string, filled when the block ends)."""
    out: list[str] = []
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        try:
            saved = os.dup(2)
        except OSError:  # no fd 2 (an embedded interpreter): nothing to capture
            yield out
            return
        os.dup2(tmp.fileno(), 2)
        try:
            yield out
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            out.append(tmp.read().decode("utf-8", "replace"))


@contextlib.contextmanager
def _opencv_errors_logged():
    """OpenCV's hand-eye solvers report "failed" only through its logger, at ERROR: the app may have silenced
    that logger (lapreco_hil.app.noise), so it is let through to the (captured) stderr for the call."""
    saved = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(max(saved, cv2.utils.logging.LOG_LEVEL_ERROR))
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(saved)


def solve_closed_form(stations: list[Station], method: str) -> np.ndarray:
    """X by one of OpenCV's methods; CalibrationError when the method reports failure or gives no rigid,
    finite transform."""
    if len(stations) < 3:
        raise CalibrationError(f"hand-eye needs at least 3 stations where the board is seen, got {len(stations)}")
    with _captured_stderr() as err, _opencv_errors_logged():
        R, t = cv2.calibrateHandEye([s.T_base_tip[:3, :3] for s in stations],
                                    [s.T_base_tip[:3, 3] for s in stations],
                                    [s.T_camera_board[:3, :3] for s in stations],
                                    [s.T_camera_board[:3, 3] for s in stations], method=METHODS[method])
    message = " ".join(line.strip() for line in err[0].splitlines() if line.strip())
    if "fail" in message.lower():
        raise CalibrationError(f"OpenCV: {message}")
    if message:
        log.debug("hand-eye %s: OpenCV said: %s", method, message)
    R, t = np.asarray(R, float), np.asarray(t, float).ravel()
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise CalibrationError("no finite solution (degenerate motion?)")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError("the solution's rotation is not a rotation")
    return make_T(R, t)


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


def _optimize(graph, values):
    """Levenberg-Marquardt to a tight tolerance: the problems are small, the answer is the calibration."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def _rms_px(residuals: np.ndarray) -> float:
    """The RMS image distance (px) of stacked (u, v) residuals."""
    return float(np.sqrt(np.mean(residuals.reshape(-1, 2) ** 2) * 2))


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
    result = _optimize(graph, values)
    X_ = result.atPose3(X(0)).matrix()
    B_ = result.atPose3(B(0)).matrix()
    per_station = {}
    for i, s in enumerate(stations):
        r = _reprojection(K, result.atPose3(T(i)), result.atPose3(X(0)), result.atPose3(B(0)), s.object_points, s.uv)
        per_station[s.name] = _rms_px(r)
    return X_, B_, per_station


def _joint_station_factor(K, station: Station, index: int, tip_pose, noise) -> gtsam.CustomFactor:
    """Reprojection of one station's corners with its tip pose FK(q + dq): the unknown is the joint error dq."""
    obj, uv, q = station.object_points, station.uv, np.asarray(station.q, float)
    side = np.zeros(len(q)) if station.side is None else np.asarray(station.side, float)
    eps = 1e-6

    def residual(dq, x, b):
        return _reprojection(K, _pose3(tip_pose(q + dq)), x, b, obj, uv)

    def error(this, values, H):
        # the link is where the encoder reads, plus the play on the side of motion, plus the wander dq
        dq = values.atVector(Q(index)) + side * values.atVector(L(0))
        x, b = values.atPose3(X(0)), values.atPose3(B(0))
        r0 = residual(dq, x, b)
        if H is not None:
            J = np.empty((len(r0), len(dq)))
            for d in range(len(dq)):
                step = np.zeros(len(dq))
                step[d] = eps
                J[:, d] = (residual(dq + step, x, b) - residual(dq - step, x, b)) / (2 * eps)
            H[0] = J
            H[3] = J * side
            for slot, pose in ((1, x), (2, b)):
                Jp = np.empty((len(r0), 6))
                for d in range(6):
                    delta = np.zeros(6)
                    delta[d] = eps
                    args = [x, b]
                    args[slot - 1] = pose.retract(delta)
                    plus = residual(dq, *args)
                    args[slot - 1] = pose.retract(-delta)
                    Jp[:, d] = (plus - residual(dq, *args)) / (2 * eps)
                H[slot] = Jp
        return r0

    return gtsam.CustomFactor(noise, [Q(index), X(0), B(0), L(0)], error)


def _wander_factor(prev, this, a: float, noise) -> gtsam.CustomFactor:
    def error(factor, values, H):
        if H is not None:
            n = len(values.atVector(this))
            H[0] = -a * np.eye(n)
            H[1] = np.eye(n)
        return values.atVector(this) - a * values.atVector(prev)

    return gtsam.CustomFactor(noise, [prev, this], error)


REFINEMENTS = ("poses", "joints")


def refine_in_joint_space(stations: list[Station], X0: np.ndarray, camera: CameraModel, tip_pose,
                          joint_sigma, sigma_px: float = 0.5, huber_k: float = 1.345,
                          wander_time_s: float = 0.0, backlash=None) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """(X, B, per-station reprojection RMS in px): X, the board pose and every station's joint error dq
    (prior: the robot's joint sigma, per joint, SI) from the board corners' reprojections under Huber's loss.
    A joint error moves the tip the way the arm can move (a rotation about the remote centre carries its
    translation with it), which constrains the stations more than free 6-DOF tip poses do, IF the arm's
    errors are what this model says; state them for the arm at hand:

    - ``wander_time_s``: how long a deflection of the links from their readings lasts (elastic joints, cable
      stretch), as the time constant of an Ornstein-Uhlenbeck process: the joint errors of stations closer
      in time than this are linked. 0 (default): every station's joint error independent.
    - ``backlash``: per joint (or one value for all), the expected half-play of its transmission (rad or m),
      the prior sigma of one backlash per joint shared by the session and applied on the side of the
      direction of motion (``Station.side``). None or 0 (default): no backlash term.
    """
    if not (math.isfinite(wander_time_s) and wander_time_s >= 0):
        raise CalibrationError(f"the joints' wander time constant must be >= 0 s, got {wander_time_s!r}")
    K = camera.K
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    sigma = np.asarray(joint_sigma, float)
    prior = gtsam.noiseModel.Diagonal.Sigmas(sigma)
    Bs = board_in_base(stations, X0)
    B0 = Bs[int(np.argmin([np.linalg.norm(b[:3, 3] - np.median(Bs[:, :3, 3], axis=0)) for b in Bs]))]
    values.insert(X(0), _pose3(X0))
    values.insert(B(0), _pose3(B0))
    # the backlash, one per joint for the whole session, held to zero with the play the caller expects
    play = np.broadcast_to(np.asarray(0.0 if backlash is None else backlash, float), sigma.shape)
    if not np.all(np.isfinite(play) & (play >= 0)):
        raise CalibrationError(f"the joints' backlash must be >= 0 (rad or m) per joint, got {backlash!r}")
    values.insert(L(0), np.zeros(len(sigma)))
    graph.add(gtsam.PriorFactorVector(L(0), np.zeros(len(sigma)),
                                      gtsam.noiseModel.Diagonal.Sigmas(np.maximum(play, 1e-12))))
    timed = all(st.t_s is not None for st in stations) and wander_time_s > 0
    for i, s in enumerate(stations):
        values.insert(Q(i), np.zeros(len(sigma)))
        if not timed or i == 0:
            graph.add(gtsam.PriorFactorVector(Q(i), np.zeros(len(sigma)), prior))
        else:  # the wander as an Ornstein-Uhlenbeck process: dq_i = a dq_(i-1) + what is new since
            a = float(np.exp(-abs(s.t_s - stations[i - 1].t_s) / wander_time_s))
            graph.add(_wander_factor(Q(i - 1), Q(i), a, gtsam.noiseModel.Diagonal.Sigmas(
                sigma * np.sqrt(max(1 - a * a, 1e-6)))))
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
                                               gtsam.noiseModel.Isotropic.Sigma(2 * len(s.uv), sigma_px))
        graph.add(_joint_station_factor(K, s, i, tip_pose, noise))
    result = _optimize(graph, values)
    X_ = result.atPose3(X(0)).matrix()
    B_ = result.atPose3(B(0)).matrix()
    per_station = {}
    for i, s in enumerate(stations):
        side = np.zeros(len(sigma)) if s.side is None else s.side
        tip = _pose3(tip_pose(np.asarray(s.q, float) + result.atVector(Q(i)) + side * result.atVector(L(0))))
        r = _reprojection(K, tip, result.atPose3(X(0)), result.atPose3(B(0)), s.object_points, s.uv)
        per_station[s.name] = _rms_px(r)
    return X_, B_, per_station


def pose_difference(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two transforms."""
    return float(np.degrees(rotation_angle(Ta[:3, :3].T @ Tb[:3, :3]))), \
        float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) * 1e3)


def method_agreement(methods: dict[str, dict]) -> dict:
    """How far the methods' solutions lie from their consensus (chordal mean rotation, median translation),
    in deg and mm, per method and at most. A method far outside the others' spread (Andreff's linear
    translation is the usual one) is named an outlier and left out of the largest."""
    Xs = np.array([m["T_tip_camera"] for m in methods.values()])
    U, _, Vt = np.linalg.svd(Xs[:, :3, :3].sum(axis=0))
    R_mean = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    t_med = np.median(Xs[:, :3, 3], axis=0)
    per = {name: {"rotation_deg": float(np.degrees(rotation_angle(R_mean.T @ X[:3, :3]))),
                  "translation_mm": float(np.linalg.norm(X[:3, 3] - t_med) * 1e3)}
           for name, X in zip(methods, Xs)}
    med_rot = float(np.median([p["rotation_deg"] for p in per.values()]))
    med_trans = float(np.median([p["translation_mm"] for p in per.values()]))
    outliers = [name for name, p in per.items() if len(per) >= 3 and
                ((p["rotation_deg"] > OUTLIER_FACTOR * med_rot and p["rotation_deg"] > MAX_METHOD_SPREAD_DEG) or
                 (p["translation_mm"] > OUTLIER_FACTOR * med_trans and p["translation_mm"] > MAX_METHOD_SPREAD_MM))]
    kept = [p for name, p in per.items() if name not in outliers]
    return {"rotation_deg": max(p["rotation_deg"] for p in kept),
            "translation_mm": max(p["translation_mm"] for p in kept), "per_method": per, "outliers": outliers}


def calibrate_hand_eye(stations: list[Station], camera: CameraModel, refinement: str = "poses", tip_pose=None,
                       joint_sigma=None, **refine_options) -> dict:
    """Every closed-form method, the refinement from the most consistent one, its reprojection residual,
    the methods' agreement, and warnings (motion, disagreement, failed methods). ``refinement``: "poses"
    (default: free tip poses with a 6-DOF prior, ``refine``) or "joints" (the joint errors are the unknowns,
    ``refine_in_joint_space``; needs ``tip_pose`` (q -> the robot's T_base_tip), ``joint_sigma`` and the
    stations' joint readings). ``refine_options`` go to the refinement chosen."""
    if refinement not in REFINEMENTS:
        raise CalibrationError(f"hand-eye refinement '{refinement}' is not one of {', '.join(REFINEMENTS)}")
    if refinement == "joints" and (tip_pose is None or joint_sigma is None or any(st.q is None for st in stations)):
        raise CalibrationError("the joint-space hand-eye refinement needs the robot's kinematics, its joint "
                               "sigma and every station's joint reading")
    warnings = motion_warnings(stations)
    methods, failed, agreement = closed_form_methods(stations, warnings)
    for w in warnings:
        log.warning("hand-eye: %s", w)
    best = min(methods, key=lambda n: methods[n]["translation_rms_mm"] + methods[n]["rotation_rms_deg"])
    if refinement == "joints":
        X_, B_, reproj = refine_in_joint_space(stations, methods[best]["T_tip_camera"], camera, tip_pose,
                                               joint_sigma, **refine_options)
    else:
        X_, B_, reproj = refine(stations, methods[best]["T_tip_camera"], camera, **refine_options)
    per = np.array(list(reproj.values()))
    refined = {**station_consistency(stations, X_), "reprojection_rms_px": float(np.sqrt(np.mean(per**2))),
               "reprojection_per_station_px": reproj}
    return {"methods": methods, "initial_method": best, "T_tip_camera": X_, "T_base_board": B_,
            "refined": refined, "agreement": agreement, "warnings": warnings, "stations": len(stations),
            "failed_methods": failed, "refinement": refinement}


def closed_form_methods(stations: list[Station], warnings: list[str]) -> tuple[dict, dict, dict]:
    """(methods, failed, agreement): every closed-form method's X with its station consistency, the methods
    that failed and why, and their agreement; appends to ``warnings`` what they say about the data."""
    methods, failed = {}, {}
    for name in METHODS:
        try:
            Xm = solve_closed_form(stations, name)
        except (cv2.error, CalibrationError) as exc:  # a method can break down on some data
            failed[name] = (str(exc).strip().splitlines() or ["failed"])[-1]
            continue
        methods[name] = {"T_tip_camera": Xm, **station_consistency(stations, Xm)}
    if not methods:
        raise CalibrationError(f"every hand-eye method failed: {failed}")
    for name, why in failed.items():
        warnings.append(f"method {name} failed: {why}")
    agreement = method_agreement(methods)
    for name in agreement["outliers"]:
        p = agreement["per_method"][name]
        warnings.append(f"method {name} is far from the others ({p['rotation_deg']:.2f} deg / "
                        f"{p['translation_mm']:.1f} mm): left out of the agreement")
    if agreement["rotation_deg"] > MAX_METHOD_SPREAD_DEG or agreement["translation_mm"] > MAX_METHOD_SPREAD_MM:
        warnings.append(f"the methods disagree by up to {agreement['rotation_deg']:.2f} deg / "
                        f"{agreement['translation_mm']:.2f} mm (want <= {MAX_METHOD_SPREAD_DEG} deg / "
                        f"{MAX_METHOD_SPREAD_MM} mm): the motion does not pin the hand-eye down")
    return methods, failed, agreement


# --- an optically tracked scope ---------------------------------------------------------------------------------------
#
# A marker on the scope and a marker on the board, both seen by an optical tracker: in the board marker's frame the
# scope marker's pose A_i = T_boardmarker_scopemarker is known at every view (the tracker's "robot"), the camera
# sees the printed pattern (C_i = T_camera_pattern by PnP), and A_i X C_i = T_boardmarker_pattern for every view:
# the same AX = XB as a robot's, with X = T_scopemarker_camera and the pattern's place on its marker the constant.
# A stereo scope has two cameras on one marker: one hand-eye (the left camera's) and the rig T_left_right, both
# estimated, so the two cameras cannot disagree about the scope (two free hand-eyes would let each camera's own
# errors bend the rig that triangulation then uses).

# The tracker's error in a marker-to-marker pose, 1 sigma (an NDI Polaris is good to ~0.25 mm RMS per marker;
# a rotation of a few mrad from a marker ~5 cm across): the prior on every view's T_boardmarker_scopemarker
TRACKER_ROT_SIGMA = 0.003
TRACKER_TRANS_SIGMA = 0.0004
# a tracked scope's session is a handful of snapshots, not a robot's scan
MIN_TRACKED_VIEWS = 8
TRACKED_MORE_VIEWS = "take more tracked views"
TRACKED_ROTATE = "tilt the board (or the scope) more between views"


def tracker_pose(T_tracker_boardmarker_mm: np.ndarray, T_tracker_scopemarker_mm: np.ndarray) -> np.ndarray:
    """T_boardmarker_scopemarker in metres from the tracker's two marker poses (as trackers report them, mm)."""
    T_ = np.linalg.inv(np.asarray(T_tracker_boardmarker_mm, float)) @ np.asarray(T_tracker_scopemarker_mm, float)
    T_[:3, 3] *= 1e-3
    return T_


@dataclass
class TrackedView:
    name: str
    T_boardmarker_scopemarker: np.ndarray  # metres
    detections: dict  # camera ("left", "right") -> (pixels (M, 2) as seen, distorted; board point ids (M,))


def pattern_station(name: str, T_boardmarker_scopemarker: np.ndarray, pixels: np.ndarray, ids: np.ndarray,
                    board: Board, camera: CameraModel, min_points: int = 8) -> Station | None:
    """A station of one camera at one tracked view: the pattern's pose by PnP with the camera's lens."""
    if len(ids) < min_points:
        return None
    obj, pts = board.object_points[np.asarray(ids, int)], np.asarray(pixels, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, pts, camera.K, camera.dist_array, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, pts, camera.K, camera.dist_array, rvec, tvec)
    return Station(name, np.asarray(T_boardmarker_scopemarker, float), make_T(cv2.Rodrigues(rvec)[0], tvec), obj,
                   camera.undistort_pixels(pts))


def _camera_poses(tip: gtsam.Pose3, x: gtsam.Pose3, rig: gtsam.Pose3 | None) -> gtsam.Pose3:
    pose = tip.compose(x)
    return pose if rig is None else pose.compose(rig)


def _tracked_residual(K, poses, obj, uv) -> np.ndarray:
    tip, x, b = poses[:3]
    T_cam_board = _camera_poses(tip, x, poses[3] if len(poses) > 3 else None).inverse().compose(b).matrix()
    pc = obj @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    proj = pc[:, :2] / pc[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return (proj - uv).ravel()


def _tracked_factor(K, station: Station, keys: list, noise) -> gtsam.CustomFactor:
    """The dots' reprojections of one camera at one view: keys [T_i, X, B] (the hand-eye camera) or
    [T_i, X, B, E] (the other camera of the rig, at T_i X E)."""
    obj, uv = station.object_points, station.uv
    eps = 1e-6

    def error(this, values, H):
        poses = [values.atPose3(k) for k in keys]
        r0 = _tracked_residual(K, poses, obj, uv)
        if H is not None:
            for slot in range(len(keys)):
                J = np.empty((len(r0), 6))
                for d in range(6):
                    delta = np.zeros(6)
                    delta[d] = eps
                    moved = list(poses)
                    moved[slot] = poses[slot].retract(delta)
                    plus = _tracked_residual(K, moved, obj, uv)
                    moved[slot] = poses[slot].retract(-delta)
                    J[:, d] = (plus - _tracked_residual(K, moved, obj, uv)) / (2 * eps)
                H[slot] = J
        return r0

    return gtsam.CustomFactor(noise, keys, error)


def robust_pixel_scale(stations: list[Station], cameras: list[CameraModel]) -> float:
    """The dots' pixel noise (1 sigma) as the data show it: the MAD-scaled median of the PnP residuals of every
    camera at every view (what the refinement's loss is scaled to, rather than an assumed figure)."""
    res = []
    for s, cam in zip(stations, cameras):
        T_ = s.T_camera_board
        pc = s.object_points @ T_[:3, :3].T + T_[:3, 3]
        proj = pc[:, :2] / pc[:, 2:3] * np.array([cam.fx, cam.fy]) + np.array([cam.cx, cam.cy])
        res.append((proj - s.uv).ravel())
    r = np.concatenate(res)
    return float(max(1.4826 * np.median(np.abs(r - np.median(r))), 0.05))


def refine_tracked(stations: dict[str, list[Station]], cameras: dict[str, CameraModel], X0: np.ndarray,
                   T_left_right0: np.ndarray | None = None, sigma_px: float | None = None,
                   tracker_rot_sigma: float = TRACKER_ROT_SIGMA, tracker_trans_sigma: float = TRACKER_TRANS_SIGMA,
                   cauchy_k: float = 2.0) -> dict:
    """The joint robust refinement of a tracked scope: unknowns X = T_scopemarker_camera (of the first camera
    named in ``stations``), B = T_boardmarker_pattern, every view's T_boardmarker_scopemarker (the tracker's
    reading as a prior) and, with two cameras, the rig T_left_right (first camera -> second); the dots'
    reprojections under a Cauchy loss scaled to ``sigma_px`` (default: the data's own, ``robust_pixel_scale``).
    Stations of one view share its name (and so its tracker pose)."""
    sides = list(stations)
    if len(sides) == 2 and T_left_right0 is None:
        raise CalibrationError("a stereo hand-eye needs a starting rig T_left_right")
    if sigma_px is None:
        flat = [(s, cameras[side]) for side in sides for s in stations[side]]
        sigma_px = robust_pixel_scale([f[0] for f in flat], [f[1] for f in flat])
    names = list(dict.fromkeys(s.name for side in sides for s in stations[side]))  # the views, in order
    index = {n: i for i, n in enumerate(names)}
    tip = {s.name: s.T_base_tip for side in sides for s in stations[side]}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([tracker_rot_sigma] * 3 + [tracker_trans_sigma] * 3))
    Bs = board_in_base(stations[sides[0]], X0)
    B0 = Bs[int(np.argmin([np.linalg.norm(b[:3, 3] - np.median(Bs[:, :3, 3], axis=0)) for b in Bs]))]
    values.insert(X(0), _pose3(X0))
    values.insert(B(0), _pose3(B0))
    if len(sides) == 2:
        values.insert(E(0), _pose3(T_left_right0))
    for n, i in index.items():
        values.insert(T(i), _pose3(tip[n]))
        graph.add(gtsam.PriorFactorPose3(T(i), _pose3(tip[n]), prior))
    for c, side in enumerate(sides):
        for s in stations[side]:
            keys = [T(index[s.name]), X(0), B(0)] + ([E(0)] if c == 1 else [])
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k),
                                                   gtsam.noiseModel.Isotropic.Sigma(2 * len(s.uv), sigma_px))
            graph.add(_tracked_factor(cameras[side].K, s, keys, noise))
    result = _optimize(graph, values)
    rig = result.atPose3(E(0)) if len(sides) == 2 else None
    per_view: dict[str, dict[str, float]] = {}
    for c, side in enumerate(sides):
        for s in stations[side]:
            poses = [result.atPose3(T(index[s.name])), result.atPose3(X(0)), result.atPose3(B(0))]
            r = _tracked_residual(cameras[side].K, poses + ([rig] if c == 1 else []), s.object_points, s.uv)
            per_view.setdefault(side, {})[s.name] = _rms_px(r)
    tracker_moves = [pose_difference(tip[n], result.atPose3(T(i)).matrix()) for n, i in index.items()]
    return {"T_scopemarker_camera": result.atPose3(X(0)).matrix(),
            "T_boardmarker_pattern": result.atPose3(B(0)).matrix(),
            "T_left_right": None if rig is None else rig.matrix(), "sigma_px": sigma_px,
            "reprojection_per_view_px": per_view,
            "tracker_correction_rms_deg": float(np.sqrt(np.mean([m[0] ** 2 for m in tracker_moves]))),
            "tracker_correction_rms_mm": float(np.sqrt(np.mean([m[1] ** 2 for m in tracker_moves])))}


def tracked_stations(views: list[TrackedView], side: str, board: Board, camera: CameraModel) -> list[Station]:
    """One camera's stations (views where it saw enough of the pattern for PnP)."""
    out = []
    for v in views:
        if side in v.detections:
            st = pattern_station(v.name, v.T_boardmarker_scopemarker, *v.detections[side], board, camera)
            if st is not None:
                out.append(st)
    return out


def calibrate_tracked_hand_eye(views: list[TrackedView], board: Board, cameras: dict[str, CameraModel],
                               log_warnings: bool = True, **refine_options) -> dict:
    """Hand-eye of a tracked scope: per camera (``cameras``: one, or "left" and "right"), OpenCV's closed-form
    methods with their agreement and warnings; then the joint robust refinement (``refine_tracked``) of the
    first camera's hand-eye, the pattern on its marker and, with two cameras, the rig. The report: the
    refined transforms, the reprojection RMS (px) per camera, the tracker corrections, per-camera methods."""
    sides = list(cameras)
    if not 1 <= len(sides) <= 2:
        raise CalibrationError(f"a tracked hand-eye takes one camera or a stereo pair, got {len(sides)}")
    per_camera, stations, warnings = {}, {}, []
    for side in sides:
        st = tracked_stations(views, side, board, cameras[side])
        if len(st) < 3:
            raise CalibrationError(f"the {side} camera saw the pattern in {len(st)} of {len(views)} tracked views; "
                                   f"at least 3 are needed")
        side_warnings = motion_warnings(st, min_stations=MIN_TRACKED_VIEWS, more_views=TRACKED_MORE_VIEWS,
                                        rotate=TRACKED_ROTATE)
        methods, failed, agreement = closed_form_methods(st, side_warnings)
        best = min(methods, key=lambda n: methods[n]["translation_rms_mm"] + methods[n]["rotation_rms_deg"])
        per_camera[side] = {"methods": methods, "failed_methods": failed, "agreement": agreement,
                            "initial_method": best, "views": len(st)}
        stations[side] = st
        warnings += [f"{side} camera: {w}" for w in side_warnings]
    for w in warnings:
        (log.warning if log_warnings else log.debug)("tracked hand-eye: %s", w)
    X0 = per_camera[sides[0]]["methods"][per_camera[sides[0]]["initial_method"]]["T_tip_camera"]
    rig0 = None
    if len(sides) == 2:
        X1 = per_camera[sides[1]]["methods"][per_camera[sides[1]]["initial_method"]]["T_tip_camera"]
        rig0 = np.linalg.inv(X0) @ X1
    refined = refine_tracked(stations, cameras, X0, rig0, **refine_options)
    rms = {side: float(np.sqrt(np.mean(np.square(list(r.values())))))
           for side, r in refined["reprojection_per_view_px"].items()}
    return {**refined, "reprojection_rms_px": rms, "cameras": sides, "per_camera": per_camera,
            "warnings": warnings, "views": len(views)}


def triangulate_view(view: TrackedView, T_scopemarker_camera: np.ndarray, T_left_right: np.ndarray,
                     cameras: dict[str, CameraModel]) -> tuple[np.ndarray, np.ndarray]:
    """(ids, points (M, 3) in the board marker's frame, metres): the dots both cameras saw at this view,
    triangulated with the cameras placed by the TRACKER's pose and the hand-eye (no image-based pose)."""
    left, right = list(cameras)
    if left not in view.detections or right not in view.detections:
        raise CalibrationError(f"{view.name}: the pattern was not found in both cameras; nothing to triangulate")
    T_bm_l = view.T_boardmarker_scopemarker @ T_scopemarker_camera
    T_bm_r = T_bm_l @ T_left_right
    (pl, il), (pr, ir) = view.detections[left], view.detections[right]
    ids, a, b = np.intersect1d(np.asarray(il, int), np.asarray(ir, int), return_indices=True)
    if len(ids) == 0:
        return ids, np.empty((0, 3))
    nl = cv2.undistortPoints(np.asarray(pl, np.float64)[a].reshape(-1, 1, 2), cameras[left].K,
                             cameras[left].dist_array).reshape(-1, 2)
    nr = cv2.undistortPoints(np.asarray(pr, np.float64)[b].reshape(-1, 1, 2), cameras[right].K,
                             cameras[right].dist_array).reshape(-1, 2)
    Pl, Pr = np.linalg.inv(T_bm_l)[:3], np.linalg.inv(T_bm_r)[:3]
    X_h = cv2.triangulatePoints(Pl, Pr, nl.T, nr.T)
    return ids, (X_h[:3] / X_h[3]).T


def grid_error_mm(ids: np.ndarray, points: np.ndarray, T_boardmarker_pattern: np.ndarray, board: Board) -> dict:
    """Triangulated dots (board marker frame) against the known grid placed by T_boardmarker_pattern:
    mean / RMS / max distance in mm, the count, and the length of the mean error vector (``offset_mm``: what
    the poses put wrong for the view as a whole, with the dots' own triangulation scatter averaged out)."""
    grid = board.object_points[ids] @ T_boardmarker_pattern[:3, :3].T + T_boardmarker_pattern[:3, 3]
    diff = (points - grid) * 1e3
    d = np.linalg.norm(diff, axis=1)
    return {"dots": int(len(d)), "mean_mm": float(d.mean()), "rms_mm": float(np.sqrt(np.mean(d**2))),
            "max_mm": float(d.max()), "offset_mm": float(np.linalg.norm(diff.mean(axis=0)))}


def leave_one_view_out(views: list[TrackedView], board: Board, cameras: dict[str, CameraModel],
                       **refine_options) -> dict:
    """The tracked hand-eye's accuracy on views it was not fitted to: for each view, calibrate (stereo) on the
    others, triangulate the held-out view's dots with the cameras placed by its tracker pose and that
    hand-eye, and compare with the grid placed by that calibration's T_boardmarker_pattern. Per held-out view
    mean / RMS / max (mm), and over all dots of all held-out views. Views one camera missed are not held out."""
    if len(cameras) != 2:
        raise CalibrationError("the leave-one-view-out figure triangulates: it needs a stereo pair")
    per_view, all_d = {}, []
    for k, held in enumerate(views):
        if not all(side in held.detections for side in cameras):
            continue  # a view one camera missed has nothing to triangulate
        fit = calibrate_tracked_hand_eye(views[:k] + views[k + 1:], board, cameras, log_warnings=False,
                                         **refine_options)
        ids, pts = triangulate_view(held, fit["T_scopemarker_camera"], fit["T_left_right"], cameras)
        err = grid_error_mm(ids, pts, fit["T_boardmarker_pattern"], board)
        per_view[held.name] = err
        grid = board.object_points[ids] @ fit["T_boardmarker_pattern"][:3, :3].T + fit["T_boardmarker_pattern"][:3, 3]
        all_d.append(np.linalg.norm(pts - grid, axis=1) * 1e3)
    d = np.concatenate(all_d)
    return {"per_view": per_view, "mean_mm": float(d.mean()), "rms_mm": float(np.sqrt(np.mean(d**2))),
            "max_mm": float(d.max()), "dots": int(len(d)),
            "worst_view_mean_mm": float(max(v["mean_mm"] for v in per_view.values()))}
