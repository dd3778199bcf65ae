"""Stereo scopes in the mapper (partner views tied by the rig's extrinsic, depth from the first frame), the
pixel-noise scale of few-view fits, and the tracking funnel."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.config import MapperConfig
from lapreco_hil.funnel import Funnel
from lapreco_hil.geometry import Rotation, inv_T, look_at, make_T, rotation_angle
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping.mapper import Mapper, local_schedule
from lapreco_hil.mapping.prediction import MotionPredictor
from lapreco_hil.mapping.synthetic import make_problem
from lapreco_hil.types import Observations, PosePrior

K0 = np.array([[420.0, 0, 330], [0, 425.0, 245], [0, 0, 1]])
K1 = np.array([[410.0, 0, 318], [0, 416.0, 251], [0, 0, 1]])  # a real pair's two lenses differ


def _project(K, T_world_camera, X):
    T = inv_T(T_world_camera)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return np.column_stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]])


def _stereo_world(rng, n_points=400, n_frames=3, noise_px=0.3):
    rig = Rig((CameraModel(640, 480, K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]),
               CameraModel(640, 480, K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2])),
              (np.eye(4), make_T(Rotation.from_rotvec([0, 0.01, 0]).as_matrix(), np.array([0.005, 0, 0]))),
              sigma_rotation_rad=0.0005, sigma_translation_m=0.0001)
    xy = np.column_stack([rng.uniform(-0.03, 0.03, n_points), rng.uniform(-0.022, 0.022, n_points)])
    pts = np.column_stack([xy, 0.07 + 0.006 * np.sin(xy[:, 0] * 90)])
    poses = [look_at(np.array([0.004 * i, 0.0, 0.0]), np.array([0.004 * i, 0.0, 0.07]), np.array([0, -1.0, 0]))
             for i in range(n_frames)]
    frames = []
    for i, T in enumerate(poses):
        uv0 = _project(K0, T, pts) + rng.normal(0, noise_px, (n_points, 2))
        uv1 = _project(K1, T @ rig.T_cam0_cam[1], pts) + rng.normal(0, noise_px, (n_points, 2))
        ids = np.arange(n_points, dtype=np.int64)
        colors = np.zeros((n_points, 3), np.uint8)
        obs = Observations(i, i * 40_000_000, ids, uv0, colors)
        partner = Observations(i, i * 40_000_000, ids, uv1, colors, camera=1)
        cov = np.diag([0.002**2] * 3 + [0.0005**2] * 3)
        noisy = T @ make_T(Rotation.from_rotvec(rng.normal(0, 0.002, 3)).as_matrix(), rng.normal(0, 0.0005, 3))
        frames.append((obs, PosePrior(noisy, cov, i * 40_000_000), partner))
    return rig, pts, poses, frames


def test_a_stereo_rig_makes_points_from_its_first_frame_and_keeps_its_extrinsic():
    rng = np.random.default_rng(3)
    rig, pts, poses, frames = _stereo_world(rng)
    mapper = Mapper(K0, MapperConfig(), rig=rig)
    obs, prior, partner = frames[0]
    assert mapper.add(obs, prior, partners=[partner])
    assert len(mapper.landmarks) >= 0.9 * len(pts)  # depth from the first frame: the baseline is the parallax
    for obs, prior, partner in frames[1:]:
        mapper.add(obs, prior, partners=lambda p=partner: [p])
    result = mapper.finish()
    assert result.stats["partner_views"] >= 1
    assert result.inlier.mean() > 0.95
    # seen from the first camera, the points lie where the rig's geometry puts them (0.3 px at 70 mm with a
    # 5 mm baseline: a fraction of a millimetre; the world frame adds the pose prior's own error)
    T_est, T_true = inv_T(result.keyframes[0].T_world_camera), inv_T(poses[0])
    est = result.points[result.inlier] @ T_est[:3, :3].T + T_est[:3, 3]
    true = pts[result.landmark_ids[result.inlier]] @ T_true[:3, :3].T + T_true[:3, 3]
    assert np.median(np.linalg.norm(est - true, axis=1)) < 0.3e-3
    for kf in result.keyframes:
        if kf.reference is None:
            continue
        T_ref = result.keyframes[kf.reference].T_world_camera
        T_rel = inv_T(T_ref) @ kf.T_world_camera
        assert rotation_angle(T_rel[:3, :3].T @ rig.T_cam0_cam[1][:3, :3]) < 3 * rig.sigma_rotation_rad
        assert np.linalg.norm(T_rel[:3, 3] - rig.T_cam0_cam[1][:3, 3]) < 3 * rig.sigma_translation_m


def test_a_mono_mapper_ignores_partner_views():
    rng = np.random.default_rng(4)
    _, _, _, frames = _stereo_world(rng, n_frames=1)
    obs, prior, partner = frames[0]
    mapper = Mapper(K0, MapperConfig())  # no rig
    mapper.add(obs, prior, partners=[partner])
    assert len(mapper.landmarks) == 0 and len(mapper.keyframes) == 1


def test_the_pixel_scale_of_a_two_view_fit_is_the_pixel_noise():
    """A point seen twice keeps a quarter of the noise in its residuals: the raw MAD would call the noise half
    what it is, and a fixed floor under it would label good points outliers."""
    rng = np.random.default_rng(5)
    syn = make_problem(rng, n_views=2, n_points=800, pixel_noise=0.6)
    result = ba.solve_robust(syn.problem, local_schedule(MapperConfig()))
    assert result.stats["sigma_px"] == pytest.approx(0.6, rel=0.2)
    assert result.stats["inlier_obs"].mean() > 0.98


def test_motion_prediction_gives_depths_of_mapped_tracks_and_the_map_range():
    rng = np.random.default_rng(6)
    rig, pts, poses, frames = _stereo_world(rng, n_frames=1)
    mapper = Mapper(K0, MapperConfig(), rig=rig)
    obs, prior, partner = frames[0]
    mapper.add(obs, prior, partners=[partner])
    predictor = MotionPredictor(mapper, (0.01, 0.3))
    T_next = prior.T_world_camera @ make_T(np.eye(3), np.array([0.003, 0, 0]))
    motion = predictor.motion(T_next)
    assert np.allclose(motion.T_cur_prev[:3, 3], [-0.003, 0, 0], atol=1e-9)
    assert len(motion.track_ids) >= 0.9 * len(pts)
    z = (pts[motion.track_ids] @ inv_T(poses[0])[2, :3] + inv_T(poses[0])[2, 3])
    assert np.median(np.abs(motion.depth_m - z)) < 1e-3
    near, far = motion.depth_range_m
    assert near < z.min() and far > z.max() and far < 0.3  # the map's range, not the scene default


def test_the_funnel_names_the_stage_that_lost_the_points():
    f = Funnel()
    f.add({"corners": 351, "after_lk": 259, "after_drift_check": 9, "candidates": 5, "triangulated": 0})
    assert f.lossy_stage() == "after_drift_check"
    assert "most were lost at after_drift_check" in f.summary()
    g = Funnel()
    g.add({"corners": 800, "after_lk": 780, "after_drift_check": 760, "candidates": 700, "triangulated": 650,
           "inliers": 640})
    assert g.lossy_stage() is None
    assert "per frame, summed: after_lk 780" in g.summary() and "distinct tracks: candidates 700" in g.summary()
    # one stereo frame: no LK step; its candidates are left-right matches of the corners, and that is where the
    # points went (an inverted rig found 4 of 1797), not at the inliers
    h = Funnel()
    h.add({"corners": 1797, "after_lk": 0, "after_drift_check": 0, "candidates": 4, "triangulated": 4,
           "inliers": 1})
    assert h.lossy_stage() == "candidates"


def test_a_rig_runs_funnel_names_its_left_right_matching_and_leaves_out_tracking_it_never_did():
    """One stereo frame whose partner view finds only a third of the tracks: the funnel counts the left-right
    matching by name (searched, found, dropped for want of a partner), says there was no tracking over time (not
    'after_lk 0 -> after_drift_check 0') and names the left-right matching as where the points went."""
    rng = np.random.default_rng(9)
    rig, pts, _, frames = _stereo_world(rng, n_frames=1)
    obs, prior, partner = frames[0]
    obs = replace(obs, funnel={"corners": len(obs), "after_lk": 0, "after_drift_check": 0})
    found = np.arange(len(partner)) % 3 == 0
    partner = Observations(partner.frame_seq, partner.t_ns, partner.track_ids[found], partner.uv[found],
                           partner.colors[found], camera=1)
    mapper = Mapper(K0, MapperConfig(), rig=rig)
    mapper.add(obs, prior, partners=[partner])
    funnel = mapper.finish().stats["funnel"]
    assert funnel["frames"] == 1 and funnel["partner_searched"] == len(pts)
    assert funnel["partner_matched"] == found.sum() and funnel["without_partner"] == len(pts) - found.sum()
    assert funnel["candidates"] == found.sum()
    line = Funnel(funnel).summary()
    assert "after_lk" not in line and "one frame: no tracking over time" in line
    assert f"left-right matching: {found.sum()} of {len(pts)} tracks found in a partner view" in line
    assert line.endswith("(most were lost at left-right matching)")
    # over three frames a track the partner view never finds still gets a point from the scope's motion: it is
    # searched, not found, and not counted as lost for want of a partner
    rig, pts, _, frames = _stereo_world(np.random.default_rng(10), n_frames=3)
    mapper = Mapper(K0, MapperConfig(), rig=rig)
    for obs, prior, partner in frames:
        keep = partner.track_ids >= 100  # tracks 0-99 never found in the partner view
        mapper.add(obs, prior, partners=[Observations(partner.frame_seq, partner.t_ns, partner.track_ids[keep],
                                                      partner.uv[keep], partner.colors[keep], camera=1)])
    funnel = mapper.finish().stats["funnel"]
    assert funnel["frames"] == 3 and funnel["partner_searched"] == len(pts)
    assert funnel["partner_matched"] == len(pts) - 100 and funnel["without_partner"] == 0
    assert "per frame, summed" in Funnel(funnel).summary()


def test_a_point_seen_by_both_eyes_at_two_instants_is_an_inlier():
    """With a stereo rig a point needs both eyes at two instants: each instant's left-right match is a depth of
    its own and the second instant the second look (a fast scan sees most points at two instants only). Both
    eyes at one of the two instants is not enough, nor is a pair whose partner view is an outlier, nor the
    reference camera alone at three instants: one eye's views agree as well on a feature only that eye sees so
    (an occluding contour's crossing with the tissue behind it: on the simulated liver such points lay 1.2-1.6
    mm RMS from the surface, the others 0.4-0.5; docs/results.md, session 16). Without a rig (or without the
    instants) the reference camera's three instants make an inlier."""
    rng = np.random.default_rng(8)
    rig, _, _, _ = _stereo_world(rng, n_frames=1)
    mapper = Mapper(K0, MapperConfig(), rig=rig)
    points = np.array([[0.0, 0.0, 0.07]] * 3)
    # keyframes 0, 2, 4: the reference camera at instants 0, 2, 4; keyframes 1, 3: their partners at 0 and 2
    obs_point = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2, 2])
    obs_kf = np.array([0, 1, 2, 3, 0, 1, 2, 0, 2, 4])
    reference = np.isin(obs_kf, [0, 2, 4])
    instant = np.where(reference, obs_kf, obs_kf - 1)
    centres = np.column_stack([obs_kf * 0.0005, np.zeros(len(obs_kf)), np.zeros(len(obs_kf))])  # narrow pairs
    good = np.ones(len(obs_point), bool)

    def inliers(good, instants=instant):
        return mapper._inlier_points(obs_point, good, 3, 5, reference, 3, points, centres, instants).tolist()

    assert inliers(good) == [True, False, False]
    assert inliers(good, None) == [False, False, True]  # (without the instants: the reference camera's rule)
    partner_out = good.copy()
    partner_out[3] = False
    assert inliers(partner_out) == [False, False, False]
    # a map of one instant (a two-frame stereo session): both eyes at that instant
    one = np.array([0, 0, 1])
    assert mapper._inlier_points(one, np.ones(3, bool), 2, 2, np.array([True, False, True]), 1, points[:2],
                                 centres[:3], np.zeros(3, np.int64)).tolist() == [True, False]
    mono = Mapper(K0, MapperConfig())
    assert mono._inlier_points(obs_point[reference], good[reference], 3, 3, None, None, points,
                               centres[reference], instant[reference]).tolist() == [False, False, True]
