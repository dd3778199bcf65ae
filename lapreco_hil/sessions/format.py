"""The lapreco session format, version 1: metadata and the CSV tables (docs/session-format.md is the
specification; this module is its one reader and writer of metadata).

A session is a folder::

    session.json            metadata (this module: SessionMeta)
    frames.csv              seq,t_ns,file            one row per frame, oldest first
    frames/000000.png ...   lossless images (PNG; any format OpenCV reads losslessly)
    joints.csv              seq,t_ns,<joint names>   when pose_source = "joints"
    robot.urdf              the robot model          when pose_source = "joints" (or a packaged name)
    camera_poses.csv        t_ns,tx,ty,tz,qx,qy,qz,qw  when pose_source = "camera_poses"
    truth/surface.ply       optional ground truth, world frame
    truth/camera_poses.csv  optional ground truth, same columns as camera_poses.csv
    events.csv              t_ns,device,event,detail  device faults and health changes while recording

Rows are appended while recording; a row is complete only when it ends with a newline, so a session cut
short by a crash reads up to its last complete row.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lapreco_hil.camera import N_DIST, CameraModel
from lapreco_hil.errors import SessionError
from lapreco_hil.types import RobotDescription

FORMAT = "lapreco-session"
VERSION = 1
META_FILE = "session.json"
FRAMES_FILE = "frames.csv"
FRAMES_DIR = "frames"
JOINTS_FILE = "joints.csv"
CAMERA_POSES_FILE = "camera_poses.csv"
TRUTH_SURFACE_FILE = "truth/surface.ply"
TRUTH_POSES_FILE = "truth/camera_poses.csv"
EVENTS_FILE = "events.csv"
EVENT_COLUMNS = ("t_ns", "device", "event", "detail")

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
TIME_UNITS = ("ns",)
POSE_SOURCES = ("joints", "camera_poses")
POSE_COLUMNS = ("t_ns", "tx", "ty", "tz", "qx", "qy", "qz", "qw")


@dataclass(frozen=True)
class PoseSigma:
    """1-sigma error of given camera poses (an optical tracker's accuracy), used as the BA prior."""

    rotation_rad: float = 0.002
    translation_m: float = 0.0005


@dataclass(frozen=True)
class SessionMeta:
    camera: CameraModel
    pose_source: str  # "joints" | "camera_poses"
    robot: RobotDescription | None = None  # urdf is relative to the session folder or a packaged name
    joint_names: tuple[str, ...] = ()
    joint_units: tuple[str, ...] = ()  # per joint: "angle" (revolute) or "length" (prismatic)
    pose_sigma: PoseSigma = field(default_factory=PoseSigma)
    time_offset_ns: int = 0  # pose/joint time = video time + offset
    length_unit: str = "m"
    angle_unit: str = "rad"
    nominal_fps: float | None = None
    complete: bool = False
    counts: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)  # free-form: what wrote it (devices, scene, seed)
    health: dict = field(default_factory=dict)  # informative: the devices' faults while recording

    @property
    def joint_scale(self) -> np.ndarray:
        """Per-joint factor from the file's units to SI (rad, m)."""
        return np.array([LENGTH_UNITS[self.length_unit] if u == "length" else ANGLE_UNITS[self.angle_unit]
                         for u in self.joint_units])

    def to_json(self) -> dict:
        cam = self.camera
        doc: dict = {
            "format": FORMAT,
            "version": VERSION,
            "units": {"length": self.length_unit, "angle": self.angle_unit, "time": "ns"},
            "time_base": "capture time in integer nanoseconds of one monotonic clock shared by frames, "
                         "joints and poses",
            "camera": {"width": cam.width, "height": cam.height,
                       "K": [[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]],
                       "dist": list(cam.dist), "fov_radius_px": cam.fov_radius_px},
            "pose_source": self.pose_source,
            "time_offset_ns": self.time_offset_ns,
            "complete": self.complete,
            "counts": self.counts,
            "source": self.source,
        }
        if self.health:
            doc["health"] = self.health
        if self.nominal_fps:
            doc["nominal_fps"] = self.nominal_fps
        if self.robot is not None:
            doc["robot"] = {"urdf": self.robot.urdf, "tip_frame": self.robot.tip_frame,
                            "joint_names": list(self.joint_names), "joint_units": list(self.joint_units),
                            "T_world_base": self.robot.T_world_base.tolist()}
            if self.robot.T_tip_camera is not None:  # absent: a calibration session (no hand-eye yet)
                doc["robot"]["T_tip_camera"] = self.robot.T_tip_camera.tolist()
        if self.pose_source == "camera_poses":
            doc["camera_poses"] = {"sigma_rotation_rad": self.pose_sigma.rotation_rad,
                                   "sigma_translation_m": self.pose_sigma.translation_m}
        return doc


