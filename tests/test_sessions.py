"""Sessions: record a simulated session, replay it (twice, identically), a hand-written two-view session,
and every kind of bad or cut-short session giving one clear error."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from lapreco_hil.cli.main import main
from lapreco_hil.app.replay import run_replay
from lapreco_hil.errors import SessionError
from lapreco_hil.geometry import make_T, pose_error, tum_values
from lapreco_hil.sessions import Session

SIM = ["--scene", "skull", "--resolution", "320x240", "--device", "cpu", "--no-progress"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, warp_cpu):
    """A 30-frame simulated session with ground truth, written by `lapreco sim-record`."""
    path = tmp_path_factory.mktemp("rec") / "skull"
    assert main(["sim-record", *SIM, "--frames", "30", "--out", str(path)]) == 0
    return path


def test_sim_record_writes_a_complete_session_with_truth(recorded):
    s = Session(recorded)
    assert s.meta.complete and s.meta.pose_source == "joints" and len(s) == 30
    assert s.meta.robot.urdf == "robot.urdf" and (recorded / "robot.urdf").is_file()
    assert np.all(np.diff(s.frame_t_ns) == 40_000_000)  # 25 fps capture times, not processing times
    # joint readings at the robot's rate (200 Hz), bracketing every frame
    t_joint = np.array([j.t_ns for j in s.joint_samples])
    assert len(t_joint) > 5 * len(s) and t_joint[0] <= s.frame_t_ns[0] and t_joint[-1] >= s.frame_t_ns[-1]
    truth = s.ground_truth()
    assert truth.surface.n_points > 1000
    # frames are lossless: re-reading a PNG gives back the bytes that were rendered
    image = s.frame(3).image
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8 and image.std() > 10


def test_replay_is_deterministic_and_reports_accuracy(recorded, tmp_path, warp_cpu):
    reports = [run_replay(str(recorded), str(tmp_path / f"r{i}"), tracker="opencv", device=warp_cpu,
                          progress=False, surface="alpha") for i in range(2)]
    for name in ("trajectory.tum", "points.ply", "mesh.ply"):
        assert (tmp_path / "r0" / name).read_bytes() == (tmp_path / "r1" / name).read_bytes(), name
    r = reports[0]
    assert r["frames"]["processed"] == 30 and r["inliers"] > 50
    acc = r["accuracy"]
    assert acc["points_to_surface"]["rms_mm"] < 3.0
    assert acc["camera_refined"]["position_rms_mm"] < acc["camera_raw_fk"]["position_rms_mm"]


@pytest.mark.parametrize("link", ["serial", "canopen"])
def test_record_through_real_driver_and_emulator_then_replay_twice(link, tmp_path, warp_cpu):
    session = tmp_path / "linked"
    assert main(["sim-record", *SIM, "--frames", "20", "--robot-link", link, "--sim-speed", "0.3",
                 "--out", str(session)]) == 0
    s = Session(session)
    assert len(s) == 20 and s.meta.source["robot_link"] == link
    t_joint = np.array([j.t_ns for j in s.joint_samples])
    assert np.all(np.diff(t_joint) > 0) and len(t_joint) > 3 * len(s)  # denser than the frames
    r = [run_replay(str(session), str(tmp_path / f"r{i}"), tracker="opencv", device=warp_cpu, progress=False,
                    surface="alpha")
         for i in range(2)]
    assert (tmp_path / "r0" / "trajectory.tum").read_bytes() == (tmp_path / "r1" / "trajectory.tum").read_bytes()
    assert r[0]["inliers"] == r[1]["inliers"] > 30
    assert r[0]["accuracy"]["camera_raw_fk"]["position_rms_mm"] < 1.0


def test_replay_with_the_warp_tracker_and_no_drift_check(recorded, tmp_path, warp_cpu):
    r = run_replay(str(recorded), str(tmp_path / "w"), tracker="warp", device=warp_cpu, drift_check=False,
                   progress=False, surface="alpha")
    assert r["tracker"] == "warp" and r["drift_check"] is False and r["inliers"] > 50


def write_stereo_session(folder: Path, warp_device: str, baseline_m: float = 0.006) -> tuple[np.ndarray, ...]:
    """Two frames and two given camera poses, written with json/csv/cv2 only, as docs/session-format.md
    tells another program to; the images are rendered by the simulated world at the two poses."""
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    world = SimWorld(SimSettings(scene="skull", width=320, height=240, device=warp_device))
    T0 = world.true_camera_pose(1_000_000_000)
    T1 = T0 @ make_T(np.eye(3), [baseline_m, 0.0, 0.0])
    (folder / "frames").mkdir(parents=True)
    frames, poses = ["seq,t_ns,file"], ["t_ns,tx,ty,tz,qx,qy,qz,qw"]
    for i, T in enumerate((T0, T1)):
        image, _ = world.renderer.render(T, seed=i)
        cv2.imwrite(str(folder / "frames" / f"view{i}.png"), image)
        frames.append(f"{i},{5000 + i},frames/view{i}.png")
        poses.append(f"{5000 + i}," + ",".join(f"{v:.12g}" for v in tum_values(T)))
    (folder / "frames.csv").write_text("\n".join(frames) + "\n")
    (folder / "camera_poses.csv").write_text("\n".join(poses) + "\n")
    cam = world.camera
    (folder / "session.json").write_text(json.dumps({
        "format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
        "camera": {"width": cam.width, "height": cam.height, "K": cam.K.tolist(), "dist": list(cam.dist)},
        "pose_source": "camera_poses",
        "camera_poses": {"sigma_rotation_rad": 0.0005, "sigma_translation_m": 0.0002}}))
    (folder / "truth").mkdir()
    world.surface_mesh().save(str(folder / "truth" / "surface.ply"))
    return T0, T1


def test_hand_written_two_view_session_reconstructs(tmp_path, warp_cpu):
    T0, T1 = write_stereo_session(tmp_path / "stereo", warp_cpu)
    r = run_replay(str(tmp_path / "stereo"), str(tmp_path / "out"), tracker="opencv", device=warp_cpu,
                   progress=False)
    # (the two frames are read as one frame of a rig of two: one keyframe and its partner view)
    assert r["pose_source"] == "camera_poses" and r["keyframes"] == 1 and r["partner_views"] == 1
    assert r["inliers"] >= 20
    assert r["accuracy"]["points_to_surface"]["median_mm"] < 1.5
    traj = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert traj.shape == (2, 8)
    pos_err = np.linalg.norm(traj[:, 1:4] - np.array([T0[:3, 3], T1[:3, 3]]), axis=1)
    assert np.all(pos_err < 0.002)


def test_session_in_millimetres_and_degrees_reads_as_si(recorded, tmp_path):
    s_m = Session(recorded)
    copy = tmp_path / "mm"
    shutil.copytree(recorded, copy)
    meta = json.loads((copy / "session.json").read_text())
    meta["units"] = {"length": "mm", "angle": "deg", "time": "ns"}
    meta["robot"]["T_world_base"] = [[1, 0, 0, 10.0], [0, 1, 0, -20.0], [0, 0, 1, 30.0], [0, 0, 0, 1]]
    T_tip_camera = np.array(meta["robot"]["T_tip_camera"], float)
    T_tip_camera[:3, 3] *= 1000.0
    meta["robot"]["T_tip_camera"] = T_tip_camera.tolist()  # units.length applies to every translation
    (copy / "session.json").write_text(json.dumps(meta))
    lines = (copy / "joints.csv").read_text().splitlines()
    scale = np.array([180 / np.pi, 180 / np.pi, 1000.0, 180 / np.pi])
    out = [lines[0]] + [",".join(c[:2] + [repr(float(v) * float(k)) for v, k in zip(c[2:], scale)])
                        for c in (ln.split(",") for ln in lines[1:])]
    (copy / "joints.csv").write_text("\n".join(out) + "\n")
    s_mm = Session(copy)
    q_m = np.array([j.q for j in s_m.joint_samples])
    q_mm = np.array([j.q for j in s_mm.joint_samples])
    np.testing.assert_allclose(q_mm, q_m, rtol=1e-7, atol=1e-12)
    # the robot's transforms too (they were once read as metres whatever the unit: a 1000x hand-eye)
    np.testing.assert_allclose(s_mm.meta.robot.T_tip_camera, s_m.meta.robot.T_tip_camera, atol=1e-12)
    np.testing.assert_allclose(s_mm.meta.robot.T_world_base[:3, 3], [0.010, -0.020, 0.030], atol=1e-12)
    # and written back in the session's unit
    from lapreco_hil.sessions.writer import SessionWriter

    with SessionWriter(tmp_path / "again", s_mm.meta, copy / "robot.urdf"):
        pass
    again = json.loads((tmp_path / "again" / "session.json").read_text())
    assert again["units"]["length"] == "mm" and again["robot"]["T_world_base"][0][3] == pytest.approx(10.0)
    np.testing.assert_allclose(np.array(again["robot"]["T_tip_camera"]), T_tip_camera, atol=1e-9)


# --- bad sessions: one clear error naming the file and the problem -------------------------------------------------

def _edit_json(folder: Path, **changes) -> None:
    meta = json.loads((folder / "session.json").read_text())
    meta.update(changes)
    (folder / "session.json").write_text(json.dumps(meta))


def _edit_line(folder: Path, name: str, lineno: int, new: str) -> None:
    lines = (folder / name).read_text().splitlines()
    lines[lineno - 1] = new
    (folder / name).write_text("\n".join(lines) + "\n")


BAD = {
    "unknown version": (lambda f: _edit_json(f, version=7), "session.json", "unknown session format version 7"),
    "wrong units": (lambda f: _edit_json(f, units={"length": "furlong", "angle": "rad", "time": "ns"}),
                    "session.json", "units.length' is 'furlong'"),
    "seconds": (lambda f: _edit_json(f, units={"length": "m", "angle": "rad", "time": "s"}),
                "session.json", "integer nanoseconds"),
    "no metadata": (lambda f: (f / "session.json").unlink(), "skull", "no session.json"),
    "bad json": (lambda f: (f / "session.json").write_text("{\"format\": "), "session.json", "not valid JSON"),
    "missing frame file": (lambda f: (f / "frames" / "000004.png").unlink(), "frames.csv",
                           "line 6: frame file 'frames/000004.png' is missing"),
    "backwards time": (lambda f: _edit_line(f, "frames.csv", 4, "2,1000000000,frames/000002.png"), "frames.csv",
                       "line 4: t_ns 1000000000 does not increase"),
    "text timestamp": (lambda f: _edit_line(f, "joints.csv", 3, "1,soon,0,0,0.1,0"), "joints.csv",
                       "line 3: column 't_ns' = 'soon' is not an integer"),
    "nan joint": (lambda f: _edit_line(f, "joints.csv", 5, "3,1015000000,nan,0,0.1,0"), "joints.csv",
                  "line 5: column 'yaw' = 'nan' is not a finite number"),
    "missing joint column": (lambda f: _edit_line(f, "joints.csv", 5, "3,1015000000,0,0.1,0"), "joints.csv",
                             "line 5: 5 columns, expected 6"),
    "corrupt image": (lambda f: (f / "frames" / "000000.png").write_bytes(b"\x89PNG garbage"), "000000.png",
                      "cannot decode"),
    "not rigid": (lambda f: _edit_json(f, robot={**json.loads((f / "session.json").read_text())["robot"],
                                                 "T_tip_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                  [0, 0, 0, 1]]}),
                  "session.json", "robot.T_tip_camera' is not a rigid transform"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_session_gives_one_clear_line(case, recorded, tmp_path, capsys):
    corrupt, file_part, message = BAD[case]
    folder = tmp_path / "skull"
    shutil.copytree(recorded, folder)
    corrupt(folder)
    status = main(["replay", str(folder), "--out", str(tmp_path / "out"), "--tracker", "opencv", "--device", "cpu",
                   "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert len(err.splitlines()) == 1 and err.startswith("lapreco: error: "), err
    assert file_part in err and message in err, err


def test_unfinished_last_rows_are_ignored(recorded, tmp_path):
    folder = tmp_path / "cut"
    shutil.copytree(recorded, folder)
    _edit_json(folder, complete=False)  # a recorder killed mid-row never closed the session
    with open(folder / "frames.csv", "a") as fh:
        fh.write("30,2200000000,frames/0000")  # a row cut short by a kill: no newline
    with open(folder / "joints.csv", "a") as fh:
        fh.write("999,2200000000,0.1,0.")
    s = Session(folder)
    assert len(s) == 30 and set(s.truncated) == {"frames.csv", "joints.csv"}
    # a session closed cleanly was not cut short: its last rows are read, and one that does not parse is an error
    _edit_json(folder, complete=True)
    with pytest.raises(SessionError, match="frames.csv: line 32: frame file 'frames/0000' is missing"):
        Session(folder)


def test_a_complete_sessions_last_joint_row_without_a_newline_is_read(recorded, tmp_path):
    folder = tmp_path / "unterminated"
    shutil.copytree(recorded, folder)
    n = len(Session(folder).joint_samples)
    last = (folder / "joints.csv").read_text().splitlines()[-1].split(",")
    with open(folder / "joints.csv", "a") as fh:
        fh.write(",".join([str(int(last[0]) + 1), str(int(last[1]) + 5_000_000), *last[2:]]))  # no newline
    s = Session(folder)
    assert len(s.joint_samples) == n + 1 and s.truncated == []
    with open(folder / "joints.csv", "a") as fh:
        fh.write("\n999,2200000000,0.1,0.")  # cut inside the row
    with pytest.raises(SessionError, match="joints.csv: line [0-9]+: 4 columns, expected 6 \\(the last line"):
        Session(folder)


@pytest.mark.parametrize("kill_after_rows", [3, 9, 17])
def test_kill_9_during_recording_leaves_a_replayable_session(kill_after_rows, tmp_path, warp_cpu):
    """A real recorder process killed with SIGKILL at several moments (after N rows, plus a random delay so
    the kill lands anywhere in the writer's cycle: encoding, renaming, appending): every frame it listed is
    complete."""
    delay_s = float(np.random.default_rng().uniform(0.0, 0.08))
    print(f"kill {delay_s * 1e3:.0f} ms after row {kill_after_rows}")  # shown if the test fails
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "lapreco_hil.cli.main", "sim-record", *SIM, "--frames", "400",
                             "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            csv = out / "frames.csv"
            if csv.is_file() and csv.read_text().count("\n") > kill_after_rows:
                break
            time.sleep(0.05)
        time.sleep(delay_s)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    s = Session(out)
    assert not s.meta.complete and len(s) >= kill_after_rows
    for i in range(len(s)):
        assert s.frame(i).image.shape == (240, 320, 3)  # every listed frame decodes
    assert s.joint_samples[-1].t_ns >= s.frame_t_ns[-1] - 40_000_000
    r = run_replay(str(out), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False)
    assert r["frames"]["processed"] == len(s) and r["session_complete"] is False


def test_existing_session_is_never_overwritten(recorded, tmp_path, capsys):
    status = main(["sim-record", *SIM, "--frames", "2", "--out", str(recorded)])
    assert status == 2 and "already exists and is not empty" in capsys.readouterr().err
    assert len(Session(recorded)) == 30


def test_replay_robot_refuses_a_pose_session(tmp_path, warp_cpu):
    from lapreco_hil.registry import DeviceContext, open_robot

    write_stereo_session(tmp_path / "stereo", warp_cpu)
    with pytest.raises(SessionError, match="carries camera poses, not joint readings"):
        open_robot(f"replay://{tmp_path / 'stereo'}", DeviceContext())


def test_given_pose_source_interpolates_on_se3():
    from lapreco_hil.geometry import rot_z
    from lapreco_hil.pose_sources import GivenPoseSource

    T0 = make_T(np.eye(3), [0, 0, 0])
    T1 = make_T(rot_z(0.2), [0.01, 0, 0])
    src = GivenPoseSource(np.array([100, 200]), np.array([T0, T1]), 0.001, 0.0005)
    mid = src.prior_at(150).T_world_camera
    assert pose_error(mid, make_T(rot_z(0.1), [0.005, 0, 0]))[0] < 1e-12
    assert pose_error(mid, make_T(rot_z(0.1), [0.005, 0, 0]))[1] < 1e-12
    assert np.array_equal(src.prior_at(100).T_world_camera, T0) and np.array_equal(src.prior_at(200).T_world_camera, T1)
    # outside the poses' span there is no pose: never the end pose held
    assert not src.has_pose(50) and not src.has_pose(900)
    assert src.prior_at(150).cov[0, 0] == pytest.approx(1e-6)


def test_frames_before_the_first_joint_reading_are_skipped_and_counted(recorded, tmp_path, warp_cpu):
    """Video that starts before the robot's stream (another recorder, a slow link): those frames cannot have a
    pose prior, so the replay skips and counts them and maps the rest, instead of failing."""
    session = tmp_path / "late-joints"
    shutil.copytree(recorded, session)
    s = Session(session)
    start = s.frame_t_ns[6]  # the first reading is the one taken at frame 6's capture time
    lines = (session / "joints.csv").read_text().splitlines(keepends=True)
    kept = [ln for ln in lines[1:] if int(ln.split(",")[1]) >= start]
    assert 0 < len(kept) < len(lines) - 1
    (session / "joints.csv").write_text(lines[0] + "".join(kept))
    r = run_replay(str(session), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False)
    assert int(lines[len(lines) - len(kept)].split(",")[1]) == start  # (the robot samples at frame times too)
    # frames 0-5 come before the first reading: no pose (never the first one held); frame 6 sits on it
    assert r["frames"]["without_pose"] == 6 and r["frames"]["processed"] == 24 and r["frames"]["dropped"] == 0
    assert r["frames"]["without_pose_by_cause"] == {"before_first": 6, "after_last": 0, "in_gap": 0}
    assert r["inliers"] > 50


@pytest.mark.parametrize("queue", [1, 8])
def test_real_time_replay_holds_queue_frames_for_a_late_reader(recorded, queue):
    """A real-time replay is a grabber: it plays at the recorded rate (25 fps here) and holds the newest
    ``queue`` frames. A reader 2.5 frame periods late loses frames with a one-frame queue and none with eight;
    a frame it still gets carries its capture time on this host's clock, so the time it waited counts."""
    from lapreco_hil.registry import DeviceContext, open_grabber

    grabber = open_grabber(f"replay://{recorded}?pace=realtime&queue={queue}", DeviceContext(device="cpu"))
    with grabber:
        first = grabber.read()
        time.sleep(0.1)
        read_at = time.monotonic_ns()
        second = grabber.read()
    period = grabber.session.frame_period_ns
    if queue == 1:
        assert second.seq > first.seq + 1  # gone before it was read
    else:
        assert second.seq == first.seq + 1
        assert second.host_ns - first.host_ns == second.t_ns - first.t_ns == period
        assert read_at - second.host_ns > 0.05e9  # it waited in the grabber's queue


def test_replay_queue_must_hold_a_frame(recorded):
    from lapreco_hil.errors import ConfigError
    from lapreco_hil.registry import DeviceContext, open_grabber

    with pytest.raises(ConfigError, match="queue must be at least 1 frame, got 0"):
        open_grabber(f"replay://{recorded}?pace=realtime&queue=0", DeviceContext(device="cpu"))
