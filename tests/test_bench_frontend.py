"""``lapreco bench frontend``: its live-path pass gives every frame after the first the camera's motion (the
true relative pose and the tracks' rendered depths), as a live run's pose source and map do."""

import numpy as np

from lapreco_hil.bench import frontend as bench
from lapreco_hil.geometry import inv_T


def test_the_live_path_pass_gives_each_frame_its_true_motion_and_depths(warp_cpu):
    camera, frames, truth = bench._frames("skull", 160, 120, 3, "cpu")
    motion = bench._live_motion(truth, bench.SCENE_DEPTH_M)
    assert motion(None, 0) is None
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd
    from lapreco_hil.config import TrackerConfig

    fe = OpenCVFrontEnd(camera, TrackerConfig(max_features=100, min_distance_px=4.0))
    obs = fe.process(frames[0])
    m = motion(obs, 1)
    np.testing.assert_allclose(m.T_cur_prev, inv_T(truth[1][1]) @ truth[0][1], atol=1e-12)
    assert len(m.track_ids) > 0.5 * len(obs) and np.all(m.depth_m > 0)
    assert set(m.track_ids) <= set(obs.track_ids)

    result = bench.run("cpu", [(160, 120)], [100], frames=4, warmup=1)
    live = result["rows"][0]["warp"]["with_motion"]
    assert live["total_ms"] > 0 and live["tracks_median"] > 0
    locked = result["rows"][0]["warp"]["page_locked"]  # the frames staged as the live capture thread does
    assert locked["total_ms"] > 0 and locked["with_motion_ms"] > 0
    assert "+motion" in bench.format_table(result) and "locked" in bench.format_table(result)


def test_the_kernel_profile_adds_each_kernels_time_per_frame_without_prefix_or_hash():
    from types import SimpleNamespace as A

    acts = [A(name="forward kernel _make_lk_track__locals___lk_track_3aae74a0", elapsed=0.5),
            A(name="forward kernel _make_lk_track__locals___lk_track_3aae74a0", elapsed=0.3),
            A(name="memcpy HtoD", elapsed=0.1), A(name="forward kernel _score_ca2ea228", elapsed=0.2)]
    times = bench.kernel_times(acts, frames=2)
    assert list(times) == ["lk_track", "_score", "memcpy HtoD"]  # costliest first
    np.testing.assert_allclose(list(times.values()), [0.4, 0.1, 0.05])
    row = {"resolution": "1920x1080", "features": 2000, "ratio_total": 1.0, "ratio_lk": 1.0, "opencv": {
        "total_ms": 1.0, "stages_ms": {}}, "warp": {"total_ms": 1.0, "stages_ms": {}, "tracks_median": 1,
                                                   "kernels_ms": times}}
    table = bench.format_table({"device": "cuda:0", "frames": 2, "warmup": 1, "cpu_threads": 2, "rows": [row]})
    assert "lk_track 0.400, _score 0.100, memcpy HtoD 0.050" in table


def test_the_warp_rows_alone_leave_the_baseline_out(warp_cpu):
    """``lapreco bench frontend --warp-only``: the Warp rows without OpenCV's (slow on the CPU at 4K); the table
    shows the baseline's columns empty."""
    result = bench.run("cpu", [(160, 120)], [100], frames=3, warmup=1, baseline=False)
    row = result["rows"][0]
    assert "opencv" not in row and row["warp"]["total_ms"] > 0
    assert "160x120" in bench.format_table(result) and " nan " in bench.format_table(result)
