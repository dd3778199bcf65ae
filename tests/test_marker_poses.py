"""A tracked scope as the pose source (pose_source "marker_poses"): a session written by hand from the simulated
world's true camera poses through a chosen hand-eye T_marker_camera and tracker placement T_world_tracker
replays with points and the true poses as priors; a calibration session needs --hand-eye; a bad row or field
is one line naming the file, line and column; ``lapreco record --marker`` with the NDI emulator on a pty (driven
by the simulated camera's true poses) writes marker_poses.csv and events.csv and replays; out-of-volume and
high-RMS samples are refused and counted; ``lapreco run`` takes exactly one of --robot / --marker."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.calib.files import write_handeye_yaml
from lapreco_hil.cli.main import main
from lapreco_hil.errors import ConfigError, SessionError
from lapreco_hil.geometry import inv_T, make_T, pose_error, tum_values
from lapreco_hil.pose_sources import MarkerPoseSource
from lapreco_hil.registry import DeviceContext, open_grabber, open_tracker
from lapreco_hil.sessions import format as fmt
from lapreco_hil.sessions.session import Session
from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

FAST = "reset_wait_ms=100&timeout_ms=300"
# the scope's marker sits 12 cm up the shaft from the lens, turned; the tracker stands 1.5 m from the world origin
T_MARKER_CAMERA = make_T(Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix(), [0.01, -0.02, 0.12])
T_WORLD_TRACKER = make_T(Rotation.from_euler("zyx", [0.5, 0.2, -2.8]).as_matrix(), [0.3, -0.1, 1.5])


def marker_pose(T_world_camera: np.ndarray, T_world_tracker=T_WORLD_TRACKER) -> np.ndarray:
    """T_tracker_marker that makes the camera pose T_world_camera (the composition the source undoes)."""
    return inv_T(T_world_tracker) @ T_world_camera @ inv_T(T_MARKER_CAMERA)


def pose_cells(T: np.ndarray, scale: float = 1.0) -> str:
    """tx,ty,tz,qx,qy,qz,qw with the translation in a unit of ``scale`` metres."""
    v = tum_values(T)
    v[:3] = [x / scale for x in v[:3]]
    return ",".join(f"{x:.12g}" for x in v)


def marker_row(t_ns: int, tool: str, T: np.ndarray, rms: float = 0.2, inside: int = 1, scale: float = 1.0) -> str:
    return f"{t_ns},{tool},{pose_cells(T, scale)},{rms},{inside}\n"


@pytest.fixture(scope="module")
def skull_session(tmp_path_factory, warp_cpu):
    """24 simulated frames at 10 fps (256x192) with ground truth: enough baseline for points (12 frames at 25 fps
    map none, whatever the pose source)."""
    from lapreco_hil.app.record import sim_record

    path = tmp_path_factory.mktemp("sessions") / "skull-24"
    sim_record("skull", str(path), frames=24, fps=10.0, resolution=(256, 192), device=warp_cpu, progress=False)
    return path


def tracked_copy(src, dst, *, hand_eye: bool, unit: str = "mm") -> None:
    """A marker_poses session from a recorded joints session: its frames, ground truth, and marker poses of the
    scope's tool ('scope') made from the true camera poses, a second tool's ('board') that must be ignored, and
    two scope samples the source must refuse (out of volume; a marker fit of 3 mm)."""
    shutil.copytree(src / "frames", dst / "frames")
    shutil.copytree(src / "truth", dst / "truth")
    shutil.copy(src / "frames.csv", dst / "frames.csv")
    doc = json.loads((src / "session.json").read_text())
    scale = fmt.LENGTH_UNITS[unit]
    doc.pop("robot")
    tracker = {"tool": "scope", "T_world_tracker": T_WORLD_TRACKER.tolist()}
    if hand_eye:
        tracker["T_marker_camera"] = T_MARKER_CAMERA.tolist()
    for T in tracker.values():
        if isinstance(T, list):
            for row in T[:3]:
                row[3] /= scale
    doc.update({"pose_source": "marker_poses", "tracker": tracker, "counts": {},
                "units": {**doc["units"], "length": unit}})
    (dst / "session.json").write_text(json.dumps(doc))
    t, T_true = fmt.read_pose_table(src / "truth" / "camera_poses.csv", 1.0)
    rows = []
    for i, (ti, Ti) in enumerate(zip(t, T_true)):
        rows.append(marker_row(int(ti), "scope", marker_pose(Ti), scale=scale))
        rows.append(marker_row(int(ti), "board", np.eye(4), scale=scale))
        if i == 3:  # between frames 3 and 4: refused, so it cannot bend the interpolation
            mid = (int(ti) + int(t[i + 1])) // 2
            rows.append(marker_row(mid, "scope", make_T(np.eye(3), [5.0, 0, 0]), inside=0, scale=scale))
            rows.append(marker_row(mid + 1, "scope", make_T(np.eye(3), [5.0, 0, 0]), rms=3.0, scale=scale))
    (dst / "marker_poses.csv").write_text(",".join(fmt.MARKER_COLUMNS) + "\n" + "".join(rows))
    if unit != "m":  # the ground truth in the session's unit too
        import pyvista as pv

        (dst / "truth" / "camera_poses.csv").write_text(",".join(fmt.POSE_COLUMNS) + "\n" + "".join(
            f"{int(ti)},{pose_cells(Ti, scale)}\n" for ti, Ti in zip(t, T_true)))
        pv.read(str(src / fmt.TRUTH_SURFACE_FILE)).scale(1 / scale).save(str(dst / fmt.TRUTH_SURFACE_FILE))


def test_a_hand_written_marker_session_gives_the_true_poses_and_replays_with_points(skull_session, tmp_path,
                                                                                  warp_cpu):
    from lapreco_hil.app.replay import run_replay

    session = tmp_path / "tracked"
    tracked_copy(skull_session, session, hand_eye=True)
    s = Session(session)
    assert s.meta.tracker.tool == "scope" and s.meta.tracker.T_marker_camera is not None
    np.testing.assert_allclose(s.meta.tracker.T_world_tracker, T_WORLD_TRACKER, atol=1e-9)  # mm in the file
    source = MarkerPoseSource(s.meta.tracker, table=s.markers)
    assert source.rejected_by_cause == {"out_of_volume": 1, "rms_above_limit": 1} and source.other_tools == len(s)
    truth = s.ground_truth().camera_pose
    for t in s.frame_t_ns:
        assert source.has_pose(int(t))
        dt, dr = pose_error(source.prior_at(int(t)).T_world_camera, truth(int(t)))
        assert dt < 1e-6 and dr < 1e-6
    report = run_replay(str(session), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False,
                        surface="alpha")
    assert report["pose_source"] == "marker_poses" and report["frames"]["processed"] == len(s)
    assert report["marker_samples_refused_by_cause"] == {"out_of_volume": 1, "rms_above_limit": 1}
    assert report["inliers"] > 50 and (tmp_path / "out" / "points.ply").is_file()
    assert report["accuracy"]["camera_raw_fk"]["position_rms_mm"] < 0.01
    assert report["accuracy"]["points_to_surface"]["median_mm"] < 5.0


def test_a_calibration_session_replays_only_with_a_hand_eye(skull_session, tmp_path, warp_cpu):
    from lapreco_hil.app.replay import run_replay

    session = tmp_path / "calib"
    tracked_copy(skull_session, session, hand_eye=False, unit="m")
    with pytest.raises(ConfigError, match=r"tool 'scope'\) has no hand-eye \(T_marker_camera.*--hand-eye"):
        run_replay(str(session), str(tmp_path / "none"), tracker="opencv", device=warp_cpu, progress=False)
    assert not (tmp_path / "none").exists()
    write_handeye_yaml(tmp_path / "handeye.yaml", T_MARKER_CAMERA, tip_frame="scope_marker")
    report = run_replay(str(session), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False,
                        surface="alpha", hand_eye_file=str(tmp_path / "handeye.yaml"))
    assert report["inliers"] > 50 and report["accuracy"]["camera_raw_fk"]["position_rms_mm"] < 0.01


GOOD = marker_row(1000, "scope", np.eye(4)).rstrip("\n").split(",")
BAD_ROWS = [
    ({9: "abc"}, "line 3: column 'rms_mm' = 'abc' is not a finite number"),
    ({10: "yes"}, "line 3: column 'in_volume' = 'yes' must be 1"),
    ({5: "0.9"}, "line 3: quaternion"),
    ({0: "1000"}, "line 3: t_ns 1000 of tool 'scope' does not increase (its previous row, line 2"),
    ({1: 'sco"pe'}, "line 3: column 'tool' = 'sco\"pe' is not a tool name"),
]


@pytest.mark.parametrize("change, message", BAD_ROWS, ids=[m.split(":")[1] for _, m in BAD_ROWS])
def test_a_bad_marker_row_is_one_line_naming_file_line_and_column(change, message, skull_session, tmp_path):
    session = tmp_path / "s"
    tracked_copy(skull_session, session, hand_eye=True)
    bad = list(GOOD)
    bad[0] = "2000"
    for k, v in change.items():
        bad[k] = v
    (session / "marker_poses.csv").write_text(",".join(fmt.MARKER_COLUMNS) + "\n" + ",".join(GOOD) + "\n"
                                              + ",".join(bad) + "\n")
    with pytest.raises(SessionError) as err:
        Session(session)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{session / 'marker_poses.csv'}: ") and message in text, text


def test_bad_tracker_fields_name_the_field(skull_session, tmp_path):
    session = tmp_path / "s"
    tracked_copy(skull_session, session, hand_eye=True)
    doc = json.loads((session / "session.json").read_text())
    for change, message in [(lambda tr: tr.pop("tool"), "field 'tracker.tool' is missing"),
                            (lambda tr: tr.update(sigma_translation_m=-1.0), "field 'tracker.sigma_translation_m' "
                                                                            "must be positive"),
                            (lambda tr: tr["T_marker_camera"][0].__setitem__(0, 2.0),
                             "field 'tracker.T_marker_camera' is not a rigid transform"),
                            (lambda tr: tr.update(tool="nobody"), "no row of the scope's tool 'nobody'")]:
        bad = json.loads(json.dumps(doc))
        change(bad["tracker"])
        (session / "session.json").write_text(json.dumps(bad))
        with pytest.raises(SessionError, match="^[^\n]*" + message.replace("(", r"\(").replace(")", r"\)")):
            Session(session)


def _board_calibration_session(tmp_path, warp_cpu, frames, resolution, T_tracker_boardmarker, late_ns=0):
    """The simulated ChArUco board scene as a tracked scope's calibration session (no hand-eye): the scope's
    marker poses from the true camera poses and the board marker's, both stamped ``late_ns`` late."""
    from lapreco_hil.app.record import sim_record

    src, cal = tmp_path / "src", tmp_path / "cal"
    sim_record("board", str(src), frames=frames, resolution=resolution, device=warp_cpu, progress=False)
    cal.mkdir()
    shutil.copytree(src / "frames", cal / "frames")
    shutil.copy(src / "frames.csv", cal / "frames.csv")
    doc = json.loads((src / "session.json").read_text())
    doc.pop("robot")
    doc.update(pose_source="marker_poses", tracker={"tool": "scope"}, counts={})
    (cal / "session.json").write_text(json.dumps(doc))
    t, T_true = fmt.read_pose_table(src / "truth" / "camera_poses.csv", 1.0)
    (cal / "marker_poses.csv").write_text(",".join(fmt.MARKER_COLUMNS) + "\n" + "".join(
        marker_row(int(ti) + late_ns, "scope", marker_pose(Ti))
        + marker_row(int(ti) + late_ns, "board", T_tracker_boardmarker) for ti, Ti in zip(t, T_true)))
    return cal


