"""The tracking bench on real frames: its homography truth agrees with the warped images, its metrics are right
on hand-made trackers, the pose prediction it hands a front-end is the true motion, and a real front-end run on
a real frame at a slow speed stays within 1 px."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lapreco_hil.bench import tracking as tb
from lapreco_hil.cli.main import main
from lapreco_hil.errors import ConfigError
from lapreco_hil.types import Observations


@pytest.fixture(scope="module")
def liver():
    return tb.load_real_frames(names=("liver",))[0]


@pytest.fixture(scope="module")
def hamlyn():
    return tb.load_real_frames(names=("hamlyn-phantom",))[0]


def test_the_real_frames_load_with_their_calibrations():
    frames = {f.name: f for f in tb.load_real_frames()}
    assert set(frames) == {"liver", "hamlyn-phantom", "laparoscope-chessboard", "viking-dotgrid"}
    assert frames["liver"].image.shape == (1080, 1920, 3) and not frames["liver"].calibrated
    assert frames["liver"].K[0, 0] == pytest.approx(0.8 * 1920)
    assert frames["hamlyn-phantom"].K[0, 0] == pytest.approx(391.656525)  # its own calibration file
    with pytest.raises(ConfigError, match="unknown real frame 'nope'"):
        tb.load_real_frames(names=("nope",))


def test_each_step_is_scaled_to_the_requested_median_displacement(hamlyn):
    seq = tb.make_sequence(hamlyn, 20.0, 9, photometric=False, segment_frames=1)
    assert seq.kinds[1:] == ["translate"] * 2 + ["rotate"] * 2 + ["zoom"] * 2 + ["tilt"] * 2
    for k in range(1, 9):
        T_cur_prev = seq.T_cam_ref[k] @ np.linalg.inv(seq.T_cam_ref[k - 1])
        assert tb.median_displacement(seq.camera.K, seq.T_cam_ref[k - 1], T_cur_prev, seq.size) == \
            pytest.approx(20.0, abs=0.01)


def test_the_homography_truth_agrees_with_the_warped_image(liver):
    """LK on the clean warped images finds each corner where the homographies say it went, to 0.1 px, for a step
    of every motion kind (a few px, where LK itself is accurate)."""
    seq = tb.make_sequence(liver, 3.0, 9, photometric=False, segment_frames=1)
    lk = dict(winSize=(21, 21), maxLevel=2, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-4))
    for k in range(1, 9):
        prev = cv2.cvtColor(seq.images[k - 1], cv2.COLOR_BGR2GRAY)
        cur = cv2.cvtColor(seq.images[k], cv2.COLOR_BGR2GRAY)
        corners = cv2.goodFeaturesToTrack(prev, 300, 0.05, 20).reshape(-1, 2)
        truth = seq.truth(k, seq.to_reference(k - 1, corners))
        found, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, corners.reshape(-1, 1, 2).astype(np.float32),
                                                    None, **lk)
        ok = status.ravel() == 1
        moved = np.linalg.norm(truth - corners, axis=1)
        error = np.linalg.norm(found.reshape(-1, 2)[ok] - truth[ok], axis=1)
        assert np.median(moved) > 2.0, seq.kinds[k]  # the step is big enough to tell a wrong truth
        assert ok.mean() > 0.9 and np.median(error) < 0.1, (seq.kinds[k], np.median(error))


class ScriptedTracker:
    """A front-end that reports fixed plane points where the homographies put them, plus a bias after their
    first frame; tracks in ``lost_after`` stop being reported after that frame."""

    def __init__(self, seq, uv_ref, bias=(0.0, 0.0), lost_after: dict[int, int] | None = None):
        self.seq, self.uv_ref, self.bias = seq, uv_ref, np.asarray(bias, float)
        self.lost_after = lost_after or {}

    def process(self, frame):
        k = frame.seq
        ids = np.array([i for i in range(len(self.uv_ref)) if k <= self.lost_after.get(i, 10**9)], np.int64)
        uv = self.seq.truth(k, self.uv_ref[ids]) + (self.bias if k > 0 else 0.0)
        return Observations(k, frame.t_ns, ids, uv, np.zeros((len(ids), 3), np.uint8))


def _central_points(seq, n=40):
    w, h = seq.size
    rng = np.random.default_rng(3)
    return np.column_stack([rng.uniform(0.35 * w, 0.65 * w, n), rng.uniform(0.35 * h, 0.65 * h, n)])


@pytest.fixture(scope="module")
def slow_hamlyn(hamlyn):
    return tb.make_sequence(hamlyn, 5.0, 14, photometric=False)


def test_a_perfect_tracker_scores_zero_error_and_full_survival(slow_hamlyn):
    pts = _central_points(slow_hamlyn)
    obs, _ = tb.track_sequence(ScriptedTracker(slow_hamlyn, pts), slow_hamlyn)
    s = tb.summarize([tb.score_tracks(obs, slow_hamlyn.H, slow_hamlyn.size, survival_frames=10)])
    assert s["observations"] == 40 * 13
    assert s["median_error_px"] < 1e-9 and s["within_1px"] == 1.0
    assert s["survival_eligible"] == 40 and s["survival"] == 1.0
    assert s["tracks_per_frame"] == 40


def test_a_tracker_with_a_2px_bias_scores_2px_and_none_within_1px(slow_hamlyn):
    obs, _ = tb.track_sequence(ScriptedTracker(slow_hamlyn, _central_points(slow_hamlyn), bias=(1.2, -1.6)),
                               slow_hamlyn)
    s = tb.summarize([tb.score_tracks(obs, slow_hamlyn.H, slow_hamlyn.size)])
    assert s["median_error_px"] == pytest.approx(2.0, abs=1e-9)
    assert s["within_1px"] == 0.0 and s["within_3px"] == 1.0


def test_survival_counts_the_tracks_lost_before_n_frames(slow_hamlyn):
    lost = {i: 4 for i in range(0, 40, 4)}  # a quarter of the tracks are gone after frame 4
    obs, _ = tb.track_sequence(ScriptedTracker(slow_hamlyn, _central_points(slow_hamlyn), lost_after=lost),
                               slow_hamlyn)
    s = tb.summarize([tb.score_tracks(obs, slow_hamlyn.H, slow_hamlyn.size, survival_frames=10)])
    assert s["survival"] == pytest.approx(0.75)
    assert s["median_error_px"] < 1e-9


class MotionRecorder(ScriptedTracker):
    def __init__(self, seq, uv_ref):
        super().__init__(seq, uv_ref)
        self.motions = {}

    def process(self, frame, motion=None):
        self.motions[frame.seq] = motion
        return super().process(frame)


@pytest.mark.parametrize("mode", ["depth", "epipolar"])
def test_the_prediction_handed_to_the_front_end_is_the_true_motion(hamlyn, mode):
    """With depth, each live track's previous true position, lifted to its depth and moved by T_cur_prev, lands
    on its true position in the new frame; without, the depth range holds the true depths."""
    seq = tb.make_sequence(hamlyn, 20.0, 9, photometric=False, segment_frames=1)
    pts = _central_points(seq, 10)
    tracker = MotionRecorder(seq, pts)
    tb.track_sequence(tracker, seq, predict=mode)
    assert tracker.motions[0] is None
    K_inv = np.linalg.inv(seq.camera.K)
    for k in range(1, 9):
        m = tracker.motions[k]
        prev, cur = seq.truth(k - 1, pts), seq.truth(k, pts)
        z_true = tb.plane_depth(seq.camera.K, seq.T_cam_ref[k - 1], prev)
        assert m.depth_range_m[0] < z_true.min() and z_true.max() < m.depth_range_m[1]
        if mode == "epipolar":
            assert len(m.track_ids) == 0 and len(m.depth_m) == 0
            continue
        np.testing.assert_array_equal(m.track_ids, np.arange(10))
        X_prev = (np.column_stack([prev, np.ones(10)]) @ K_inv.T) * m.depth_m[:, None]
        X_cur = X_prev @ m.T_cur_prev[:3, :3].T + m.T_cur_prev[:3, 3]
        uv = X_cur @ seq.camera.K.T
        np.testing.assert_allclose(uv[:, :2] / uv[:, 2:], cur, atol=1e-6)


def test_predicting_with_a_front_end_that_takes_no_motion_is_a_clear_error(slow_hamlyn):
    with pytest.raises(ConfigError, match="takes no camera motion.*--predict off"):
        tb.track_sequence(ScriptedTracker(slow_hamlyn, _central_points(slow_hamlyn)), slow_hamlyn, predict="depth")


@pytest.mark.slow
@pytest.mark.parametrize("tracker,frame,device", [("opencv", "liver", "cpu"), ("warp", "hamlyn-phantom", "cpu")])
def test_a_real_front_end_tracks_a_real_frame_within_1px_at_a_slow_speed(tracker, frame, device, warp_cpu):
    result = tb.run([tracker], [device], [10.0], ["off"], frames=12, frame_names=(frame,))
    (row,) = result["rows"]
    assert row["tracks_per_frame"] > 100
    assert row["within_1px"] >= 0.9, row


def test_bench_tracking_cli_prints_the_table_and_writes_json(tmp_path, capsys, warp_cpu):
    out = tmp_path / "tracking.json"
    assert main(["bench", "tracking", "--tracker", "opencv", "--device", "cpu", "--speeds", "10", "--frames", "3",
                 "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "opencv" in table and "median px" in table
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["tracker"] == "opencv" and row["speed_px"] == 10.0 and row["predict"] == "off"
    assert set(row["per_frame"]) == {"liver", "hamlyn-phantom", "laparoscope-chessboard", "viking-dotgrid"}


@pytest.mark.parametrize("argv,message", [
    (["--speeds", "10,-5"], "--speeds: -5 is out of range: must be >= 0"),
    (["--speeds", "10,,20"], "--speeds: '10,,20' must be comma-separated numbers"),
    (["--frames", "1"], "--frames: 1 is out of range: must be >= 2"),
    (["--predict", "maybe"], "--predict: invalid choice"),
])
def test_bench_tracking_refuses_bad_arguments_in_one_line(argv, message, capsys):
    assert main(["bench", "tracking", *argv]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"lapreco: error: {message}"), lines


@pytest.mark.parametrize("predict,modes", [("off", ["off"]), ("on", ["depth", "epipolar"]),
                                           ("both", ["off", "depth", "epipolar"])])
def test_bench_tracking_runs_the_prediction_modes_asked_for(predict, modes, monkeypatch):
    from lapreco_hil.app.bench import bench_tracking

    seen = {}
    monkeypatch.setattr(tb, "run", lambda trackers, devices, speeds, predict_modes, frames: seen.update(
        trackers=trackers, devices=devices, speeds=speeds, modes=predict_modes, frames=frames) or {})
    bench_tracking(("opencv",), "cpu", [0, 20], frames=5, predict=predict)
    assert seen == {"trackers": ["opencv"], "devices": ["cpu"], "speeds": [0.0, 20.0], "modes": modes, "frames": 5}
