"""The fused surface's two bounds that the depth maps alone do not show: a moving instrument leaves no surface in
the fused mesh (multi-view stereo against the simulator's liver with its instrument, then TSDF fusion and
meshing), and memory stays flat over many keyframes through DenseSurface (the volume's block cap, the kept
keyframes' cap). Warp's CPU device by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lapreco_hil.config import DepthConfig, FusionConfig
from lapreco_hil.dense.fusion import TsdfVolume
from lapreco_hil.dense.types import DepthMap, KeyframeView
from lapreco_hil.evaluation.accuracy import surface_distances

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
SWEEP = DepthConfig(method="sweep")  # the plane sweep (the pipeline's default is "patchmatch" since session 17)
SIZE = (256, 192)


def liver_keyframes(instrument: str):
    """Five keyframes of the liver world with its instrument ("moving": where the simulator moves it at each
    keyframe's time; "static": held where it is at the reference's time), and the instrument's surface points
    (world, metres) as the keyframes saw it."""
    from lapreco_hil.bench.dense import WORLD_OFFSETS_S, _fov_mask, _K, _landmark_range, _pinhole
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    width, height = SIZE
    tissue = SimWorld(SimSettings(scene="liver", width=width, height=height, device=DEVICE))
    world = SimWorld(SimSettings(scene="liver", width=width, height=height, device=DEVICE, instrument=True))
    camera = _pinhole(world.camera, width, height)
    mask = _fov_mask(camera)
    K = _K(camera)
    t_ref = world.now_ns() + int(2.0 * 1e9)
    views, tool_points, rendered = [], [], []
    for i, dt in enumerate(WORLD_OFFSETS_S[:5]):
        t = t_ref + int(dt * 1e9)
        T = world.true_camera_pose(t)
        world._move_instrument(t if instrument == "moving" else t_ref)
        image, depth = world.renderer.render(T, seed=i, camera=camera)
        _, truth = tissue.renderer.render(T, seed=i, camera=camera)
        tool = mask & (np.abs(depth - truth) > 1e-4)
        ys, xs = np.nonzero(tool)
        z = depth[ys, xs]
        pc = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=1)
        tool_points.append(pc @ T[:3, :3].T + T[:3, 3])
        views.append(KeyframeView(i, image[:, :, ::-1].copy(), K, T, mask, _landmark_range(truth)))
        rendered.append(DepthMap(i, np.where(mask, depth, 0).astype(np.float32), mask.astype(np.float32), K, T))
    return views, np.concatenate(tool_points), tissue.surface_mesh(), rendered


@pytest.fixture(scope="module")
def fused_with_instrument(warp_cpu):
    """The moving instrument: the fused surface's points from multi-view stereo ("stereo") and from the renderer's
    depth, which has the instrument in it ("rendered"), the instrument's points, the true tissue surface."""
    from lapreco_hil.dense.depth import compute_depths

    views, tool, tissue, rendered = liver_keyframes("moving")
    out = {"tool": tool, "tissue": tissue}
    for name, maps in (("stereo", compute_depths(views, SWEEP, DEVICE).values()), ("rendered", rendered)):
        volume = TsdfVolume(FusionConfig(), DEVICE)
        for depth_map in maps:
            volume.integrate(depth_map, views[depth_map.kf_id].colour)
        out[name] = volume.extract_points()[0]
    return out


def on_instrument(points: np.ndarray, tool: np.ndarray, tissue) -> np.ndarray:
    """Fused points within 1 mm of the instrument's surface and more than 1 mm from the tissue (where the
    instrument touches the tissue the two cannot be told apart)."""
    near_tool = np.isfinite(cKDTree(tool).query(points, distance_upper_bound=0.001)[0])
    return near_tool & (surface_distances(points, tissue) > 0.001)


def test_a_moving_instrument_leaves_no_surface_in_the_fused_mesh(fused_with_instrument):
    tool, tissue = fused_with_instrument["tool"], fused_with_instrument["tissue"]
    points = fused_with_instrument["stereo"]
    assert len(tool) > 5000 and len(points) > 5000  # the instrument was in view; the tissue was fused
    # measured: 0 of 14474 fused points on the moving instrument (9423 instrument pixels in the five views)
    assert np.count_nonzero(on_instrument(points, tool, tissue)) <= 0.001 * len(points)
    # the tissue around it keeps its accuracy (measured: median 0.15 mm, none beyond 5 mm)
    d = surface_distances(points, tissue)
    assert np.median(d) < 0.0003 and np.mean(d > 0.005) < 0.005


def test_fused_depth_that_has_the_instrument_puts_it_in_the_mesh(fused_with_instrument):
    """The control: fusion itself does not carve a moving instrument away (each map's band only reaches 2 mm
    about its own surface), so it is the depth maps' multi-view checks that keep it out, and the check above
    finds an instrument where one was fused (measured: 9000 of 175198 fused points on it)."""
    tool, tissue = fused_with_instrument["tool"], fused_with_instrument["tissue"]
    assert np.count_nonzero(on_instrument(fused_with_instrument["rendered"], tool, tissue)) > 1000


