"""Evaluation: similarity ICP to a true surface recovers a known transform, reports ~0 for points on the
surface and a large error for a corrupted reconstruction; `lapreco compare` writes the seed's table."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.cli.main import main
from lapreco_hil.evaluation.icp import align_similarity, evaluate_points, sample_surface
from lapreco_hil.geometry import make_T


@pytest.fixture(scope="module")
def skull(skull_world):
    return skull_world.surface_mesh()


def test_icp_recovers_a_known_similarity_and_reports_zero_on_the_surface(skull):
    pts = sample_surface(skull, 0.002, seed=1)
    pts = pts[np.random.default_rng(1).choice(len(pts), 3000, replace=False)]
    s = 1.03
    T = make_T(Rotation.from_euler("xyz", [3, -2, 4], degrees=True).as_matrix(), [0.004, -0.003, 0.002])
    moved = s * pts @ T[:3, :3].T + T[:3, 3]  # a scaled, rotated, shifted copy
    result = align_similarity(moved, skull)
    back = moved @ result.T[:3, :3].T + result.T[:3, 3]
    assert result.scale == pytest.approx(1 / s, abs=0.002)
    assert np.sqrt(np.mean(np.sum((back - pts) ** 2, axis=1))) < 0.0005  # within 0.5 mm of where they were
    assert result.rms_m < 0.0002
    exact = evaluate_points(pts, skull)
    assert exact["icp"]["rms_mm"] < 0.2 and exact["unaligned"]["rms_mm"] < 0.01


def test_a_corrupted_reconstruction_reports_a_large_error(skull):
    pts = sample_surface(skull, 0.002, seed=2)[:2000]
    rng = np.random.default_rng(3)
    corrupted = pts + rng.normal(0, 0.004, pts.shape)  # 4 mm noise on every point
    result = evaluate_points(corrupted, skull)
    assert result["icp"]["rms_mm"] > 2.5


@pytest.mark.slow
def test_evaluate_command_and_its_errors(skull, tmp_path, capsys, warp_cpu):
    from lapreco_hil.app.demo import run_demo

    truth = tmp_path / "truth.ply"
    skull.save(str(truth))
    run_demo(scene="skull", frames=30, resolution=(320, 240), out=str(tmp_path / "run"), device=warp_cpu,
             tracker="opencv", progress=False)
    assert main(["evaluate", str(tmp_path / "run"), "--truth", str(truth), "--json", str(tmp_path / "e.json")]) == 0
    ev = json.loads((tmp_path / "e.json").read_text())
    assert ev["icp"]["rms_mm"] < 3.0 and 0.97 < ev["similarity"]["scale"] < 1.03 and not ev["warnings"]
    assert 0 < ev["coverage"]["covered_fraction"] <= 1
    assert main(["evaluate", str(tmp_path), "--truth", str(truth)]) == 2
    assert "points.ply: missing" in capsys.readouterr().err


@pytest.mark.slow
def test_compare_writes_the_seed_table(small_skull_session, tmp_path, warp_cpu):
    assert main(["compare", str(small_skull_session), "--out", str(tmp_path / "cmp"), "--device", "cpu",
                 "--no-progress"]) == 0
    result = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    names = [r["variant"] for r in result["variants"]]
    assert names == ["warp-drift", "warp", "opencv-drift", "opencv"]
    for r in result["variants"]:
        # every variant reconstructed something and was measured against the true surface
        assert r["inliers"] >= 10, r
        assert len(r["tracking_ms_per_frame"]) == 12 and min(r["tracking_ms_per_frame"]) > 0
        assert r["icp_rms_mm"] is not None and 0 < r["icp_rms_mm"] < 10, r
        assert r["device"] == "cpu"
    md = (tmp_path / "cmp" / "comparison.md").read_text().splitlines()
    rows = {r["variant"]: next(line for line in md if f"(`{r['variant']}`" in line) for r in result["variants"]}
    for r in result["variants"]:
        cells = [c.strip() for c in rows[r["variant"]].strip("|").split("|")]
        assert cells[1] == str(r["inliers"])  # our figure, next to the seed's
        ran_on = cells[0].split("(`")[0]
        assert "GPU" not in ran_on, cells[0]  # a CPU run is never labelled GPU
    assert rows["warp-drift"].startswith("| Warp on CPU (cpu) drift corr.") and "seed: GPU drift corr." in \
        rows["warp-drift"]
    assert "| 5138 / 8658 |" in rows["warp-drift"] and "| 16217 / 21894 |" in rows["opencv-drift"]
    assert (tmp_path / "cmp" / "tracking_time.png").stat().st_size > 5000
