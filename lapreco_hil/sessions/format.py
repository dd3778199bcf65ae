"""The lapreco session format, versions 1 and 2: metadata and the CSV tables (docs/session-format.md is the
specification; this module is its one reader and writer of metadata). Version 1 holds one camera; version 2
a rig of cameras (a stereo scope), each frame one image per camera.

A session is a folder::

    session.json            metadata (this module: SessionMeta)
    frames.csv              seq,t_ns,file            one row per frame, oldest first (version 1)
                            seq,t_ns,camera,file     one row per camera of each frame (version 2)
    frames/000000.png ...   lossless images (PNG; any format OpenCV reads losslessly)
    masks/left.png          a camera's field-of-view mask (version 2, optional)
    joints.csv              seq,t_ns,<joint names>   when pose_source = "joints"
    robot.urdf              the robot model          when pose_source = "joints" (or a packaged name)
    camera_poses.csv        t_ns,tx,ty,tz,qx,qy,qz,qw  when pose_source = "camera_poses"
    marker_poses.csv        t_ns,tool,tx,ty,tz,qx,qy,qz,qw,rms_mm,in_volume  when pose_source = "marker_poses"
    truth/surface.ply       optional ground truth, world frame
    truth/camera_poses.csv  optional ground truth, same columns as camera_poses.csv
    events.csv              t_ns,device,event,detail  device faults and health changes while recording

Rows are appended while recording; a row is complete only when it ends with a newline, so a session cut
short by a crash reads up to its last complete row.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lapreco_hil.camera import N_DIST, CameraModel, FieldOfView, Rig, read_fov_mask
from lapreco_hil.errors import CalibrationError, SessionError
from lapreco_hil.types import RobotDescription

log = logging.getLogger(__name__)

FORMAT = "lapreco-session"
VERSION = 2  # the newest version this module reads and writes (a one-camera session is written as version 1)
VERSIONS = (1, 2)
META_FILE = "session.json"
FRAMES_FILE = "frames.csv"
FRAMES_DIR = "frames"
MASKS_DIR = "masks"
FRAME_COLUMNS = {1: ("seq", "t_ns", "file"), 2: ("seq", "t_ns", "camera", "file")}
CAMERA_NAME = re.compile(r"[A-Za-z0-9_-]{1,32}")
JOINTS_FILE = "joints.csv"
CAMERA_POSES_FILE = "camera_poses.csv"
TRUTH_SURFACE_FILE = "truth/surface.ply"
TRUTH_POSES_FILE = "truth/camera_poses.csv"
EVENTS_FILE = "events.csv"
EVENT_COLUMNS = ("t_ns", "device", "event", "detail")

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
TIME_UNITS = ("ns",)
POSE_SOURCES = ("joints", "camera_poses", "marker_poses")
POSE_COLUMNS = ("t_ns", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
MARKER_POSES_FILE = "marker_poses.csv"
# T_tracker_marker of every tracked tool (the scope's and any other), with the device's quality fields
MARKER_COLUMNS = ("t_ns", "tool", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "rms_mm", "in_volume")
# the keys each object of session.json allows (a misspelled optional key would otherwise be ignored unseen)
CAMERA_KEYS = ("width", "height", "K", "dist", "fov_radius_px")  # version 1's camera
RIG_KEYS = ("cameras", "T_cam0_cam", "sigma_rotation_rad", "sigma_translation_m")
RIG_CAMERA_KEYS = ("name", "width", "height", "K", "dist", "fov")
UNITS_KEYS = ("length", "angle", "time")
ROBOT_KEYS = ("urdf", "tip_frame", "joint_names", "joint_units", "T_tip_camera", "T_world_base")
CAMERA_POSES_KEYS = ("sigma_rotation_rad", "sigma_translation_m")
TRACKER_KEYS = ("tool", "T_marker_camera", "T_world_tracker", "sigma_rotation_rad", "sigma_translation_m", "max_rms_mm")
FOV_SHAPE_KEYS = {"circle": ("cx", "cy", "r"), "ellipse": ("cx", "cy", "a", "b", "angle_deg")}
TOOL_NAME = re.compile(r"[^,\r\n\"]{1,64}")
DEFAULT_MAX_RMS_MM = 1.0  # a marker fit worse than this is refused (a Polaris's typical RMS is 0.1-0.3 mm)


@dataclass(frozen=True)
class PoseSigma:
    """1-sigma error of given camera poses (an optical tracker's accuracy), used as the BA prior."""

    rotation_rad: float = 0.002
    translation_m: float = 0.0005


@dataclass(frozen=True)
class TrackerSetup:
    """How a tracked scope's marker poses become camera poses (session.json's ``tracker``):
    T_world_camera = T_world_tracker @ T_tracker_marker @ T_marker_camera, for the tool ``tool``. Without
    ``T_marker_camera`` (the hand-eye) the session is a calibration session. Translations in metres."""

    tool: str
    T_marker_camera: np.ndarray | None = None
    T_world_tracker: np.ndarray = field(default_factory=lambda: np.eye(4))
    sigma: PoseSigma = field(default_factory=PoseSigma)
    max_rms_mm: float = DEFAULT_MAX_RMS_MM


@dataclass(frozen=True)
class MarkerTable:
    """marker_poses.csv read: per row its time, tool, T_tracker_marker (metres), RMS (mm) and volume flag."""

    t_ns: np.ndarray  # (N,) int64, increasing per tool
    tools: tuple[str, ...]
    poses: np.ndarray  # (N, 4, 4)
    rms_mm: np.ndarray  # (N,)
    in_volume: np.ndarray  # (N,) bool

    def __len__(self) -> int:
        return len(self.t_ns)


def default_camera_names(n: int) -> tuple[str, ...]:
    return ("left", "right") if n == 2 else ("camera",) if n == 1 else tuple(f"cam{k}" for k in range(n))


@dataclass(frozen=True)
class SessionMeta:
    camera: CameraModel  # camera 0 of the rig (the one camera of a version-1 session)
    pose_source: str  # "joints" | "camera_poses" | "marker_poses"
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
    # every camera with its extrinsics (SI units); None: a rig of one, ``camera``
    rig: Rig | None = None
    camera_names: tuple[str, ...] = ()  # one per camera of the rig (default: left, right for a pair)
    file_version: int = 0  # the version of the session.json it was read from (0: made in memory)
    tracker: TrackerSetup | None = None  # pose_source "marker_poses": the tool, hand-eye and tracker placement

    def __post_init__(self) -> None:
        if self.rig is None:
            object.__setattr__(self, "rig", Rig.mono(self.camera))
        elif self.rig.cameras[0] != self.camera:
            raise ValueError("SessionMeta: camera must be the rig's camera 0")
        if not self.camera_names:
            object.__setattr__(self, "camera_names", default_camera_names(len(self.rig)))
        if len(self.camera_names) != len(self.rig) or len(set(self.camera_names)) != len(self.camera_names) \
                or not all(CAMERA_NAME.fullmatch(n) for n in self.camera_names):
            raise ValueError(f"SessionMeta: camera names {self.camera_names} must be one per camera, distinct, "
                             f"of letters, digits, '_' and '-'")

    @property
    def version(self) -> int:
        """The format version this metadata is written in: 1 for one camera whose field of view version 1
        can hold (none, or a circle about the principal point); 2 otherwise."""
        return 1 if len(self.rig) == 1 and self.camera.fov is None else 2

    @property
    def joint_scale(self) -> np.ndarray:
        """Per-joint factor from the file's units to SI (rad, m)."""
        return np.array([LENGTH_UNITS[self.length_unit] if u == "length" else ANGLE_UNITS[self.angle_unit]
                         for u in self.joint_units])

    def to_json(self, folder: Path | None = None) -> dict:
        """session.json's content; ``folder`` (the session's) is needed only for a camera with a mask
        field of view, whose file must lie inside it."""
        version = self.version
        doc: dict = {
            "format": FORMAT,
            "version": version,
            "units": {"length": self.length_unit, "angle": self.angle_unit, "time": "ns"},
            "time_base": "capture time in integer nanoseconds of one monotonic clock shared by frames, "
                         "joints and poses",
        }
        if version == 1:
            doc["camera"] = {**_intrinsics_json(self.camera), "fov_radius_px": self.camera.fov_radius_px}
        else:
            scale = LENGTH_UNITS[self.length_unit]
            cameras = []
            for name, cam in zip(self.camera_names, self.rig.cameras):
                entry = {"name": name, **_intrinsics_json(cam)}
                if cam.field_of_view is not None:
                    entry["fov"] = _fov_json(cam.field_of_view, folder)
                cameras.append(entry)
            T = [np.asarray(T, float).copy() for T in self.rig.T_cam0_cam]
            for m in T:
                m[:3, 3] /= scale
            doc["rig"] = {"cameras": cameras, "T_cam0_cam": [m.tolist() for m in T],
                          "sigma_rotation_rad": self.rig.sigma_rotation_rad,
                          "sigma_translation_m": self.rig.sigma_translation_m}
        doc.update({
            "pose_source": self.pose_source,
            "time_offset_ns": self.time_offset_ns,
            "complete": self.complete,
            "counts": self.counts,
            "source": self.source,
        })
        if self.health:
            doc["health"] = self.health
        if self.nominal_fps:
            doc["nominal_fps"] = self.nominal_fps
        if self.robot is not None:
            scale = LENGTH_UNITS[self.length_unit]  # units.length applies to every translation
            doc["robot"] = {"urdf": self.robot.urdf, "tip_frame": self.robot.tip_frame,
                            "joint_names": list(self.joint_names), "joint_units": list(self.joint_units),
                            "T_world_base": _in_unit(self.robot.T_world_base, scale)}
            if self.robot.T_tip_camera is not None:  # absent: a calibration session (no hand-eye yet)
                doc["robot"]["T_tip_camera"] = _in_unit(self.robot.T_tip_camera, scale)
        if self.pose_source == "camera_poses":
            doc["camera_poses"] = {"sigma_rotation_rad": self.pose_sigma.rotation_rad,
                                   "sigma_translation_m": self.pose_sigma.translation_m}
        if self.tracker is not None:
            doc["tracker"] = _tracker_json(self.tracker, LENGTH_UNITS[self.length_unit])
        return doc


def _in_unit(T: np.ndarray, scale: float) -> list:
    """A rigid transform in metres as the session's length unit writes it (``scale``: metres per unit)."""
    m = np.asarray(T, float).copy()
    m[:3, 3] /= scale
    return m.tolist()


def _tracker_json(tracker: TrackerSetup, scale: float) -> dict:
    doc = {"tool": tracker.tool, "T_world_tracker": _in_unit(tracker.T_world_tracker, scale),
           "sigma_rotation_rad": tracker.sigma.rotation_rad, "sigma_translation_m": tracker.sigma.translation_m,
           "max_rms_mm": tracker.max_rms_mm}
    if tracker.T_marker_camera is not None:  # absent: a calibration session (no hand-eye yet)
        doc["T_marker_camera"] = _in_unit(tracker.T_marker_camera, scale)
    return doc


def _tracker(t: "_Fields", scale: float) -> TrackerSetup:
    tool = t.get("tool", str)
    if not TOOL_NAME.fullmatch(tool):
        raise t._fail("tool", f"is {tool!r}; give the scope's tool name as marker_poses.csv's 'tool' column "
                              f"has it (1-64 characters, no comma or quote)")

    default = PoseSigma()
    sigma = PoseSigma(_positive(t, "sigma_rotation_rad", default.rotation_rad),
                      _positive(t, "sigma_translation_m", default.translation_m))
    return TrackerSetup(tool, _rigid_in_metres(t, "T_marker_camera", scale) if "T_marker_camera" in t.data else None,
                        _rigid_in_metres(t, "T_world_tracker", scale) if "T_world_tracker" in t.data else np.eye(4),
                        sigma,
                        _positive(t, "max_rms_mm", DEFAULT_MAX_RMS_MM))


def _intrinsics_json(cam: CameraModel) -> dict:
    return {"width": cam.width, "height": cam.height,
            "K": [[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]], "dist": list(cam.dist)}


def _fov_json(fov: FieldOfView, folder: Path | None) -> dict:
    if fov.kind == "circle":
        return {"circle": {"cx": fov.cx, "cy": fov.cy, "r": fov.r}}
    if fov.kind == "ellipse":
        return {"ellipse": {"cx": fov.cx, "cy": fov.cy, "a": fov.a, "b": fov.b, "angle_deg": fov.angle_deg}}
    path = Path(fov.mask_file)
    if folder is not None:
        try:
            path = path.resolve().relative_to(Path(folder).resolve())
        except ValueError:
            raise SessionError(f"field-of-view mask '{fov.mask_file}' is not inside the session folder "
                               f"'{folder}'; copy it there (SessionWriter does)") from None
    return {"mask": path.as_posix()}


class _Fields:
    """Typed access to a JSON object, with errors that name the file and the field."""

    def __init__(self, data, where: str, source: str) -> None:
        if not isinstance(data, dict):
            raise SessionError(f"{source}: '{where or 'top level'}' must be a JSON object")
        self.data, self.where, self.source = data, where, source

    def _name(self, key: str) -> str:
        if key.startswith("["):  # a list element: rig.cameras[1]
            return f"{self.where}{key}"
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

    def only(self, allowed: tuple[str, ...]) -> "_Fields":
        """These fields, refusing any key not in ``allowed``: a misspelled optional key would otherwise be
        ignored and its default used unseen."""
        unknown = [k for k in self.data if k not in allowed]
        if unknown:
            raise self._fail(unknown[0], f"is unknown; '{self.where}' allows {', '.join(allowed)}")
        return self

    def sub(self, key: str) -> "_Fields":
        return _Fields(self.get(key, dict), self._name(key), self.source)

    def elements(self, key: str, n: int | None = None) -> "_Fields":
        """A JSON list as fields named ``key[i]`` (``n``: the length it must have)."""
        value = self.get(key, list)
        if not value or n is not None and len(value) != n:
            raise self._fail(key, f"must be a list of {n if n is not None else 'one or more'} entries, "
                                  f"got {len(value)}")
        return _Fields({f"[{i}]": v for i, v in enumerate(value)}, self._name(key), self.source)


def _rigid_in_metres(f: _Fields, key: str, scale: float) -> np.ndarray:
    """A rigid transform field in the session's length unit (``scale``: metres per unit), in metres."""
    m = _check_rigid(f, key).copy()
    m[:3, 3] *= scale
    return m


def _check_rigid(f: _Fields, key: str) -> np.ndarray:
    T = f.matrix(key, (4, 4))
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0 or \
            not np.allclose(T[3], [0, 0, 0, 1]):
        raise f._fail(key, "is not a rigid transform (rotation must be orthonormal, last row 0 0 0 1)")
    return T


def _camera(cam: _Fields, fov_of) -> CameraModel:
    """One camera's intrinsics (and, through ``fov_of(cam, width, height)``, its field of view)."""
    cam.only(CAMERA_KEYS if fov_of is None else RIG_CAMERA_KEYS)
    width, height = cam.get("width", int), cam.get("height", int)
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise cam._fail("width", f"and height ({width}x{height}) must be 1..16384")
    K = cam.matrix("K", (3, 3))
    dist = np.array(cam.get("dist", list, []), dtype=object)
    if len(dist) > N_DIST or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                     for v in dist):
        raise cam._fail("dist", f"must be up to {N_DIST} finite numbers in OpenCV's order (k1 k2 p1 p2 k3 k4 k5 k6 "
                                f"s1 s2 s3 s4)")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise cam._fail("K", "must have positive focal lengths")
    dist_t = tuple(float(v) for v in dist)
    if fov_of is None:  # version 1: a circle about the principal point
        radius = cam.get("fov_radius_px", float, 0.0)
        if radius < 0:
            raise cam._fail("fov_radius_px", f"must be positive (or 0: no field of view), got {radius!r}")
        if radius > 0:
            _check_covers(cam, "fov_radius_px", f"= {radius!r} about the principal point ({K[0, 2]:g}, "
                                                f"{K[1, 2]:g})", FieldOfView.circle(K[0, 2], K[1, 2], radius),
                          width, height)
        return CameraModel(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist_t, radius)
    return CameraModel(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist_t,
                       fov=fov_of(cam, width, height))


