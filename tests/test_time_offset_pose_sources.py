"""Every pose source has a clock of its own, and its offset is estimated and watched alike: a simulated session
(120 frames, 320x240) turned into a tracked scope's (marker_poses.csv at 60 Hz) and into given camera poses
(camera_poses.csv at 50 Hz), each stamped late by a known offset. ``calibrate time-offset`` finds it (and 0 for
the unshifted copy) within its uncertainty and a few ms; ``replay`` reports the offset its own tracks see
(report.json ``time_offset``); a live ``run --marker`` watches its tracker's clock too."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.calib.time_offset import PoseSeries, estimate_time_offset, track_session
from lapreco_hil.cli.main import main
from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import CalibrationError
from lapreco_hil.geometry import inv_T, make_T, tum_values
from lapreco_hil.sessions import format as fmt
from lapreco_hil.sessions.session import Session

FRAMES = 120
OFFSET_MS = 40.0  # the tracker's stamps (and the given poses') this late: pose time = video time + 40 ms
SEARCH_MS = 200.0
# a scope's marker 15 cm up its shaft, turned; the tracker 1.5 m from the world origin (as test_marker_poses)
T_MARKER_CAMERA = make_T(Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix(), [0.01, -0.02, 0.15])
T_WORLD_TRACKER = make_T(Rotation.from_euler("zyx", [0.5, 0.2, -2.8]).as_matrix(), [0.3, -0.1, 1.5])


@pytest.fixture(scope="module")
def simulated(tmp_path_factory, warp_cpu):
    """A recorded simulated session (joint readings, frames, truth) and the simulated world's true camera pose at
    any time of its clock (the camera's path between frames, not an interpolation of the frames' poses)."""
    from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
    from lapreco_hil.sessions.recorder import record
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    out = tmp_path_factory.mktemp("clocks") / "joints"
    settings = SimSettings(scene="skull", width=320, height=240, device="cpu")
    context = DeviceContext(device="cpu")
    context.shared("sim", "skull", lambda: SimWorld(settings))
    robot, grabber = open_robot("sim://skull", context), open_grabber(f"sim://skull?frames={FRAMES}", context)
    with robot, grabber:
        record(grabber, robot, str(out), max_frames=FRAMES, progress=False)
    return out, grabber.ground_truth.camera_pose


def _pose_cells(T: np.ndarray) -> str:
    return ",".join(f"{x:.12g}" for x in tum_values(T))


def _sample_times(src, rate_hz: float) -> np.ndarray:
    """The pose source's own sampling instants (true time) over the frames' span and a little beyond."""
    t = Session(src).frame_t_ns
    return np.arange(int(t[0]) - 100_000_000, int(t[-1]) + 100_000_000, int(round(1e9 / rate_hz)), dtype=np.int64)


def _copy_frames(src, dst, pose_source: str, **fields) -> None:
    dst.mkdir(parents=True)
    shutil.copytree(src / "frames", dst / "frames")
    shutil.copytree(src / "truth", dst / "truth")
    shutil.copy(src / "frames.csv", dst / "frames.csv")
    doc = json.loads((src / "session.json").read_text())
    doc.pop("robot")
    doc.update({"pose_source": pose_source, "counts": {}, "source": {}, **fields})
    (dst / "session.json").write_text(json.dumps(doc))


def tracked_session(src, dst, true_pose, offset_ms: float, rate_hz: float = 60.0):
    """A tracked scope's session (metres): the scope marker's pose at each tracker instant t, stamped
    t + offset_ms on the tracker's clock, and a second tool's (a board's) that must be ignored."""
    _copy_frames(src, dst, "marker_poses", tracker={"tool": "scope", "T_world_tracker": T_WORLD_TRACKER.tolist(),
                                                    "T_marker_camera": T_MARKER_CAMERA.tolist()})
    rows = []
    for t in _sample_times(src, rate_hz):
        T = inv_T(T_WORLD_TRACKER) @ true_pose(int(t)) @ inv_T(T_MARKER_CAMERA)
        stamp = int(t) + int(round(offset_ms * 1e6))
        rows.append(f"{stamp},scope,{_pose_cells(T)},0.2,1\n{stamp},board,{_pose_cells(np.eye(4))},0.2,1\n")
    (dst / fmt.MARKER_POSES_FILE).write_text(",".join(fmt.MARKER_COLUMNS) + "\n" + "".join(rows))
    return dst


def given_session(src, dst, true_pose, offset_ms: float, rate_hz: float = 50.0):
    """Camera poses given directly (another system's), at their own rate, stamped t + offset_ms."""
    _copy_frames(src, dst, "camera_poses")
    rows = [f"{int(t) + int(round(offset_ms * 1e6))},{_pose_cells(true_pose(int(t)))}\n"
            for t in _sample_times(src, rate_hz)]
    (dst / fmt.CAMERA_POSES_FILE).write_text(",".join(fmt.POSE_COLUMNS) + "\n" + "".join(rows))
    return dst


MAKERS = {"marker_poses": tracked_session, "camera_poses": given_session}


@pytest.fixture(scope="module")
def observations(simulated):
    """The tracks of the frames (the same frames in every copy)."""
    src, _ = simulated
    return track_session(Session(src), PipelineConfig())


@pytest.mark.parametrize("offset_ms", (OFFSET_MS, 0.0))
@pytest.mark.parametrize("pose_source", sorted(MAKERS))
def test_the_offset_of_a_tracker_or_of_given_poses_is_found(simulated, observations, tmp_path, pose_source,
                                                            offset_ms):
    src, true_pose = simulated
    session = Session(MAKERS[pose_source](src, tmp_path / "s", true_pose, offset_ms))
    assert session.meta.pose_source == pose_source
    est = estimate_time_offset(session, search_s=SEARCH_MS / 1e3, obs=observations)
    print(pose_source, offset_ms, est.summary())
    error_ms, sigma_ms = est.offset_ns * 1e-6 - offset_ms, est.sigma_ns * 1e-6
    assert est.pose_source == pose_source and len(est.backlash) == 0
    assert 0.0 < sigma_ms < 5.0
    assert abs(error_ms) <= max(sigma_ms, 1.0) and abs(error_ms) < 3.0, (error_ms, sigma_ms)
    if offset_ms:  # the poses at the offset fit the tracks better than those at 0
        assert est.cost_at_offset_px < 0.8 * est.cost_at_zero_px


def test_a_noisy_trackers_offset_is_found_within_its_uncertainty(simulated, observations, tmp_path):
    """Every tracker sample off by its own noise (0.25 mm, 2 mrad on the camera pose, white): the series is
    smoothed as joint readings are, so the noise neither makes the cost jagged nor hides from the jackknife
    (unsmoothed, this session read 33.0 +- 1.6 ms at a true 40, and -11.7 +- 0.9 at a true 0)."""
    src, true_pose = simulated
    rng = np.random.default_rng(0)

    def noisy(t_ns: int) -> np.ndarray:
        return true_pose(t_ns) @ make_T(Rotation.from_rotvec(rng.normal(0.0, 2e-3, 3)).as_matrix(),
                                        rng.normal(0.0, 0.25e-3, 3))

    session = Session(tracked_session(src, tmp_path / "noisy", noisy, OFFSET_MS))
    est = estimate_time_offset(session, search_s=SEARCH_MS / 1e3, obs=observations)
    print(est.summary())
    error_ms, sigma_ms = est.offset_ns * 1e-6 - OFFSET_MS, est.sigma_ns * 1e-6
    assert abs(error_ms) < 5.0 and abs(error_ms) < 3.0 * sigma_ms, (error_ms, sigma_ms)


def test_pose_series_interpolates_on_se3_and_holds_its_ends():
    T0 = make_T(np.eye(3), [0.0, 0.0, 0.0])
    T1 = make_T(Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix(), [0.02, 0.0, -0.01])
    series = PoseSeries(np.array([1_000, 2_000]), np.stack([T0, T1]))
    mid = series.at(np.array([500, 1_500, 2_500]))
    np.testing.assert_allclose(mid[0], T0, atol=1e-12)
    np.testing.assert_allclose(mid[2], T1, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(mid[1][:3, :3]).as_rotvec(), [0, 0, 0.2], atol=1e-12)
    np.testing.assert_allclose(mid[1][:3, 3], [0.01, 0.0, -0.005], atol=1e-12)
    with pytest.raises(CalibrationError):
        PoseSeries(np.array([1, 1]), np.stack([T0, T1]))


def test_calibrate_time_offset_on_a_tracked_scope_session_prints_and_applies_it(simulated, tmp_path, capsys):
    src, true_pose = simulated
    s = tracked_session(src, tmp_path / "mk40", true_pose, OFFSET_MS)
    assert main(["calibrate", "time-offset", str(s), "--search-ms", str(SEARCH_MS), "--apply",
                 "--json", str(tmp_path / "to.json")]) == 0
    out = capsys.readouterr().out
    assert "tracker time = video time + 4" in out and "+- " in out, out
    doc = json.loads((tmp_path / "to.json").read_text())
    assert doc["pose_source"] == "marker_poses" and abs(doc["offset_ms"] - OFFSET_MS) < 3.0
    assert abs(Session(s).meta.time_offset_ns * 1e-6 - OFFSET_MS) < 3.0
    # a hand-eye for given camera poses, or a joints-only option, is one line saying so
    g = given_session(src, tmp_path / "g", true_pose, 0.0)
    assert main(["calibrate", "time-offset", str(g), "--joint-wander-s", "0.1"]) == 2
    assert "--joint-wander-s" in capsys.readouterr().err


@pytest.mark.parametrize("pose_source", sorted(MAKERS))
def test_replay_reports_the_offset_its_tracks_see(simulated, tmp_path, pose_source, warp_cpu):
    """Replayed with no offset applied, a pose source 40 ms late: the watch reads it from the run's own tracks
    (below the 50 ms warning threshold: no drift called)."""
    from lapreco_hil.app.replay import run_replay

    src, true_pose = simulated
    s = MAKERS[pose_source](src, tmp_path / "s", true_pose, OFFSET_MS)
    report = run_replay(str(s), str(tmp_path / "out"), tracker="opencv", device=warp_cpu, progress=False)
    watched = report["time_offset"]
    print(pose_source, watched)
    assert watched["applied_ms"] == 0.0 and watched["estimated_ms"] is not None
    assert abs(watched["estimated_ms"] - OFFSET_MS) < 15.0, watched
    assert json.loads((tmp_path / "out" / "report.json").read_text())["time_offset"] == watched


def test_a_live_run_with_a_tracker_watches_its_clock(tmp_path, warp_cpu, monkeypatch):
    """``lapreco run --marker``: the live run watches the tracker's clock as it watches a robot's (report.json
    time_offset: the offset in use and what the run's own tracks say), set up as test_marker_poses' live run."""
    import lapreco_hil.app.run as app_run
    from lapreco_hil.calib.files import write_handeye_yaml
    from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

    from test_marker_poses import keep_the_runs_grabber

    write_handeye_yaml(tmp_path / "handeye.yaml", T_MARKER_CAMERA)
    holder = {}

    def scope_mm(t_ns: int):  # the scope marker's pose (mm) on the tracker's clock, the tracker at the world origin
        if not holder.get("open"):  # the grabber lays simulated time on the host clock when it opens
            return None
        T = holder["grabber"].ground_truth.camera_pose(t_ns) @ inv_T(T_MARKER_CAMERA)
        T[:3, 3] *= 1e3
        return T, True

    keep_the_runs_grabber(monkeypatch, holder)
    with NDITrackerEmulator(wired=[scope_mm], frame_rate_hz=60) as emu:
        report = app_run.run(None, "sim://skull?width=320&height=240&fps=10&frames=80", str(tmp_path / "out"),
                             marker_url=f"ndi://{emu.port}?rate=60&reset_wait_ms=100&timeout_ms=300",
                             hand_eye_file=str(tmp_path / "handeye.yaml"), tracker="opencv", device=warp_cpu,
                             progress=False)
    watched = report["time_offset"]
    print(report["frames"], watched)
    assert report["tracker_tool"] == "handle 0A" and report["frames"]["processed"] >= 8
    assert watched is not None and watched["applied_ms"] == 0.0 and watched["drifted"] is False
    assert watched["window_samples"] >= 1  # fed with the tracks and the tracker's motion (a reading needs 50)
