"""Hand-eye of an optically tracked scope (calib.handeye's tracked part, app.handeye_tracked, the CLI): the real
Viking stereo laparoscope with its tracked dot board (the leave-one-view-out triangulation figure,
docs/calibration-handeye.md), a synthetic tracked set-up of known hand-eye, and the warnings for too little data.
The data and their licence: tests/data/README.md."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lapreco_hil.app.handeye_tracked import calibrate_tracked_views, read_tracker_matrix, tracked_views
from lapreco_hil.calib.boards import parse_board
from lapreco_hil.calib.files import read_handeye_yaml
from lapreco_hil.calib.handeye import (TrackedView, calibrate_tracked_hand_eye, grid_error_mm, leave_one_view_out,
                                       pose_difference, tracker_pose, triangulate_view)
from lapreco_hil.camera import CameraModel
from lapreco_hil.cli.main import main
from lapreco_hil.errors import CalibrationError
from lapreco_hil.geometry import look_at, make_T

VIKING = Path(__file__).parent / "data" / "viking-tracked-dotgrid"
SIDES = ("left", "right")


def _owner_camera(side: str) -> CameraModel:
    K = np.loadtxt(VIKING / f"calib.{side}.intrinsics.txt")
    return CameraModel(1920, 1080, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(np.loadtxt(VIKING / f"calib.{side}.distortion.txt")))


def _viking_views() -> list[TrackedView]:
    dots = np.load(VIKING / "dots.npz")
    return [TrackedView(f"view {i}", tracker_pose(read_tracker_matrix(VIKING / f"calib.tracking.model.{i}.txt"),
                                                  read_tracker_matrix(VIKING / f"calib.tracking.{i}.txt")),
                        {s: (dots[f"{s}{i}_points"].astype(np.float64), dots[f"{s}{i}_ids"].astype(np.int64))
                         for s in SIDES}) for i in range(10)]


@pytest.fixture(scope="module")
def viking():
    return _viking_views(), parse_board("viking"), {s: _owner_camera(s) for s in SIDES}


# --- the real tracked Viking session ----------------------------------------------------------------------------------

def test_viking_leave_one_view_out_dots_lie_within_a_millimetre_of_the_grid(viking):
    views, board, cameras = viking
    loo = leave_one_view_out(views, board, cameras)
    print({k: round(v["mean_mm"], 3) for k, v in loo["per_view"].items()}, loo["mean_mm"], loo["rms_mm"])
    # the done-when figure (docs/calibration-handeye.md): measured 0.90 mean, 1.15 RMS over 3271 dots
    assert loo["mean_mm"] <= 1.0 and len(loo["per_view"]) == 10 and loo["dots"] > 3000
    assert loo["worst_view_mean_mm"] < 1.1  # measured 1.03 (view 1)
    # what the poses put wrong per view (the triangulation scatter averaged out): measured 0.06-0.49 mm
    assert max(v["offset_mm"] for v in loo["per_view"].values()) < 0.7
    # the figure sees a hand-eye error: the same held-out view with the hand-eye turned by one degree
    fit = calibrate_tracked_hand_eye(views[1:], board, cameras, log_warnings=False)
    turned = make_T(cv2.Rodrigues(np.array([0.0, np.deg2rad(1.0), 0.0]))[0], np.zeros(3))
    good = grid_error_mm(*triangulate_view(views[0], fit["T_scopemarker_camera"], fit["T_left_right"], cameras),
                         fit["T_boardmarker_pattern"], board)
    bad = grid_error_mm(*triangulate_view(views[0], fit["T_scopemarker_camera"] @ turned, fit["T_left_right"], cameras),
                        fit["T_boardmarker_pattern"], board)
    print(good, bad)
    assert bad["offset_mm"] > good["offset_mm"] + 1.0 and bad["mean_mm"] > 1.0 > good["mean_mm"]


def test_viking_calibration_report(viking, tmp_path):
    views, board, cameras = viking
    out = tmp_path / "handeye.yaml"
    r = calibrate_tracked_views(views, "viking", cameras, str(out), json_file=str(tmp_path / "r.json"),
                                leave_one_out=False)
    # OpenCV's methods per camera agree to a tenth of a degree and a millimetre; Andreff fails (named)
    for side in SIDES:
        agree = r["per_camera"][side]["agreement"]
        assert agree["rotation_deg"] < 0.2 and agree["translation_mm"] < 1.0
        assert set(r["per_camera"][side]["methods"]) >= {"tsai", "park", "horaud"}
    assert any("andreff failed" in w for w in r["warnings"])
    assert not any("rotation" in w or "only" in w for w in r["warnings"])  # 10 views, ~34 deg: enough motion
    # the dot board's ~3 px (docs/calibration.md: its lens RMS is ~2.7 px too)
    assert all(2.0 < v < 4.0 for v in r["reprojection_rms_px"].values())
    baseline = np.linalg.norm(r["T_left_right"][:3, 3]) * 1e3
    assert 4.0 < baseline < 5.0 and r["T_left_right"][0, 3] > 0  # the right channel 4.6 mm to the right
    # the camera sits ~27 cm from the scope's marker, down the scope's shaft
    assert 0.25 < np.linalg.norm(r["T_scopemarker_camera"][:3, 3]) < 0.30
    written = read_handeye_yaml(out)
    assert np.allclose(written["T_tip_camera"], r["T_scopemarker_camera"]) and written["tip_frame"] == "scope_marker"
    assert (tmp_path / "r.json").exists()


# --- a synthetic tracked set-up of known hand-eye ---------------------------------------------------------------------

def _synthetic(n_views: int, tilt_deg: float, seed: int, noise_px: float = 0.3, tracker_mm: float = 0.1,
               tracker_mrad: float = 0.3):
    """A stereo scope with a known hand-eye and rig looking at a dot board on its marker from n views (the
    camera on a sphere about the board's centre, tilted up to ``tilt_deg``); the dots projected with OpenCV,
    with pixel noise and tracker noise."""
    rng = np.random.default_rng(seed)
    board = parse_board("viking")
    cameras = {"left": CameraModel(1920, 1080, 1766.0, 1770.0, 916.0, 459.0, (-0.29, 0.0, 0.007, 0.0, 0.37)),
               "right": CameraModel(1920, 1080, 1792.0, 1792.0, 1113.0, 478.0, (-0.28, 0.0, 0.005, 0.0, 0.35))}
    X = make_T(cv2.Rodrigues(np.array([2.0, -0.4, 0.9]))[0], np.array([-0.025, 0.003, -0.273]))
    rig = make_T(cv2.Rodrigues(np.array([0.0, 0.026, 0.0]))[0], np.array([0.0045, 0.0, 0.0003]))
    B = make_T(cv2.Rodrigues(np.array([1.2, 0.3, -0.2]))[0], np.array([-0.02, 0.0, -0.02]))
    centre = B[:3, :3] @ board.object_points.mean(axis=0) + B[:3, 3]
    normal = B[:3, :3] @ np.array([0.0, 0.0, -1.0])  # the camera looks at the printed side
    views = []
    for i in range(n_views):
        axis = np.cross(normal, rng.normal(size=3))
        tilt = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(0.3, 1.0) * tilt_deg))[0]
        eye = centre + tilt @ normal * rng.uniform(0.10, 0.15)
        T_bm_cam = look_at(eye, centre + rng.normal(0, 0.005, 3), B[:3, :3] @ np.array([0.0, -1.0, 0.0]))
        T_bm_sm = T_bm_cam @ np.linalg.inv(X)
        detections = {}
        for side, cam_pose in (("left", T_bm_cam), ("right", T_bm_cam @ rig)):
            T_cam_pattern = np.linalg.inv(cam_pose) @ B
            rvec = cv2.Rodrigues(T_cam_pattern[:3, :3])[0]
            uv = cv2.projectPoints(board.object_points, rvec, T_cam_pattern[:3, 3], cameras[side].K,
                                   cameras[side].dist_array)[0].reshape(-1, 2)
            inside = np.flatnonzero((uv[:, 0] > 20) & (uv[:, 0] < 1900) & (uv[:, 1] > 20) & (uv[:, 1] < 1060))
            detections[side] = (uv[inside] + rng.normal(0, noise_px, (len(inside), 2)), inside)
        noisy = T_bm_sm @ make_T(cv2.Rodrigues(rng.normal(0, tracker_mrad * 1e-3, 3))[0],
                                 rng.normal(0, tracker_mm * 1e-3, 3))
        views.append(TrackedView(f"view {i}", noisy, detections))
    return views, board, cameras, X, rig, B


def test_a_synthetic_tracked_scope_of_known_hand_eye_is_recovered():
    views, board, cameras, X, rig, B = _synthetic(12, 35.0, seed=1)
    r = calibrate_tracked_hand_eye(views, board, cameras)
    rot, trans = pose_difference(r["T_scopemarker_camera"], X)
    print("X", rot, trans, "rig", pose_difference(r["T_left_right"], rig), "B",
          pose_difference(r["T_boardmarker_pattern"], B))
    assert rot < 0.1 and trans < 0.5
    rr, rt = pose_difference(r["T_left_right"], rig)
    assert rr < 0.05 and rt < 0.1
    br, bt = pose_difference(r["T_boardmarker_pattern"], B)
    assert br < 0.1 and bt < 0.5
    assert all(v < 0.6 for v in r["reprojection_rms_px"].values())  # 0.3 px noise in, plus the tracker's
    assert not any("rotation" in w or "only" in w for w in r["warnings"])
    # one camera alone: the same hand-eye, no rig
    mono = calibrate_tracked_hand_eye(views, board, {"left": cameras["left"]})
    assert mono["T_left_right"] is None and pose_difference(mono["T_scopemarker_camera"], X)[1] < 1.0
    # the leave-one-view-out figure on data whose truth is known: each held-out view in place to a fraction
    # of a millimetre (its own tracker noise: 0.1 mm, 0.3 mrad); the dots scatter by the triangulation (0.3 px
    # in a 4.5 mm baseline at 10-15 cm: ~0.9 mm mean)
    loo = leave_one_view_out(views, board, cameras)
    print({k: (round(v["mean_mm"], 2), round(v["offset_mm"], 2)) for k, v in loo["per_view"].items()})
    assert max(v["offset_mm"] for v in loo["per_view"].values()) < 0.5  # measured 0.05-0.38 (the tracker noise)
    # a view the right camera missed: calibrated with its left camera, not held out, no triangulation
    views[0] = TrackedView(views[0].name, views[0].T_boardmarker_scopemarker, {"left": views[0].detections["left"]})
    assert len(leave_one_view_out(views, board, cameras)["per_view"]) == 11
    with pytest.raises(CalibrationError, match="view 0: the pattern was not found in both cameras"):
        triangulate_view(views[0], X, rig, cameras)


def test_too_few_and_too_small_motions_are_warned():
    views, board, cameras, *_ = _synthetic(5, 2.0, seed=2)
    r = calibrate_tracked_hand_eye(views, board, cameras)
    text = " | ".join(r["warnings"])
    print(text)
    assert "only 5 stations" in text and "take more tracked views" in text
    assert "too little rotation" in text and "tilt the board" in text
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate_tracked_hand_eye(views[:2], board, cameras)


# --- files and the command --------------------------------------------------------------------------------------------

def test_tracker_files_and_command_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "pose.txt"
    bad.write_text("1 0 0\n0 1 0\n")
    with pytest.raises(CalibrationError, match="pose.txt: a tracker pose must be 4 rows"):
        read_tracker_matrix(bad)
    bad.write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(CalibrationError, match="not a rigid transform"):
        read_tracker_matrix(bad)
    with pytest.raises(CalibrationError, match="cannot read"):
        read_tracker_matrix(tmp_path / "missing.txt")
    # a glob for the scope's files that also catches the board's
    scope = [str(VIKING / f"calib.tracking.{i}.txt") for i in range(2)] + [str(VIKING / "calib.tracking.model.0.txt")]
    with pytest.raises(CalibrationError, match="both as a scope pose and as a board pose"):
        tracked_views(scope, [str(VIKING / "calib.tracking.model.0.txt")] * 3, {"left": [None] * 3})
    argv = ["calibrate", "handeye-tracked", "--scope-poses", str(VIKING / "calib.tracking.[0-9]*.txt"),
            "--board-poses", str(VIKING / "calib.tracking.model.*.txt"), "--left", str(VIKING / "calib.right.images.4.png"),
            "--board", "viking", "--camera", str(tmp_path / "left.yaml"), "--out", str(tmp_path / "he.yaml")]
    assert main(argv + ["--right", "x.png"]) == 2
    assert "needs both --right" in capsys.readouterr().err
    from lapreco_hil.calib.files import write_camera_yaml
    write_camera_yaml(tmp_path / "left.yaml", _owner_camera("left"))
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "10 --scope-poses, 10 --board-poses, 1 --left images" in err and len(err.strip().splitlines()) == 1
    assert main([*argv[:3], str(tmp_path / "none*.txt"), *argv[4:]]) == 2
    assert "matches no file" in capsys.readouterr().err


def test_the_command_on_the_stored_dots(tmp_path, capsys, monkeypatch):
    """The whole command with the board's detection replaced by the stored dots of the same images (the 20
    views are 15 MB; the detection itself is tested on a real view in test_lens_model_choice.py)."""
    import lapreco_hil.app.handeye_tracked as app
    from lapreco_hil.calib.files import write_camera_yaml

    dots = np.load(VIKING / "dots.npz")
    monkeypatch.setattr(app, "detect_images", lambda paths, board: [
        (dots[Path(p).stem + "_points"].astype(np.float64), dots[Path(p).stem + "_ids"].astype(np.int64))
        for p in paths])
    for side in SIDES:
        write_camera_yaml(tmp_path / f"{side}.yaml", _owner_camera(side))
    out = tmp_path / "handeye.yaml"
    argv = ["calibrate", "handeye-tracked", "--scope-poses", str(VIKING / "calib.tracking.[0-9]*.txt"),
            "--board-poses", str(VIKING / "calib.tracking.model.*.txt"),
            "--left", *[f"left{i}.png" for i in range(10)], "--right", *[f"right{i}.png" for i in range(10)],
            "--board", "viking", "--camera", str(tmp_path / "left.yaml"), "--camera-right",
            str(tmp_path / "right.yaml"), "--out", str(out), "--json", str(tmp_path / "report.json")]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "methods agree within" in text and "held out calib.tracking.9.txt" in text
    assert "leave-one-view-out: 3271 dots" in text and "rig: baseline 4.5" in text
    written = read_handeye_yaml(out)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert fs.getNode("leave_one_view_out_mean_mm").real() <= 1.0
    assert fs.getNode("T_left_right").mat().shape == (4, 4) and fs.getNode("T_boardmarker_pattern").mat()[3, 3] == 1
    fs.release()
    assert 0.25 < np.linalg.norm(written["T_tip_camera"][:3, 3]) < 0.30