def _check_covers(f: _Fields, key: str, given: str, fov: FieldOfView, width: int, height: int) -> FieldOfView:
    """``fov``, refused when it lights no pixel of the image (a shape placed off the image would replay with
    no corners at all, as an all-zero mask would)."""
    far = 2 ** 20  # px: a field of view is the scope's image circle, about the image's size
    if max(abs(fov.cx), abs(fov.cy), abs(fov.r), abs(fov.a), abs(fov.b)) > far:
        raise f._fail(key, f"{given} is too far out to draw; give the centre and size in pixels of the "
                           f"{width}x{height} image")
    if not fov.region(width, height).any():
        raise f._fail(key, f"{given} covers no pixel of the {width}x{height} image; give the centre and size "
                           f"in that image's pixels")
    return fov


def _positive(f: _Fields, key: str, default=...) -> float:
    value = f.get(key, float, default)
    if value <= 0:
        raise f._fail(key, f"must be positive, got {value!r}")
    return value


def _fov(folder: Path):
    def parse(cam: _Fields, width: int, height: int) -> FieldOfView | None:
        if "fov" not in cam.data:
            return None
        fov = cam.sub("fov")
        kinds = [k for k in ("circle", "ellipse", "mask") if k in fov.data]
        if len(kinds) != 1 or len(fov.data) != 1:
            raise cam._fail("fov", f"must hold exactly one of 'circle', 'ellipse' or 'mask', got "
                                   f"{sorted(fov.data)}")
        given = f"= {json.dumps(cam.data['fov'], separators=(', ', ': '))}"
        if kinds[0] == "circle":
            c = fov.sub("circle").only(FOV_SHAPE_KEYS["circle"])
            return _check_covers(cam, "fov", given, FieldOfView.circle(c.get("cx", float), c.get("cy", float),
                                                                       _positive(c, "r")), width, height)
        if kinds[0] == "ellipse":
            e = fov.sub("ellipse").only(FOV_SHAPE_KEYS["ellipse"])
            shape = FieldOfView.ellipse(e.get("cx", float), e.get("cy", float), _positive(e, "a"),
                                        _positive(e, "b"), e.get("angle_deg", float, 0.0))
            return _check_covers(cam, "fov", given, shape, width, height)
        name = fov.get("mask", str)
        where = f"{fov.source}: field '{fov._name('mask')}' = {name!r}"
        path = inside_session(folder, name, where, "a PNG file")
        try:
            pixels = read_fov_mask(path)
        except CalibrationError:
            raise SessionError(f"{where}: cannot decode the image (not a PNG?); give a PNG of the camera's "
                               f"size, non-zero inside the field of view") from None
        if pixels.shape != (height, width):
            raise SessionError(f"{where}: the mask is {pixels.shape[1]}x{pixels.shape[0]}, the camera is "
                               f"{width}x{height}; a mask must have its camera's size (see "
                               f"docs/session-format.md)")
        if not pixels.any():
            raise SessionError(f"{where}: the mask is all zero (nothing inside the field of view); non-zero "
                               f"pixels mark the inside")
        return FieldOfView.mask(path, pixels)
    return parse


