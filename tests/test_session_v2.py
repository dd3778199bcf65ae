"""Session format version 2: a rig of cameras (a stereo scope). Round trips through the writer and reader with two
cameras of different sizes, the Hamlyn stereo pair written by the script in docs/session-format.md, the field of
view (circle, ellipse, mask), bad rig sessions refused with one line naming the file and line or field, version 1
still read as a rig of one, and the recorder and replay:// carrying Frame.views."""

from __future__ import annotations

import json
import logging
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from fuzz_settings import FUZZ, mutated
from hypothesis import given
from hypothesis import strategies as st

from lapreco_hil.camera import CameraModel, FieldOfView, Rig
from lapreco_hil.errors import SessionError
from lapreco_hil.geometry import make_T, rot_x, rot_z
from lapreco_hil.sessions import Session, SessionMeta, SessionWriter
from lapreco_hil.types import Frame, JointSample, RobotDescription

ROOT = Path(__file__).resolve().parents[1]
HAMLYN = ROOT / "tests" / "data" / "hamlyn-phantom-stereo"
DOC = ROOT / "docs" / "session-format.md"

LEFT = CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.02), 22.0)
RIGHT = CameraModel(80, 40, 61.0, 60.5, 40.25, 19.75, (-0.05, 0.01, 0.001),
                    fov=FieldOfView.ellipse(41.0, 19.0, 35.0, 17.0, 12.0))
T_LEFT_RIGHT = make_T(rot_z(0.012) @ rot_x(-0.004), [0.0055, -0.0002, 0.0003])  # metres


def stereo_meta(length_unit: str = "mm", **kw) -> SessionMeta:
    rig = Rig((LEFT, RIGHT), (np.eye(4), T_LEFT_RIGHT), 0.0007, 0.00015)
    return SessionMeta(camera=LEFT, rig=rig, pose_source="camera_poses", length_unit=length_unit, **kw)


def stereo_frames(n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(rng.integers(0, 256, (48, 64, 3), np.uint8), 1_000_000_000 + 40_000_000 * i, 10 + i,
                  views=(rng.integers(0, 256, (40, 80, 3), np.uint8),)) for i in range(n)]


def write_stereo(folder: Path, n: int = 4, **kw) -> list[Frame]:
    frames = stereo_frames(n)
    with SessionWriter(folder, stereo_meta(**kw)) as w:
        for f in frames:
            w.add_frame(f)
            w.add_camera_pose(f.t_ns, make_T(np.eye(3), [0.001 * f.seq, 0.0, 0.0]))
    return frames


# --- round trip -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("unit", ["mm", "m"])
def test_two_cameras_of_different_sizes_round_trip_bit_exact(tmp_path, unit):
    frames = write_stereo(tmp_path / "s", length_unit=unit)
    doc = json.loads((tmp_path / "s" / "session.json").read_text())
    assert doc["version"] == 2 and "camera" not in doc
    assert [c["name"] for c in doc["rig"]["cameras"]] == ["left", "right"]
    scale = 1000.0 if unit == "mm" else 1.0  # translations in the session's unit
    assert doc["rig"]["T_cam0_cam"][1][0][3] == pytest.approx(0.0055 * scale)
    assert (tmp_path / "s" / "frames.csv").read_text().splitlines()[:3] == [
        "seq,t_ns,camera,file", "10,1000000000,0,frames/left/000000.png", "10,1000000000,1,frames/right/000000.png"]

    s = Session(tmp_path / "s")
    assert len(s) == 4 and s.meta.complete and s.meta.counts["frames"] == 4
    assert s.rig.cameras == (LEFT, RIGHT) and s.camera == LEFT and s.meta.camera_names == ("left", "right")
    assert s.rig.cameras[1].fov == RIGHT.fov and s.rig.cameras[0].fov_radius_px == 22.0
    np.testing.assert_allclose(s.rig.T_cam0_cam[0], np.eye(4), atol=0)
    np.testing.assert_allclose(s.rig.T_cam0_cam[1], T_LEFT_RIGHT, rtol=0, atol=1e-15)
    assert (s.rig.sigma_rotation_rad, s.rig.sigma_translation_m) == (0.0007, 0.00015)
    for i, f in enumerate(frames):
        got = s.frame(i)
        assert (got.seq, got.t_ns, got.n_cameras) == (f.seq, f.t_ns, 2)
        assert np.array_equal(got.image, f.image) and np.array_equal(got.views[0], f.views[0])
        assert got.views[0].shape == (40, 80, 3)  # each camera at its own size: nothing resampled


def test_one_camera_is_still_written_as_version_1(tmp_path):
    meta = SessionMeta(camera=LEFT, pose_source="camera_poses")
    frame = stereo_frames(1)[0]
    with SessionWriter(tmp_path / "s", meta) as w:
        w.add_frame(Frame(frame.image, frame.t_ns, frame.seq))
        w.add_camera_pose(frame.t_ns, np.eye(4))
    doc = json.loads((tmp_path / "s" / "session.json").read_text())
    assert doc["version"] == 1 and doc["camera"]["fov_radius_px"] == 22.0 and "rig" not in doc
    assert (tmp_path / "s" / "frames.csv").read_text().splitlines() == ["seq,t_ns,file",
                                                                       "10,1000000000,frames/000000.png"]
    s = Session(tmp_path / "s")
    assert len(s.rig) == 1 and s.frame(0).views == ()


