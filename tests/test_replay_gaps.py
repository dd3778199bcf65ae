"""Replays never fail silently: frames the pose data does not cover get no pose (counted by cause, warned
about once), a session shorter than its session.json says is flagged, and frame paths stay inside the
session folder. The sessions here are written as docs/session-format.md tells another program to (json, csv
and cv2 only, not lapreco's writer); the images and joint readings come from the simulated world."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from lapreco_hil.errors import SessionError
from lapreco_hil.geometry import AFTER_LAST, BEFORE_FIRST, IN_GAP, make_T, rot_z
from lapreco_hil.sessions import Session

FRAME_PERIOD_NS = 40_000_000  # 25 fps
JOINT_PERIOD_NS = 5_000_000  # 200 Hz
T0_NS = 1_000_000_000
N_FRAMES = 20


def _covered(t_ns: int, spans) -> bool:
    return any(lo <= t_ns <= hi for lo, hi in spans)


def write_joint_session(folder: Path, warp_device: str, joint_spans=None, n_frames: int = N_FRAMES) -> dict:
    """A joints session as another program would write it. ``joint_spans``: the (start, end) ns intervals
    that joints.csv covers (default: the whole video and a little beyond). Returns session.json's content."""
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    world = SimWorld(SimSettings(scene="skull", width=320, height=240, device=warp_device))
    frame_t = [T0_NS + i * FRAME_PERIOD_NS for i in range(n_frames)]
    if joint_spans is None:
        joint_spans = [(frame_t[0] - 2 * JOINT_PERIOD_NS, frame_t[-1] + 2 * JOINT_PERIOD_NS)]
    (folder / "frames").mkdir(parents=True)
    with open(folder / "frames.csv", "w") as f:
        f.write("seq,t_ns,file\n")
        for i, t in enumerate(frame_t):
            image, _ = world.renderer.render(world.true_camera_pose(t), seed=i)
            cv2.imwrite(str(folder / "frames" / f"{i:06d}.png"), image)
            f.write(f"{i},{t},frames/{i:06d}.png\n")
    joint_t = np.arange(frame_t[0] - 10 * JOINT_PERIOD_NS, frame_t[-1] + 10 * JOINT_PERIOD_NS, JOINT_PERIOD_NS)
    kept = [int(t) for t in joint_t if _covered(int(t), joint_spans)]
    with open(folder / "joints.csv", "w") as f:
        f.write("seq,t_ns,yaw,pitch,insertion,roll\n")
        for i, t in enumerate(kept):
            q = world.arm.true_joints(world.seconds(t))
            f.write(f"{i},{t}," + ",".join(f"{v:.12g}" for v in q) + "\n")
    cam = world.camera
    meta = {"format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
            "camera": {"width": cam.width, "height": cam.height, "K": cam.K.tolist(), "dist": list(cam.dist)},
            "pose_source": "joints",
            "robot": {"urdf": world.robot_model, "tip_frame": world.tip_frame,
                      "joint_names": ["yaw", "pitch", "insertion", "roll"],
                      "joint_units": ["angle", "angle", "length", "angle"],
                      "T_tip_camera": world.T_tip_camera.tolist()},
            "nominal_fps": 25.0, "complete": True,
            "counts": {"frames": n_frames, "joint_samples": len(kept)}}
    (folder / "session.json").write_text(json.dumps(meta))
    return meta


def _replay(session: Path, out: Path, warp_cpu: str) -> dict:
    from lapreco_hil.app.replay import run_replay

    return run_replay(str(session), str(out), tracker="opencv", device=warp_cpu, progress=False, surface="alpha")


def test_frames_past_the_end_of_joints_csv_get_no_pose_and_a_warning(tmp_path, warp_cpu, caplog):
    """joints.csv ends halfway through the video: the second half is counted, not mapped with the last
    reading held, and one warning gives the count and the time span."""
    session = tmp_path / "half"
    last_covered = T0_NS + 9 * FRAME_PERIOD_NS
    write_joint_session(session, warp_cpu, [(T0_NS - 10 * JOINT_PERIOD_NS, last_covered + 2 * JOINT_PERIOD_NS)])
    with caplog.at_level(logging.WARNING):
        r = _replay(session, tmp_path / "out", warp_cpu)
    assert r["frames"]["in"] == N_FRAMES and r["frames"]["processed"] == 10
    assert r["frames"]["without_pose"] == 10 and r["frames"]["dropped"] == 0
    assert r["frames"]["without_pose_by_cause"] == {BEFORE_FIRST: 0, AFTER_LAST: 10, IN_GAP: 0}
    # only the covered frames are in the trajectory
    traj = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert len(traj) == 10 and traj[-1, 0] <= last_covered * 1e-9 + 1e-6
    warnings = [m for m in caplog.messages if "after the last joint reading" in m]
    assert len(warnings) == 1, caplog.messages
    assert warnings[0].startswith("10 frames after the last joint reading were skipped")
    assert "0.400..0.760 s of the video" in warnings[0]


