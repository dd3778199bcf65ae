"""``calibrate lens`` and ``calibrate stereo``: from image files to calibration files and a report, callable
without the CLI (the CLI parses arguments and prints what these return)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from lapreco_hil.calib.boards import parse_board
from lapreco_hil.calib.files import write_camera_info_yaml, write_camera_yaml, write_stereo_yaml
from lapreco_hil.calib.lens import (LensResult, calibrate_detections, calibrate_lens, detect_views, load_images,
                          save_check_image, save_coverage_image)
from lapreco_hil.calib.stereo import StereoResult, calibrate_stereo
from lapreco_hil.errors import CalibrationError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LensRun:
    result: LensResult
    images: int
    written: tuple[str, ...]  # the files written


def run_lens_calibration(image_paths: list[str], board_spec: str, out: str, model: str = "auto",
                         ros_out: str | None = None, camera_name: str = "camera") -> LensRun:
    """Calibrate one camera; write ``out`` (OpenCV YAML), its ``.check.png`` and ``.coverage.png``, and, when
    asked, a ROS camera_info YAML."""
    board = parse_board(board_spec)
    images = load_images(image_paths)
    result = calibrate_lens(images, board, model)
    extra = {"rms_px": result.rms_px, "model": result.model, "views": len(result.per_view_rms_px),
             "std_cx_px": result.std["cx"], "std_cy_px": result.std["cy"]}
    for s in result.scores:
        if s.held_out_rms_px is not None:
            extra[f"held_out_rms_px_{s.model}"] = s.held_out_rms_px
    if ros_out:  # before writing anything: a model ROS cannot hold is refused up front
        from lapreco_hil.calib.files import ros_distortion

        ros_distortion(result.camera)
    write_camera_yaml(out, result.camera, extra)
    check = Path(out).with_suffix(".check.png")
    coverage = Path(out).with_suffix(".coverage.png")
    save_check_image(check, result, images)
    save_coverage_image(coverage, result)
    written = [out, str(check), str(coverage)]
    if ros_out:
        write_camera_info_yaml(ros_out, result.camera, camera_name)
        written.append(ros_out)
    return LensRun(result, len(images), tuple(written))


@dataclass(frozen=True)
class StereoRun:
    result: StereoResult
    lens0: LensResult
    lens1: LensResult


def run_stereo_calibration(left: list[str], right: list[str], board_spec: str, out: str, model: str = "auto",
                           refine_intrinsics: bool = False) -> StereoRun:
    """Calibrate each camera from its own views, then the rig from the pairs (``left[i]`` with ``right[i]``);
    write ``out`` (OpenCV YAML)."""
    if len(left) != len(right):
        raise CalibrationError(f"--left has {len(left)} images and --right {len(right)}; give them in pairs, "
                               f"in the same order")
    board = parse_board(board_spec)
    images0, images1 = load_images(left), load_images(right)
    det0, rej0 = detect_views(images0, board)
    det1, rej1 = detect_views(images1, board)
    sizes = {im.shape[:2] for im in (*images0.values(), *images1.values())}
    if len(sizes) > 1:
        raise CalibrationError(f"the left and right images differ in size: {sorted(sizes)}")
    h, w = sizes.pop()
    lens0 = calibrate_detections(det0, (w, h), board, model, rejected=rej0)
    lens1 = calibrate_detections(det1, (w, h), board, model, rejected=rej1)
    result = calibrate_stereo(det0, det1, list(zip(left, right)), board, lens0.camera, lens1.camera,
                              refine_intrinsics)
    write_stereo_yaml(out, result.cam0, result.cam1, result.R, result.T, result.E, result.F,
                      {"rms_px": result.rms_px, "rectified_epipolar_error_px": result.rectified_epipolar_error_px,
                       "pairs": len(result.pairs), "cam0_model": lens0.model, "cam1_model": lens1.model})
    return StereoRun(result, lens0, lens1)
