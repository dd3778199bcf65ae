"""Calibration files in OpenCV's YAML (cv2.FileStorage), the exchange format of the app.

camera.yaml: ``image_width``, ``image_height``, ``camera_matrix`` (3x3), ``distortion_coefficients``
(1xN, OpenCV's order, N <= 12), optional ``fov_radius_px`` — the keys of OpenCV's calibration samples.
handeye.yaml: ``T_tip_camera`` (4x4, metres), optional ``robot_model`` and ``tip_frame``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..camera import N_DIST, CameraModel
from ..errors import CalibrationError


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


def read_camera_yaml(path: str | Path) -> CameraModel:
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