def _rig(r: _Fields, length_scale: float, folder: Path) -> tuple[Rig, tuple[str, ...]]:
    r.only(RIG_KEYS)
    cams = r.elements("cameras")
    n = len(cams.data)
    cameras, names = [], []
    for i in range(n):
        c = cams.sub(f"[{i}]")
        name = c.get("name", str)
        if not CAMERA_NAME.fullmatch(name) or name in names:
            raise c._fail("name", f"is {name!r}; camera names must be distinct, 1-32 letters, digits, '_' or '-'")
        names.append(name)
        cameras.append(_camera(c, _fov(folder)))
    T = r.elements("T_cam0_cam", n)
    transforms = []
    for i in range(n):
        m = _check_rigid(T, f"[{i}]").copy()
        if i == 0 and not np.allclose(m, np.eye(4), atol=1e-9):
            raise T._fail("[0]", "must be the identity (camera 0 is the rig's reference)")
        m[:3, 3] *= length_scale
        transforms.append(m)
    defaults = Rig.mono(cameras[0])
    rig = Rig(tuple(cameras), tuple(transforms),
              _positive(r, "sigma_rotation_rad", defaults.sigma_rotation_rad),
              _positive(r, "sigma_translation_m", defaults.sigma_translation_m))
    return rig, tuple(names)