def test_a_hand_written_version_1_session_reads_as_a_rig_of_one(tmp_path):
    folder = tmp_path / "v1"
    (folder / "frames").mkdir(parents=True)
    image = np.random.default_rng(3).integers(0, 256, (48, 64, 3), np.uint8)
    cv2.imwrite(str(folder / "frames" / "a.png"), image)
    (folder / "frames.csv").write_text("seq,t_ns,file\n0,5000,frames/a.png\n")
    (folder / "camera_poses.csv").write_text("t_ns,tx,ty,tz,qx,qy,qz,qw\n5000,0,0,0,0,0,0,1\n")
    (folder / "session.json").write_text(json.dumps({
        "format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
        "camera": {"width": 64, "height": 48, "K": LEFT.K.tolist(), "dist": [0.1, -0.02], "fov_radius_px": 22},
        "pose_source": "camera_poses"}))
    s = Session(folder)
    assert s.camera == LEFT and s.rig.cameras == (LEFT,) and not s.rig.is_stereo
    frame = s.frame(0)
    assert np.array_equal(frame.image, image) and frame.views == ()


def write_v1(folder: Path, n: int = 2, ext: str = "png", camera: dict | None = None, **top) -> Path:
    """A version-1 camera-pose session by hand: ``n`` frames, ``camera`` fields over LEFT's, ``top`` over
    session.json's top level."""
    (folder / "frames").mkdir(parents=True)
    rng = np.random.default_rng(3)
    rows, poses = ["seq,t_ns,file"], ["t_ns,tx,ty,tz,qx,qy,qz,qw"]
    for i in range(n):
        cv2.imwrite(str(folder / "frames" / f"{i}.{ext}"), rng.integers(0, 256, (48, 64, 3), np.uint8))
        rows.append(f"{i},{5000 + i * 1000},frames/{i}.{ext}")
        poses.append(f"{5000 + i * 1000},0,0,{0.001 * i},0,0,0,1")
    (folder / "frames.csv").write_text("\n".join(rows) + "\n")
    (folder / "camera_poses.csv").write_text("\n".join(poses) + "\n")
    cam = {"width": 64, "height": 48, "K": LEFT.K.tolist(), "dist": [0.1, -0.02], "fov_radius_px": 22,
           **(camera or {})}
    (folder / "session.json").write_text(json.dumps({
        "format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
        "camera": cam, "pose_source": "camera_poses", **top}))
    return folder


BAD_V1 = {
    "negative fov radius": ({"camera": {"fov_radius_px": -3}},
                            "field 'camera.fov_radius_px' must be positive (or 0: no field of view), got -3.0"),
    "fov circle off the image": ({"camera": {"fov_radius_px": 10, "K": [[50, 0, 5000], [0, 51, 5000], [0, 0, 1]]}},
                                 "field 'camera.fov_radius_px' = 10.0 about the principal point (5000, 5000) covers "
                                 "no pixel of the 64x48 image"),
    "misspelled camera field": ({"camera": {"distortion": [0.1]}},
                                "field 'camera.distortion' is unknown; 'camera' allows width, height, K, dist, "
                                "fov_radius_px"),
    "a rig in version 1": ({"rig": {"cameras": [], "T_cam0_cam": []}},
                           "field 'rig' is a version-2 field; set \"version\": 2 for a rig"),
    "misspelled units field": ({"units": {"length": "m", "angle": "rad", "time": "ns", "lenght": "mm"}},
                               "field 'units.lenght' is unknown; 'units' allows length, angle, time"),
    "misspelled camera_poses field": ({"camera_poses": {"sigma_rot": 0.01}},
                                      "field 'camera_poses.sigma_rot' is unknown; 'camera_poses' allows "
                                      "sigma_rotation_rad, sigma_translation_m"),
    # a misspelled hand-eye made a calibration session (no hand-eye) of a robot session without a word
    "misspelled robot field": ({"pose_source": "joints", "robot": {
        "urdf": "ecm", "tip_frame": "ecm_tip", "joint_names": ["a"], "joint_units": ["angle"],
        "T_tip_cam": np.eye(4).tolist()}}, "field 'robot.T_tip_cam' is unknown; 'robot' allows urdf, tip_frame, "
                                           "joint_names, joint_units, T_tip_camera, T_world_base"),
    "misspelled tracker field": ({"pose_source": "marker_poses", "tracker": {"tool": "scope", "max_rms": 1.0}},
                                 "field 'tracker.max_rms' is unknown; 'tracker' allows tool, T_marker_camera"),
}


@pytest.mark.parametrize("case", sorted(BAD_V1))
def test_a_bad_version_1_session_gives_one_clear_line(case, tmp_path):
    """Version 1 is checked as strictly as version 2 (a field of view, unknown keys)."""
    changes, message = BAD_V1[case]
    folder = write_v1(tmp_path / "v1", camera=changes.get("camera"),
                      **{k: v for k, v in changes.items() if k != "camera"})
    with pytest.raises(SessionError) as exc:
        Session(folder)
    text = str(exc.value)
    assert "\n" not in text and "session.json" in text and message in text, text


def test_extra_top_level_keys_are_still_allowed(tmp_path):
    """The top level of session.json is open (informative fields of other writers); the objects are not."""
    s = Session(write_v1(tmp_path / "v1", notes={"operator": "A"}, my_tool_version="3.1"))
    assert len(s) == 2 and s.camera == LEFT


