"""A real endoscope stereo pair (the Hamlyn in-vivo phantom, tests/data/hamlyn-phantom-stereo) written by an
outside program's own script (json/csv/cv2 only, as docs/session-format.md shows) and replayed: it must make
hundreds of points that reproject within half a pixel, and keep the calibrated relative pose."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lapreco_hil.app.replay import run_replay
from lapreco_hil.evaluation.compare import read_tum

HAMLYN = Path(__file__).parent / "data" / "hamlyn-phantom-stereo"


def quaternion_xyzw(R) -> tuple[float, float, float, float]:
    """Hamilton quaternion of a rotation matrix (the session format's qx qy qz qw)."""
    w = math.sqrt(max(0.0, 1.0 + R[0][0] + R[1][1] + R[2][2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + R[0][0] - R[1][1] - R[2][2])) / 2, R[2][1] - R[1][2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - R[0][0] + R[1][1] - R[2][2])) / 2, R[0][2] - R[2][0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - R[0][0] - R[1][1] + R[2][2])) / 2, R[1][0] - R[0][1])
    return x, y, z, w


def write_two_frame_session(out: Path) -> np.ndarray:
    """The pair as a version-1 camera-pose session of two frames (one camera model: the right image is
    resampled to the left intrinsics; both have zero distortion). Returns T_world_right (mm)."""
    K_left = np.loadtxt(HAMLYN / "calib.left.intrinsic.txt")
    K_right = np.loadtxt(HAMLYN / "calib.right.intrinsic.txt")
    T_right_left = np.loadtxt(HAMLYN / "calib.l2r.4x4")  # maps left-camera points (mm) to the right camera
    left = cv2.imread(str(HAMLYN / "f7_dynamic_deint_L_0100.png"))
    right = cv2.imread(str(HAMLYN / "f7_dynamic_deint_R_0100.png"))
    h, w = left.shape[:2]
    map_x, map_y = cv2.initUndistortRectifyMap(K_right, None, None, K_left, (w, h), cv2.CV_32FC1)
    right = cv2.remap(right, map_x, map_y, cv2.INTER_LINEAR)
    T_world_right = np.linalg.inv(T_right_left)
    os.makedirs(out / "frames")
    with open(out / "frames.csv", "w") as f, open(out / "camera_poses.csv", "w") as p:
        f.write("seq,t_ns,file\n")
        p.write("t_ns,tx,ty,tz,qx,qy,qz,qw\n")
        for i, (image, T) in enumerate(((left, np.eye(4)), (right, T_world_right))):
            t_ns = 1_000_000_000 + 40_000_000 * i
            cv2.imwrite(str(out / f"frames/{i:06d}.png"), image)
            f.write(f"{i},{t_ns},frames/{i:06d}.png\n")
            q = quaternion_xyzw(T[:3, :3].tolist())
            p.write(f"{t_ns},{T[0, 3]},{T[1, 3]},{T[2, 3]},{q[0]},{q[1]},{q[2]},{q[3]}\n")
    json.dump({"format": "lapreco-session", "version": 1, "units": {"length": "mm", "angle": "rad", "time": "ns"},
               "camera": {"width": w, "height": h, "K": K_left.tolist(), "dist": [0, 0, 0, 0, 0]},
               "pose_source": "camera_poses",
               "camera_poses": {"sigma_rotation_rad": 0.0005, "sigma_translation_m": 0.0001}},
              open(out / "session.json", "w"))
    return T_world_right


@pytest.mark.slow
def test_the_hamlyn_pair_as_a_two_frame_session_reconstructs_hundreds_of_points(tmp_path):
    session = tmp_path / "hamlyn"
    T_world_right = write_two_frame_session(session)
    report = run_replay(str(session), str(tmp_path / "out"), tracker="opencv", device="cpu", progress=False)
    assert report["inliers"] >= 500, report["funnel"]
    assert report["reprojection"]["median_px"] <= 0.5
    # the pair is matched as a stereo rig's one frame (Session._pair_as_rig): the second view a partner view
    assert report["two_frames_as_rig"]["second_frame_t_ns"] > 0 and report["partner_views"] == 1
    # the calibrated relative pose is kept (the trajectory is in metres), both frames' poses in it
    _, (left, right) = read_tum(tmp_path / "out" / "trajectory.tum")
    T_rel = np.linalg.inv(left) @ right
    T_true = T_world_right.copy()
    T_true[:3, 3] /= 1000.0
    dR = T_rel[:3, :3].T @ T_true[:3, :3]
    assert math.degrees(math.acos(min(1.0, (np.trace(dR) - 1) / 2))) < 0.05
    assert np.linalg.norm(T_rel[:3, 3] - T_true[:3, 3]) < 0.1e-3
    assert set(report["funnel"]) >= {"corners", "after_lk", "after_drift_check", "candidates", "triangulated",
                                     "inliers"}


def _documented_v2_script() -> str:
    """docs/session-format.md's worked stereo example (the one that reads calib.l2r.4x4)."""
    doc = (Path(__file__).parents[1] / "docs" / "session-format.md").read_text()
    return next(b for b in re.findall(r"```python\n(.*?)```", doc, re.S) if "calib.l2r.4x4" in b)


@pytest.mark.slow
def test_the_hamlyn_pair_as_a_version_2_stereo_session_reconstructs_hundreds_of_points(tmp_path):
    """One rig frame, each camera with its own intrinsics (nothing resampled): the points come from the left-right
    matches of the first and only frame."""
    script = tmp_path / "hamlyn_session.py"
    script.write_text(_documented_v2_script())
    subprocess.run([sys.executable, str(script), str(HAMLYN), str(tmp_path / "hamlyn-v2")], check=True)
    report = run_replay(str(tmp_path / "hamlyn-v2"), str(tmp_path / "out"), tracker="opencv", device="cpu",
                        progress=False)
    assert report["inliers"] >= 500, report["funnel"]
    assert report["reprojection"]["median_px"] <= 0.5
    (rig_fit,) = report["rig_check"]  # the rig judged against the frame: it fits
    assert rig_fit["problem"] is None and rig_fit["in_front_share"] > 0.95