def inside_session(folder: Path, name: str, where: str, what: str = "a file") -> Path:
    """The file a session names, checked: a relative path, inside the session folder (after following
    symbolic links), and there. ``where`` starts the error (the file, line or field and the name), ``what``
    says what the file must be (an image file, a PNG file)."""
    if not name or Path(name).is_absolute() or name.startswith(("/", "\\")) or name[1:2] == ":":
        raise SessionError(f"{where} is not a relative path; paths must be relative to the session folder "
                           f"(e.g. frames/000000.png)")
    file = folder / name
    root = folder.resolve()
    try:
        resolved = file.resolve()
    except (OSError, RuntimeError, ValueError) as exc:  # a symbolic-link loop, a NUL in the name
        raise SessionError(f"{where} cannot be resolved ({exc})") from None
    if not resolved.is_relative_to(root):
        raise SessionError(f"{where} leads outside the session folder (to '{resolved}'); paths must stay "
                           f"inside it")
    if resolved.is_dir():
        raise SessionError(f"{where} is a folder, not {what}")
    if not resolved.is_file():
        raise SessionError(f"{where} is missing")
    return file


def meta_from_json(doc, source: str, folder: Path | None = None) -> SessionMeta:
    """Metadata from session.json's content; ``source`` names it in errors, ``folder`` is the session's
    (default: the folder of ``source``), where version 2's mask files are read."""
    f = _Fields(doc, "", source)
    fmt = f.get("format", str)
    if fmt != FORMAT:
        raise f._fail("format", f"is {fmt!r}, expected '{FORMAT}'")
    version = f.get("version", int)
    if version not in VERSIONS:
        raise SessionError(f"{source}: unknown session format version {version} (this lapreco reads versions "
                           f"{', '.join(map(str, VERSIONS))}); upgrade lapreco-hil or rewrite the session")
    units = f.sub("units").only(UNITS_KEYS)
    length, angle, time = units.get("length", str), units.get("angle", str), units.get("time", str)
    if length not in LENGTH_UNITS:
        raise units._fail("length", f"is {length!r}; use one of {', '.join(LENGTH_UNITS)}")
    if angle not in ANGLE_UNITS:
        raise units._fail("angle", f"is {angle!r}; use one of {', '.join(ANGLE_UNITS)}")
    if time not in TIME_UNITS:
        raise units._fail("time", f"is {time!r}; timestamps must be integer nanoseconds ('ns')")

    if version == 1:
        if "rig" in f.data:
            raise f._fail("rig", "is a version-2 field; set \"version\": 2 for a rig (a version-1 session gives "
                                 "its one camera in 'camera')")
        camera = _camera(f.sub("camera"), None)
        rig, names = Rig.mono(camera), ()
    else:
        if "camera" in f.data:
            raise f._fail("camera", "is a version-1 field; a version-2 session gives its cameras in 'rig'")
        rig, names = _rig(f.sub("rig"), LENGTH_UNITS[length], folder or Path(source).parent)
        camera = rig.cameras[0]

    pose_source = f.get("pose_source", str)
    if pose_source not in POSE_SOURCES:
        raise f._fail("pose_source", f"is {pose_source!r}; use 'joints', 'camera_poses' or 'marker_poses'")
    robot = None
    joint_names: tuple[str, ...] = ()
    joint_units: tuple[str, ...] = ()
    if pose_source == "joints" or "robot" in f.data:
        # a misspelled T_tip_camera would make a calibration session (no hand-eye) of it without a word
        r = f.sub("robot").only(ROBOT_KEYS)
        joint_names = tuple(r.get("joint_names", list))
        joint_units = tuple(r.get("joint_units", list))
        if not joint_names or not all(isinstance(n, str) and n for n in joint_names):
            raise r._fail("joint_names", "must be a non-empty list of names")
        if len(joint_units) != len(joint_names) or not all(u in ("angle", "length") for u in joint_units):
            raise r._fail("joint_units", "must give 'angle' or 'length' for each joint in joint_names")
        robot = RobotDescription(r.get("urdf", str), r.get("tip_frame", str),
                                 _rigid_in_metres(r, "T_tip_camera", LENGTH_UNITS[length])
                                 if "T_tip_camera" in r.data else None,
                                 _rigid_in_metres(r, "T_world_base", LENGTH_UNITS[length])
                                 if "T_world_base" in r.data else np.eye(4))
    sigma = PoseSigma()
    if pose_source == "camera_poses" and "camera_poses" in f.data:
        p = f.sub("camera_poses").only(CAMERA_POSES_KEYS)
        sigma = PoseSigma(p.get("sigma_rotation_rad", float, sigma.rotation_rad),
                          p.get("sigma_translation_m", float, sigma.translation_m))
        if sigma.rotation_rad <= 0 or sigma.translation_m <= 0:
            raise p._fail("sigma_rotation_rad", "and sigma_translation_m must be positive")
    tracker = _tracker(f.sub("tracker").only(TRACKER_KEYS), LENGTH_UNITS[length]) if pose_source == "marker_poses" else None
    fps = f.get("nominal_fps", float, None)
    return SessionMeta(camera=camera, pose_source=pose_source, robot=robot, joint_names=joint_names,
                       joint_units=joint_units, pose_sigma=sigma, time_offset_ns=f.get("time_offset_ns", int, 0),
                       length_unit=length, angle_unit=angle, nominal_fps=fps,
                       complete=f.get("complete", bool, True), counts=f.get("counts", dict, {}),
                       source=f.get("source", dict, {}), health=f.get("health", dict, {}), rig=rig,
                       camera_names=names, file_version=version, tracker=tracker)


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
    return meta_from_json(doc, str(path), folder)