def test_calibrate_handeye_tracked_reads_a_calibration_session(tmp_path, warp_cpu, capsys):
    """The next step after ``lapreco record --marker`` without a hand-eye: the simulated ChArUco board scene, the
    scope's and the board marker's poses made from the true camera and board poses; the hand-eye comes back."""
    from lapreco_hil.calib.files import read_handeye_yaml
    from lapreco_hil.calib.handeye import pose_difference
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    world = SimWorld(SimSettings(scene="board", width=480, height=360, device=warp_cpu))
    T_world_pattern = world.T_world_scene @ world.scene.board[1]
    T_boardmarker_pattern = make_T(Rotation.from_euler("x", 0.4).as_matrix(), [0.05, 0.0, -0.01])
    T_tracker_boardmarker = inv_T(T_WORLD_TRACKER) @ T_world_pattern @ inv_T(T_boardmarker_pattern)
    cal = _board_calibration_session(tmp_path, warp_cpu, 60, (480, 360), T_tracker_boardmarker)
    board = "charuco:10x7:0.004:0.003:DICT_5X5_100"
    assert main(["calibrate", "handeye-tracked", "--session", str(cal), "--board-tool", "board", "--board", board,
                 "--stride", "3", "--out", str(tmp_path / "handeye.yaml")]) == 0
    rot_deg, trans_mm = pose_difference(read_handeye_yaml(tmp_path / "handeye.yaml")["T_tip_camera"],
                                        T_MARKER_CAMERA)
    # 2.4 s of the scan (under 10 deg of rotation between views): measured 0.37 deg / 0.71 mm
    assert rot_deg < 1.0 and trans_mm < 2.0, (rot_deg, trans_mm)
    capsys.readouterr()
    assert main(["calibrate", "handeye-tracked", "--session", str(cal), "--board-tool", "scope", "--board", board,
                 "--out", str(tmp_path / "x.yaml")]) == 2
    assert "--board-tool 'scope' is the scope's tool" in capsys.readouterr().err
    # too few views at a coarse stride: the error says which stride it used and what to try
    assert main(["calibrate", "handeye-tracked", "--session", str(cal), "--board-tool", "board", "--board", board,
                 "--stride", "30", "--out", str(tmp_path / "x.yaml")]) == 2
    assert "at least 3 are needed; --stride 30 took every 30th frame of the session: try --stride 1" \
        in capsys.readouterr().err


