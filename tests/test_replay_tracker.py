"""``replay://SESSION`` as a tracker: a marker-pose session's rows served as the NDI driver delivers them (every
tool's, metres, RMS, volume flag, the tracker's clock as recorded), paced by the grabber of the same session as
the replay robot is; alone (``devices --probe``) it plays by itself. ``lapreco run --marker replay://S --grabber
replay://S`` maps the tracked scope; a session without marker poses, or a grabber of another session, is one
line naming it."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
import pyvista as pv

from lapreco_hil.calib.files import write_handeye_yaml
from lapreco_hil.cli.main import main
from lapreco_hil.drivers.health import HealthState
from lapreco_hil.drivers.tracker.base import TrackerDriver
from lapreco_hil.errors import ConfigError, SessionError
from lapreco_hil.registry import DeviceContext, open_grabber, open_tracker
from lapreco_hil.sessions.session import Session

from test_marker_poses import T_MARKER_CAMERA, skull_session, tracked_copy  # noqa: F401


@pytest.fixture(scope="module")
def tracked(skull_session, tmp_path_factory):  # noqa: F811
    """The 24-frame skull session as a tracked scope (mm in the file): tools 'scope' and 'board', one scope row
    out of the volume and one with a 3 mm marker fit."""
    path = tmp_path_factory.mktemp("replay-tracker") / "tracked"
    path.mkdir()
    tracked_copy(skull_session, path, hand_eye=True)
    return path


def test_it_serves_every_row_as_recorded_paced_by_the_grabber_of_its_session(tracked):
    s = Session(tracked)
    context = DeviceContext(device="cpu")
    url = f"replay://{tracked}"
    grabber, tracker = open_grabber(url, context), open_tracker(url, context)
    assert isinstance(tracker, TrackerDriver) and tracker.clock_domain == "recorded"
    assert tracker.tools == ("scope", "board") and tracker.health.state is HealthState.DISCONNECTED
    got, states = [], set()
    with grabber, tracker:
        assert tracker.read(timeout_s=0.05) == []  # no frame handed on yet: nothing is due
        while (frame := grabber.read()) is not None:
            new = tracker.read()
            # what a live run would have in hand: up to one frame period after the frame, nothing later
            assert all(m.t_ns <= frame.t_ns + s.frame_period_ns for m in new)
            assert any(m.t_ns == frame.t_ns for m in new + got)
            got += new
            states.add(tracker.health.state)
        assert tracker.read(timeout_s=0.05) == []  # the end: nothing more, after the whole wait
    table = s.markers
    assert len(got) == len(table) == tracker.readings_delivered
    # every tool's row, in time order (each tool's as in the file), in metres, with its RMS and volume flag
    order = np.argsort(table.t_ns, kind="stable")
    assert [m.tool for m in got] == [table.tools[k] for k in order]
    assert [m.t_ns for m in got] == table.t_ns[order].tolist() and [m.seq for m in got] == list(range(len(got)))
    np.testing.assert_allclose(np.array([m.T_tracker_marker for m in got]), table.poses[order], atol=1e-12)
    assert [m.rms_mm for m in got] == table.rms_mm[order].tolist()
    assert [m.in_volume for m in got] == table.in_volume[order].tolist() and sum(not m.in_volume for m in got) == 1
    scope = next(m for m in got if m.tool == "scope")
    assert np.abs(scope.T_tracker_marker[:3, 3]).max() < 5.0  # metres (the file holds mm)
    # the out-of-volume row is a counted fault; the scope's next pose came in the same frame period
    assert tracker.faults["out_of_volume"] == 1 and tracker.faults["crc_errors"] == 0
    assert states == {HealthState.OK} and tracker.health.state is HealthState.DISCONNECTED  # closed


def test_health_is_degraded_while_a_tools_latest_pose_is_outside_the_volume(tracked, tmp_path):
    shutil.copytree(tracked, tmp_path / "s")
    table = tmp_path / "s" / "marker_poses.csv"
    lines = table.read_text().splitlines()
    last = max(i for i, line in enumerate(lines) if line.split(",")[1] == "scope")
    lines[last] = lines[last][:-1] + "0"  # in_volume, the last column
    table.write_text("\n".join(lines) + "\n")
    tracker = open_tracker(f"replay://{tmp_path / 's'}", DeviceContext())  # alone, afap: every row at once
    with tracker:
        assert len(tracker.read()) == len(lines) - 1
        health = tracker.health
        assert health.state is HealthState.DEGRADED and health.detail == "scope: out of volume"
        assert dict(tracker.faults) == {"out_of_volume": 2}


def test_alone_it_plays_by_itself_and_the_probe_shows_every_tool(tracked, capsys):
    tracker = open_tracker(f"replay://{tracked}?pace=realtime", DeviceContext())
    with tracker:
        first = tracker.read(timeout_s=0.05)
        assert {m.tool for m in first} == {"scope", "board"} and len({m.t_ns for m in first}) == 1  # recorded rate
    assert main(["devices", "--probe", f"replay://{tracked}", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    assert f"tracker replay://{tracked}: {len(Session(tracked).markers)} poses" in out
    lines = out.splitlines()
    scope = next(line.split() for line in lines if line.strip().startswith("scope "))
    assert scope[1] == "26" and 10.0 <= float(scope[2]) < 11.5 and scope[-1] == "1"  # 24 + 2 refusable at 10 fps
    assert any(line.strip().startswith("board ") for line in lines)
    assert "health: ok" in lines and "faults: out_of_volume 1" in lines


def test_a_session_without_marker_poses_or_with_another_sessions_grabber_is_one_line(skull_session,  # noqa: F811
                                                                                      tracked, tmp_path, capsys):
    joints = str(skull_session)
    with pytest.raises(SessionError, match="^" + re.escape(
            f"session '{joints}' has no marker poses to replay as a tracker: its pose source is joint readings "
            f"(pose_source 'joints'); open it as a robot (--robot replay://{joints})") + "$"):
        open_tracker(f"replay://{skull_session}", DeviceContext())
    write_handeye_yaml(tmp_path / "he.yaml", T_MARKER_CAMERA)
    assert main(["run", "--marker", f"replay://{skull_session}", "--grabber", f"replay://{skull_session}",
                 "--hand-eye", str(tmp_path / "he.yaml"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no marker poses" in err[0] and "pose_source 'joints'" in err[0], err
    assert not (tmp_path / "o").exists()
    context = DeviceContext()
    tracker = open_tracker(f"replay://{tracked}", context)
    open_grabber(f"replay://{skull_session}", context)
    with pytest.raises(ConfigError, match="plays with the grabber of its own session"):
        tracker.open()


@pytest.mark.slow
def test_run_marker_replay_maps_the_tracked_scope_close_to_the_truth(tracked, tmp_path, capsys):
    from lapreco_hil.evaluation.accuracy import surface_distances
    from lapreco_hil.evaluation.compare import read_tum
    from lapreco_hil.geometry import pose_error

    write_handeye_yaml(tmp_path / "he.yaml", T_MARKER_CAMERA)
    base = ["run", "--marker", f"replay://{tracked}", "--grabber", f"replay://{tracked}?pace=realtime",
            "--hand-eye", str(tmp_path / "he.yaml"), "--tracker", "opencv", "--device", "cpu", "--surface", "alpha",
            "--no-progress"]
    # two tools: a --tool must be one the session has; without one, the session's tracker.tool is the scope's
    assert main([*base, "--tool", "nope", "--out", str(tmp_path / "o2")]) == 2
    assert "has no tool 'nope'; its tools: scope, board" in capsys.readouterr().err

    out = tmp_path / "out"
    assert main([*base, "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    s = Session(tracked)
    assert report["tracker_tool"] == "scope" and report["marker"] == f"replay://{tracked}"
    assert report["frames"]["processed"] >= len(s) - 4 and report["inliers"] > 50, report["frames"]
    assert report["marker_samples_refused_by_cause"] == {"out_of_volume": 1, "rms_above_limit": 1}
    assert report["tracker_faults"] == {"out_of_volume": 1}
    # the session's tracker block places the tracker in the world (T_world_tracker), as a replay does: the map
    # and the report's accuracy are in the truth's frame
    assert not np.allclose(s.meta.tracker.T_world_tracker, np.eye(4))
    truth = s.ground_truth()
    points = np.asarray(pv.read(str(out / "points.ply")).points, float)
    d = surface_distances(points, truth.surface)
    assert np.median(d) < 2e-3 and np.percentile(d, 95) < 6e-3, (np.median(d), np.percentile(d, 95))
    assert report["accuracy"]["points_to_surface"]["median_mm"] < 2.0
    t_s, T = read_tum(out / "trajectory.tum")  # (seconds)
    errors = np.array([pose_error(Ti, truth.camera_pose(int(round(ti * 1e9)))) for ti, Ti in zip(t_s, T)])
    assert len(t_s) >= len(s) - 4 and errors[:, 0].max() < 1e-3 and np.degrees(errors[:, 1]).max() < 0.2
    # without --hand-eye the session's own T_marker_camera serves
    out2 = tmp_path / "out-session-hand-eye"
    assert main([*base[:5], *base[7:], "--out", str(out2)]) == 0, capsys.readouterr().err
    assert json.loads((out2 / "report.json").read_text())["inliers"] > 50



def test_a_live_run_from_a_recording_applies_its_declared_clock_offset_and_probes_it_by_its_pose_source(
        skull_session, tracked, tmp_path, capsys):  # noqa: F811
    """A recorded session's pose source keeps the clock offset its session.json declares when it is run live
    (``--robot/--marker replay://S``), as a replay applies it; a live device's is 0 until calibrated. ``devices
    --probe replay://S`` reads a joints session as a robot and a marker session as a tracker."""
    from lapreco_hil.app.run import _declared_offset_ns
    from lapreco_hil.registry import open_robot

    shifted = tmp_path / "shifted"
    shutil.copytree(skull_session, shifted)
    doc = json.loads((shifted / "session.json").read_text())
    doc["time_offset_ns"] = 12_345_678
    (shifted / "session.json").write_text(json.dumps(doc))
    context = DeviceContext()
    assert _declared_offset_ns(open_robot(f"replay://{shifted}", context)) == 12_345_678
    assert _declared_offset_ns(open_robot("sim://skull?width=64&height=48", DeviceContext())) == 0
    assert main(["devices", "--probe", f"replay://{shifted}", "--seconds", "0.2"]) == 0
    assert "no marker poses" not in capsys.readouterr().out
    assert main(["devices", "--probe", f"replay://{tracked}", "--seconds", "0.2"]) == 0
    assert "scope" in capsys.readouterr().out