def test_a_version_1_pair_of_frames_reads_as_one_rig_frame_when_asked(tmp_path):
    """Session.pair_frames_as_rig (what a replay asks for): two frames with poses at their own times become one
    frame of a rig of two, camera 1 at the poses' relative transform; other readers see two frames; frames at
    one place (no baseline) or without poses at their times stay two frames."""
    s = Session(write_v1(tmp_path / "pair"))
    assert len(s) == 2 and not s.pair_as_rig  # (an export, a live run's replay:// grabber)
    assert s.pair_frames_as_rig()
    assert len(s) == 1 and s.pair_as_rig and len(s.rig) == 2 and s.second_frame == (1, 6000)
    assert np.allclose(s.rig.T_cam0_cam[1][:3, 3], [0.0, 0.0, 0.001])
    frame = s.frame(0)
    assert frame.t_ns == 5000 and len(frame.views) == 1 and frame.views[0].shape == frame.image.shape
    assert not s.pair_frames_as_rig()  # (once)

    still = write_v1(tmp_path / "still")
    (still / "camera_poses.csv").write_text("t_ns,tx,ty,tz,qx,qy,qz,qw\n5000,0,0,0,0,0,0,1\n6000,0,0,0,0,0,0,1\n")
    s = Session(still)
    assert not s.pair_frames_as_rig() and len(s) == 2
    s = Session(write_v1(tmp_path / "offset"))
    assert not s.pair_frames_as_rig(offset_ns=500) and len(s) == 2  # no pose at the frames' times


def test_a_jpeg_frame_is_read_with_one_warning_per_session(tmp_path, caplog):
    s = Session(write_v1(tmp_path / "jpeg", n=3, ext="jpg"))
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.sessions"):
        frames = [s.frame(i) for i in range(len(s))] + [s.frame(0)]
    assert all(f.image.shape == (48, 64, 3) for f in frames)  # read, not refused
    jpeg = [r.getMessage() for r in caplog.records if "JPEG" in r.getMessage()]
    assert len(jpeg) == 1 and "0.jpg" in jpeg[0] and "JPEG artefacts bias tracking" in jpeg[0], jpeg
    caplog.clear()
    s = Session(write_v1(tmp_path / "png", n=3))
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.sessions"):
        [s.frame(i) for i in range(len(s))]
    assert not [r for r in caplog.records if "JPEG" in r.getMessage()]


# --- a last line without a newline: read in a session closed cleanly, left out in one cut short ------------------

def _strip_final_newline(file: Path, tail: str = "") -> None:
    file.write_text(file.read_text().rstrip("\n") + tail)


def test_a_complete_sessions_last_row_without_a_newline_is_read(tmp_path):
    folder = write_v1(tmp_path / "s", n=3)
    for name in ("frames.csv", "camera_poses.csv"):
        _strip_final_newline(folder / name)
    s = Session(folder)
    assert s.meta.complete and len(s) == 3 and len(s.pose_t_ns) == 3 and s.truncated == []
    assert s.frame(2).t_ns == 7000 and s.poses[2][2, 3] == pytest.approx(0.002)


@pytest.mark.parametrize("name, tail, message", [
    ("frames.csv", "\n3,8000,frames/3.p", "frames.csv: line 5: frame file 'frames/3.p' is missing"),
    ("frames.csv", "\n3,80", "frames.csv: line 5: 2 columns, expected 3 (the last line, without a newline"),
    ("camera_poses.csv", "\n8000,0,0,0.", "camera_poses.csv: line 5: 4 columns, expected 8"),
])
def test_a_complete_sessions_unfinished_last_row_is_an_error(name, tail, message, tmp_path):
    folder = write_v1(tmp_path / "s", n=3)
    _strip_final_newline(folder / name, tail)
    with pytest.raises(SessionError, match=re.escape(message)):
        Session(folder)


def test_an_unfinished_last_row_of_a_session_cut_short_is_left_out_with_a_warning(tmp_path, caplog):
    folder = write_v1(tmp_path / "s", n=3, complete=False)
    _strip_final_newline(folder / "frames.csv", "\n3,80")
    _strip_final_newline(folder / "camera_poses.csv", "\n8000,0,0,0.")
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.sessions"):
        s = Session(folder)
    assert len(s) == 3 and len(s.pose_t_ns) == 3 and s.truncated == ["frames.csv"]
    cut = [r.getMessage() for r in caplog.records if "no newline" in r.getMessage()]
    assert len(cut) == 2 and "frames.csv: line 5" in cut[0] and "camera_poses.csv: line 5" in cut[1], cut


def test_marker_poses_follow_the_same_last_row_rule(tmp_path):
    from lapreco_hil.sessions import format as fmt

    path = tmp_path / "marker_poses.csv"
    rows = ",".join(fmt.MARKER_COLUMNS) + "\n1000,scope,0,0,0,0,0,0,1,0.2,1\n2000,scope,0,0,0,0,0,0,1,0.2,1"
    path.write_text(rows)
    table, truncated = fmt.read_marker_table(path, 1.0, complete=True)
    assert len(table) == 2 and not truncated
    table, truncated = fmt.read_marker_table(path, 1.0, complete=False)
    assert len(table) == 1 and truncated
    path.write_text(rows[:-4])  # cut inside the last row
    with pytest.raises(SessionError, match="marker_poses.csv: line 3: 10 columns, expected 11"):
        fmt.read_marker_table(path, 1.0, complete=True)


