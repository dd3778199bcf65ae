"""Recording when a pose source fails, and what a recording holds (an outside review of `record` and `run --record`):

- a robot lost partway (its emulator stops answering) keeps the session on disk and readable, the summary says
  how many frames come after its last reading, and `lapreco record` / `lapreco run` end with one error line that
  names the device, what happened, what to do and where the data is; a gap it recovers from is reported, not an
  error;
- `lapreco run --record` writes what `lapreco record` writes (events.csv, session.json's source and health), through
  the same recorder;
- a simulated camera beside a real robot records no ground truth (it shows the simulator's scope, not where the
  robot holds it), with one warning that says why; a robot in the grabber's world (sim://, link=serial) keeps it.

The robot is the simulated one read through the real Dynamixel driver and its emulator on a pty
(``sim://...&link=serial``); the emulator falls silent (``faults.silent``, a cut data line) when the world's clock
reaches a chosen time, so the frames after it are the ones without readings whatever the machine's load."""

from __future__ import annotations

import csv
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lapreco_hil.cli.main import main
from lapreco_hil.sessions import Session

FPS = 20
URL = f"sim://skull?width=160&height=120&fps={FPS}&speed=1"  # the world's clock flows at real time
T0_S = 1.0  # the simulated world's first frame time (simulators/world/world.py: T0_NS)
SILENT_AFTER_S = 0.8  # the robot's emulator stops answering this long after the first frame


class SilenceRobot:
    """Keeps the robot the command opens (patched over ``module.open_robot``) and silences its emulator once the
    world's clock reaches ``T0_S + at_s``; for ``for_s`` seconds (a gap) or for good (None: the robot is lost)."""

    def __init__(self, monkeypatch, module, at_s: float = SILENT_AFTER_S, for_s: float | None = None) -> None:
        self.robot, self.at_s, self.for_s, self.silenced_at_ns = None, at_s, for_s, None
        real = module.open_robot

        def keep(url, context):
            self.robot = real(url, context)
            threading.Thread(target=self._inject, daemon=True).start()
            return self.robot

        monkeypatch.setattr(module, "open_robot", keep)

    def _inject(self) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and self.robot.emulator is None:  # (made when the robot opens)
            time.sleep(0.005)
        world, emulator = self.robot.world, self.robot.emulator
        while time.monotonic() < deadline and world.now_ns() < (T0_S + self.at_s) * 1e9:
            time.sleep(0.002)
        emulator.faults.silent = True
        self.silenced_at_ns = world.now_ns()
        if self.for_s is not None:
            while world.now_ns() < self.silenced_at_ns + self.for_s * 1e9:
                time.sleep(0.002)
            emulator.faults.silent = False