def keep_the_runs_grabber(monkeypatch, holder: dict) -> None:
    """``lapreco run``'s grabber put in ``holder["grabber"]`` when opened, and ``holder["open"]`` set once it is
    open: an emulated tracker that follows the simulated world reads the true poses through it."""
    from lapreco_hil.app import run as app_run

    real_open_grabber = app_run.open_grabber

    def keep(url, context):
        grabber = holder["grabber"] = real_open_grabber(url, context)
        real_open = grabber.open

        def open_and_say_so():
            real_open()
            holder["open"] = True

        grabber.open = open_and_say_so
        return grabber

    monkeypatch.setattr(app_run, "open_grabber", keep)


def test_frames_a_tracked_calibration_leaves_out_are_counted_with_their_cause(tmp_path, warp_cpu, caplog):
    """A tracker clock 40 ms late that session.json does not declare leaves the first frames without a pose of
    the scope before them: they were left out of the calibration without a word."""
    import logging

    from lapreco_hil.app.handeye_tracked import tracked_views_from_session
    from lapreco_hil.calib.boards import parse_board

    cal = _board_calibration_session(tmp_path, warp_cpu, 12, (320, 240), np.eye(4), late_ns=40_000_000)
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.app.handeye_tracked"):
        views, _ = tracked_views_from_session(str(cal), parse_board("charuco:10x7:0.004:0.003:DICT_5X5_100"),
                                              "board", stride=1)
    (line,) = [r.getMessage() for r in caplog.records]
    assert f"{12 - len(views)} of 12 frames used left out" in line and "tool 'scope'" in line
    assert "time_offset_ns" in line and len(views) < 12


