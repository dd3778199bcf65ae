"""More source views in the final build (``[depth] final_source_views``): surface that few of four neighbours see
finds ``best_k`` views that see it among more. Rendered views of a textured plane; Warp's CPU device by default
(LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import DepthConfig, PipelineConfig
from lapreco_hil.geometry import make_T
from textures import plane_grey_views

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(320, 240, 600.0, 600.0, 159.5, 119.5)
PLANE_Z_M = 0.05
TEXEL_M = 5e-5
# the reference at 0; to its right views near the preferred angle, to its left two at narrow ones: the four best
# sources all lie to the right, so the reference's left band (3.6 mm, 43 px) is seen by none of them
CAMERA_X_M = {0: 0.0, 1: 0.0036, 2: 0.0044, 3: 0.0052, 4: 0.006, 5: -0.0018, 6: -0.0022}


def _views():
    from lapreco_hil.dense.types import KeyframeView

    views = {}
    for i, grey in plane_grey_views(CAMERA, PLANE_Z_M, TEXEL_M, CAMERA_X_M).items():
        x0 = CAMERA_X_M[i]
        colour = np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
        views[i] = KeyframeView(i, colour, CAMERA.K.copy(), make_T(np.eye(3), [x0, 0.0, 0.0]),
                                depth_range_m=(0.04, 0.06))
    return views


def test_more_sources_give_the_band_four_one_sided_sources_miss(warp_cpu):
    """With 4 sources (all to the right) the reference's left band gets no depth; with 6 the two left views are
    among them, the best two per pixel score there, and the band gets depths on the plane."""
    from lapreco_hil.dense.depth import choose_sources, compute_depth

    views = _views()
    others = [views[i] for i in views if i != 0]
    four = choose_sources(views[0], others, 4)
    assert all(CAMERA_X_M[s.kf_id] > 0 for s in four)
    six = choose_sources(views[0], others, 6)
    assert len(six) == 6
    band = (slice(8, 232), slice(5, 38))
    with_four = compute_depth(views[0], four, DepthConfig(), DEVICE).depth_m[band]
    with_six = compute_depth(views[0], six, DepthConfig(), DEVICE).depth_m[band]
    assert np.count_nonzero(with_four) < 0.02 * with_four.size
    kept = with_six[with_six > 0]
    assert kept.size > 0.5 * with_six.size
    assert np.mean(np.abs(kept - PLANE_Z_M) < 0.001) > 0.99


def test_the_final_build_chooses_final_source_views_and_the_live_fusion_source_views():
    """``final_source_views`` sources for each map of the final build (the consistency check's), ``source_views``
    for the live incremental fusion. A stand-in depth function (a plane)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views
    from lapreco_hil.dense.types import DepthMap

    camera = CameraModel(160, 120, 150.0, 150.0, 79.5, 59.5)
    poses = {i: make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(8)}
    rng = np.random.default_rng(0)
    made = {}

    def depth_fn(ref, sources, config, device):
        made.setdefault(ref.kf_id, []).append(len(sources))
        depth = np.full((120, 160), 0.05, np.float32)
        return DepthMap(ref.kf_id, depth, np.full_like(depth, 0.8), ref.K, ref.T_world_camera)

    depth_fn.check_geometry = lambda depth, maps, config, device, min_views: depth
    config = PipelineConfig()
    config = dataclasses.replace(config, depth=dataclasses.replace(config.depth, source_views=2, final_source_views=6,
                                                                   coarse_level=0, consistency_fill_px=0))
    dense = DenseSurface(camera, config, "cpu", depth_fn=depth_fn, sources_fn=nearest_views)
    for k, T in poses.items():
        dense.add_view(k, rng.integers(0, 255, (120, 160, 3), np.uint8), T)
    assert dense.fuse_pending(kf_ids=[0, 1]) == 2
    assert made == {0: [2], 1: [2]}
    dense.build_at(poses, {k: (0.04, 0.06) for k in poses})
    assert all(made[k][-1] == 6 for k in range(2, 8))
