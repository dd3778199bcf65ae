"""Calibration workflows: lens (real OpenCV sample images; simulated views with known coefficients), hand-eye
(synthetic stations with known truth; a simulated board session end to end), the video-kinematics time
offset (a simulated session with an injected offset), and the files the rest of the app reads."""

from __future__ import annotations

import glob
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.calib.boards import parse_board
from lapreco_hil.calib.files import read_camera_yaml, read_handeye_yaml, write_camera_yaml
from lapreco_hil.calib.handeye import Station, calibrate_hand_eye, pose_difference
from lapreco_hil.calib.lens import calibrate_lens
from lapreco_hil.camera import CameraModel
from lapreco_hil.cli.main import main
from lapreco_hil.errors import CalibrationError
from lapreco_hil.geometry import inv_T, look_at, make_T, transform_points

DATA = Path(__file__).parent / "data" / "opencv-chessboard"
BOARD = "charuco:10x7:0.004:0.003:DICT_5X5_100"


# --- lens ---------------------------------------------------------------------------------------------------------

def test_lens_on_the_real_opencv_sample_images(tmp_path, capsys):
    images = sorted(glob.glob(str(DATA / "left*.jpg")))
    assert len(images) == 13
    out = tmp_path / "camera.yaml"
    assert main(["calibrate", "lens", *images, "--board", "chessboard:9x6:0.025", "--model", "paper",
                 "--out", str(out)]) == 0
    cam = read_camera_yaml(out)
    assert (cam.width, cam.height) == (640, 480)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    rms = fs.getNode("rms_px").real()
    fs.release()
    assert rms < 0.5  # sub-pixel on real images (measured 0.24 px)
    assert 500 < cam.fx < 560 and abs(cam.fx - cam.fy) < 0.02 * cam.fx
    assert cam.dist[0] < -0.2  # this webcam's barrel distortion
    assert (tmp_path / "camera.check.png").is_file()
    assert "13 of 13 views" in capsys.readouterr().out


def _board_world(warp_device):
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    return SimWorld(SimSettings(scene="board", width=640, height=480, device=warp_device))


def _board_views(world, n: int, seed: int) -> tuple[dict, dict]:
    """Views of the simulated board from tilted poses (10-50 deg) at 45-65 mm, and their true poses."""
    T_wb = world.T_world_scene @ world.scene.board[1]
    centre = transform_points(T_wb, np.array([[0.02, 0.014, 0.0]]))[0]
    normal, ex, ey = -T_wb[:3, 2], T_wb[:3, 0], T_wb[:3, 1]
    rng = np.random.default_rng(seed)
    images, poses = {}, {}
    for i in range(n):
        tilt, az, dist = np.deg2rad(rng.uniform(10, 50)), rng.uniform(0, 2 * np.pi), rng.uniform(0.045, 0.065)
        d = np.cos(tilt) * normal + np.sin(tilt) * (np.cos(az) * ex + np.sin(az) * ey)
        target = centre + rng.uniform(-0.006, 0.006) * ex + rng.uniform(-0.004, 0.004) * ey
        T = look_at(target + dist * d, target, -ey)
        images[f"view{i}"], _ = world.renderer.render(T, seed=seed * 1000 + i)
        poses[f"view{i}"] = inv_T(T) @ T_wb
    return images, poses


@pytest.mark.parametrize("model", ["paper", "standard"])
def test_lens_recovers_known_coefficients_on_simulated_views(model, warp_cpu):
    world = _board_world(warp_cpu)
    truth = world.camera
    board = parse_board(BOARD)
    images, _ = _board_views(world, 24, seed=1)
    result = calibrate_lens(images, board, model)
    cam = result.camera
    assert result.rms_px < 0.25 and not result.rejected
    # the well-determined parameters, with stated tolerances
    assert abs(cam.fx / truth.fx - 1) < 0.005 and abs(cam.fy / truth.fy - 1) < 0.005
    # the principal point trades off against the tangential and thin-prism terms (their effects here are
    # ~0.2 px at the image edge, under the noise): it is looser in the models that have them
    pp_tol = 5.0 if model == "standard" else 12.0
    assert abs(cam.cx - truth.cx) < pp_tol and abs(cam.cy - truth.cy) < pp_tol
    assert abs(cam.dist[0] - truth.dist[0]) < 0.01 and abs(cam.dist[1] - truth.dist[1]) < 0.03
    # and what matters: the model predicts held-out views of the board to a fraction of a pixel
    held_out, _ = _board_views(world, 6, seed=2)
    errs = []
    for img in held_out.values():
        pts, ids = board.detect(img)
        obj = board.object_points[ids]
        _, rvec, tvec = cv2.solvePnP(obj, pts, cam.K, cam.dist_array, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(obj, pts, cam.K, cam.dist_array, rvec, tvec)
        proj = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist_array)[0].reshape(-1, 2)
        errs.append(proj - pts)
    e = np.concatenate(errs)
    assert np.sqrt(np.mean(np.sum(e**2, axis=1))) < 0.3


