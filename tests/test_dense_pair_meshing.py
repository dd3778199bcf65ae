"""The meshing threshold of a two-view final build (``[fusion] pair_mesh_min_weight``, docs/dense.md "Session 25"):
a stereo pair's maps are each checked against the other, the only view there is, so a depth both confirm is meshed
whatever its confidence; a multi-view build keeps ``mesh_min_weight``. Depth maps here are a plane's true depths at
a low confidence (as filled and semi-global depths carry), with a wrong patch in one view, so what is tested is the
check and the meshing, not stereo. Warp's CPU device by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.geometry import make_T

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(160, 120, 150.0, 150.0, 79.5, 59.5)
PLANE_Z_M = 0.04  # the plane z = 40 mm; the cameras at z = 0 look along +z, 3 mm apart along x
WRONG_Z_M = 0.03  # keyframe 0's wrong patch: 10 mm nearer
WEAK = 0.2  # each map's confidence: two of them sum to less than mesh_min_weight (0.5)


class WeakPlane:
    """A depth function: the plane's depth at confidence WEAK everywhere, 10 mm nearer on a patch of keyframe 0
    only; it checks geometry as multi-view stereo's kept estimator does."""

    def __init__(self) -> None:
        from lapreco_hil.config import DepthConfig
        from lapreco_hil.dense.depth import DepthEstimator

        self.estimator = DepthEstimator(DepthConfig(), DEVICE)

    def __call__(self, ref, sources, config, device):
        depth = np.full((CAMERA.height, CAMERA.width), PLANE_Z_M, np.float32)
        if ref.kf_id == 0:
            depth[40:70, 60:90] = WRONG_Z_M
        return DepthMap(ref.kf_id, depth, np.full_like(depth, WEAK), ref.K, ref.T_world_camera)

    def check_geometry(self, depth_map, maps, config, device, min_views):
        return self.estimator.check_geometry(depth_map, maps, min_views)


def _build(views: int, **fusion):
    """The final build of ``views`` keyframes 3 mm apart: (fused points in metres, the surface)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    config = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, **fusion))
    dense = DenseSurface(CAMERA, config, DEVICE, depth_fn=WeakPlane(), sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    poses = {i: make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(views)}
    for i, T in poses.items():
        dense.add_view(i, rng.integers(0, 255, (CAMERA.height, CAMERA.width, 3), np.uint8), T)
    return dense.build_at(poses, {i: (0.02, 0.06) for i in poses}).points, dense


def test_a_pair_meshes_the_depths_both_views_confirm_however_weak(warp_cpu):
    """Two weak maps (0.2 each) that confirm each other: with the pair's threshold the plane is meshed, within
    1 mm, and the one view's wrong patch is not (the check removed it); with mesh_min_weight (0.5, the rule before)
    nothing is, for 0.2 + 0.2 never reaches it."""
    points, dense = _build(2)
    assert dense.checked_against == [1, 1]
    assert dense.mesh_min_weight() == PipelineConfig().fusion.pair_mesh_min_weight == 0.0
    assert dense.report()["mesh_min_weight"] == 0.0
    assert len(points) > 2000
    assert np.all(np.abs(points[:, 2] - PLANE_Z_M) < 1e-3)
    assert not np.any(np.abs(points[:, 2] - WRONG_Z_M) < 2e-3)
    before, _ = _build(2, pair_mesh_min_weight=0.5)
    assert len(before) == 0


def test_a_multi_view_build_keeps_the_mesh_min_weight(warp_cpu):
    """Five keyframes: every map is checked against several others, so a voxel still needs mesh_min_weight (single
    weak views leave no surface); only where three or more weak maps overlap is there a surface."""
    points, dense = _build(5)
    assert max(dense.checked_against) > 1
    assert dense.mesh_min_weight() == PipelineConfig().fusion.mesh_min_weight
    pair_points, _ = _build(5, mesh_min_weight=0.0)
    assert 0 < len(points) < len(pair_points)