# --- live: the NDI emulator on a pty ---------------------------------------------------------------------------

def test_record_with_the_ndi_emulator_follows_the_true_camera_and_replays(tmp_path, warp_cpu):
    """The emulator reports the marker pose that puts the simulated camera at its true pose; the recorded session
    holds every tool's rows and the tracker's faults (a second tool out of the volume) in events.csv, and its
    replay with the hand-eye gets priors within the tracker's latency of the truth and maps points."""
    from lapreco_hil.app.replay import run_replay
    from lapreco_hil.sessions.recorder import record_tracked

    ctx = DeviceContext(device=warp_cpu)
    # 40 frames: the grabber plays on the host clock from when it opens, and the tracker's bring-up after it took
    # 14 of 20 frames once on a slow run of the suite
    grabber = open_grabber("sim://skull?width=320&height=240&fps=10&frames=40", ctx)
    truth = grabber.ground_truth.camera_pose

    def scope_mm(t_ns: int):  # the emulator's frame time is on the host clock, as the grabber's once it is open
        T = marker_pose(truth(t_ns)).copy()
        T[:3, 3] *= 1e3
        return T, True

    state = {"n": 0}

    def board(t_ns: int):
        state["n"] += 1
        return make_T(np.eye(3), [100.0, 0, -1500.0]), state["n"] % 4 != 0  # every 4th pose out of the volume

    with NDITrackerEmulator(wired=[scope_mm, board], frame_rate_hz=60) as emu:
        tracker = open_tracker(f"ndi://{emu.port}?rate=60&{FAST}", ctx)
        with grabber, tracker:
            setup = fmt.TrackerSetup("handle 0A", None, T_WORLD_TRACKER)
            stats = record_tracked(grabber, tracker, str(tmp_path / "rec"), setup, progress=False)
    s = Session(tmp_path / "rec")
    assert s.meta.pose_source == "marker_poses" and s.meta.tracker.T_marker_camera is None  # a calibration session
    assert stats.frames == len(s) >= 8 and stats.scope_samples >= 2 * len(s)
    assert set(s.markers.tools) == {"handle 0A", "handle 0B"} and not s.markers.in_volume.all()
    events = (tmp_path / "rec" / fmt.EVENTS_FILE).read_text()
    assert "tracker ndi://" in events and "fault:out_of_volume" in events
    assert s.meta.health["tracker_faults"]["out_of_volume"] >= 1
    write_handeye_yaml(tmp_path / "handeye.yaml", T_MARKER_CAMERA)
    report = run_replay(str(tmp_path / "rec"), str(tmp_path / "out"), tracker="opencv", device=warp_cpu,
                        progress=False, surface="alpha", hand_eye_file=str(tmp_path / "handeye.yaml"))
    assert report["frames"]["processed"] >= len(s) - 2 and report["inliers"] > 30
    # the poses are stamped when the reply arrives, a frame period (16 ms) or so after they were measured
    assert report["accuracy"]["camera_raw_fk"]["position_rms_mm"] < 1.0


