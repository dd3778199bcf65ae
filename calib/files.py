"""Calibration files in OpenCV's YAML (cv2.FileStorage), the exchange format of the app.

camera.yaml: ``image_width``, ``image_height``, ``camera_matrix`` (3x3), ``distortion_coefficients``
(1xN, OpenCV's order, N <= 12), optional ``fov_radius_px`` — the keys of OpenCV's calibration samples.
A ROS ``camera_info`` YAML (camera_calibration_parsers' plain YAML: ``image_width``, ``image_height``,
``camera_name``, ``camera_matrix``, ``distortion_model`` plumb_bob | rational_polynomial,
``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``, each matrix as rows/cols/data) is
written by :func:`write_camera_info_yaml`; :func:`read_camera_yaml` reads either, telling them apart by the
``%YAML:1.0`` header that cv2.FileStorage writes and ROS does not, and by camera_info's keys.
handeye.yaml: ``T_tip_camera`` (4x4, metres), optional ``robot_model`` and ``tip_frame``.
rig.yaml (stereo): ``cam0_*`` and ``cam1_*`` (``image_width``, ``image_height``, ``camera_matrix``,
``distortion_coefficients``), ``T_cam0_cam1`` (4x4, metres: camera 1's frame in camera 0's), and OpenCV's
``R``, ``T`` (camera 0 -> camera 1 coordinates), ``E``, ``F``.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import N_DIST, CameraModel
from lapreco_hil.errors import CalibrationError


def _open(path: str | Path, mode: int) -> cv2.FileStorage:
    path = Path(path)
    if mode == cv2.FILE_STORAGE_READ and not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    try:
        fs = cv2.FileStorage(str(path), mode)
    except (cv2.error, SystemError) as exc:  # OpenCV's bindings raise either for a malformed file
        reason = getattr(exc, "err", None) or str(exc.__cause__ or exc)
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file ({reason.strip()})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot open as OpenCV YAML/XML")
    return fs


def _node(fs: cv2.FileStorage, key: str, path) -> cv2.FileNode:
    try:
        return fs.getNode(key)
    except cv2.error:  # the document's top level is not a map of keys (a list, a scalar, a broken header)
        raise CalibrationError(f"{path}: not a map of calibration keys; write it with cv2.FileStorage or "
                               f"'lapreco calibrate'") from None


def _mat(fs: cv2.FileStorage, key: str, path, shape=None) -> np.ndarray:
    node = _node(fs, key, path)
    if node.empty():
        raise CalibrationError(f"{path}: missing '{key}'")
    try:
        m = node.mat()
    except cv2.error as exc:  # a matrix node with missing or inconsistent rows/cols/dt/data
        raise CalibrationError(f"{path}: '{key}' is not a valid matrix ({exc.err.strip()}); write it with "
                               f"cv2.FileStorage") from None
    if m is None:
        raise CalibrationError(f"{path}: '{key}' is not a matrix (write it with cv2.FileStorage)")
    m = np.asarray(m, np.float64)
    if shape is not None and m.shape != shape:
        raise CalibrationError(f"{path}: '{key}' is {m.shape[0]}x{m.shape[1]}, expected {shape[0]}x{shape[1]}")
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{path}: '{key}' has non-finite values")
    return m


def _int(fs: cv2.FileStorage, key: str, path) -> int:
    node = _node(fs, key, path)
    if node.empty() or not node.isInt():
        raise CalibrationError(f"{path}: missing or non-integer '{key}'")
    return int(node.real())


ROS_MODELS = {"plumb_bob": 5, "rational_polynomial": 8}
ROS_KEYS = (b"camera_matrix", b"distortion_model", b"distortion_coefficients", b"camera_name",
            b"rectification_matrix", b"projection_matrix")


def _is_ros_yaml(path: Path) -> bool:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read ({exc.strerror})") from None
    # not OpenCV YAML, XML or JSON, and one of camera_info's keys (any: a file missing some gets the ROS reader's
    # error naming the key it lacks)
    return not data.lstrip().startswith((b"%YAML", b"<?xml", b"{")) and any(
        re.search(rb"^" + key + rb"\s*:", data, re.M) for key in ROS_KEYS)


def read_camera_yaml(path: str | Path) -> CameraModel:
    """A camera from OpenCV's YAML/XML or from a ROS camera_info YAML (detected from the file)."""
    path = Path(path)
    if path.is_file() and _is_ros_yaml(path):
        return read_camera_info_yaml(path)
    fs = _open(path, cv2.FILE_STORAGE_READ)
    try:
        w, h = _int(fs, "image_width", path), _int(fs, "image_height", path)
        K = _mat(fs, "camera_matrix", path, (3, 3))
        dist = _mat(fs, "distortion_coefficients", path).ravel()
        fov = _node(fs, "fov_radius_px", path)
        fov_r = 0.0 if fov.empty() else float(fov.real())
    finally:
        fs.release()
    if dist.size > N_DIST:
        raise CalibrationError(f"{path}: {dist.size} distortion coefficients; OpenCV's model has at most {N_DIST}")
    if w < 1 or h < 1 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{path}: image size and focal lengths must be positive")
    return CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(dist.tolist()), fov_r)


