"""PatchMatch's geometric term (ACMM's second pass; ``[depth] final_geometric_pass``): each source's score of a plane
loses its forward-backward reprojection error through that source's first-pass map, so a pixel whose windows barely
tell planes apart takes the plane the other maps agree on. Rendered views of a textured plane, the reference blurred
in a patch (a frame's motion or defocus blur: its windows there match the sharp sources weakly). Warp's CPU device
by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import DepthConfig, PipelineConfig
from lapreco_hil.geometry import make_T
from textures import plane_grey_views

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(320, 240, 600.0, 600.0, 159.5, 119.5)
PLANE_Z_M = 0.05
TEXEL_M = 5e-5
CAMERA_X_M = {0: 0.0, 1: 0.003, 2: -0.003, 3: 0.005, 4: -0.005}
BLURRED = (slice(80, 160), slice(110, 210))  # the reference's blurred patch (rows, columns)
INSIDE = (slice(84, 156), slice(114, 206))  # ... less its border


def _views(blur_px: float = 3.0):
    from lapreco_hil.dense.types import KeyframeView

    rng = np.random.default_rng(0)
    views = {}
    for i, grey in plane_grey_views(CAMERA, PLANE_Z_M, TEXEL_M, CAMERA_X_M).items():
        x0 = CAMERA_X_M[i]
        grey = grey + rng.normal(0.0, 2.0, grey.shape)
        if i == 0 and blur_px > 0:
            grey[BLURRED] = cv2.GaussianBlur(grey, (0, 0), blur_px)[BLURRED]
        colour = np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
        views[i] = KeyframeView(i, colour, CAMERA.K.copy(), make_T(np.eye(3), [x0, 0.0, 0.0]),
                                depth_range_m=(0.04, 0.06))
    return views


def _plane_map(view):
    from lapreco_hil.dense.types import DepthMap

    shape = (CAMERA.height, CAMERA.width)
    return DepthMap(view.kf_id, np.full(shape, PLANE_Z_M, np.float32), np.ones(shape, np.float32), view.K,
                    view.T_world_camera, {})


def _on_plane(depth: np.ndarray) -> float:
    """The share of the blurred patch (less its border) with a depth within 0.5 mm of the plane."""
    d = depth[INSIDE]
    return float(np.mean((d > 0) & (np.abs(d - PLANE_Z_M) < 5e-4)))


def test_the_geometric_term_gives_a_blurred_patch_the_depth_the_sources_maps_agree_on(warp_cpu):
    """Without the term the blurred patch keeps few depths on the plane (its windows match weakly, the planes they
    pick scatter); with the sources' maps of the plane as the term, several times more."""
    from lapreco_hil.dense.depth import DepthEstimator

    views = _views()
    sources = [views[i] for i in (1, 2, 3, 4)]
    estimator = DepthEstimator(DepthConfig(), DEVICE, host_buffers=0)
    without = estimator.compute(views[0], sources)
    with_term = estimator.compute(views[0], sources, geometry={s.kf_id: _plane_map(s) for s in sources})
    assert "geometry_sources" not in without.stats
    assert with_term.stats["geometry_sources"] == [1, 2, 3, 4]
    assert _on_plane(without.depth_m) < 0.1
    assert _on_plane(with_term.depth_m) > 0.2
    # and outside the patch it costs nothing
    rest = np.ones(without.depth_m.shape, bool)
    rest[BLURRED] = False
    near = lambda d: np.mean((d[rest] > 0) & (np.abs(d[rest] - PLANE_Z_M) < 5e-4))
    assert near(with_term.depth_m) >= near(without.depth_m) - 0.01


def test_with_no_maps_or_no_weight_the_map_is_the_first_passs(warp_cpu):
    """The term is off without maps and with ``geometric_pass_weight`` 0: the very map of a plain ``compute``."""
    from lapreco_hil.dense.depth import DepthEstimator

    views = _views(blur_px=0.0)
    sources = [views[i] for i in (1, 2, 3, 4)]
    maps = {s.kf_id: _plane_map(s) for s in sources}
    plain = DepthEstimator(DepthConfig(), DEVICE, host_buffers=0).compute(views[0], sources).depth_m
    estimator = DepthEstimator(DepthConfig(geometric_pass_weight=0.0), DEVICE, host_buffers=0)
    np.testing.assert_array_equal(estimator.compute(views[0], sources, geometry=maps).depth_m, plain)
    estimator = DepthEstimator(DepthConfig(), DEVICE, host_buffers=0)
    np.testing.assert_array_equal(estimator.compute(views[0], sources, geometry={}).depth_m, plain)


def test_the_final_build_makes_each_map_again_with_its_sources_first_maps(warp_cpu, monkeypatch):
    """``final_geometric_pass``: every map of the final build is made twice, the second time with the first pass's
    maps of its sources (and the coarse level); off, once."""
    from lapreco_hil.dense.depth import DepthEstimator
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    compute = DepthEstimator.compute

    def spy(self, ref, sources, *args, geometry=None, **kwargs):
        calls.append((ref.kf_id, ref.size, sorted(geometry or {})))
        return compute(self, ref, sources, *args, geometry=geometry, **kwargs)

    monkeypatch.setattr(DepthEstimator, "compute", spy)
    views = _views(blur_px=0.0)
    for second in (False, True):
        calls = []
        base = PipelineConfig()
        config = dataclasses.replace(base, depth=dataclasses.replace(base.depth, final_geometric_pass=second))
        dense = DenseSurface(CAMERA, config, DEVICE, sources_fn=nearest_views)
        for i, v in views.items():
            dense.add_view(i, v.colour[:, :, ::-1], v.T_world_camera)
        result = dense.build_at({i: v.T_world_camera for i, v in views.items()}, {i: (0.04, 0.06) for i in views})
        assert dense.fused == 5 and len(result.points) > 1000
        full = max(size for _, size, _ in calls)
        calls = [(kf, g) for kf, size, g in calls if size == full]  # (not the coarse level's maps)
        if not second:
            assert len(calls) == 5 and all(not g for _, g in calls)
        else:
            assert len(calls) == 10
            assert all(not g for _, g in calls[:5])
            assert all(len(g) == 4 and kf not in g for kf, g in calls[5:])


def test_a_two_view_build_makes_each_map_once(warp_cpu, monkeypatch):
    """A map of one source (a stereo pair, a run of two keyframes) gets no second pass: the one partner's map is
    what its left-right check tests."""
    from lapreco_hil.dense.depth import DepthEstimator
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    calls = []
    compute = DepthEstimator.compute

    def spy(self, ref, sources, *args, geometry=None, **kwargs):
        calls.append(bool(geometry))
        return compute(self, ref, sources, *args, geometry=geometry, **kwargs)

    monkeypatch.setattr(DepthEstimator, "compute", spy)
    views = _views(blur_px=0.0)
    base = PipelineConfig()
    config = dataclasses.replace(base, depth=dataclasses.replace(base.depth, final_geometric_pass=True))
    dense = DenseSurface(CAMERA, config, DEVICE, sources_fn=nearest_views)
    for i in (1, 2):
        dense.add_view(i, views[i].colour[:, :, ::-1], views[i].T_world_camera)
    result = dense.build_at({i: views[i].T_world_camera for i in (1, 2)}, {i: (0.04, 0.06) for i in (1, 2)})
    assert dense.fused == 2 and len(result.points) > 1000
    assert calls and not any(calls)
