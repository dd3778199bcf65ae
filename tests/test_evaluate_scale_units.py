"""lapreco evaluate keeps the metric scale and the truth's unit honest: the headline is the unaligned figure and a
rigid ICP (scale 1), never a similarity ICP that shrinks the map onto a flat truth; the similarity's scale is an
extra, with a warning when it is far from 1 or when the truth is too flat to pin an alignment down; a truth in
millimetres is refused (or read as such with --truth-unit mm, or in its session's unit), and a coverage that
cannot be told says why."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyvista as pv

from lapreco_hil.app.evaluate import evaluate
from lapreco_hil.camera import CameraModel
from lapreco_hil.cli.main import main
from lapreco_hil.errors import ConfigError
from lapreco_hil.evaluation.icp import evaluate_points
from lapreco_hil.sessions.format import SessionMeta


def _plane() -> pv.PolyData:
    """A 20 x 20 cm plane at z = 0.1 m."""
    return pv.Plane(center=(0, 0, 0.1), direction=(0, 0, 1), i_size=0.2, j_size=0.2, i_resolution=40,
                    j_resolution=40).triangulate()


def _hills_z(x, y):
    return 0.1 + 0.01 * np.sin(2 * np.pi * x / 0.08) * np.cos(2 * np.pi * y / 0.06) + 2.0 * x * y


def _hills() -> pv.PolyData:
    """A 12 x 12 cm bumpy surface (about 2 cm of relief), no symmetry an alignment could slide along."""
    x, y = np.meshgrid(np.linspace(-0.06, 0.06, 121), np.linspace(-0.06, 0.06, 121))
    return pv.StructuredGrid(x, y, _hills_z(x, y)).extract_surface(algorithm="dataset_surface").triangulate()


def _points_on_plane(rng) -> np.ndarray:
    """A 12 x 9 cm cloud on the plane: 1 mm of noise along its normal and 5 % of points 8 mm off."""
    n = 600
    pts = np.column_stack([rng.uniform(-0.06, 0.06, n), rng.uniform(-0.045, 0.045, n), np.full(n, 0.1)])
    pts[:, 2] += rng.normal(0, 0.001, n)
    pts[: n // 20, 2] += 0.008
    return pts


def _points_on_hills(rng, n: int = 1500) -> np.ndarray:
    x, y = rng.uniform(-0.045, 0.045, n), rng.uniform(-0.045, 0.045, n)
    return np.column_stack([x, y, _hills_z(x, y) + rng.normal(0, 0.0002, n)])


def test_a_flat_truth_keeps_the_scale_at_one_and_warns_that_it_pins_nothing_else():
    pts = _points_on_plane(np.random.default_rng(0))
    ev = evaluate_points(pts, _plane())
    raw, icp, sim = ev["unaligned"], ev["icp"], ev["similarity"]
    assert icp["scale"] == 1.0 and icp["alignment"].startswith("rigid")
    # a rigid motion cannot shrink the cloud onto the plane: the headline stays near the unaligned figure
    assert icp["rms_mm"] > 0.9 * raw["rms_mm"] and raw["rms_mm"] > 1.5
    # the similarity is still reported (what scale the map would need), though the plane leaves it free
    assert np.isfinite(sim["scale"]) and sim["scale"] > 0
    assert ev["relief"]["flat"] and not icp["transform_trusted"] and not sim["trusted"]
    assert len(ev["warnings"]) == 1 and "nearly flat" in ev["warnings"][0]
    assert "rotation about its normal" in ev["warnings"][0] and "scale" in ev["warnings"][0]
    assert ev["coverage"]["covered_fraction"] is None and "no camera poses" in ev["coverage"]["why"]


def test_a_curved_truth_reports_the_needed_scale_and_warns_when_it_is_far_from_one():
    rng = np.random.default_rng(1)
    hills = _hills()
    pts = _points_on_hills(rng)
    ev = evaluate_points(pts, hills)
    assert not ev["relief"]["flat"] and not ev["warnings"]
    assert ev["similarity"]["scale"] == pytest.approx(1.0, abs=0.01)
    assert ev["icp"]["rms_mm"] < 0.4 and ev["unaligned"]["rms_mm"] < 0.4

    c = pts.mean(0)
    big = c + 1.08 * (pts - c)  # a map 8 % too large (e.g. a wrong hand-eye or unit)
    ev = evaluate_points(big, hills)
    assert ev["similarity"]["scale"] == pytest.approx(1 / 1.08, abs=0.02)
    assert ev["icp"]["scale"] == 1.0 and ev["icp"]["rms_mm"] > 2 * ev["similarity"]["rms_mm"]
    assert len(ev["warnings"]) == 1 and "scale the map by 0.9" in ev["warnings"][0]


def _run_folder(tmp_path, points: np.ndarray):
    run = tmp_path / "run"
    run.mkdir()
    pv.PolyData(points).save(str(run / "points.ply"))
    return run


def _session(tmp_path, mesh_in_unit: pv.PolyData, unit: str):
    sess = tmp_path / f"session-{unit}"
    (sess / "truth").mkdir(parents=True)
    meta = SessionMeta(camera=CameraModel(320, 240, 200.0, 200.0, 160.0, 120.0), pose_source="camera_poses",
                       length_unit=unit)
    (sess / "session.json").write_text(json.dumps(meta.to_json()))
    mesh_in_unit.save(str(sess / "truth" / "surface.ply"))
    return sess


def test_a_truth_in_millimetres_is_refused_or_read_in_its_unit(tmp_path, capsys):
    rng = np.random.default_rng(2)
    hills = _hills()
    run = _run_folder(tmp_path, _points_on_hills(rng, 800))
    truth_mm = tmp_path / "hills_mm.ply"
    hills.scale(1000.0).save(str(truth_mm))
    with pytest.raises(ConfigError, match=r"hills_mm\.ply: .*looks like millimetres.*--truth-unit mm"):
        evaluate(str(run), str(truth_mm))
    assert main(["evaluate", str(run), "--truth", str(truth_mm)]) == 2
    err = capsys.readouterr().err
    assert "hills_mm.ply" in err and "millimetres" in err and len(err.strip().splitlines()) == 1

    ev = evaluate(str(run), str(truth_mm), truth_unit="mm")
    assert ev["truth"]["unit"] == "mm" and ev["icp"]["rms_mm"] < 0.4 and not ev["warnings"]
    assert "trajectory.tum is missing" in ev["coverage"]["why"]

    # a session's truth is in the session's unit: the session folder or its truth/surface.ply
    sess = _session(tmp_path, hills.scale(1000.0), "mm")
    for truth in (sess, sess / "truth" / "surface.ply"):
        ev = evaluate(str(run), str(truth))
        assert ev["truth"]["unit"] == "mm" and "session.json" in ev["truth"]["unit_from"]
        assert ev["unaligned"]["rms_mm"] < 0.4
    # --truth-unit overrides the session's, and the check still catches the wrong one
    with pytest.raises(ConfigError, match="millimetres"):
        evaluate(str(run), str(sess), truth_unit="m")

    # points in millimetres against a truth in metres: refused too
    (tmp_path / "mm").mkdir()
    run_mm = _run_folder(tmp_path / "mm", _points_on_hills(rng, 800) * 1000.0)
    truth_m = tmp_path / "hills_m.ply"
    hills.save(str(truth_m))
    with pytest.raises(ConfigError, match="far larger than the truth"):
        evaluate(str(run_mm), str(truth_m))


def test_evaluate_prints_the_unaligned_and_rigid_figures_first_and_the_scale_as_an_extra(tmp_path, capsys, caplog):
    run = _run_folder(tmp_path, _points_on_plane(np.random.default_rng(3)))
    truth = tmp_path / "plane.ply"
    _plane().save(str(truth))
    assert main(["evaluate", str(run), "--truth", str(truth), "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    first, second = out.strip().splitlines()[:2]
    assert first.index("before alignment RMS") < first.index("after rigid ICP (scale fixed at 1) RMS")
    assert "scale 0." not in first and "coverage n/a: no camera poses" in first
    assert second.startswith("lapreco evaluate: similarity ICP (an extra") and "meaningless" in second
    assert "nearly flat" in caplog.text
    ev = json.loads((tmp_path / "e.json").read_text())
    assert ev["relief"]["flat"] and ev["icp"]["scale"] == 1.0