def write_camera_yaml(path: str | Path, camera: CameraModel, extra: dict[str, float] | None = None) -> None:
    fs = _open(path, cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", camera.width)
        fs.write("image_height", camera.height)
        fs.write("camera_matrix", camera.K)
        fs.write("distortion_coefficients", camera.dist_array.reshape(1, -1))
        fs.write("fov_radius_px", float(camera.fov_radius_px))
        for k, v in (extra or {}).items():
            fs.write(k, v)
    finally:
        fs.release()


def _ros_matrix(name: str, m: np.ndarray) -> str:
    data = ", ".join(repr(float(v)) for v in np.asarray(m, np.float64).ravel())
    return f"{name}:\n  rows: {m.shape[0]}\n  cols: {m.shape[1]}\n  data: [{data}]\n"


def ros_distortion(camera: CameraModel) -> tuple[str, np.ndarray]:
    """(distortion_model, coefficients) for camera_info; thin-prism terms have no ROS model."""
    d = camera.dist_array
    if np.any(d[8:] != 0):
        raise CalibrationError("ROS camera_info has no thin-prism model (s1..s4 are not zero): calibrate with "
                               "--model standard or rational (or auto) to write camera_info")
    if np.any(d[5:8] != 0):
        return "rational_polynomial", d[:8]
    return "plumb_bob", d[:5]


def write_camera_info_yaml(path: str | Path, camera: CameraModel, camera_name: str = "camera") -> None:
    """ROS camera_info YAML for one unrectified camera: R = identity, P = [K | 0]."""
    model, d = ros_distortion(camera)
    P = np.hstack([camera.K, np.zeros((3, 1))])
    text = (f"image_width: {camera.width}\nimage_height: {camera.height}\ncamera_name: {camera_name}\n"
            + _ros_matrix("camera_matrix", camera.K) + f"distortion_model: {model}\n"
            + _ros_matrix("distortion_coefficients", d.reshape(1, -1))
            + _ros_matrix("rectification_matrix", np.eye(3)) + _ros_matrix("projection_matrix", P))
    try:
        Path(path).write_text(text)
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot write ({exc.strerror})") from None


def _ros_node_matrix(fs, key: str, path) -> np.ndarray:
    node = _node(fs, key, path)
    if node.empty() or not node.isMap():
        raise CalibrationError(f"{path}: missing '{key}' (a map of rows, cols, data)")
    rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
    if not (rows.isInt() and cols.isInt() and data.isSeq()):
        raise CalibrationError(f"{path}: '{key}' needs integer rows, cols and a data list")
    r, c = int(rows.real()), int(cols.real())
    if data.size() != r * c:
        raise CalibrationError(f"{path}: '{key}' has {data.size()} values for {r}x{c}")
    m = np.array([data.at(i).real() for i in range(data.size())], np.float64).reshape(r, c)
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{path}: '{key}' has non-finite values")
    return m


def read_camera_info_yaml(path: str | Path) -> CameraModel:
    path = Path(path)
    text = path.read_text(errors="replace")
    try:  # cv2.FileStorage parses plain YAML given OpenCV's header
        fs = cv2.FileStorage("%YAML:1.0\n---\n" + text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):
        raise CalibrationError(f"{path}: not a readable ROS camera_info YAML") from None
    try:
        w, h = _int(fs, "image_width", path), _int(fs, "image_height", path)
        K = _ros_node_matrix(fs, "camera_matrix", path)
        model_node = _node(fs, "distortion_model", path)
        if model_node.empty():
            raise CalibrationError(f"{path}: missing 'distortion_model' (plumb_bob or rational_polynomial)")
        model = model_node.string() if model_node.isString() else ""
        d = _ros_node_matrix(fs, "distortion_coefficients", path).ravel()
    finally:
        fs.release()
    if model not in ROS_MODELS:
        raise CalibrationError(f"{path}: distortion_model '{model}' is not one of {', '.join(ROS_MODELS)}")
    if K.shape != (3, 3) or d.size > ROS_MODELS[model]:
        raise CalibrationError(f"{path}: camera_matrix must be 3x3 and {model} has at most "
                               f"{ROS_MODELS[model]} coefficients")
    if w < 1 or h < 1 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{path}: image size and focal lengths must be positive")
    return CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d.tolist()))


