"""Holes of the depth maps filled for the final build's consistency check (lapreco_hil.dense.fill, used by
``DenseSurface._fuse_consistent`` when ``[depth] consistency_fill_px`` > 0). The maps are analytic (a plane seen
by a row of cameras), so what is tested is the filling and its vetting, not stereo. Warp's CPU device by default
(LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import DepthConfig, PipelineConfig
from lapreco_hil.dense.fill import fill_holes
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.geometry import make_T

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
CAMERA = CameraModel(160, 120, 150.0, 150.0, 79.5, 59.5)
PLANE_Z_M = 0.04  # the plane z = 40 mm in the world; cameras at z = 0 look along +z, 3 mm apart along x
PATCH_X_M = (0.0035, 0.0070)  # a region of the plane (world x, y) ...
PATCH_Y_M = (-0.005, 0.003)
PIT_Z_M = 0.045  # ... that is a pit 5 mm deep in the second test


def _map(depth: np.ndarray, kf_id: int = 0) -> DepthMap:
    return DepthMap(kf_id, depth.astype(np.float32), np.full(depth.shape, 0.8, np.float32), CAMERA.K, np.eye(4))


def test_a_hole_in_a_slanted_plane_is_filled_with_the_planes_depth_and_a_gap_between_surfaces_is_not(warp_cpu):
    """Inverse depth is affine along a plane: a 10x12 px hole in a plane at 36 degrees comes back at the plane's
    depth (to float precision), at half the ends' confidence. A hole across the edge between two surfaces 4 mm apart
    (a step) stays open about the edge: each end's line predicts the other end 10% off."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float64)
    rho = 25.0 + 0.12 * (u - CAMERA.cx) + 0.02 * (v - CAMERA.cy)  # inverse depth, 1/m
    plane = (1.0 / rho).astype(np.float32)
    holed = plane.copy()
    holed[50:60, 70:82] = 0.0
    filled = fill_holes(_map(holed), max_px=24, max_rel=0.03, device=DEVICE)
    assert filled.stats["filled_pixels"] == 120
    assert np.max(np.abs(filled.depth_m[50:60, 70:82] - plane[50:60, 70:82]) / plane[50:60, 70:82]) < 1e-5
    np.testing.assert_allclose(filled.confidence[50:60, 70:82], 0.4)
    assert np.array_equal(filled.depth_m[holed > 0], holed[holed > 0])

    true_step = np.where(u < 76, 0.040, 0.044).astype(np.float32)
    step = true_step.copy()
    step[50:60, 70:82] = 0.0
    across = fill_holes(_map(step), max_px=24, max_rel=0.03, device=DEVICE)
    filled = across.depth_m[50:60, 70:82] > 0
    # (a few pixels near the hole's corners are bridged by two lines on their own side, and filled right)
    assert np.count_nonzero(filled) <= 12  # (of 120)
    np.testing.assert_allclose(across.depth_m[50:60, 70:82][filled], true_step[50:60, 70:82][filled], rtol=1e-5)
    assert not filled[:, 3:9].any()  # nothing within 3 px of the step
    assert fill_holes(_map(step), max_px=0, max_rel=0.03, device=DEVICE).stats is None  # 0: the map as it is


def _pixels_of(x_m: tuple[float, float], y_m: tuple[float, float], z_m: float, camera_x_m: float):
    u = CAMERA.cx + CAMERA.fx * (np.asarray(x_m) - camera_x_m) / z_m
    v = CAMERA.cy + CAMERA.fy * np.asarray(y_m) / z_m
    return (int(np.ceil(v[0])), int(np.floor(v[1])) + 1), (int(np.ceil(u[0])), int(np.floor(u[1])) + 1)


class PlaneMaps:
    """A depth function: the plane's true depth seen from keyframe ``i`` at x = 3 i mm, with the patch a hole in
    every map (a textureless patch: no keyframe matches it), or, with ``pit``, the patch 5 mm deep (the pit's
    floor) in every map but keyframe 2's, where it is a hole. It checks geometry as the kept estimator does."""

    def __init__(self, pit: bool) -> None:
        from lapreco_hil.dense.depth import DepthEstimator

        self.estimator = DepthEstimator(DepthConfig(), DEVICE)
        self.pit = pit

    def __call__(self, ref, sources, config, device):
        depth = np.full((CAMERA.height, CAMERA.width), PLANE_Z_M, np.float32)
        camera_x = float(ref.T_world_camera[0, 3])
        if self.pit and ref.kf_id != 2:
            (v0, v1), (u0, u1) = _pixels_of(PATCH_X_M, PATCH_Y_M, PIT_Z_M, camera_x)
            depth[v0:v1, u0:u1] = PIT_Z_M
        else:
            (v0, v1), (u0, u1) = _pixels_of(PATCH_X_M, PATCH_Y_M, PLANE_Z_M, camera_x)
            depth[v0:v1, u0:u1] = 0.0
        return DepthMap(ref.kf_id, depth, np.full_like(depth, 0.8), ref.K, ref.T_world_camera)

    def check_geometry(self, depth_map, maps, config, device, min_views):
        return self.estimator.check_geometry(depth_map, maps, min_views)


def _build(pit: bool, fill_px: int) -> np.ndarray:
    """The final build of five keyframes (the consistency check on: the defaults); the fused points (metres)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    config = dataclasses.replace(base, depth=dataclasses.replace(base.depth, consistency_fill_px=fill_px))
    dense = DenseSurface(CAMERA, config, DEVICE, depth_fn=PlaneMaps(pit), sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    poses = {i: make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(5)}
    for i, T in poses.items():
        dense.add_view(i, rng.integers(0, 255, (CAMERA.height, CAMERA.width, 3), np.uint8), T)
    result = dense.build_at(poses, {i: (0.02, 0.06) for i in poses})
    assert dense.fused == 5
    return result.points


def _inside_patch(points: np.ndarray, z_m: float) -> int:
    """Fused points well inside the patch (1 mm from its border: a voxel's reach), within 1 mm of depth z_m."""
    x, y, z = points.T
    return int(np.count_nonzero((x > PATCH_X_M[0] + 0.001) & (x < PATCH_X_M[1] - 0.001) & (y > PATCH_Y_M[0] + 0.001)
                                & (y < PATCH_Y_M[1] - 0.001) & (np.abs(z - z_m) < 0.001)))


def test_the_final_build_fills_a_patch_no_keyframe_matched(warp_cpu):
    """A patch of the plane that every keyframe lost (13x30 px in each map): without filling the fused surface
    has a hole there; with it, every map's hole is filled at the plane's depth and the neighbours' filled maps
    confirm one another."""
    assert _inside_patch(_build(pit=False, fill_px=0), PLANE_Z_M) == 0
    assert _inside_patch(_build(pit=False, fill_px=24), PLANE_Z_M) > 20


def test_a_filled_depth_that_other_keyframes_contradict_is_not_fused(warp_cpu):
    """The patch is a pit 5 mm deep that four keyframes see; keyframe 2 lost it, and filling its hole from the
    rim puts it at the rim's depth: the other maps see the pit's floor there, so none confirms it, and no point
    of the fused surface lies across the pit at the rim's depth; the floor is fused."""
    points = _build(pit=True, fill_px=24)
    assert _inside_patch(points, PLANE_Z_M) == 0
    assert _inside_patch(points, PIT_Z_M) > 20


def test_the_fill_kernel_compiles_for_cuda(sm90_ptx):
    """CI has no GPU: the filling's kernel still compiles for an H100 (sm_90)."""
    from lapreco_hil.dense.warp import fill

    assert "fill_holes" in sm90_ptx(fill)
