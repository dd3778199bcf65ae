"""Rigid transforms as 4x4 float64 matrices named ``T_a_b`` (maps points from frame b to frame a)."""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def rigid(T: np.ndarray) -> np.ndarray:
    """The nearest rigid transform (rotation projected onto SO(3)): products of poses drift off it, and a
    pose composed again and again (a correction carried from keyframe to keyframe) must not."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return make_T(R, T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a rotation matrix, robust near 0 and pi."""
    return float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(position error in metres, rotation error in radians) between two camera poses T_world_camera."""
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    return dt, rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction s in [0, 1] between T0 and T1: slerp on rotation, linear on translation
    (the SE(3) interpolation used for poses at frame times). s outside [0, 1] extrapolates."""
    return interpolate_poses(np.asarray(T0)[None], np.asarray(T1)[None], np.array([s], float))[0]


def interpolate_poses(T0: np.ndarray, T1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``interpolate_pose`` for stacks of pose pairs (N, 4, 4) at fractions ``s`` (N,), in one pass."""
    s = np.asarray(s, float)
    r0 = Rotation.from_matrix(T0[:, :3, :3])
    dr = (r0.inv() * Rotation.from_matrix(T1[:, :3, :3])).as_rotvec()
    out = np.tile(np.eye(4), (len(s), 1, 1))
    out[:, :3, :3] = (r0 * Rotation.from_rotvec(s[:, None] * dr)).as_matrix()
    out[:, :3, 3] = (1.0 - s)[:, None] * T0[:, :3, 3] + s[:, None] * T1[:, :3, 3]
    return out


def to_tum(t_ns: int, T: np.ndarray) -> str:
    """One TUM trajectory line: ``t tx ty tz qx qy qz qw``, the time in seconds written exactly from integer
    nanoseconds (a wall-clock stamp, ~1.8e9 s, has no exact float64 nanoseconds)."""
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    x, y, z = T[:3, 3]
    t_ns = int(t_ns)
    sign, t_ns = ("-", -t_ns) if t_ns < 0 else ("", t_ns)
    return f"{sign}{t_ns // 10**9}.{t_ns % 10**9:09d} {x:.9f} {y:.9f} {z:.9f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}"


def pose_from_tum(values) -> np.ndarray:
    """T from ``tx ty tz qx qy qz qw`` (Hamilton quaternion, scalar last, as in TUM files)."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in values)
    q = np.array([qx, qy, qz, qw])
    n = np.linalg.norm(q)
    if not np.isfinite(n) or abs(n - 1.0) > 1e-3:
        raise ValueError(f"quaternion ({qx}, {qy}, {qz}, {qw}) is not a unit quaternion (norm {n:.6g})")
    return make_T(Rotation.from_quat(q / n).as_matrix(), [tx, ty, tz])


def tum_values(T: np.ndarray) -> list[float]:
    """``[tx, ty, tz, qx, qy, qz, qw]`` of T."""
    return [*map(float, T[:3, 3]), *map(float, Rotation.from_matrix(T[:3, :3]).as_quat())]


@dataclass(frozen=True)
class SampledPoses:
    """Poses T_world_camera known at times (a tracker, a robot's readings, ground truth): interpolated on
    SE(3) in between, held at the ends. Call it with a time in ns."""

    t_ns: np.ndarray  # (N,) int64, strictly increasing
    poses: np.ndarray  # (N, 4, 4)

    def __call__(self, t_ns: int) -> np.ndarray:
        times = self.t_ns
        i = int(np.searchsorted(times, t_ns, side="right"))
        if i == 0:
            return self.poses[0]
        if i >= len(times):
            return self.poses[-1]
        s = (t_ns - times[i - 1]) / (times[i] - times[i - 1])
        return interpolate_pose(self.poses[i - 1], self.poses[i], s)


# A pose at time t is interpolated only between two samples around t that are at most this many median sample
# periods apart: across a longer gap (a link that dropped out) the motion in between is unknown.
MAX_GAP_PERIODS = 3.0

# why a time has no pose (the keys of report.json's frames.without_pose_by_cause)
BEFORE_FIRST, AFTER_LAST, IN_GAP = "before_first", "after_last", "in_gap"
NO_POSE_CAUSES = (BEFORE_FIRST, AFTER_LAST, IN_GAP)


def max_gap_ns(times, periods: float = MAX_GAP_PERIODS) -> float:
    """The longest interval between two samples that a pose may be interpolated across: ``periods`` times
    the median interval of ``times`` (infinite with fewer than two samples: no period is known)."""
    t = np.asarray(times, dtype=np.int64)
    if len(t) < 2:
        return float("inf")
    return periods * float(np.median(np.diff(t)))


def no_pose_cause(times, t_ns: int, gap_ns: float) -> str | None:
    """Why there is no pose at ``t_ns`` among samples at ``times`` (sorted): ``BEFORE_FIRST``,
    ``AFTER_LAST``, ``IN_GAP`` (the samples around it are more than ``gap_ns`` apart), or None when two
    samples bracket it (or one sits exactly at it). A pose is never held or extrapolated."""
    n = len(times)
    if n == 0 or t_ns < times[0]:
        return BEFORE_FIRST
    if t_ns > times[n - 1]:
        return AFTER_LAST
    i = bisect.bisect_left(times, t_ns)  # (a list or an array)
    if times[i] == t_ns:
        return None
    return IN_GAP if times[i] - times[i - 1] > gap_ns else None


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """T_world_camera of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # image y points down, against `up`
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


__all__ = [
    "AFTER_LAST",
    "BEFORE_FIRST",
    "IN_GAP",
    "MAX_GAP_PERIODS",
    "NO_POSE_CAUSES",
    "Rotation",
    "SampledPoses",
    "inv_T",
    "interpolate_pose",
    "look_at",
    "make_T",
    "max_gap_ns",
    "no_pose_cause",
    "pose_error",
    "pose_from_tum",
    "rot_x",
    "rot_z",
    "rotation_angle",
    "to_tum",
    "transform_points",
    "tum_values",
]