@pytest.fixture
def wired():
    """An Aurora-like emulator: the scope's sensor (handle 0A) moving, out of the volume when asked (``outside``,
    or for the measurements numbered in ``outside_range``)."""
    state = {"outside": False, "outside_range": range(0), "n": 0}

    def scope(t_ns: int):
        s = t_ns * 1e-9
        T = make_T(Rotation.from_euler("z", 0.7 * s).as_matrix(), [30.0 * np.sin(s), 0.0, -1200.0])
        state["n"] += 1
        return T, not state["outside"] and state["n"] not in state["outside_range"]

    emu = NDITrackerEmulator(wired=[scope], frame_rate_hz=60)
    yield emu, state
    emu.close()


def wait_until(predicate, timeout_s: float = 3.0) -> None:
    import time

    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout_s, "condition not reached in time"
        time.sleep(0.01)


def test_out_of_volume_samples_are_refused_and_counted_and_degrade_health(wired):
    import time

    from lapreco_hil.drivers.health import HealthState

    emu, state = wired
    with open_tracker(f"ndi://{emu.port}?rate=60&{FAST}", DeviceContext()) as tracker:
        source = MarkerPoseSource(fmt.TrackerSetup("handle 0A", np.eye(4)), tracker=tracker)
        wait_until(lambda: source.poll() and len(source.track) >= 3)
        t = source.track.last_time_ns - 1
        assert source.has_pose(t) and source.rejected == 0
        state["outside"] = True
        wait_until(lambda: source.poll() is not None and source.rejected_by_cause.get("out_of_volume", 0) >= 3)
        health = source.health
        before = len(source.track)
        time.sleep(0.1)
        source.poll()
        assert len(source.track) == before  # nothing accepted while outside
        assert not source.has_pose(time.monotonic_ns())  # after the last accepted pose: none, after a short wait
    assert health.state is HealthState.DEGRADED and "outside the tracker's characterised volume" in health.detail
    assert source.without_pose.as_dict()["after_last"] == 1 and source.last_refusal