def _events(folder: Path) -> list[dict]:
    with open(folder / "events.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("lapreco: error:")]
    assert len(err) == 1, err
    return err[0]


def test_record_with_the_robot_lost_keeps_the_session_and_fails_naming_the_robot(tmp_path, monkeypatch, capsys,
                                                                                 caplog, warp_cpu):
    import lapreco_hil.app.record as app_record

    out = tmp_path / "rec"
    SilenceRobot(monkeypatch, app_record)
    robot_url = URL + "&link=serial"
    with caplog.at_level(logging.WARNING):
        rc = main(["record", "--robot", robot_url, "--grabber", URL + "&frames=40", "--out", str(out), "--device",
                   warp_cpu, "--no-progress"])
    assert rc == 2
    err = _error_line(capsys)
    assert f"record: robot '{robot_url}' stopped delivering readings" in err
    assert "check its cable and power" in err and f"the recording is kept at {out}" in err
    # the summary: how many frames come after the robot's last reading, and when that was
    (summary,) = [m for m in caplog.messages if "come after its last reading" in m]
    assert summary.startswith(f"record: robot {robot_url}: ") and "of 40 frames" in summary and "lost" in summary
    # nothing recorded is lost: the session is closed, complete and readable
    s = Session(out)
    assert s.meta.complete and len(s) == 40 and len(s.joint_samples) > 20
    coverage = s.meta.health["pose_coverage"]
    assert coverage["lost"] and coverage["after_last"] >= 10, coverage
    assert abs(coverage["last_reading_s"] - SILENT_AFTER_S) < 0.2, coverage
    assert any(e["device"] == f"robot {robot_url}" for e in _events(out))
    assert s.ground_truth() is not None  # (the robot moves the grabber's world: its truth belongs)


def test_record_reports_a_gap_the_robot_recovers_from_and_succeeds(tmp_path, monkeypatch, capsys, caplog, warp_cpu):
    import lapreco_hil.app.record as app_record

    out = tmp_path / "rec"
    SilenceRobot(monkeypatch, app_record, for_s=0.5)
    with caplog.at_level(logging.WARNING):
        rc = main(["record", "--robot", URL + "&link=serial", "--grabber", URL + "&frames=40", "--out", str(out),
                   "--device", warp_cpu, "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    (summary,) = [m for m in caplog.messages if "gap" in m and "after which its readings resumed" in m]
    assert "come after its last reading" not in summary
    coverage = Session(out).meta.health["pose_coverage"]
    assert not coverage["lost"] and coverage["after_last"] == 0 and coverage["in_gap"] >= 6, coverage
    assert coverage["longest_gap_s"] >= 0.4, coverage


@pytest.mark.slow
def test_run_with_the_robot_lost_writes_its_outputs_and_recording_and_fails_naming_the_robot(
        tmp_path, monkeypatch, capsys, warp_cpu):
    import lapreco_hil.app.run as app_run

    out, rec = tmp_path / "out", tmp_path / "rec"
    SilenceRobot(monkeypatch, app_run)
    robot_url = URL + "&link=serial"
    rc = main(["run", "--robot", robot_url, "--grabber", URL + "&frames=40", "--out", str(out), "--record", str(rec),
               "--device", warp_cpu, "--tracker", "opencv", "--surface", "alpha", "--no-progress"])
    stdout = capsys.readouterr().out
    assert rc == 2
    # (the summary first, then the error line)
    (summary,) = [line for line in stdout.splitlines() if "come after its last reading" in line]
    assert summary.startswith(f"lapreco run: robot {robot_url}: ") and "of 40 frames" in summary
    report = json.loads((out / "report.json").read_text())
    assert report["pose_coverage"]["lost"] and report["pose_coverage"]["after_last"] >= 10
    s = Session(rec)
    assert s.meta.complete and len(s) >= 30 and s.meta.health["pose_coverage"]["lost"]
    assert any(e["device"] == f"robot {robot_url}" for e in _events(rec))


def test_run_error_line_names_the_robot_and_what_to_do(tmp_path, monkeypatch, capsys, warp_cpu):
    """(The error line of the lost run above, from the same code path without the pipeline's cost: the outputs
    and the recording are named.)"""
    from lapreco_hil.sessions.recorder import DeviceLostError, PoseCoverage, check_pose_coverage

    coverage = PoseCoverage("robot", "serial:///dev/ttyUSB0?ids=1,2,3,4", 101, after_last=67,
                            first_frame_ns=0, last_frame_ns=4_000_000_000, first_reading_ns=0,
                            last_reading_ns=1_320_000_000, gap_limit_ns=30e6, silent_received_s=2.68,
                            late_received_s=0.0, after_received=67)
    with pytest.raises(DeviceLostError) as exc:
        check_pose_coverage("run", coverage, "the outputs are in OUT and the recording is kept at REC",
                            problem="stale: no reading for 2.7 s", warn=False)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("run: robot 'serial:///dev/ttyUSB0?ids=1,2,3,4' stopped delivering")
    assert "none received in the last 2.68 s of the capture" in msg
    assert "67 of 101 frames come after it" in msg and "1.32 s after the first frame" in msg
    assert "check its cable and power" in msg and msg.endswith("the recording is kept at REC")
    # a short silence at the very end (a late reply or two) is not a lost robot
    assert not PoseCoverage("robot", "x", 101, after_last=2, first_frame_ns=0, last_frame_ns=4_000_000_000,
                            last_reading_ns=3_900_000_000, gap_limit_ns=30e6, silent_received_s=0.1).lost
    # nor are readings whose stamps end early but that were received to the end (a clock offset not declared), or
    # whose receipts are not known: the stamps alone never fail a command
    offset = PoseCoverage("robot", "x", 101, after_last=67, first_frame_ns=0, last_frame_ns=4_000_000_000,
                          last_reading_ns=1_320_000_000, gap_limit_ns=30e6, silent_received_s=0.0)
    assert not offset.lost and "calibrate time-offset" in offset.summary()
    assert not PoseCoverage("robot", "x", 101, after_last=67, first_frame_ns=0, last_frame_ns=4_000_000_000,
                            last_reading_ns=1_320_000_000, gap_limit_ns=30e6).lost


@pytest.mark.slow
def test_run_record_writes_what_record_writes(tmp_path, monkeypatch, capsys, warp_cpu):
    """The same devices and the same fault (a gap the robot recovers from: each command exits 0 and says so), once
    through `lapreco record` and once through `lapreco run --record`: the two sessions hold the same files and the
    same metadata fields (source, health with the pose coverage, events.csv)."""
    import lapreco_hil.app.record as app_record
    import lapreco_hil.app.run as app_run

    robot_url, grabber_url = URL + "&link=serial", URL + "&frames=40"
    SilenceRobot(monkeypatch, app_record, for_s=0.5)
    assert main(["record", "--robot", robot_url, "--grabber", grabber_url, "--out", str(tmp_path / "recorded"),
                 "--device", warp_cpu, "--no-progress"]) == 0
    SilenceRobot(monkeypatch, app_run, for_s=0.5)
    capsys.readouterr()
    assert main(["run", "--robot", robot_url, "--grabber", grabber_url, "--out", str(tmp_path / "out"),
                 "--record", str(tmp_path / "run-recorded"), "--device", warp_cpu, "--tracker", "opencv",
                 "--surface", "alpha", "--no-progress"]) == 0
    stdout = capsys.readouterr().out
    assert any("after which its readings resumed" in line for line in stdout.splitlines()), stdout

    a, b = tmp_path / "recorded", tmp_path / "run-recorded"

    def entries(folder: Path) -> set[str]:
        return {p.name for p in folder.iterdir()} | {f"truth/{p.name}" for p in (folder / "truth").iterdir()}

    assert entries(a) == entries(b) and "events.csv" in entries(a) and "truth/camera_poses.csv" in entries(a)
    ma, mb = (json.loads((f / "session.json").read_text()) for f in (a, b))
    assert set(ma) == set(mb)
    assert ma["source"] == mb["source"] == {"robot": robot_url, "grabber": grabber_url}
    assert set(ma["health"]) == set(mb["health"]) and "pose_coverage" in mb["health"]
    assert set(ma["counts"]) == set(mb["counts"]) and mb["counts"]["events"] > 0
    assert mb["health"]["pose_coverage"]["in_gap"] > 0 and not mb["health"]["pose_coverage"]["lost"]
    for folder in (a, b):
        assert any(e["device"] == f"robot {robot_url}" and e["event"].startswith(("health:", "fault:"))
                   for e in _events(folder))


def test_a_simulated_camera_beside_a_real_robot_records_no_ground_truth(tmp_path, capsys, caplog, warp_cpu):
    """The robot: a Dynamixel chain on a pty whose joints are not the simulated world's."""
    from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map
    from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

    out = tmp_path / "rec"
    grabber_url = "sim://skull?width=160&height=120&fps=10&frames=8"
    with DynamixelChainEmulator([1, 2, 3, 4], dynamixel_joint_map("ecm"),
                                lambda t_ns: np.array([0.1, -0.2, 0.12, 0.3])) as emu, \
            caplog.at_level(logging.WARNING):
        robot_url = f"serial://{emu.port}?ids=1,2,3,4&rate=100"
        rc = main(["record", "--robot", robot_url, "--grabber", grabber_url, "--robot-model", "ecm", "--tip-frame",
                   "ecm_tip", "--out", str(out), "--device", warp_cpu, "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    s = Session(out)  # (a simulated camera beside a real robot plays in real time: the first frame may pass)
    assert len(s) >= 6 and len(s.joint_samples) > 0
    assert s.ground_truth() is None and not (out / "truth").exists()
    (warning,) = [m for m in caplog.messages if "ground truth" in m]
    assert f"grabber '{grabber_url}'" in warning and f"robot '{robot_url}'" in warning
    assert "left out" in warning and "meaningless" in warning


def test_a_simulated_robot_and_camera_record_their_ground_truth(tmp_path, caplog, warp_cpu):
    out = tmp_path / "rec"
    url = "sim://skull?width=160&height=120"
    with caplog.at_level(logging.WARNING):
        assert main(["record", "--robot", url, "--grabber", url + "&frames=5", "--out", str(out), "--device",
                     warp_cpu, "--no-progress"]) == 0
    truth = Session(out).ground_truth()
    assert truth is not None and truth.surface is not None and truth.camera_pose is not None
    assert not [m for m in caplog.messages if "ground truth" in m]


@pytest.mark.parametrize("offset_ms", [-600, 400])
def test_a_kinematics_clock_offset_is_not_a_lost_robot(tmp_path, caplog, capsys, offset_ms, warp_cpu):
    """A robot whose clock is offset from the video's (its readings stamped 600 ms early, or 400 ms late) with no
    offset declared: its stamps end before the last frame (or start after the first), but its readings came to the
    end of the capture. Lost is judged on when they were received: exit 0, the coverage a warning that names the
    offset, never 'stopped delivering readings'."""
    out = tmp_path / "rec"
    with caplog.at_level(logging.WARNING):
        rc = main(["sim-record", "--scene", "skull", "--out", str(out), "--frames", "30", "--resolution", "160x120",
                   "--device", warp_cpu, "--kinematics-offset-ms", str(offset_ms), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "stopped delivering" not in err and "lost" not in " ".join(caplog.messages)
    coverage = Session(out).meta.health["pose_coverage"]
    assert not coverage["lost"] and coverage["received_silent_at_end_s"] < 0.25, coverage
    assert coverage["time_offset_ms"] == 0.0
    if offset_ms < 0:  # (30 frames at 25 fps: the last 0.6 s of them after the last stamp)
        assert coverage["after_last"] >= 13 and "received to the end of the capture" in coverage["summary"]
    else:
        assert coverage["before_first"] >= 8 and coverage["after_last"] == 0, coverage
        assert "received from the start of the capture" in coverage["summary"]
    (summary,) = [m for m in caplog.messages if "clock is likely offset" in m]
    assert "calibrate time-offset" in summary


def test_a_declared_time_offset_is_applied_to_the_coverage(tmp_path):
    """The same stamps with the session's time_offset_ns: pose time = video time + offset."""
    from lapreco_hil.sessions.recorder import coverage_of

    frames = [1_000_000_000 + i * 40_000_000 for i in range(30)]
    readings = [t - 600_000_000 for t in range(960_000_000, 2_200_000_000, 5_000_000)]  # stamped 600 ms early
    assert coverage_of("robot", "x", frames, readings).after_last >= 13
    declared = coverage_of("robot", "x", frames, readings, time_offset_ns=-600_000_000)
    assert declared.after_last == declared.before_first == declared.in_gap == 0 and declared.summary() is None
    assert declared.as_dict()["time_offset_ms"] == -600.0


class _Device:
    """What SessionRecorder reads of a device besides its samples: its URL, health and faults."""

    def __init__(self, url: str) -> None:
        from types import SimpleNamespace

        self.url, self.health, self.faults = SimpleNamespace(raw=url), None, {}


@pytest.mark.parametrize("leaves_by", ["out_of_volume", "rms"])
def test_tracker_samples_a_replay_refuses_cover_no_frame(tmp_path, leaves_by):
    """A scope that leaves the tracker's volume (or whose marker fit goes bad) for the last frames: the tracker
    still delivers its poses, recorded with their flags, but a replay refuses them, so they cover no frame. The
    coverage says so (frames after the last usable reading), as a warning: the tracker was not lost."""
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.sessions import format as fmt
    from lapreco_hil.sessions.recorder import SessionRecorder
    from lapreco_hil.types import Frame, MarkerSample

    camera = CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.02), 22.0)
    meta = fmt.SessionMeta(camera=camera, pose_source="marker_poses", length_unit="mm",
                           tracker=fmt.TrackerSetup("scope", np.eye(4), max_rms_mm=1.0))
    recorder = SessionRecorder(tmp_path / "s", meta, _Device("sim://grabber"), _Device("ndi:///dev/ttyUSB0"),
                               console=False)
    leaves_at = 1_600_000_000  # usable until then, for 7 of the 20 frames (1.65 .. 1.95 s) not

    def sample(t: int, seq: int, tool: str = "scope") -> MarkerSample:
        out = tool == "scope" and t > leaves_at
        return MarkerSample(np.eye(4), t, seq, tool, 2.5 if out and leaves_by == "rms" else 0.2,
                            not (out and leaves_by == "out_of_volume"))

    samples = [s for i, t in enumerate(range(980_000_000, 2_020_000_000, 20_000_000))
               for s in (sample(t, i), sample(t + 1, i, "board"))]
    with recorder:
        for i in range(20):
            t = 1_000_000_000 + i * 50_000_000
            recorder.add_joints([s for s in samples if s.t_ns <= t])
            samples = [s for s in samples if s.t_ns > t]
            recorder.add_frame(Frame(np.zeros((48, 64, 3), np.uint8), t, i))
        recorder.add_joints(samples)
    coverage = recorder.coverage
    assert max(recorder.writer.pose_times) <= leaves_at and recorder.writer.n_markers == 2 * 52
    assert coverage.after_last == 7 and not coverage.lost, coverage
    assert coverage.summary().startswith("tracker ndi:///dev/ttyUSB0: 7 of 20 frames come after its last reading")


def test_a_run_whose_every_reading_was_refused_has_no_coverage_crash(warp_cpu):
    """`lapreco run` with no reading accepted at all: the pose coverage of an empty robot track (an empty
    PoseAtTime is falsy) is one of frames before the first reading, never an AttributeError, and not a lost robot
    (a source that delivered nothing usable is the run's own error: the live run mapped no frames)."""
    from lapreco_hil.app.run import _pose_coverage, _watch_receipts
    from lapreco_hil.config import PipelineConfig
    from lapreco_hil.pose_sources import RobotPoseSource
    from lapreco_hil.registry import DeviceContext, open_robot
    from lapreco_hil.sessions.recorder import check_pose_coverage

    robot = open_robot("sim://skull?width=160&height=120", DeviceContext())
    poses = RobotPoseSource(robot, robot.description, PipelineConfig().prior)
    receipts = _watch_receipts(poses)
    for t in (1_000_000_000, 1_050_000_000, 1_100_000_000):  # frames came; no reading was accepted
        poses.has_pose(t)
    coverage = _pose_coverage(poses, robot, 3, receipts)
    assert len(poses.pose_at) == 0 and coverage.before_first == 3 and coverage.last_reading_ns is None
    assert not coverage.lost
    check_pose_coverage("run", coverage, "kept")  # (no DeviceLostError: the run's own error names the cause)


@pytest.mark.slow
def test_run_with_every_reading_refused_ends_with_its_one_line_error(tmp_path, monkeypatch, capsys, warp_cpu):
    from lapreco_hil.pose_sources import RobotPoseSource

    monkeypatch.setattr(RobotPoseSource, "_refusal",
                        lambda self, s: ("beyond limits", "joint 'j1' = 9 beyond its limits [-1, 1] (margin included)"))
    url = "sim://skull?width=160&height=120"
    rc = main(["run", "--robot", url, "--grabber", url + "&frames=10", "--out", str(tmp_path / "out"), "--device",
               warp_cpu, "--tracker", "opencv", "--surface", "alpha", "--no-progress"])
    captured = capsys.readouterr()
    assert rc != 0 and "AttributeError" not in captured.err + captured.out
    (err,) = [line for line in captured.err.splitlines() if line.startswith("lapreco: error:")]
    assert "mapped no frames" in err and "refused" in err and "beyond limits" in err, err