def test_lens_with_the_wrong_board_is_a_clear_error(tmp_path, capsys):
    images = sorted(glob.glob(str(DATA / "left*.jpg")))[:5]
    status = main(["calibrate", "lens", *images, "--board", "chessboard:7x5:0.025", "--out", str(tmp_path / "c.yaml")])
    err = capsys.readouterr().err
    # (the classic detector can find a 7x5 patch inside the 9x6 board in a few views: still refused)
    assert status == 2 and "of 5 images; at least 4 are needed" in err and "inner corners" in err


def test_lens_with_images_of_two_sizes_names_a_file_of_each_size_in_wxh(tmp_path, capsys):
    small, big, small2 = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "c.png"
    cv2.imwrite(str(small), np.zeros((288, 360, 3), np.uint8))
    cv2.imwrite(str(big), np.zeros((1080, 1920, 3), np.uint8))
    cv2.imwrite(str(small2), np.zeros((288, 360, 3), np.uint8))
    status = main(["calibrate", "lens", str(small), str(big), str(small2), "--board", BOARD,
                   "--out", str(tmp_path / "c.yaml")])
    err = capsys.readouterr().err
    assert status == 2 and f"{small} is 360x288" in err and f"{big} is 1920x1080" in err, err
    assert str(small2) not in err and "(288, 360)" not in err, err


# --- hand-eye -------------------------------------------------------------------------------------------------------

X_TRUE = make_T(Rotation.from_euler("xyz", [30, 2, -3], degrees=True).as_matrix(), [0.001, -0.0015, 0.002])
B_TRUE = make_T(Rotation.from_euler("xyz", [180, 0, 10], degrees=True).as_matrix(), [0.0, 0.0, 0.05])
CAM = CameraModel(640, 480, 500, 500, 320, 240)


def synthetic_stations(n: int, rng, one_axis: bool = False, pixel_noise: float = 0.3, robot_rot: float = 0.0005,
                       robot_trans: float = 0.0001) -> list[Station]:
    board = parse_board(BOARD)
    obj = board.object_points
    out = []
    for i in range(n):
        rv = np.array([0, 0, 1.0]) * rng.normal(0, 0.25) if one_axis else rng.normal(0, 0.15, 3)
        offset = [rng.normal(0, 0.003) - 0.018, rng.normal(0, 0.003) - 0.012, 0.06 + rng.normal(0, 0.005)]
        C = make_T(Rotation.from_rotvec(rv).as_matrix(), offset)  # T_camera_board
        A = B_TRUE @ inv_T(C) @ inv_T(X_TRUE)
        pc = transform_points(C, obj)
        uv = pc[:, :2] / pc[:, 2:3] * 500 + 320 - np.array([0, 80]) + rng.normal(0, pixel_noise, (len(obj), 2))
        _, r, t = cv2.solvePnP(obj, uv, CAM.K, None, flags=cv2.SOLVEPNP_SQPNP)
        noisy_A = A @ make_T(Rotation.from_rotvec(rng.normal(0, robot_rot, 3)).as_matrix(),
                             rng.normal(0, robot_trans, 3))
        out.append(Station(f"s{i}", noisy_A, make_T(cv2.Rodrigues(r)[0], t.ravel()), obj, uv))
    return out


def test_hand_eye_methods_and_refinement_against_truth():
    rng = np.random.default_rng(5)
    result = calibrate_hand_eye(synthetic_stations(30, rng), CAM)
    errors = {m: pose_difference(v["T_tip_camera"], X_TRUE) for m, v in result["methods"].items()}
    refined = pose_difference(result["T_tip_camera"], X_TRUE)
    print({m: (round(r, 3), round(t, 3)) for m, (r, t) in errors.items()}, refined)
    good = [e for m, e in errors.items() if m != "andreff"]  # Andreff's linear solution is the least accurate
    assert all(r < 0.5 and t < 1.0 for r, t in good)
    best_rot, best_trans = min(e[0] for e in errors.values()), min(e[1] for e in errors.values())
    # the joint robust refinement is at least as good as the best closed-form method
    assert refined[0] <= best_rot * 1.05 and refined[1] <= best_trans * 1.05
    assert refined[0] < 0.2 and refined[1] < 0.5
    # the only warning: Andreff's translation broke down on these data, left out of the methods' agreement
    assert [w.split(" is far")[0] for w in result["warnings"]] == ["method andreff"]