def test_high_rms_samples_are_refused_and_counted(wired):
    emu, _ = wired
    with open_tracker(f"ndi://{emu.port}?rate=60&{FAST}", DeviceContext()) as tracker:
        # the emulator reports a fit RMS of 0.2 mm for handle 0A: above a 0.15 mm limit, below the default 1 mm
        strict = MarkerPoseSource(fmt.TrackerSetup("handle 0A", np.eye(4), max_rms_mm=0.15), tracker=tracker)
        wait_until(lambda: strict.poll() is not None and strict.rejected >= 5)
    assert strict.rejected_by_cause == {"rms_above_limit": strict.rejected} and len(strict.track) == 0
    assert "RMS 0.2 mm above the limit 0.15 mm" in strict.last_refusal
    lenient = MarkerPoseSource(fmt.TrackerSetup("handle 0A", np.eye(4)), table=fmt.MarkerTable(
        np.array([1, 2]), ("handle 0A",) * 2, np.stack([np.eye(4)] * 2), np.array([0.2, 0.2]), np.array([True] * 2)))
    assert lenient.rejected == 0 and len(lenient.track) == 2


def test_a_long_marker_table_keeps_its_first_poses():
    """A session's table is held whole (a live track drops its oldest half past a capacity; a table must not:
    ten minutes at 60 Hz are 36000 samples, and the first frames need the first ones)."""
    n = 20_000
    t = np.arange(n, dtype=np.int64) * 16_666_667
    poses = np.stack([make_T(np.eye(3), [i * 1e-5, 0.0, 0.0]) for i in range(n)])
    table = fmt.MarkerTable(t, ("s",) * n, poses, np.full(n, 0.2), np.ones(n, bool))
    source = MarkerPoseSource(fmt.TrackerSetup("s", np.eye(4)), table=table)
    assert source.has_pose(int(t[1]) + 5) and source.has_pose(int(t[-2]))
    np.testing.assert_allclose(source.prior_at(int(t[1])).T_world_camera[0, 3], 1e-5)


def test_a_scope_tool_the_tracker_lacks_or_no_pose_of_it_is_a_clear_error(wired, tmp_path, warp_cpu, capsys):
    emu, state = wired
    # 2 s of frames: the simulated grabber plays on the host clock from when it opens, and a tracker whose replies
    # are missing takes its timeouts to come up (4 frames were over before the recording began, once in three runs)
    grabber_url = "sim://skull?width=320&height=240&fps=15&frames=30"
    assert main(["record", "--marker", f"ndi://{emu.port}?{FAST}", "--grabber", grabber_url, "--tool", "nope",
                 "--out", str(tmp_path / "a"), "--device", warp_cpu, "--no-progress"]) == 2
    state["outside"] = False
    emu.faults.missing = True
    assert main(["record", "--marker", f"ndi://{emu.port}?{FAST}", "--grabber", grabber_url,
                 "--out", str(tmp_path / "b"), "--device", warp_cpu, "--no-progress"]) == 2
    assert fmt.read_meta(tmp_path / "b").complete  # the frames are kept
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "has no tool 'nope'; its tools: handle 0A" in err[0], err
    assert "delivered no pose of the scope's tool 'handle 0A' during" in err[1] and "missing" in err[1], err