# --- CSV tables ---------------------------------------------------------------------------------------------

def read_rows(path: Path, header: tuple[str, ...], min_columns: int | None = None,
              complete: bool = True) -> tuple[list[list[str]], bool]:
    """The rows of a table (after its header) and whether an unfinished last row was left out.

    The header must start with ``header``. A last line without a newline is a row a crash cut short only in
    a session not closed cleanly (``complete`` False): it is left out with a warning. A session closed cleanly
    was written whole, so that line is read as a row like any other (a program that wrote it need not end
    the file with a newline), and a line that does not parse is an error.
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
    unterminated = lines[-1] != ""  # the last piece has no newline
    truncated = unterminated and not complete  # a row cut short by a crash
    if truncated:
        log.warning("%s: line %d has no newline: a row cut short when the recording stopped; it is left out",
                    path, len(lines))
    if not complete or not unterminated:
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
            cut = (" (the last line, without a newline, of a session marked complete: a copy cut short?)"
                   if unterminated and complete and lineno == len(lines) else "")
            raise SessionError(f"{path}: line {lineno}: {len(cells)} columns, expected {ncols}{cut}")
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


def read_pose_table(path: Path, length_scale: float, complete: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), T_world_camera (N, 4, 4)) from a table with POSE_COLUMNS; translations to metres.
    ``complete``: whether the session was closed cleanly (see read_rows)."""
    from lapreco_hil.geometry import pose_from_tum

    rows, _ = read_rows(path, POSE_COLUMNS, complete=complete)
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