def test_a_frame_whose_views_do_not_match_the_rig_is_refused(tmp_path):
    frame = stereo_frames(1)[0]
    with SessionWriter(tmp_path / "s", stereo_meta()) as w:
        with pytest.raises(SessionError, match="carries 1 image\\(s\\) \\(Frame.views\\), the session's rig has 2"):
            w.add_frame(Frame(frame.image, frame.t_ns, frame.seq))
        with pytest.raises(SessionError, match="camera 1 \\(right\\) of frame seq 10 is 64x48, the session's "
                                               "camera is 80x40"):
            w.add_frame(Frame(frame.image, frame.t_ns, frame.seq, views=(frame.image,)))


def test_a_frames_rows_are_appended_only_once_all_its_images_are_in_place(tmp_path, monkeypatch):
    """Crash safety for a rig: camera 1's image still being written holds back camera 0's row too."""
    release = threading.Event()
    encode = SessionWriter._encode

    def slow_right(self, image, seq, final):
        if final.parent.name == "right":
            assert release.wait(10)
        encode(self, image, seq, final)

    monkeypatch.setattr(SessionWriter, "_encode", slow_right)
    frame = stereo_frames(1)[0]
    with SessionWriter(tmp_path / "s", stereo_meta(), workers=2) as w:
        w.add_frame(frame)
        deadline = 50
        while not (tmp_path / "s" / "frames" / "left" / "000000.png").is_file() and deadline:
            threading.Event().wait(0.02)
            deadline -= 1
        assert (tmp_path / "s" / "frames" / "left" / "000000.png").is_file()
        w._drain()
        assert (tmp_path / "s" / "frames.csv").read_text() == "seq,t_ns,camera,file\n"
        release.set()
    assert len((tmp_path / "s" / "frames.csv").read_text().splitlines()) == 3


# --- the Hamlyn stereo pair, written by the documented script -----------------------------------------------------

def doc_script() -> str:
    """The worked example's Python block in docs/session-format.md (the one that reads calib.l2r.4x4)."""
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    scripts = [b for b in blocks if "calib.l2r.4x4" in b]
    assert len(scripts) == 1, "docs/session-format.md must hold the Hamlyn example script once"
    return scripts[0]


def test_the_documented_script_writes_the_hamlyn_pair_as_one_rig_frame(tmp_path):
    script = tmp_path / "hamlyn_session.py"
    script.write_text(doc_script())
    out = tmp_path / "hamlyn-session"
    run = subprocess.run([sys.executable, str(script), str(HAMLYN), str(out)], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    s = Session(out)
    assert len(s) == 1 and s.meta.length_unit == "mm" and s.meta.camera_names == ("left", "right")
    left, right = s.rig.cameras
    np.testing.assert_array_equal(left.K, np.loadtxt(HAMLYN / "calib.left.intrinsic.txt"))
    np.testing.assert_array_equal(right.K, np.loadtxt(HAMLYN / "calib.right.intrinsic.txt"))
    assert (left.width, left.height) == (right.width, right.height) == (360, 288) and left != right
    # calib.l2r.4x4 maps left points to the right camera: the rig holds its inverse, in metres
    l2r = np.loadtxt(HAMLYN / "calib.l2r.4x4")
    expected = np.linalg.inv(l2r)
    expected[:3, 3] *= 1e-3
    np.testing.assert_allclose(s.rig.T_cam0_cam[1], expected, atol=1e-6)  # the file: R to 1e-6
    assert s.rig.baseline_m() == pytest.approx(0.00552, abs=1e-5)
    assert s.rig.T_cam0_cam[1][0, 3] > 0.005  # the right camera on the left one's +x side
    frame = s.frame(0)
    assert np.array_equal(frame.image, cv2.imread(str(HAMLYN / "f7_dynamic_deint_L_0100.png")))
    assert np.array_equal(frame.views[0], cv2.imread(str(HAMLYN / "f7_dynamic_deint_R_0100.png")))
    # the rig's extrinsics put the tissue in front of both cameras: points tracked from left to right and
    # triangulated with them lie at positive depth (the l2r matrix itself, not inverted, puts them behind)
    grey = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in (frame.image, frame.views[0])]
    corners = cv2.goodFeaturesToTrack(grey[0], 300, 0.01, 8)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(grey[0], grey[1], corners, None, winSize=(21, 21), maxLevel=3)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(grey[1], grey[0], moved, None, winSize=(21, 21), maxLevel=3)
    ok = (status.ravel() == 1) & (status_back.ravel() == 1) & (np.linalg.norm(back - corners, axis=2).ravel() < 0.5)
    assert ok.sum() > 50
    T_right_left = np.linalg.inv(s.rig.T_cam0_cam[1])
    P0 = left.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = right.K @ T_right_left[:3]
    X = cv2.triangulatePoints(P0, P1, corners[ok].reshape(-1, 2).T, moved[ok].reshape(-1, 2).T)
    depth_m = X[2] / X[3]
    assert np.mean(depth_m > 0) > 0.95 and 0.03 < np.median(depth_m) < 0.12, np.median(depth_m)  # ~61 mm


def test_the_documented_version_2_metadata_reads(tmp_path):
    """The session.json example of docs/session-format.md is a valid version-2 document (its mask in place)."""
    from lapreco_hil.sessions.format import meta_from_json

    blocks = [b for b in re.findall(r"```json\n(.*?)```", DOC.read_text(), re.S) if '"version": 2' in b]
    assert len(blocks) == 1
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "right.png"), np.full((288, 360), 255, np.uint8))
    meta = meta_from_json(json.loads(blocks[0]), str(tmp_path / "session.json"), tmp_path)
    assert meta.camera_names == ("left", "right") and meta.rig.cameras[1].fov.kind == "mask"
    assert meta.rig.cameras[0].fov == FieldOfView.circle(180, 144, 170)
    assert meta.rig.T_cam0_cam[1][0, 3] == pytest.approx(0.005520766)  # mm in the file, metres inside