class _Fields:
    """Typed access to a JSON object, with errors that name the file and the field."""

    def __init__(self, data, where: str, source: str) -> None:
        if not isinstance(data, dict):
            raise SessionError(f"{source}: '{where or 'top level'}' must be a JSON object")
        self.data, self.where, self.source = data, where, source

    def _name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def _fail(self, key: str, what: str) -> SessionError:
        return SessionError(f"{self.source}: field '{self._name(key)}' {what} (see docs/session-format.md)")

    def get(self, key: str, kind, default=...):
        if key not in self.data:
            if default is ...:
                raise self._fail(key, "is missing")
            return default
        value = self.data[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise self._fail(key, f"must be {getattr(kind, '__name__', kind)}, got {value!r}")
        if kind is float and not math.isfinite(value):
            raise self._fail(key, f"must be a finite number, got {value!r}")
        return value

    def matrix(self, key: str, shape: tuple[int, int]) -> np.ndarray:
        value = self.get(key, list)
        try:
            m = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self._fail(key, f"must be a {shape[0]}x{shape[1]} array of numbers") from None
        if m.shape != shape or not np.all(np.isfinite(m)):
            raise self._fail(key, f"must be a {shape[0]}x{shape[1]} array of finite numbers")
        return m

    def sub(self, key: str) -> "_Fields":
        return _Fields(self.get(key, dict), self._name(key), self.source)


def _check_rigid(f: _Fields, key: str) -> np.ndarray:
    T = f.matrix(key, (4, 4))
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0 or \
            not np.allclose(T[3], [0, 0, 0, 1]):
        raise f._fail(key, "is not a rigid transform (rotation must be orthonormal, last row 0 0 0 1)")
    return T


def meta_from_json(doc, source: str) -> SessionMeta:
    f = _Fields(doc, "", source)
    fmt = f.get("format", str)
    if fmt != FORMAT:
        raise f._fail("format", f"is '{fmt}', expected '{FORMAT}'")
    version = f.get("version", int)
    if version != VERSION:
        raise SessionError(f"{source}: unknown session format version {version} (this lapreco reads version "
                           f"{VERSION}); upgrade lapreco-hil or rewrite the session")
    units = f.sub("units")
    length, angle, time = units.get("length", str), units.get("angle", str), units.get("time", str)
    if length not in LENGTH_UNITS:
        raise units._fail("length", f"is '{length}'; use one of {', '.join(LENGTH_UNITS)}")
    if angle not in ANGLE_UNITS:
        raise units._fail("angle", f"is '{angle}'; use one of {', '.join(ANGLE_UNITS)}")
    if time not in TIME_UNITS:
        raise units._fail("time", f"is '{time}'; timestamps must be integer nanoseconds ('ns')")

    cam = f.sub("camera")
    width, height = cam.get("width", int), cam.get("height", int)
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise cam._fail("width", f"and height ({width}x{height}) must be 1..16384")
    K = cam.matrix("K", (3, 3))
    dist = np.array(cam.get("dist", list, []), dtype=object)
    if len(dist) > N_DIST or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in dist):
        raise cam._fail("dist", f"must be up to {N_DIST} numbers in OpenCV's order (k1 k2 p1 p2 k3 k4 k5 k6 "
                                f"s1 s2 s3 s4)")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise cam._fail("K", "must have positive focal lengths")
    camera = CameraModel(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(float(v) for v in dist),
                         cam.get("fov_radius_px", float, 0.0))

    pose_source = f.get("pose_source", str)
    if pose_source not in POSE_SOURCES:
        raise f._fail("pose_source", f"is '{pose_source}'; use 'joints' or 'camera_poses'")
    robot = None
    joint_names: tuple[str, ...] = ()
    joint_units: tuple[str, ...] = ()
    if pose_source == "joints" or "robot" in f.data:
        r = f.sub("robot")
        joint_names = tuple(r.get("joint_names", list))
        joint_units = tuple(r.get("joint_units", list))
        if not joint_names or not all(isinstance(n, str) and n for n in joint_names):
            raise r._fail("joint_names", "must be a non-empty list of names")
        if len(joint_units) != len(joint_names) or not all(u in ("angle", "length") for u in joint_units):
            raise r._fail("joint_units", "must give 'angle' or 'length' for each joint in joint_names")
        robot = RobotDescription(r.get("urdf", str), r.get("tip_frame", str),
                                 _check_rigid(r, "T_tip_camera") if "T_tip_camera" in r.data else None,
                                 _check_rigid(r, "T_world_base") if "T_world_base" in r.data else np.eye(4))
    sigma = PoseSigma()
    if pose_source == "camera_poses" and "camera_poses" in f.data:
        p = f.sub("camera_poses")
        sigma = PoseSigma(p.get("sigma_rotation_rad", float, sigma.rotation_rad),
                          p.get("sigma_translation_m", float, sigma.translation_m))
        if sigma.rotation_rad <= 0 or sigma.translation_m <= 0:
            raise p._fail("sigma_rotation_rad", "and sigma_translation_m must be positive")
    fps = f.get("nominal_fps", float, None)
    return SessionMeta(camera=camera, pose_source=pose_source, robot=robot, joint_names=joint_names,
                       joint_units=joint_units, pose_sigma=sigma, time_offset_ns=f.get("time_offset_ns", int, 0),
                       length_unit=length, angle_unit=angle, nominal_fps=fps,
                       complete=f.get("complete", bool, True), counts=f.get("counts", dict, {}),
                       source=f.get("source", dict, {}), health=f.get("health", dict, {}))