def read_marker_table(path: Path, length_scale: float, complete: bool = True) -> tuple[MarkerTable, bool]:
    """marker_poses.csv (MARKER_COLUMNS; translations to metres) and whether an unfinished last row was left out
    (``complete``: whether the session was closed cleanly, see read_rows). Times must increase per tool
    (several tools may share a reply's time)."""
    from lapreco_hil.geometry import pose_from_tum

    rows, truncated = read_rows(path, MARKER_COLUMNS, complete=complete)
    n = len(rows)
    t = np.empty(n, np.int64)
    poses, rms, inside = np.empty((n, 4, 4)), np.empty(n), np.empty(n, bool)
    tools: list[str] = []
    last: dict[str, tuple[int, int]] = {}  # tool -> (its last t_ns, line)
    for i, r in enumerate(rows):
        lineno = i + 2
        t[i] = parse_int(path, lineno, "t_ns", r[0])
        tool = r[1]
        if not TOOL_NAME.fullmatch(tool):
            raise SessionError(f"{path}: line {lineno}: column 'tool' = '{tool}' is not a tool name (1-64 "
                               f"characters, no comma or quote)")
        vals = [parse_float(path, lineno, c, v) for c, v in zip(MARKER_COLUMNS[2:9], r[2:9])]
        try:
            poses[i] = pose_from_tum(vals)
        except ValueError as exc:
            raise SessionError(f"{path}: line {lineno}: {exc}") from None
        poses[i, :3, 3] *= length_scale
        rms[i] = parse_float(path, lineno, "rms_mm", r[9])
        if rms[i] < 0:
            raise SessionError(f"{path}: line {lineno}: column 'rms_mm' = '{r[9]}' is negative")
        if r[10] not in ("0", "1"):
            raise SessionError(f"{path}: line {lineno}: column 'in_volume' = '{r[10]}' must be 1 (inside the "
                               f"tracker's characterised volume) or 0")
        inside[i] = r[10] == "1"
        if tool in last and t[i] <= last[tool][0]:
            raise SessionError(f"{path}: line {lineno}: t_ns {t[i]} of tool '{tool}' does not increase (its "
                               f"previous row, line {last[tool][1]}: {last[tool][0]}); each tool's timestamps "
                               f"must be strictly increasing")
        last[tool] = (int(t[i]), lineno)
        tools.append(tool)
    return MarkerTable(t, tuple(tools), poses, rms, inside), truncated
