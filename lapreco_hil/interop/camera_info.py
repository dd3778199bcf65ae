"""ROS ``camera_info`` <-> :class:`~lapreco_hil.camera.CameraModel`.

The message's fields (sensor_msgs/CameraInfo, Foxglove's CameraCalibration: width, height, distortion_model,
D, K, R, P) for the MCAP export and the bag import. The YAML file (camera_calibration_parsers' format) is read
and written by :mod:`lapreco_hil.calib.files` next to OpenCV's YAML (``read_camera_yaml`` tells them apart);
its functions are re-exported here so that everything camera_info lives under one name.

ROS knows two of OpenCV's models: ``plumb_bob`` (k1, k2, p1, p2, k3) and ``rational_polynomial`` (k1, k2, p1,
p2, k3, k4, k5, k6). OpenCV's thin-prism terms (s1..s4, the seed paper's model) have no ROS name."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lapreco_hil.calib.files import (ROS_MODELS, read_camera_info_yaml, ros_distortion,  # noqa: F401 (re-exported)
                                     write_camera_info_yaml)
from lapreco_hil.camera import CameraModel
from lapreco_hil.errors import CalibrationError

__all__ = ["CameraInfoFields", "ROS_MODELS", "camera_from_camera_info", "camera_info_fields",
           "read_camera_info_yaml", "write_camera_info_yaml"]


@dataclass(frozen=True)
class CameraInfoFields:
    """A camera as camera_info gives it: K (3x3 row-major, 9), D (model's length), R (identity: unrectified),
    P = [K | 0] (12). ``dropped``: the OpenCV terms left out because ROS has no model for them."""

    width: int
    height: int
    distortion_model: str
    D: tuple[float, ...]
    K: tuple[float, ...]
    R: tuple[float, ...]
    P: tuple[float, ...]
    dropped: tuple[str, ...] = ()


def camera_info_fields(camera: CameraModel, allow_dropping: bool = False) -> CameraInfoFields:
    """The camera_info fields of ``camera``. A camera with thin-prism terms is refused (CalibrationError)
    unless ``allow_dropping`` (a picture for a viewer, where rational_polynomial is the nearest model): then
    the terms are left out and named in ``dropped``."""
    d = camera.dist_array
    dropped: tuple[str, ...] = ()
    if np.any(d[8:] != 0):
        if not allow_dropping:
            ros_distortion(camera)  # raises with the remedy
        dropped = tuple(f"s{i + 1}" for i in range(4) if d[8 + i] != 0)
        model, coeffs = "rational_polynomial", d[:8]
    else:
        model, coeffs = ros_distortion(camera)
    K = camera.K
    P = np.hstack([K, np.zeros((3, 1))])
    return CameraInfoFields(camera.width, camera.height, model, tuple(float(v) for v in coeffs),
                            tuple(float(v) for v in K.ravel()), tuple(float(v) for v in np.eye(3).ravel()),
                            tuple(float(v) for v in P.ravel()), dropped)


def camera_from_camera_info(width: int, height: int, distortion_model: str, D, K, where: str) -> CameraModel:
    """The camera of a camera_info message (``where`` names it in errors: the bag and topic). An empty D is no
    distortion; K[0] = 0 is ROS's mark of an uncalibrated camera and is refused."""
    K = np.asarray(K, np.float64).ravel()
    D = np.asarray(D, np.float64).ravel()
    if K.size != 9:
        raise CalibrationError(f"{where}: K has {K.size} values, expected 9 (3x3 row-major)")
    if K[0] == 0 or K[4] == 0:
        raise CalibrationError(f"{where}: the camera is uncalibrated (K[0] = 0, ROS's mark); calibrate it "
                               f"('lapreco calibrate lens') and pass --camera camera.yaml")
    model = distortion_model or ("plumb_bob" if D.size == 0 or not np.any(D) else "")
    if model not in ROS_MODELS:
        raise CalibrationError(f"{where}: distortion_model '{distortion_model}' is not one of "
                               f"{', '.join(ROS_MODELS)}; pass --camera camera.yaml with the lens in OpenCV's model")
    if D.size > ROS_MODELS[model]:
        raise CalibrationError(f"{where}: {model} has at most {ROS_MODELS[model]} coefficients, D has {D.size}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D))) or width < 1 or height < 1 or K[0] < 0 or K[4] < 0:
        raise CalibrationError(f"{where}: image size and focal lengths must be positive and K, D finite")
    return CameraModel(int(width), int(height), K[0], K[4], K[2], K[5], tuple(D.tolist()))