def test_lapreco_record_marker_writes_marker_poses_and_events_and_says_what_next(wired, tmp_path, warp_cpu, capsys):
    emu, state = wired
    state["outside_range"] = range(10, 20)  # out of the volume a while: recorded with the flag, counted in events
    assert main(["record", "--marker", f"ndi://{emu.port}?rate=60&{FAST}", "--grabber",
                 "sim://skull?width=320&height=240&fps=10&frames=20", "--out", str(tmp_path / "rec"), "--device",
                 warp_cpu, "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "marker poses" in out and "is a calibration session" in out and "--hand-eye handeye.yaml" in out
    assert f"lapreco calibrate handeye-tracked --session {tmp_path / 'rec'} --board-tool TOOL" in out
    s = Session(tmp_path / "rec")
    rows = (tmp_path / "rec" / fmt.MARKER_POSES_FILE).read_text().splitlines()
    assert rows[0] == ",".join(fmt.MARKER_COLUMNS) and len(rows) - 1 == len(s.markers) >= 2 * len(s)
    assert set(s.markers.tools) == {"handle 0A"} and s.markers.in_volume.any() and not s.markers.in_volume.all()
    assert np.allclose(s.markers.poses[:, 2, 3], -1.2)  # the emulator's -1200 mm, in metres
    assert "fault:out_of_volume" in (tmp_path / "rec" / fmt.EVENTS_FILE).read_text()
    assert s.meta.counts["marker_poses"] == len(s.markers)


# --- run ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, message", [
    ([], "give exactly one pose source: --robot URL (a robot holding the scope) or --marker URL"),
    (["--robot", "sim://skull", "--marker", "ndi:///dev/ttyNDI-nope"], "not both"),
    (["--marker", "ndi:///dev/ttyNDI-nope"], "the scope's hand-eye is missing (T_marker_camera): pass --hand-eye"),
])
def test_run_needs_exactly_one_pose_source_and_a_hand_eye_for_a_marker(argv, message, tmp_path, capsys):
    assert main(["run", *argv, "--grabber", "sim://skull", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "o").exists()


def test_run_with_a_marker_maps_the_tracked_scope_live(tmp_path, warp_cpu, monkeypatch):
    import lapreco_hil.app.run as app_run

    # 80 frames: the tracker's stream and the grabber start on their own clocks, and the first frames may come
    # before the first marker pose (a 20-frame run mapped 7 once in a full test run on 2 cores); the simulated
    # grabber plays on the host clock from when it opens, and on 2026-12-07 a 30-frame run saw only its last 3-7
    # frames (frames 'in': the run's start took most of its 3 s), at the session's first commit too
    ctx_frames = "sim://skull?width=320&height=240&fps=10&frames=80"
    write_handeye_yaml(tmp_path / "handeye.yaml", T_MARKER_CAMERA)
    holder = {}

    def scope_mm(t_ns: int):
        if not holder.get("open"):  # the grabber lays simulated time on the host clock when it opens
            return None
        T = marker_pose(holder["grabber"].ground_truth.camera_pose(t_ns), np.eye(4))
        T[:3, 3] *= 1e3
        return T, True

    keep_the_runs_grabber(monkeypatch, holder)  # the test's emulator needs the run's grabber for the true poses
    with NDITrackerEmulator(wired=[scope_mm], frame_rate_hz=60) as emu:
        report = app_run.run(None, ctx_frames, str(tmp_path / "out"), marker_url=f"ndi://{emu.port}?rate=60&{FAST}",
                             hand_eye_file=str(tmp_path / "handeye.yaml"), tracker="opencv", device=warp_cpu,
                             progress=False, record=str(tmp_path / "rec"))
    assert report["marker"].startswith("ndi://") and report["tracker_tool"] == "handle 0A"
    assert report["frames"]["processed"] >= 8 and report["inliers"] > 20
    # every frame the source made is accounted for, those before capture began included (but for the last few:
    # the simulated camera ends at its 80th frame's time, and frames a late reader missed then are not seen)
    f = report["frames"]
    assert 75 <= f["passed_before_start"] + f["in"] + f["dropped_source"] <= 80, f
    assert report["accuracy"]["camera_raw_fk"]["position_rms_mm"] < 1.0
    rec = Session(tmp_path / "rec")
    assert rec.meta.pose_source == "marker_poses" and len(rec.markers) >= len(rec)
    np.testing.assert_allclose(rec.meta.tracker.T_marker_camera, T_MARKER_CAMERA, atol=1e-9)
