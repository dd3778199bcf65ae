"""The dense surface's multi-view consistency check (lapreco_hil.dense.surface ``_fuse_consistent``, through
``DepthEstimator.check_geometry``): the final build makes every keyframe's map first, then fuses of each only the
depths its neighbours' maps confirm. Depth maps here are a plane's true depths with a wrong patch in each (a
different place in each keyframe, as wrong matches are), so what is tested is the check, not stereo. Warp's CPU
device by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

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
PLANE_Z_M = 0.04  # the plane z = 40 mm in the world; the cameras at z = 0 look along +z, 3 mm apart along x
WRONG_Z_M = 0.03  # the wrong patches' depth: 10 mm nearer


class PlaneWithWrongPatches:
    """A depth function: the plane's depth, but 10 mm nearer on a 25x30 px patch whose place in the image
    moves with the keyframe (25 px further right each time: about 10 mm apart on the plane, so no two keyframes'
    patches meet). It checks geometry as multi-view stereo's kept estimator does."""

    def __init__(self) -> None:
        from lapreco_hil.dense.depth import DepthEstimator
        from lapreco_hil.config import DepthConfig

        self.estimator = DepthEstimator(DepthConfig(), DEVICE)
        self.calls = 0

    def __call__(self, ref, sources, config, device):
        self.calls += 1
        depth = np.full((CAMERA.height, CAMERA.width), PLANE_Z_M, np.float32)
        x0 = 10 + 25 * ref.kf_id
        depth[40:70, x0:x0 + 25] = WRONG_Z_M
        return DepthMap(ref.kf_id, depth, np.full_like(depth, 0.8), ref.K, ref.T_world_camera)

    def check_geometry(self, depth_map, maps, config, device, min_views):
        return self.estimator.check_geometry(depth_map, maps, min_views)


def _build(consistency_views: int) -> np.ndarray:
    """The final build of five keyframes; the fused points (metres)."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    base = PipelineConfig()
    config = dataclasses.replace(base, depth=dataclasses.replace(base.depth, consistency_views=consistency_views))
    depth_fn = PlaneWithWrongPatches()
    dense = DenseSurface(CAMERA, config, DEVICE, depth_fn=depth_fn, sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    poses = {i: make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(5)}
    for i, T in poses.items():
        dense.add_view(i, rng.integers(0, 255, (CAMERA.height, CAMERA.width, 3), np.uint8), T)
    result = dense.build_at(poses, {i: (0.02, 0.06) for i in poses})
    assert depth_fn.calls == 5 and dense.fused == 5
    return result.points


def test_the_final_build_fuses_only_depths_that_other_keyframes_confirm(warp_cpu):
    """Without the check every wrong patch becomes a piece of surface 10 mm in front of the plane; with it (the
    defaults: each map against its neighbours' maps, three must agree) none does, and the plane stays (measured:
    18.7% of the points on the patches without the check, none with it; 67% as many points on the plane (78%
    when two must agree): the ends of the row of five cameras see strips that fewer other keyframes see)."""
    checked = _build(consistency_views=PipelineConfig().depth.consistency_views)
    unchecked = _build(consistency_views=0)
    on_patch = [np.mean(np.abs(p[:, 2] - WRONG_Z_M) < 0.002) for p in (checked, unchecked)]
    on_plane = [np.count_nonzero(np.abs(p[:, 2] - PLANE_Z_M) < 0.001) for p in (checked, unchecked)]
    assert on_patch[1] > 0.03
    assert on_patch[0] == 0.0
    assert on_plane[0] > 0.6 * on_plane[1]


def _patch_x_m(kf_id: int) -> tuple[float, float]:
    """The world x range of keyframe ``kf_id``'s wrong patch (its columns at WRONG_Z_M in front of the camera)."""
    x0 = 10 + 25 * kf_id
    to_x = WRONG_Z_M / CAMERA.fx
    return 0.003 * kf_id + (x0 - CAMERA.cx) * to_x, 0.003 * kf_id + (x0 + 25 - CAMERA.cx) * to_x


def test_keyframes_left_to_the_final_build_are_checked_against_the_maps_fused_before(warp_cpu):
    """A live run fuses keyframes one at a time (no check: their neighbours' maps are not made yet) and leaves the
    rest to its final build: those are checked against the maps fused before (kept PNG-encoded, decoded for it)
    and against each other."""
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    dense = DenseSurface(CAMERA, PipelineConfig(), DEVICE, depth_fn=PlaneWithWrongPatches(), sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    poses = {i: make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(5)}
    for i, T in poses.items():
        dense.add_view(i, rng.integers(0, 255, (CAMERA.height, CAMERA.width, 3), np.uint8), T)
    dense.set_depth_ranges({i: (0.02, 0.06) for i in poses})
    assert dense.fuse_pending({0, 1, 2}) == 3  # as the live stage does
    points = dense.build_at(poses, {i: (0.02, 0.06) for i in poses}).points
    assert dense.fused == 5
    on_patch = np.abs(points[:, 2] - WRONG_Z_M) < 0.002
    for kf_id in range(5):
        lo, hi = _patch_x_m(kf_id)
        inside = on_patch & (points[:, 0] > lo + 0.0005) & (points[:, 0] < hi - 0.0005)
        if kf_id < 3:
            assert np.count_nonzero(inside) > 50  # fused live, unchecked
        else:
            assert np.count_nonzero(inside) == 0  # checked by the final build