def write_stereo_yaml(path: str | Path, cam0: CameraModel, cam1: CameraModel, R: np.ndarray, T: np.ndarray,
                      E: np.ndarray, F: np.ndarray, extra: dict | None = None) -> None:
    """The rig; R, T as cv2.stereoCalibrate gives them (x1 = R x0 + T, metres)."""
    T_cam1_cam0 = np.eye(4)
    T_cam1_cam0[:3, :3], T_cam1_cam0[:3, 3] = R, np.ravel(T)
    fs = _open(path, cv2.FILE_STORAGE_WRITE)
    try:
        for tag, cam in (("cam0", cam0), ("cam1", cam1)):
            fs.write(f"{tag}_image_width", cam.width)
            fs.write(f"{tag}_image_height", cam.height)
            fs.write(f"{tag}_camera_matrix", cam.K)
            fs.write(f"{tag}_distortion_coefficients", cam.dist_array.reshape(1, -1))
        fs.write("T_cam0_cam1", np.linalg.inv(T_cam1_cam0))
        fs.write("R", np.asarray(R, np.float64))
        fs.write("T", np.asarray(T, np.float64).reshape(3, 1))
        fs.write("E", np.asarray(E, np.float64))
        fs.write("F", np.asarray(F, np.float64))
        for k, v in (extra or {}).items():
            fs.write(k, v)
    finally:
        fs.release()


def read_stereo_yaml(path: str | Path) -> dict:
    """``{'cam0': CameraModel, 'cam1': CameraModel, 'T_cam0_cam1': 4x4, 'R', 'T', 'E', 'F'}``."""
    fs = _open(path, cv2.FILE_STORAGE_READ)
    try:
        out: dict = {}
        for tag in ("cam0", "cam1"):
            w, h = _int(fs, f"{tag}_image_width", path), _int(fs, f"{tag}_image_height", path)
            K = _mat(fs, f"{tag}_camera_matrix", path, (3, 3))
            d = _mat(fs, f"{tag}_distortion_coefficients", path).ravel()
            if d.size > N_DIST:
                raise CalibrationError(f"{path}: {tag} has {d.size} distortion coefficients; at most {N_DIST}")
            out[tag] = CameraModel(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d.tolist()))
        out["T_cam0_cam1"] = _mat(fs, "T_cam0_cam1", path, (4, 4))
        for key, shape in (("R", (3, 3)), ("T", (3, 1)), ("E", (3, 3)), ("F", (3, 3))):
            out[key] = _mat(fs, key, path, shape)
    finally:
        fs.release()
    return out


def read_handeye_yaml(path: str | Path) -> dict:
    """``{'T_tip_camera': 4x4, 'robot_model': str | None, 'tip_frame': str | None}``."""
    fs = _open(path, cv2.FILE_STORAGE_READ)
    try:
        T = _mat(fs, "T_tip_camera", path, (4, 4))
        out = {"T_tip_camera": T}
        for key in ("robot_model", "tip_frame"):
            node = _node(fs, key, path)
            out[key] = node.string() if not node.empty() and node.isString() else None
    finally:
        fs.release()
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: 'T_tip_camera' is not a rigid transform")
    return out


def write_handeye_yaml(path: str | Path, T_tip_camera: np.ndarray, robot_model: str | None = None,
                       tip_frame: str | None = None, extra: dict | None = None) -> None:
    fs = _open(path, cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("T_tip_camera", np.asarray(T_tip_camera, np.float64))
        if robot_model:
            fs.write("robot_model", robot_model)
        if tip_frame:
            fs.write("tip_frame", tip_frame)
        for k, v in (extra or {}).items():
            fs.write(k, v)
    finally:
        fs.release()