# --- field of view ----------------------------------------------------------------------------------------------

def write_fov_session(folder: Path, fov_json: dict | None, mask: np.ndarray | None = None,
                      size: tuple[int, int] = (80, 60)) -> Path:
    """A version-2 session of one camera with the given fov entry (and mask file), by hand."""
    w, h = size
    (folder / "frames").mkdir(parents=True)
    cv2.imwrite(str(folder / "frames" / "a.png"), np.full((h, w, 3), 90, np.uint8))
    if mask is not None:
        (folder / "masks").mkdir()
        cv2.imwrite(str(folder / "masks" / "scope.png"), mask)
    (folder / "frames.csv").write_text("seq,t_ns,camera,file\n0,5000,0,frames/a.png\n")
    (folder / "camera_poses.csv").write_text("t_ns,tx,ty,tz,qx,qy,qz,qw\n5000,0,0,0,0,0,0,1\n")
    cam = {"name": "scope", "width": w, "height": h, "K": [[70, 0, 40], [0, 70, 30], [0, 0, 1]]}
    if fov_json is not None:
        cam["fov"] = fov_json
    (folder / "session.json").write_text(json.dumps({
        "format": "lapreco-session", "version": 2, "units": {"length": "m", "angle": "rad", "time": "ns"},
        "rig": {"cameras": [cam], "T_cam0_cam": [np.eye(4).tolist()]}, "pose_source": "camera_poses"}))
    return folder


def test_a_circle_field_of_view_off_the_principal_point(tmp_path):
    s = Session(write_fov_session(tmp_path / "c", {"circle": {"cx": 30, "cy": 25, "r": 20}}))
    cam = s.camera
    assert cam.fov == FieldOfView.circle(30, 25, 20) and cam.fov_radius_px == 20
    mask = cam.fov_mask()
    yy, xx = np.mgrid[0:60, 0:80]
    d = np.hypot(xx - 30, yy - 25)
    assert np.all(mask[d <= 19] == 255) and np.all(mask[d >= 21] == 0)
    shrunk = cam.fov_mask(margin_px=5)
    assert np.all(shrunk[d <= 14] == 255) and np.all(shrunk[d >= 16] == 0)
    # a circle about the principal point is version 1's fov_radius_px: the same camera either way
    s2 = Session(write_fov_session(tmp_path / "p", {"circle": {"cx": 40, "cy": 30, "r": 20}}))
    assert s2.camera == CameraModel(80, 60, 70, 70, 40, 30, fov_radius_px=20) and s2.camera.fov is None


def test_a_circle_beyond_opencvs_coordinates_still_makes_its_mask():
    """A camera built in code (not read from a session, which bounds the circle) with a huge circle, e.g. "no
    field of view" written as r = 1e12: OpenCV's circle takes C ints and failed inside the mask."""
    everything = FieldOfView.circle(40, 30, 1e12).region(80, 60)
    assert np.all(everything == 255)
    edge = FieldOfView.circle(-1e9, 30, 1e9 + 20.0).region(80, 60)  # its edge a near-straight line at x = 20
    assert np.all(edge[:, :20] == 255) and np.all(edge[:, 21:] == 0)


def test_an_ellipse_field_of_view(tmp_path):
    s = Session(write_fov_session(tmp_path / "e", {"ellipse": {"cx": 40, "cy": 30, "a": 35, "b": 20,
                                                               "angle_deg": 90}}))
    mask = s.camera.fov_mask()
    # a = 35 along the image y axis (90 degrees), b = 20 along x
    assert mask[30 + 27, 40] == 255 and mask[30, 40 + 27] == 0 and mask[30, 40 + 19] == 255
    assert mask[30 - 27, 40] == 255 and mask[30, 40 - 21] == 0
    assert np.count_nonzero(mask) == pytest.approx(np.pi * 35 * 20 * (60 / 70), rel=0.25)  # clipped at y
    shrunk = s.camera.fov_mask(margin_px=4)  # semi-axes 31 and 16
    assert shrunk[30, 40 + 15] == 255 and shrunk[30, 40 + 17] == 0
    yy, xx = np.mgrid[0:60, 0:80]
    level = ((yy - 30) / 35.0) ** 2 + ((xx - 40) / 20.0) ** 2
    on_edge = np.abs(level - 1) < 1e-9  # pixel centres exactly on the ellipse: either way
    assert np.array_equal((mask == 255)[~on_edge], (level <= 1)[~on_edge])


def test_a_mask_field_of_view(tmp_path):
    mask = np.zeros((60, 80), np.uint8)
    mask[10:50, 15:70] = 7  # any non-zero value is inside
    s = Session(write_fov_session(tmp_path / "m", {"mask": "masks/scope.png"}, mask))
    cam = s.camera
    assert cam.fov.kind == "mask" and Path(cam.fov.mask_file).name == "scope.png"
    assert np.array_equal(cam.fov_mask(), np.where(mask > 0, 255, 0).astype(np.uint8))
    shrunk = cam.fov_mask(margin_px=3)  # pixels within 3 px of the outside are left out
    assert shrunk[13, 40] == 255 and shrunk[12, 40] == 0 and shrunk[30, 18] == 255 and shrunk[30, 17] == 0
    assert np.count_nonzero(shrunk) == (40 - 6) * (55 - 6)