def read_meta(folder: Path) -> SessionMeta:
    path = folder / META_FILE
    if not folder.is_dir():
        raise SessionError(f"session '{folder}': no such folder")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SessionError(f"session '{folder}': no {META_FILE}; not a lapreco session "
                           f"(see docs/session-format.md)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"{path}: cannot read ({exc})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    return meta_from_json(doc, str(path))


# --- CSV tables ---------------------------------------------------------------------------------------------

def read_rows(path: Path, header: tuple[str, ...], min_columns: int | None = None) -> tuple[list[list[str]], bool]:
    """Complete rows of a table (after its header) and whether an unfinished last row was left out.

    The header must start with ``header``; a row is complete when it ends with a newline.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SessionError(f"{path}: missing (the session's metadata says it should be there)") from None
    except OSError as exc:
        raise SessionError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SessionError(f"{path}: not UTF-8 text (byte {exc.start}); is it the right file?") from None
    lines = text.split("\n")
    truncated = lines[-1] != ""  # the last piece has no newline: a row cut short by a crash
    lines = lines[:-1]
    if not lines:
        raise SessionError(f"{path}: empty (expected the header '{','.join(header)}')")
    got = tuple(c.strip() for c in lines[0].rstrip("\r").split(","))
    if got[: len(header)] != header:
        raise SessionError(f"{path}: line 1: header is '{','.join(got)}', expected it to start with "
                           f"'{','.join(header)}'")
    ncols = len(got) if min_columns is None else min_columns
    rows = []
    for lineno, line in enumerate(lines[1:], start=2):
        line = line.rstrip("\r")
        if not line.strip():
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != ncols:
            raise SessionError(f"{path}: line {lineno}: {len(cells)} columns, expected {ncols}")
        rows.append(cells)
    return rows, truncated


def parse_int(path: Path, lineno: int, column: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise SessionError(f"{path}: line {lineno}: column '{column}' = '{text}' is not an integer") from None


def parse_float(path: Path, lineno: int, column: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise SessionError(f"{path}: line {lineno}: column '{column}' = '{text}' is not a finite number")
    return v


def check_increasing(path: Path, t_ns: np.ndarray, what: str = "t_ns") -> None:
    if len(t_ns) > 1:
        bad = np.flatnonzero(np.diff(t_ns) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise SessionError(f"{path}: line {i + 2}: {what} {t_ns[i]} does not increase (previous row "
                               f"{t_ns[i - 1]}); timestamps must be strictly increasing")


def read_pose_table(path: Path, length_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), T_world_camera (N, 4, 4)) from a table with POSE_COLUMNS; translations to metres."""
    from lapreco_hil.geometry import pose_from_tum

    rows, _ = read_rows(path, POSE_COLUMNS)
    t = np.array([parse_int(path, i + 2, "t_ns", r[0]) for i, r in enumerate(rows)], dtype=np.int64)
    poses = np.empty((len(rows), 4, 4))
    for i, r in enumerate(rows):
        vals = [parse_float(path, i + 2, c, v) for c, v in zip(POSE_COLUMNS[1:], r[1:])]
        try:
            poses[i] = pose_from_tum(vals)
        except ValueError as exc:
            raise SessionError(f"{path}: line {i + 2}: {exc}") from None
        poses[i, :3, 3] *= length_scale
    check_increasing(path, t)
    return t, poses