def test_hand_eye_warns_about_degenerate_motion():
    rng = np.random.default_rng(6)
    result = calibrate_hand_eye(synthetic_stations(15, rng, one_axis=True), CAM)
    assert any("parallel axes" in w for w in result["warnings"])
    little = synthetic_stations(10, rng)
    for s in little:  # all stations at (nearly) one orientation
        s.T_base_tip = make_T(np.eye(3), s.T_base_tip[:3, 3])
    from lapreco_hil.calib.handeye import motion_warnings

    assert any("too little rotation" in w for w in motion_warnings(little))


def test_hand_eye_from_a_simulated_board_session(tmp_path, warp_cpu, capsys):
    from lapreco_hil.simulators.world.world import thirty_degree_optics

    session = tmp_path / "board"
    # 6 s of the scan (rotations about three axes, up to ~16 deg apart)
    assert main(["sim-record", "--scene", "board", "--frames", "150", "--resolution", "480x360", "--device", "cpu",
                 "--no-progress", "--out", str(session)]) == 0
    meta = json.loads((session / "session.json").read_text())
    meta["robot"]["T_tip_camera"] = np.eye(4).tolist()  # the workflow must not read the answer
    (session / "session.json").write_text(json.dumps(meta))
    out = tmp_path / "handeye.yaml"
    assert main(["calibrate", "handeye", str(session), "--board", BOARD, "--stride", "3", "--out", str(out)]) == 0
    X = read_handeye_yaml(out)["T_tip_camera"]
    rot_deg, trans_mm = pose_difference(X, thirty_degree_optics())
    print(capsys.readouterr().out, rot_deg, trans_mm)
    # with the robot's compliance (about 3 mrad of joint wander) in the tip poses: measured 0.34 deg, 1.4 mm
    assert rot_deg < 1.0 and trans_mm < 3.0
    # the pipeline reads it: a replay with this hand-eye
    from lapreco_hil.app.replay import run_replay

    r = run_replay(str(session), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False,
                   surface="alpha", hand_eye_file=str(out))
    assert r["hand_eye_file"] == str(out) and r["frames"]["processed"] == 150


# --- time offset ------------------------------------------------------------------------------------------------------

def test_time_offset_is_recovered_within_one_frame(tmp_path, warp_cpu, capsys):
    session = tmp_path / "late"
    assert main(["sim-record", "--scene", "skull", "--frames", "80", "--resolution", "320x240", "--device", "cpu",
                 "--no-progress", "--kinematics-offset-ms", "80", "--out", str(session)]) == 0
    # the simulated arm's joints wander with a 0.15 s time constant (simulators/robot.py); stated, as a user
    # states their arm's, it widens the uncertainty to cover what that wander does to a 3 s session
    assert main(["calibrate", "time-offset", str(session), "--search-ms", "300", "--apply", "--joint-wander-s",
                 "0.15", "--json", str(tmp_path / "t.json")]) == 0
    est = json.loads((tmp_path / "t.json").read_text())
    print(capsys.readouterr().out)
    assert abs(est["offset_ms"] - 80.0) < 40.0  # one frame period at 25 fps
    # the arm's joint wander moves a 3 s session's estimate by tens of ms (measured -22 ms here): the stated
    # uncertainty must cover it (docs/calibration-handeye.md)
    assert abs(est["offset_ms"] - 80.0) < 3 * est["sigma_ms"]
    assert est["median_sampson_px_at_offset"] < est["median_sampson_px_at_zero"]
    applied = json.loads((session / "session.json").read_text())["time_offset_ns"]
    assert abs(applied * 1e-6 - est["offset_ms"]) < 1e-3


# --- files ----------------------------------------------------------------------------------------------------------

def test_camera_yaml_round_trip_and_bad_files(tmp_path):
    cam = CameraModel.from_paper_model(640, 480, 457.0, 456.0, 320.5, 239.5, k=(-0.28, 0.09, -0.012),
                                       t=(0.0006, -0.0004), p=(0.0008, -0.0006), fov_radius_px=272.0)
    path = tmp_path / "camera.yaml"
    write_camera_yaml(path, cam)
    again = read_camera_yaml(path)
    assert again == cam
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nimage_width: 640\n")
    with pytest.raises(CalibrationError, match="bad.yaml: missing or non-integer 'image_height'"):
        read_camera_yaml(bad)
    bad.write_text("this is : not [ yaml")
    with pytest.raises(CalibrationError, match="bad.yaml"):
        read_camera_yaml(bad)
    with pytest.raises(CalibrationError, match="no such calibration file"):
        read_camera_yaml(tmp_path / "missing.yaml")