def test_a_mask_field_of_view_is_copied_into_a_written_session(tmp_path):
    mask = np.zeros((40, 80), np.uint8)
    cv2.circle(mask, (40, 20), 18, 255, -1)
    cv2.imwrite(str(tmp_path / "scope-mask.png"), mask)
    right = CameraModel(80, 40, 61.0, 60.5, 40.25, 19.75, fov=FieldOfView.mask(tmp_path / "scope-mask.png"))
    meta = SessionMeta(camera=LEFT, rig=Rig((LEFT, right), (np.eye(4), T_LEFT_RIGHT)), pose_source="camera_poses")
    frame = stereo_frames(1)[0]
    with SessionWriter(tmp_path / "s", meta) as w:
        w.add_frame(frame)
        w.add_camera_pose(frame.t_ns, np.eye(4))
    (tmp_path / "scope-mask.png").unlink()  # the session holds its own copy
    doc = json.loads((tmp_path / "s" / "session.json").read_text())
    assert doc["rig"]["cameras"][1]["fov"] == {"mask": "masks/right.png"}
    s = Session(tmp_path / "s")
    assert np.array_equal(s.rig.cameras[1].fov_mask(), mask)


# --- bad rig sessions: one line naming the file and the line or field ---------------------------------------------

def _edit_json(folder: Path, edit) -> None:
    doc = json.loads((folder / "session.json").read_text())
    edit(doc)
    (folder / "session.json").write_text(json.dumps(doc))


def _edit_frames(folder: Path, edit) -> None:
    lines = (folder / "frames.csv").read_text().splitlines()
    (folder / "frames.csv").write_text("\n".join(edit(lines)) + "\n")


def _mask_folder(folder: Path) -> None:
    (folder / "masks" / "right.png").mkdir(parents=True)  # a folder where the mask file should be
    _edit_json(folder, lambda d: d["rig"]["cameras"][1].update(fov={"mask": "masks/right.png"}))


def _wrong_size_mask(folder: Path) -> None:
    (folder / "masks").mkdir()
    cv2.imwrite(str(folder / "masks" / "right.png"), np.full((48, 64), 255, np.uint8))  # the LEFT camera's size
    _edit_json(folder, lambda d: d["rig"]["cameras"][1].update(fov={"mask": "masks/right.png"}))