def test_a_camera_pose_session_without_a_pose_for_any_frame_says_what_to_check(tmp_path, warp_cpu):
    """No frame has a pose: the error points at the session's own pose source (camera_poses.csv here), not at
    a robot that a camera-pose session does not have."""
    from lapreco_hil.errors import ReconstructionError

    folder = tmp_path / "late-poses"
    (folder / "frames").mkdir(parents=True)
    with open(folder / "frames.csv", "w") as f:
        f.write("seq,t_ns,file\n")
        for i in range(2):
            cv2.imwrite(str(folder / "frames" / f"{i}.png"), np.full((48, 64, 3), 90, np.uint8))
            f.write(f"{i},{T0_NS + i * FRAME_PERIOD_NS},frames/{i}.png\n")
    with open(folder / "camera_poses.csv", "w") as f:  # poses that start after the video ends
        f.write("t_ns,tx,ty,tz,qx,qy,qz,qw\n")
        for i in range(2):
            f.write(f"{T0_NS + (10 + i) * FRAME_PERIOD_NS},0,0,0,0,0,0,1\n")
    (folder / "session.json").write_text(json.dumps({
        "format": "lapreco-session", "version": 1, "units": {"length": "m", "angle": "rad", "time": "ns"},
        "camera": {"width": 64, "height": 48, "K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]]},
        "pose_source": "camera_poses"}))
    with pytest.raises(ReconstructionError) as exc:
        _replay(folder, tmp_path / "out", warp_cpu)
    text = str(exc.value)
    assert text.startswith("none of the 2 frames has a pose") and "camera_poses.csv" in text, text
    assert "robot" not in text, text
    # every pose source has its own hint (the tracked scope's names marker_poses.csv)
    from lapreco_hil.pipeline import NO_POSE_HINTS
    from lapreco_hil.pose_sources import GivenPoseSource, MarkerPoseSource, RobotPoseSource

    assert "joints.csv" in NO_POSE_HINTS[RobotPoseSource.source]
    assert "camera_poses.csv" in NO_POSE_HINTS[GivenPoseSource.source]
    assert "marker_poses.csv" in NO_POSE_HINTS[MarkerPoseSource.source]


def test_frames_before_the_first_reading_and_in_a_gap_are_counted_by_cause(tmp_path, warp_cpu, caplog):
    """The joint stream starts late and drops out for 100 ms (20 periods, more than MAX_GAP_PERIODS): the
    frames before its start and inside the gap get no pose; frames close to a reading on both sides do."""
    session = tmp_path / "gappy"
    f = [T0_NS + i * FRAME_PERIOD_NS for i in range(N_FRAMES)]
    spans = [(f[2] - 2 * JOINT_PERIOD_NS, f[6] + 2 * JOINT_PERIOD_NS),  # frames 0, 1 before the first
             (f[9] - 2 * JOINT_PERIOD_NS, f[N_FRAMES - 1] + 2 * JOINT_PERIOD_NS)]  # frames 7, 8 in the gap
    write_joint_session(session, warp_cpu, spans)
    with caplog.at_level(logging.WARNING):
        r = _replay(session, tmp_path / "out", warp_cpu)
    assert r["frames"]["without_pose_by_cause"] == {BEFORE_FIRST: 2, AFTER_LAST: 0, IN_GAP: 2}
    assert r["frames"]["without_pose"] == 4 and r["frames"]["processed"] == N_FRAMES - 4
    gap = [m for m in caplog.messages if "in gaps between joint readings longer than 15 ms" in m]
    first = [m for m in caplog.messages if "before the first joint reading" in m]
    assert len(gap) == 1 and gap[0].startswith("2 frames") and "0.280..0.320 s" in gap[0]
    assert len(first) == 1 and first[0].startswith("2 frames") and "0.000..0.040 s" in first[0]


def test_a_session_shorter_than_its_metadata_says_is_flagged(tmp_path, warp_cpu, caplog):
    """frames.csv cut in half while session.json says complete with 30 frames: a warning with both numbers
    on open, and report.json carries it."""
    session = tmp_path / "cut"
    write_joint_session(session, warp_cpu, n_frames=N_FRAMES)
    lines = (session / "frames.csv").read_text().splitlines(keepends=True)
    (session / "frames.csv").write_text("".join(lines[:11]))  # header + 10 of the 20 frames
    with caplog.at_level(logging.WARNING):
        s = Session(session)
    assert len(s) == 10 and s.shortfall == {"frames": {"recorded": N_FRAMES, "found": 10}}
    warning = [m for m in caplog.messages if "shorter than its session.json says" in m]
    assert len(warning) == 1 and "frames.csv has 10 frames, 20 were recorded" in warning[0]
    r = _replay(session, tmp_path / "out", warp_cpu)
    assert r["session_shortfall"] == {"frames": {"recorded": N_FRAMES, "found": 10}}
    saved = json.loads((tmp_path / "out" / "report.json").read_text())
    assert saved["session_shortfall"]["frames"] == {"recorded": N_FRAMES, "found": 10}


def test_a_whole_session_has_no_shortfall(tmp_path, warp_cpu):
    session = tmp_path / "whole"
    write_joint_session(session, warp_cpu, n_frames=3)
    assert Session(session).shortfall == {}


def _frames_csv_with(session: Path, line: int, name: str) -> None:
    lines = (session / "frames.csv").read_text().splitlines()
    seq, t, _ = lines[line - 1].split(",")
    lines[line - 1] = f"{seq},{t},{name}"
    (session / "frames.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def small_session(tmp_path_factory, warp_cpu):
    folder = tmp_path_factory.mktemp("small") / "s"
    write_joint_session(folder, warp_cpu, n_frames=3)
    return folder


@pytest.mark.parametrize("name", ["../../../etc/passwd", "frames/../../outside.png"])
def test_a_frame_path_climbing_out_of_the_session_is_refused(name, small_session, tmp_path):
    session = tmp_path / "s"
    import shutil

    shutil.copytree(small_session, session)
    (tmp_path / "outside.png").write_bytes((session / "frames" / "000000.png").read_bytes())
    _frames_csv_with(session, 3, name)
    with pytest.raises(SessionError) as err:
        Session(session)
    msg = str(err.value)
    assert "frames.csv: line 3:" in msg and f"'{name}'" in msg and "leads outside the session folder" in msg


def test_an_absolute_frame_path_is_refused(small_session, tmp_path):
    import shutil

    session = tmp_path / "s"
    shutil.copytree(small_session, session)
    target = str((session / "frames" / "000001.png").resolve())  # even one that points inside
    _frames_csv_with(session, 2, target)
    with pytest.raises(SessionError, match=r"frames.csv: line 2: frame file '.*000001.png' is not a relative path"):
        Session(session)


def test_a_symlink_leading_out_of_the_session_is_refused(small_session, tmp_path):
    import shutil

    session = tmp_path / "s"
    shutil.copytree(small_session, session)
    outside = tmp_path / "elsewhere.png"
    outside.write_bytes((session / "frames" / "000002.png").read_bytes())
    (session / "frames" / "000002.png").unlink()
    os.symlink(outside, session / "frames" / "000002.png")
    with pytest.raises(SessionError) as err:
        Session(session)
    msg = str(err.value)
    assert "frames.csv: line 4: frame file 'frames/000002.png' leads outside the session folder" in msg
    assert str(outside.resolve()) in msg
    # a link that stays inside the folder is fine
    (session / "frames" / "000002.png").unlink()
    os.symlink("000001.png", session / "frames" / "000002.png")
    assert len(Session(session)) == 3


# --- pose sources, unit level -----------------------------------------------------------------------------------

def test_given_poses_give_no_pose_outside_their_span_or_in_a_gap():
    from lapreco_hil.kinematics import NoPoseError
    from lapreco_hil.pose_sources import GivenPoseSource

    t = np.array([0, 10, 20, 30, 100, 110, 120], np.int64)  # a gap of 70 ns > 3 x the median period 10
    poses = np.array([make_T(rot_z(0.01 * i), [0.001 * i, 0, 0]) for i in range(len(t))])
    src = GivenPoseSource(t, poses, 0.001, 0.0005)
    answers = {ft: src.has_pose(ft) for ft in (-5, 0, 15, 50, 105, 120, 121, 200)}
    assert answers == {-5: False, 0: True, 15: True, 50: False, 105: True, 120: True, 121: False, 200: False}
    assert src.without_pose.as_dict() == {BEFORE_FIRST: 1, AFTER_LAST: 2, IN_GAP: 1}
    for ft in (-5, 50, 121):
        with pytest.raises(NoPoseError):
            src.prior_at(ft)
    # the offset moves frame time onto pose time
    shifted = GivenPoseSource(t, poses, 0.001, 0.0005, offset_ns=10)
    assert shifted.has_pose(-10) and not shifted.has_pose(111)


class _ListRobot:
    """A robot that hands on prepared batches of samples, one batch per read."""

    def __init__(self, batches) -> None:
        self.batches = list(batches)
        self.reads = 0

    def read(self, timeout_s=None):
        self.reads += 1
        return self.batches.pop(0) if self.batches else []


def _robot_source(robot):
    from lapreco_hil.config import PriorConfig
    from lapreco_hil.pose_sources import RobotPoseSource
    from lapreco_hil.types import RobotDescription

    return RobotPoseSource(robot, RobotDescription("ecm", "ecm_tip", np.eye(4)), PriorConfig())


def test_robot_refusals_are_warned_about_naming_joint_and_value_rate_limited(caplog):
    from lapreco_hil.types import JointSample

    q = np.array([0.0, 0.0, 0.1, 0.0])
    bad = q.copy()
    bad[1] = 3.0  # pitch far beyond its limits
    nan = q.copy()
    nan[3] = np.nan
    robot = _ListRobot([[JointSample(bad, 1000 + i, i) for i in range(5)] + [JointSample(nan, 2000, 9)]])
    src = _robot_source(robot)
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.pose_sources"):
        assert src.poll() == []
    assert src.rejected == 6 and src.rejected_by_cause == {"beyond limits": 5, "non-finite joint value": 1}
    refused = [m for m in caplog.messages if "robot reading refused" in m]
    assert len(refused) == 1  # rate limited: one line for the burst
    assert "joint 'pitch' = 3 beyond its limits" in refused[0]
    assert "joint 'roll' = nan" in src.health.detail  # the last refusal


def test_a_frame_newer_than_the_newest_reading_waits_for_it_once(caplog):
    """A live robot's next reading is due within a period: a frame after the newest reading waits for it
    (up to reading_wait_s) and gets a pose; when the stream has ended, the first frame waits and the next
    ones do not."""
    from lapreco_hil.types import JointSample

    q = np.array([0.0, 0.0, 0.1, 0.0])
    robot = _ListRobot([[JointSample(q, 0, 0), JointSample(q, 10, 1)], [], [JointSample(q, 20, 2)]])
    src = _robot_source(robot)
    src.reading_wait_s = 0.05
    assert len(src.poll()) == 2
    assert src.has_pose(15)  # waited two reads for the reading at 20
    assert [s.t_ns for s in src.poll()] == [20]  # what the wait took is still handed on (a recorder needs it)
    assert not src.has_pose(25)  # the stream has ended: waits once, in vain
    reads = robot.reads
    assert not src.has_pose(30) and robot.reads == reads  # no second wait
    assert src.without_pose.as_dict() == {BEFORE_FIRST: 0, AFTER_LAST: 2, IN_GAP: 0}


def test_a_frame_far_beyond_the_newest_reading_does_not_wait():
    """No reading can bracket a frame further past the newest one than the gap limit (it would span a gap):
    such a frame is not kept waiting (a robot on another clock must not slow every frame down)."""
    from lapreco_hil.types import JointSample

    q = np.array([0.0, 0.0, 0.1, 0.0])
    robot = _ListRobot([[JointSample(q, 0, 0), JointSample(q, 10, 1)]])
    src = _robot_source(robot)
    src.poll()
    reads = robot.reads
    t0 = time.monotonic()
    assert not src.has_pose(41)  # 31 ns past the newest reading; the limit is 3 x 10
    assert robot.reads == reads and time.monotonic() - t0 < 0.01
    assert src.without_pose.as_dict()[AFTER_LAST] == 1