def test_memory_stays_flat_over_many_keyframes_through_the_dense_surface(warp_cpu):
    """120 keyframes along a plane, each 1 cm on (new ground each time), every third re-fused after a pose
    update, through DenseSurface with a cap of 1500 blocks and 8 kept keyframes: the volume, the kept images and
    the process stay flat once the caps are reached."""
    from lapreco_hil.bench.fusion import soak_fusion

    result = soak_fusion(DEVICE, (160, 120), keyframes=120, max_blocks=1500, keep_keyframes=8, every=10)
    samples = result["samples"]
    assert all(s["blocks"] <= 1500 for s in samples)
    # the run went far past the cap: more than a whole cap's worth evicted (measured: 2887 blocks, the pool
    # 14.7 MB throughout; the plane lies on block boundaries, so how many it touches varies with its last bit)
    assert samples[-1]["evicted_blocks"] > 1500
    assert result["unallocated_blocks"] == 0 and result["released"] == 120 - 8 and result["refused"] >= 100
    late = samples[3:]  # the caps are reached within the first 30 keyframes
    assert len({s["volume_mb"] for s in late}) == 1  # the pool stopped growing at the cap
    kept = [s["kept_images_mb"] for s in late]
    assert max(kept) < 1.2 * min(kept)
    rss = [s["rss_mb"] for s in late if s["rss_mb"] is not None]
    if rss:  # Linux: the process itself, allowing the allocator's noise (measured: within 26-60 MB, no trend)
        assert max(rss) - min(rss) < 64, rss


def test_the_fusion_kernels_compile_for_cuda(sm90_ptx):
    """CI has no GPU: the TSDF kernels still compile for an H100 (sm_90)."""
    from lapreco_hil.dense.warp import tsdf

    ptx = sm90_ptx(tsdf)
    assert ".entry" in ptx and "integrate_voxels" in ptx and "collect_blocks" in ptx and "prepare_map" in ptx


def test_blocks_a_map_found_no_room_for_are_fused_once_the_pool_has_grown(skull_world, monkeypatch):
    """A map is queued without waiting for the device's block count: in a pool too small for it, the blocks it
    could not get are fused later from its inputs still on the device. The result is bit for bit the volume of a
    pool large enough from the start."""
    from lapreco_hil.dense import fusion

    world = skull_world
    cam = world.camera
    maps = []
    for s in (0.0, 2.5, 5.0):
        T = world.true_camera_pose(1_000_000_000 + int(s * 1e9))
        image, depth = world.renderer.render(T)
        maps.append((DepthMap(len(maps), depth, (depth > 0).astype(np.float32), cam.K, T), image[..., ::-1].copy()))
    first_pool = fusion.FIRST_CAPACITY
    grown = TsdfVolume(FusionConfig(), DEVICE)  # starts with first_pool blocks
    for depth, colour in maps:
        grown.integrate(depth, colour)
    monkeypatch.setattr(fusion, "FIRST_CAPACITY", FusionConfig().max_blocks)
    roomy = TsdfVolume(FusionConfig(), DEVICE)
    for depth, colour in maps:
        roomy.integrate(depth, colour)
    a, b = grown.raw_blocks(), roomy.raw_blocks()
    assert grown.stats.refilled_blocks > 0 and roomy.stats.refilled_blocks == 0
    assert grown.stats.unallocated_blocks == 0
    assert a.keys() == b.keys() and len(a) > first_pool
    assert all(np.array_equal(x, y) for k in a for x, y in zip(a[k], b[k]))


def test_a_map_quantised_on_the_device_as_kept_is_taken_out_exactly_by_its_kept_copy(skull_world):
    """DenseSurface fuses a new map quantised on the device as it keeps it (10 um depth steps, 1/255 confidence)
    and later takes it out with the kept copy (decoded from PNG): the volume must come back empty, bit for bit.
    A map with noise in its depth and confidence, so the quantisation has work to do."""
    from lapreco_hil.dense.surface import DEPTH_UNIT_M, KEPT_STEPS

    world, cam = skull_world, skull_world.camera
    T = world.true_camera_pose(1_000_000_000)
    image, depth = world.renderer.render(T)
    rng = np.random.default_rng(1)
    noisy = np.where(depth > 0, depth + rng.normal(0.0, 3e-5, depth.shape), 0).astype(np.float32)
    confidence = np.where(depth > 0, rng.uniform(0.0, 1.2, depth.shape), 0).astype(np.float32)
    volume = TsdfVolume(FusionConfig(), DEVICE)
    n = volume.integrate(DepthMap(0, noisy, confidence, cam.K, T), image, quantise=KEPT_STEPS)
    d16, c8 = volume.quantised_map()
    assert d16.dtype == np.uint16 and c8.dtype == np.uint8
    valid = d16 > 0
    np.testing.assert_allclose(d16[valid] * DEPTH_UNIT_M, noisy[valid], atol=0.51 * DEPTH_UNIT_M)
    assert np.all(c8[~valid] == 0) and c8.max() == 255 and len(volume.raw_blocks()) > 1000
    kept = DepthMap(0, d16.astype(np.float32) * np.float32(DEPTH_UNIT_M), c8.astype(np.float32) / np.float32(255),
                    cam.K, T)
    volume.deintegrate(kept, image, integration=n, quantise=KEPT_STEPS)
    assert volume.raw_blocks() == {}