BAD = {
    "missing camera image": (lambda f: _edit_frames(f, lambda ls: ls[:4] + ls[5:]), "frames.csv",
                             "line 4: seq 11 has no image for camera 1 (right)"),
    "camera out of range": (lambda f: _edit_frames(f, lambda ls: ls[:2] + ["10,1000000000,2,frames/right/000000.png"]
                                                   + ls[3:]), "frames.csv",
                            "line 3: column 'camera' = 2 is out of range; the rig has 2 cameras"),
    "camera twice": (lambda f: _edit_frames(f, lambda ls: ls[:2] + ["10,1000000000,0,frames/left/000001.png"]
                                            + ls[3:]), "frames.csv",
                     "line 3: camera 0 (left) appears twice for seq 10 (lines 2 and 3)"),
    "cameras at different times": (lambda f: _edit_frames(f, lambda ls: ls[:2] + [
        "10,1000000001,1,frames/right/000000.png"] + ls[3:]), "frames.csv",
                                   "line 3: t_ns 1000000001 differs from line 2's 1000000000 for the same seq 10"),
    "version 1 header": (lambda f: _edit_frames(f, lambda ls: ["seq,t_ns,file"] + ls[1:]), "frames.csv",
                         "line 1: header is 'seq,t_ns,file', expected it to start with 'seq,t_ns,camera,file'"),
    "mask of the wrong size": (_wrong_size_mask, "session.json",
                               "field 'rig.cameras[1].fov.mask' = 'masks/right.png': the mask is 64x48, the camera "
                               "is 80x40"),
    "mask outside the session": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1].update(
        fov={"mask": "../elsewhere.png"})), "session.json", "leads outside the session folder"),
    "cam0 not identity": (lambda f: _edit_json(f, lambda d: d["rig"]["T_cam0_cam"].__setitem__(
        0, make_T(np.eye(3), [0.001, 0, 0]).tolist())), "session.json",
                          "field 'rig.T_cam0_cam[0]' must be the identity"),
    "extrinsics not rigid": (lambda f: _edit_json(f, lambda d: d["rig"]["T_cam0_cam"][1][0].__setitem__(0, 2.0)),
                             "session.json", "field 'rig.T_cam0_cam[1]' is not a rigid transform"),
    "one transform for two cameras": (lambda f: _edit_json(f, lambda d: d["rig"]["T_cam0_cam"].pop()),
                                      "session.json", "field 'rig.T_cam0_cam' must be a list of 2 entries, got 1"),
    "two kinds of fov": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][0].update(
        fov={"circle": {"cx": 1, "cy": 1, "r": 1}, "mask": "masks/x.png"})), "session.json",
                         "field 'rig.cameras[0].fov' must hold exactly one of"),
    "ellipse without an axis": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1]["fov"]["ellipse"].pop("b")),
                                "session.json", "field 'rig.cameras[1].fov.ellipse.b' is missing"),
    "same name twice": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1].update(name="left")),
                        "session.json", "field 'rig.cameras[1].name' is 'left'; camera names must be distinct"),
    "version 1 camera in version 2": (lambda f: _edit_json(f, lambda d: d.update(camera=d["rig"]["cameras"][0])),
                                      "session.json", "field 'camera' is a version-1 field"),
    "ellipse off the image": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1].update(
        fov={"ellipse": {"cx": 5000, "cy": 5000, "a": 10, "b": 10}})), "session.json",
                              "field 'rig.cameras[1].fov' = {\"ellipse\": {\"cx\": 5000, \"cy\": 5000, \"a\": 10, "
                              "\"b\": 10}} covers no pixel of the 80x40 image"),
    "circle off the image": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][0].update(
        fov={"circle": {"cx": -1000, "cy": 144, "r": 10}})), "session.json",
                             "field 'rig.cameras[0].fov' = {\"circle\": {\"cx\": -1000, \"cy\": 144, \"r\": 10}} "
                             "covers no pixel of the 64x48 image"),
    "circle too far out to draw": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][0].update(
        fov={"circle": {"cx": 1e12, "cy": 20, "r": 1e12}})), "session.json",
                                   "field 'rig.cameras[0].fov' = {\"circle\": {\"cx\": 1000000000000.0, \"cy\": 20, "
                                   "\"r\": 1000000000000.0}} is too far out to draw"),
    "misspelled camera field": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][0].update(
        distortion=d["rig"]["cameras"][0].pop("dist"))), "session.json",
                                "field 'rig.cameras[0].distortion' is unknown; 'rig.cameras[0]' allows name, width, "
                                "height, K, dist, fov"),
    "misspelled ellipse field": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1]["fov"]["ellipse"].update(
        angle=d["rig"]["cameras"][1]["fov"]["ellipse"].pop("angle_deg"))), "session.json",
                                 "field 'rig.cameras[1].fov.ellipse.angle' is unknown; 'rig.cameras[1].fov.ellipse' "
                                 "allows cx, cy, a, b, angle_deg"),
    "misspelled circle field": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][0].update(
        fov={"circle": {"cx": 30, "cy": 20, "radius": 10}})), "session.json",
                                "field 'rig.cameras[0].fov.circle.radius' is unknown; 'rig.cameras[0].fov.circle' "
                                "allows cx, cy, r"),
    "unknown fov field": (lambda f: _edit_json(f, lambda d: d["rig"]["cameras"][1]["fov"].update(margin_px=3)),
                          "session.json", "field 'rig.cameras[1].fov' must hold exactly one of 'circle', 'ellipse' "
                                          "or 'mask', got ['ellipse', 'margin_px']"),
    "misspelled rig field": (lambda f: _edit_json(f, lambda d: d["rig"].update(sigma_rot=0.001)), "session.json",
                             "field 'rig.sigma_rot' is unknown; 'rig' allows cameras, T_cam0_cam, sigma_rotation_rad, "
                             "sigma_translation_m"),
    "mask is a folder": (_mask_folder, "session.json",
                         "field 'rig.cameras[1].fov.mask' = 'masks/right.png' is a folder, not a PNG file"),
    "wrong size view": (lambda f: cv2.imwrite(str(f / "frames" / "right" / "000002.png"),
                                              np.zeros((48, 64, 3), np.uint8)),
                        "right/000002.png", "image is 64x48, the session's camera 'right' is 80x40"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_rig_session_gives_one_clear_line(case, tmp_path):
    corrupt, file_part, message = BAD[case]
    folder = tmp_path / "s"
    write_stereo(folder)
    corrupt(folder)
    with pytest.raises(SessionError) as exc:
        s = Session(folder)
        for i in range(len(s)):
            s.frame(i)
    text = str(exc.value)
    assert "\n" not in text and file_part in text and message in text, text


def test_a_last_frame_cut_short_by_a_crash_is_left_out(tmp_path):
    folder = tmp_path / "s"
    write_stereo(folder, n=3)
    rows = (folder / "frames.csv").read_text()
    # killed while appending the last frame's rows: camera 0's row complete, camera 1's unfinished
    (folder / "frames.csv").write_text(rows + "13,1120000000,0,frames/left/000002.png\n13,1120000000,1,fra")
    _edit_json(folder, lambda d: d.update(complete=False))  # a killed recorder never marks it complete
    s = Session(folder)
    assert len(s) == 3 and s.truncated == ["frames.csv"]
    # the same rows in a session marked complete (closed cleanly: nothing was cut short) are read, and the
    # unfinished one is an error naming its line
    _edit_json(folder, lambda d: d.update(complete=True))
    with pytest.raises(SessionError, match="frames.csv: line 9: frame file 'fra' is missing"):
        Session(folder)
    # cut between the two rows of a session never closed: the same
    (folder / "frames.csv").write_text(rows + "13,1120000000,0,frames/left/000002.png\n")
    _edit_json(folder, lambda d: d.update(complete=False))
    assert len(Session(folder)) == 3
    # in a session closed cleanly it is an error, not a crash
    _edit_json(folder, lambda d: d.update(complete=True))
    with pytest.raises(SessionError, match="frames.csv: line 8: seq 13 has no image for camera 1 \\(right\\)"):
        Session(folder)


# --- replay:// and the recorder -----------------------------------------------------------------------------------

def test_replay_of_a_rig_session_delivers_views_and_reports_the_rig(tmp_path):
    from lapreco_hil.registry import DeviceContext, open_grabber

    frames = write_stereo(tmp_path / "s")
    grabber = open_grabber(f"replay://{tmp_path / 's'}", DeviceContext(device="cpu"))
    with grabber:
        got = []
        while (f := grabber.read()) is not None:
            got.append(f)
    assert grabber.rig.cameras == (LEFT, RIGHT) and grabber.camera == LEFT
    np.testing.assert_allclose(grabber.rig.T_cam0_cam[1], T_LEFT_RIGHT, atol=1e-15)
    assert [f.seq for f in got] == [f.seq for f in frames]
    for a, b in zip(got, frames):
        assert np.array_equal(a.image, b.image) and len(a.views) == 1 and np.array_equal(a.views[0], b.views[0])


def test_the_recorder_records_a_grabbers_rig_and_views(tmp_path):
    """A stereo joints session replayed through replay:// (grabber and robot) and recorded again: the new
    session is a rig session with the same images in views; a calibration given for camera 0 replaces it."""
    from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
    from lapreco_hil.robot_models import urdf_path
    from lapreco_hil.sessions.recorder import record

    description = RobotDescription("ecm", "ecm_tip", np.eye(4))
    meta = stereo_meta(robot=description, joint_names=("yaw", "pitch", "insertion", "roll"),
                       joint_units=("angle", "angle", "length", "angle"))
    meta = SessionMeta(**{**meta.__dict__, "pose_source": "joints"})
    frames = stereo_frames(5)
    with SessionWriter(tmp_path / "src", meta, urdf_path("ecm")) as w:
        for f in frames:
            w.add_joints([JointSample(np.array([0.1, -0.2, 0.12, 0.3]), f.t_ns - 1_000_000, f.seq),
                          JointSample(np.array([0.1, -0.2, 0.12, 0.3]), f.t_ns + 1_000_000, f.seq)])
            w.add_frame(f)
    url = f"replay://{tmp_path / 'src'}"
    context = DeviceContext(device="cpu")
    grabber, robot = open_grabber(url, context), open_robot(url, context)
    calibrated = CameraModel(64, 48, 52.0, 52.5, 32.0, 24.0, (0.05,))
    with grabber, robot:
        stats = record(grabber, robot, str(tmp_path / "again"), camera=calibrated, progress=False)
    assert stats.frames == 5 and stats.joint_samples == 10
    s = Session(tmp_path / "again")
    assert json.loads((tmp_path / "again" / "session.json").read_text())["version"] == 2
    assert s.rig.cameras == (calibrated, RIGHT) and s.meta.pose_source == "joints"
    np.testing.assert_allclose(s.rig.T_cam0_cam[1], T_LEFT_RIGHT, atol=1e-15)
    for i, f in enumerate(frames):
        got = s.frame(i)
        assert np.array_equal(got.image, f.image) and np.array_equal(got.views[0], f.views[0])


# --- fuzzing: a mutated rig session is read or refused with one line ---------------------------------------------

@pytest.fixture(scope="module")
def rig_session(tmp_path_factory) -> Path:
    """A two-camera session whose right camera has a mask field of view (every fov form is reachable)."""
    folder = tmp_path_factory.mktemp("rig") / "s"
    mask = np.zeros((40, 80), np.uint8)
    mask[5:35, 10:70] = 255
    cv2.imwrite(str(folder.parent / "mask.png"), mask)
    right = CameraModel(80, 40, 61.0, 60.5, 40.25, 19.75, fov=FieldOfView.mask(folder.parent / "mask.png"))
    meta = SessionMeta(camera=LEFT, rig=Rig((LEFT, right), (np.eye(4), T_LEFT_RIGHT)), pose_source="camera_poses",
                       length_unit="mm")
    with SessionWriter(folder, meta) as w:
        for f in stereo_frames(3):
            w.add_frame(f)
            w.add_camera_pose(f.t_ns, np.eye(4))
    return folder


@st.composite
def _nested_mutation(draw, source):
    """``source`` (JSON) with one value anywhere in it replaced."""
    doc = json.loads(json.dumps(source))
    node = doc
    while True:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        key = draw(st.sampled_from(keys))
        if isinstance(node[key], (dict, list)) and node[key] and draw(st.booleans()):
            node = node[key]
            continue
        node[key] = draw(st.none() | st.booleans() | st.integers(-3, 3) | st.floats() | st.floats(-2.0, 2.0)
                         | st.text(max_size=6) | st.lists(st.integers(-1, 2), max_size=4)
                         | st.sampled_from(["left", "masks/right.png", "masks/../../x.png", "ellipse", 80, 40]))
        return doc


def _open_or_refuse(folder: Path) -> None:
    try:
        s = Session(folder)
        for i in range(len(s)):
            frame = s.frame(i)
            assert frame.n_cameras == len(s.rig)
            for k, cam in enumerate(s.rig.cameras):
                assert frame.image_of(k).shape[:2] == (cam.height, cam.width)
                assert cam.fov_mask(2.0).shape == (cam.height, cam.width)
    except SessionError as exc:
        assert "\n" not in str(exc) and str(folder) in str(exc), str(exc)


@FUZZ
@given(data=st.data())
def test_mutated_rig_metadata_is_read_or_refused_clearly(rig_session, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fuzz") / "s"
    shutil.copytree(rig_session, folder)
    doc = json.loads((folder / "session.json").read_text())
    (folder / "session.json").write_text(json.dumps(data.draw(_nested_mutation(doc))))
    _open_or_refuse(folder)


@FUZZ
@given(data=st.data())
def test_mutated_rig_frame_index_is_read_or_refused_clearly(rig_session, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fuzz") / "s"
    shutil.copytree(rig_session, folder)
    (folder / "frames.csv").write_bytes(data.draw(mutated((rig_session / "frames.csv").read_bytes())))
    _open_or_refuse(folder)
