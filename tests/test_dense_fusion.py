"""TSDF fusion (lapreco_hil.dense.fusion, dense.surface) and the dense outputs.

Fusion is tested apart from multi-view stereo: the depth maps are the simulated renderer's TRUE depth (rendered
with the undistorted pinhole camera at the keyframe's pose), so what is measured is what fusion adds: where the
mesh lies, how much of the seen surface it covers, that a map taken out leaves the volume as it was, that the
memory cap holds, that a pose update moves the surface. The run-level tests inject the same true depth in place
of ``compute_depth``; that is a stand-in for stereo, not a measure of it. The volume runs on Warp's CPU device
(or LAPRECO_TEST_DEVICE=cuda:0)."""

from __future__ import annotations

import logging
import os
import sys

import numpy as np
import pytest
import pyvista as pv

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import FusionConfig, PipelineConfig, config_from_dict
from lapreco_hil.dense import surface as dense_surface
from lapreco_hil.dense.fusion import TsdfVolume
from lapreco_hil.dense.surface import DenseSurface, dense_surface_for, nearest_views, undistortion
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.errors import ConfigError
from lapreco_hil.evaluation.accuracy import surface_distances, surface_report
from lapreco_hil.geometry import make_T

T0 = 1_000_000_000
DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")


def pinhole(camera: CameraModel) -> CameraModel:
    """The camera without its distortion and field of view: what a keyframe view is after undistortion."""
    return CameraModel(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)


def true_depth_fn(world):
    """A stand-in for compute_depth: the true surface's depth at the view's pose (confidence 1 inside its mask),
    rendered with the view's pinhole K and size (the dense canvas, which holds the whole field of view)."""

    def depth_fn(ref, sources, config, device):
        K = ref.K
        cam = CameraModel(ref.size[0], ref.size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        _, depth = world.renderer.render(ref.T_world_camera, camera=cam)
        valid = depth > 0
        if ref.mask is not None:
            valid &= ref.mask
        return DepthMap(ref.kf_id, np.where(valid, depth, 0).astype(np.float32), valid.astype(np.float32), ref.K,
                        ref.T_world_camera)

    return depth_fn


class TrueDepth:
    """``true_depth_fn`` that can be pickled to another process (the live run's dense process): it makes its own
    simulated world of ``scene`` at ``size`` on the CPU device where it is first called."""

    def __init__(self, scene: str, size: tuple[int, int]) -> None:
        self.scene, self.size = scene, size
        self._fn = None

    def __getstate__(self) -> dict:
        return {"scene": self.scene, "size": self.size, "_fn": None}

    def __call__(self, ref, sources, config, device):
        if self._fn is None:
            from lapreco_hil.simulators.world import SimSettings, SimWorld

            world = SimWorld(SimSettings(scene=self.scene, width=self.size[0], height=self.size[1], device="cpu"))
            self._fn = true_depth_fn(world)
        return self._fn(ref, sources, config, device)


def scan_poses(world, n: int, seconds: float = 5.0) -> list[np.ndarray]:
    return [world.true_camera_pose(T0 + int(s * 1e9)) for s in np.linspace(0.0, seconds, n)]


def fused_surface(world, poses, config: PipelineConfig | None = None) -> DenseSurface:
    dense = DenseSurface(world.camera, config or PipelineConfig(), DEVICE, depth_fn=true_depth_fn(world),
                         sources_fn=nearest_views)
    for i, T in enumerate(poses):
        image, _ = world.renderer.render(T)  # the grabber's frame: distorted, BGR
        dense.add_view(i, image, T)
    assert dense.fuse_pending() == len(poses)
    return dense


@pytest.fixture(scope="module")
def skull_fused(skull_world):
    poses = scan_poses(skull_world, 5)
    dense = fused_surface(skull_world, poses)
    return dense, poses, dense.extract()


def test_fused_true_depth_lies_on_the_true_surface_and_covers_what_was_seen(skull_world, skull_fused):
    dense, poses, result = skull_fused
    world, cam = skull_world, skull_world.camera
    mesh = result.mesh
    assert mesh.n_cells > 10_000
    d = surface_distances(np.asarray(mesh.points), world.surface_mesh())
    assert np.sqrt(np.mean(d**2)) < 0.0005  # measured 0.077 mm with 0.5 mm voxels
    report = surface_report(world.surface_mesh(), np.array(poses), cam.K, (cam.width, cam.height),
                            dense=result.points, mask=undistortion(cam)[2])
    assert report["seen_samples"] > 10_000
    assert report["dense"]["coverage"] >= 0.90, report  # measured 97.7%
    assert report["dense"]["beyond_5mm"] == 0.0
    # normals point out of the surface, towards the cameras that saw it
    to_camera = poses[0][:3, 3] - result.points
    assert np.mean(np.sum(to_camera * result.normals, axis=1) > 0) > 0.85
    # each vertex has the colour the keyframes saw there: compare with the first view's undistorted image
    view = dense.keyframe_view(0)
    canvas = CameraModel(view.size[0], view.size[1], view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2])
    pc = (result.points - poses[0][:3, 3]) @ poses[0][:3, :3]
    uv = np.round(pc[:, :2] / pc[:, 2:3] @ np.diag([canvas.fx, canvas.fy]) + [canvas.cx, canvas.cy]).astype(int)
    _, depth = world.renderer.render(poses[0], camera=canvas)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < canvas.width) & (uv[:, 1] >= 0) & (uv[:, 1] < canvas.height)
    uv, pc, rgb = uv[inside], pc[inside], result.colours[inside]
    front = (np.abs(depth[uv[:, 1], uv[:, 0]] - pc[:, 2]) < 0.0005) & view.mask[uv[:, 1], uv[:, 0]]
    seen = view.colour[uv[front, 1], uv[front, 0]].astype(float)
    assert front.sum() > 5000 and seen.std() > 5
    assert np.median(np.abs(rgb[front] - seen)) < 12  # several views' light differs a little


def test_taking_a_map_out_restores_the_volume_bit_for_bit(skull_world, warp_cpu):
    world = skull_world
    a, b = scan_poses(world, 2, seconds=3.0)
    depth_fn = true_depth_fn(world)
    from lapreco_hil.dense.types import KeyframeView

    def depth_map(kf_id, T, confidence):
        image = np.zeros((world.camera.height, world.camera.width, 3), np.uint8)
        m = depth_fn(KeyframeView(kf_id, image, world.camera.K, T), [], None, "cpu")
        m.confidence *= confidence
        return m

    colour = np.random.default_rng(0).integers(0, 255, (world.camera.height, world.camera.width, 3), np.uint8)
    volume = TsdfVolume(FusionConfig(), DEVICE)
    volume.integrate(depth_map(0, a, 1.0), colour)
    before = volume.raw_blocks()
    second = depth_map(1, b, 0.6)
    n = volume.integrate(second, colour[::-1].copy(), weight_scale=1.5)
    during = volume.raw_blocks()
    assert during.keys() != before.keys() or any(not np.array_equal(during[k][0], before[k][0]) for k in before)
    volume.deintegrate(second, colour[::-1].copy(), weight_scale=1.5, integration=n)
    after = volume.raw_blocks()
    assert after.keys() == before.keys()
    for key, arrays in before.items():
        for x, y in zip(arrays, after[key]):
            np.testing.assert_array_equal(x, y)


def plane_map(kf_id: int, x_m: float) -> tuple[DepthMap, np.ndarray]:
    """A camera 5 cm above a textured plane, moved ``x_m`` along it."""
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    depth = np.full((120, 160), 0.05, np.float32)
    colour = np.full((120, 160, 3), (kf_id * 20) % 255, np.uint8)
    return DepthMap(kf_id, depth, np.ones_like(depth), K, make_T(np.eye(3), [x_m, 0.0, 0.0])), colour


def test_memory_stays_under_the_block_cap_as_the_view_moves_on(warp_cpu):
    cap = 1000
    volume = TsdfVolume(FusionConfig(max_blocks=cap), DEVICE)
    first = None
    for i in range(12):
        depth, colour = plane_map(i, 0.03 * i)  # 3 cm a step: about half of each view is new ground
        volume.integrate(depth, colour)
        first = first or volume.blocks_in_use
        assert volume.blocks_in_use <= cap and volume.capacity <= cap
    assert 2 * first < cap  # two views fit: the cap is met by moving on, not by one map
    assert volume.stats.evicted_blocks > 0 and volume.stats.unallocated_blocks == 0
    points, _, _ = volume.extract_points()
    # the newest view's ground is whole, the first views' ground was dropped (the blocks unused for longest)
    half_width = 80 / 150 * 0.05
    assert points[:, 0].max() > 0.33 + 0.9 * half_width
    assert points[:, 0].min() > 0.03 + half_width


def test_kept_keyframes_are_bounded_the_oldest_let_go_first(warp_cpu):
    from lapreco_hil.simulators.world import default_camera

    camera = default_camera(64, 48)
    config = config_from_dict({"fusion": {"keep_keyframes": 3}})
    dense = DenseSurface(camera, config, DEVICE, depth_fn=lambda *a: None, sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    for i in range(6):
        dense.add_view(i, rng.integers(0, 255, (48, 64, 3), np.uint8), make_T(np.eye(3), [0.001 * i, 0, 0]))
    assert list(dense.views) == [3, 4, 5] and dense.released == 3
    view = dense.keyframe_view(5)
    w, h = dense.size  # (the canvas that holds the whole field of view: taller than the frame with this lens)
    assert view.colour.shape == (h, w, 3) and view.mask.shape == (h, w) and h > 48
    assert view.mask[h // 2, w // 2] and not view.mask[0, 0]  # the lens's circle, undistorted
    assert dense.fuse_pending() == 0 and dense.depth_failures == 3  # no depth map: nothing fused, counted


def test_a_pose_update_moves_the_surface_and_moving_back_restores_it(skull_world):
    poses = scan_poses(skull_world, 3, seconds=4.0)
    dense = fused_surface(skull_world, poses)
    original = dense.volume.raw_blocks()
    mesh0 = dense.extract().mesh
    assert dense.update_poses({i: T for i, T in enumerate(poses)}, settled=True) == 0  # unmoved: nothing re-fused
    shift = make_T(np.eye(3), [0.002, 0.0, 0.0])
    assert dense.update_poses({i: shift @ T for i, T in enumerate(poses)}, settled=True) == 3
    mesh1 = dense.extract().mesh
    moved = np.asarray(mesh1.points)
    assert np.median(surface_distances(moved, mesh0)) > 0.0005  # it left the old surface
    assert np.sqrt(np.mean(surface_distances(moved - [0.002, 0, 0], mesh0) ** 2)) < 0.0002  # and moved by 2 mm
    assert dense.update_poses({i: T for i, T in enumerate(poses)}, settled=True) == 3
    back = dense.volume.raw_blocks()
    assert back.keys() == original.keys()
    assert all(np.array_equal(x, y) for k in original for x, y in zip(original[k], back[k]))


SMALL = CameraModel(160, 120, 150.0, 150.0, 79.5, 59.5)  # a pinhole keyframe: 0.5 mm voxels, 50 mm away


def synthetic_surface(poses: list[np.ndarray], config: PipelineConfig | None = None) -> DenseSurface:
    """A DenseSurface of keyframes at ``poses`` whose depth maps are a wavy surface 48-52 mm in front of each
    (the same map whatever the pose, so a fresh fusion at other poses places the very same maps), fused."""
    ys, xs = np.mgrid[0:SMALL.height, 0:SMALL.width]

    def depth_fn(ref, sources, depth_config, device):
        depth = (0.05 + 0.002 * np.sin(xs / 9.0 + ref.kf_id) * np.cos(ys / 7.0)).astype(np.float32)
        return DepthMap(ref.kf_id, depth, np.full_like(depth, 0.8), ref.K, ref.T_world_camera)

    dense = DenseSurface(SMALL, config or PipelineConfig(), DEVICE, depth_fn=depth_fn, sources_fn=nearest_views)
    rng = np.random.default_rng(1)
    for i, T in enumerate(poses):
        dense.add_view(i, rng.integers(0, 255, (SMALL.height, SMALL.width, 3), np.uint8), T)
        dense.fuse_pending()
    return dense


def same_volume(a: DenseSurface, b: DenseSurface) -> bool:
    x, y = a.volume.raw_blocks(), b.volume.raw_blocks()
    return x.keys() == y.keys() and all(np.array_equal(p, q) for k in x for p, q in zip(x[k], y[k]))


def rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return make_T(np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]]), np.zeros(3))


def test_the_shift_bound_holds_every_fused_point_and_is_tight_for_a_translation_or_a_rotation(warp_cpu):
    from lapreco_hil.dense.surface import DEPTH_UNIT_M, reach, shift_bound

    d16 = np.full((SMALL.height, SMALL.width), round(0.05 / DEPTH_UNIT_M), np.uint16)
    d16[0, 80] = round(0.08 / DEPTH_UNIT_M)  # the map's far point sets the reach
    ys, xs = np.mgrid[0:SMALL.height, 0:SMALL.width]
    X = (np.linalg.inv(SMALL.K) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])) * d16.ravel() * DEPTH_UNIT_M
    r = reach(SMALL.K, d16)
    assert np.linalg.norm(X, axis=0).max() <= r < 1.15 * np.linalg.norm(X, axis=0).max()  # (the corner's ray)
    rng = np.random.default_rng(0)
    T0_ = make_T(np.eye(3), [0.01, 0.02, 0.0])
    for move in [make_T(np.eye(3), [0.0003, -0.0001, 0.0002]), rotation_x(0.002)] + [
            make_T(np.eye(3), rng.normal(0, 2e-4, 3)) @ rotation_x(rng.normal(0, 2e-3)) for _ in range(5)]:
        T1 = T0_ @ move
        moved = T1[:3, :3] @ X + T1[:3, 3:] - (T0_[:3, :3] @ X + T0_[:3, 3:])
        actual = np.linalg.norm(moved, axis=0).max()
        assert actual <= shift_bound(T0_, T1, r) + 1e-12
    assert shift_bound(T0_, T0_ @ make_T(np.eye(3), [3e-4, 0, 0]), r) == pytest.approx(3e-4)
    R = rotation_x(0.002)  # about the camera's x axis: the far point moves by nearly angle x reach
    moved = np.linalg.norm((T0_ @ R)[:3, :3] @ X - T0_[:3, :3] @ X, axis=0).max()
    assert shift_bound(T0_, T0_ @ R, r) < 1.15 * moved


def test_a_keyframe_nudged_below_the_threshold_is_never_refused(warp_cpu):
    poses = [make_T(np.eye(3), [0.004 * i, 0.0, 0.0]) for i in range(3)]
    dense = synthetic_surface(poses)
    assert dense.fused == 3
    before = dense.volume.raw_blocks()
    # 0.02 mm and 1.2 mrad (x the maps' 63 mm reach: 0.075 mm) each way: under a quarter of a 0.5 mm voxel
    # (0.125 mm) in all, though past the old rule's 0.5 mrad
    for k in range(6):
        sign = 1 if k % 2 else -1
        nudge = make_T(np.eye(3), [0.00002 * sign, 0.0, 0.0]) @ rotation_x(0.0012 * sign)
        assert dense.update_poses({i: T @ nudge for i, T in enumerate(poses)}) == 0
    assert dense.update_poses({}) == 0  # out of the window: settled where it is, still within the threshold
    assert dense.update_poses({i: T for i, T in enumerate(poses)}, settled=True) == 0
    after = dense.volume.raw_blocks()
    assert after.keys() == before.keys() and all(np.array_equal(p, q) for k in before for p, q in
                                                  zip(before[k], after[k]))
    assert dense.refused == 0 and dense.report()["refusions_per_keyframe"] == {"mean": 0.0, "max": 0}


def test_a_keyframe_moved_past_the_threshold_is_refused_once_after_it_settles_at_its_new_pose(warp_cpu):
    poses = [make_T(np.eye(3), [0.004 * i, 0.0, 0.0]) for i in range(3)]
    dense = synthetic_surface(poses)
    # the window moves keyframes 1 and 2 further at every bundle adjustment (0.3 mm a time, and a rotation of
    # 3 mrad: 0.19 mm at the map's reach, past the threshold alone): nothing is re-fused while they are in it
    current = list(poses)
    for k in range(1, 5):
        current[1] = poses[1] @ make_T(np.eye(3), [0.0003 * k, 0.0, 0.0])
        current[2] = poses[2] @ rotation_x(0.003 * k)
        assert dense.update_poses({1: current[1], 2: current[2]}) == 0
    assert dense.update_poses({2: current[2]}) == 1  # keyframe 1 left the window: re-fused once, at its last pose
    assert dense.update_poses({2: current[2]}) == 0
    assert dense.update_poses({}) == 1  # and keyframe 2
    assert dense.update_poses({}) == 0
    assert dict(dense.refusions) == {1: 1, 2: 1}
    assert same_volume(dense, synthetic_surface(current))  # as if fused at the new poses in the first place


def test_a_sliding_window_refuses_each_keyframe_once_and_the_final_build_uses_the_final_poses(warp_cpu):
    """Keyframes pass through a 5-keyframe window that moves each of them past the threshold at every bundle
    adjustment: the old rule (re-fuse at every move) re-fused each keyframe about five times; now each is
    re-fused once when it leaves the window, and once more by the final build if the final poses moved it."""
    from types import SimpleNamespace

    rng = np.random.default_rng(2)
    n, window = 12, 5
    current = [make_T(np.eye(3), [0.003 * i, 0.0, 0.0]) for i in range(n)]
    dense = synthetic_surface([])
    images = np.random.default_rng(1)  # (synthetic_surface's images, in the same order)
    for i in range(n):
        dense.add_view(i, images.integers(0, 255, (SMALL.height, SMALL.width, 3), np.uint8), current[i])
        dense.fuse_pending()
        newest = range(max(0, i - window + 1), i + 1)
        for k in newest:
            current[k] = current[k] @ make_T(np.eye(3), rng.normal(0.0, 0.0003, 3))
        dense.update_poses({k: current[k] for k in newest})
    assert dense.fused == n and max(dense.refusions.values()) == 1 and dense.refused == n - window
    final = [make_T(np.eye(3), [0.0, 0.0005, 0.0]) @ T for T in current]  # a last global adjustment
    keyframes = [SimpleNamespace(id=i, T_world_camera=T, track_ids=None) for i, T in enumerate(final)]
    result = dense.build(SimpleNamespace(keyframes=keyframes, landmark_ids=np.zeros(0, np.int64),
                                         points=np.zeros((0, 3)), inlier=np.zeros(0, bool)))
    stats = result.stats
    assert stats["keyframes_refused_final"] == n and stats["keyframes_refused"] == 2 * n - window
    assert stats["refusions_per_keyframe"]["max"] == 2 and stats["refusions_per_keyframe"]["mean"] < 2
    assert same_volume(dense, synthetic_surface(final))


def test_an_old_refuse_threshold_in_a_config_says_what_replaced_it():
    with pytest.raises(ConfigError, match=r"c.toml: \[fusion\] refuse_translation_m: replaced by "
                                          r"refuse_shift_voxels .*; remove it"):
        config_from_dict({"fusion": {"refuse_translation_m": 0.0001}}, "c.toml")
    with pytest.raises(ConfigError, match=r"\[fusion\] refuse_rotation_rad: replaced by refuse_shift_voxels"):
        config_from_dict({"fusion": {"refuse_rotation_rad": 0.0005}})
    assert config_from_dict({"fusion": {"refuse_shift_voxels": 0.5}}).fusion.refuse_shift_voxels == 0.5


def test_the_surface_mode_is_checked_and_a_missing_stereo_is_one_warning(monkeypatch, caplog):
    from lapreco_hil.simulators.world import default_camera

    camera = default_camera(64, 48)
    with pytest.raises(ConfigError, match=r"\[surface\] mode = 'mesh': use auto, dense or alpha"):
        dense_surface_for(camera, config_from_dict({"surface": {"mode": "mesh"}}), "cpu")
    alpha = config_from_dict({"surface": {"mode": "alpha"}})
    assert dense_surface_for(camera, alpha, "cpu") == (None, None)
    # the default, "auto": dense offline and live on a CUDA device, the alpha shape in the live runtime on the CPU
    assert isinstance(dense_surface_for(camera, PipelineConfig(), "cpu")[0], dense_surface.DenseSurface)
    assert dense_surface_for(camera, PipelineConfig(), "cpu", live=True) == (None, None)
    assert dense_surface.surface_mode(PipelineConfig(), live=True, device="cuda:0") == "dense"
    assert dense_surface.surface_mode(alpha, live=True, device="cuda:0") == "alpha"
    monkeypatch.setitem(sys.modules, "lapreco_hil.dense.depth", None)  # as if depth.py were not there
    with caplog.at_level(logging.WARNING, logger="lapreco_hil.dense.surface"):
        dense, note = dense_surface_for(camera, config_from_dict({"surface": {"mode": "dense"}}), "cpu")
    assert dense is None and "multi-view stereo is not available" in note
    assert [r.getMessage() for r in caplog.records] == [note]


@pytest.fixture(scope="module")
def apple_world(warp_cpu):
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    return SimWorld(SimSettings(scene="apple", width=192, height=144, device=warp_cpu))


def _demo(tmp_path, surface: str, scene: str = "apple"):
    from lapreco_hil.app.demo import run_demo

    return run_demo(scene=scene, frames=16, resolution=(192, 144), out=str(tmp_path), device="cpu",
                    tracker="opencv", progress=False, runtime="sequential", surface=surface)


def test_an_alpha_run_writes_the_alpha_shape_and_no_dense_ply(tmp_path, warp_cpu):
    report = _demo(tmp_path, "alpha")
    assert report["surface"] == "alpha" and report["dense"] is None and report["surface_note"] is None
    assert not (tmp_path / "dense.ply").exists()
    mesh = pv.read(tmp_path / "mesh.ply")
    points = pv.read(tmp_path / "points.ply")
    assert mesh.n_cells > 0 and report["mesh"]["triangles"] > 0
    # the alpha shape is made of the inlier points themselves
    assert np.isin(np.round(np.asarray(mesh.points), 9), np.round(np.asarray(points.points), 9)).all()
    surface = report["accuracy"]["surface"]
    assert "dense" not in surface and 0 < surface["sparse"]["coverage"] < 1


def test_a_dense_run_writes_dense_ply_and_its_mesh_with_normals_and_colours(tmp_path, apple_world, monkeypatch):
    monkeypatch.setattr(dense_surface, "stereo_functions", lambda: (true_depth_fn(apple_world), nearest_views, None))
    report = _demo(tmp_path, "dense")
    assert report["surface"] == "dense"
    dense = report["dense"]
    assert dense["keyframes_fused"] == report["keyframes"] >= 2
    assert dense["memory"]["blocks"] > 0 and dense["timings_s"]["meshing_s"] > 0
    cloud = pv.read(tmp_path / "dense.ply")
    assert cloud.n_points == dense["points"] > 1000
    normals = np.asarray(cloud.point_data["Normals"])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)
    assert np.asarray(cloud.point_data["RGB"]).std() > 1
    mesh = pv.read(tmp_path / "mesh.ply")
    assert mesh.n_cells == dense["mesh_triangles"] and "RGB" in mesh.point_data
    surface = report["accuracy"]["surface"]
    assert surface["dense"]["rms_mm"] < 0.5
    assert surface["dense"]["coverage"] > max(0.8, surface["sparse"]["coverage"])


def test_evaluate_puts_a_runs_dense_surface_beside_its_sparse_points(skull_world, tmp_path):
    """``lapreco evaluate`` on a folder written by hand: sparse points 3 mm apart and dense ones 0.4 mm apart,
    both on the true surface, seen from five poses."""
    import json

    from lapreco_hil.cli.main import main
    from lapreco_hil.evaluation.coverage import sample_surface
    from lapreco_hil.outputs import write_dense_ply, write_points_ply, write_tum

    world, cam = skull_world, skull_world.camera
    truth = world.surface_mesh()
    truth.save(str(tmp_path / "truth.ply"))
    sparse = sample_surface(truth, 0.003, seed=1)
    dense = sample_surface(truth, 0.0004, max_points=1_000_000, seed=2)
    write_points_ply(tmp_path / "points.ply", sparse, np.zeros((len(sparse), 3), np.uint8))
    write_dense_ply(tmp_path / "dense.ply", dense, np.tile([0.0, 0.0, 1.0], (len(dense), 1)),
                    np.zeros((len(dense), 3), np.uint8))
    poses = scan_poses(world, 5)
    write_tum(tmp_path / "trajectory.tum", np.arange(5) * 40_000_000, np.array(poses))
    (tmp_path / "report.json").write_text(json.dumps({"camera": {
        "width": cam.width, "height": cam.height, "K": cam.K.tolist(), "dist": list(cam.dist),
        "fov_radius_px": cam.fov_radius_px}}))
    assert main(["evaluate", str(tmp_path), "--truth", str(tmp_path / "truth.ply"), "--json",
                 str(tmp_path / "ev.json")]) == 0
    surface = json.loads((tmp_path / "ev.json").read_text())["surface"]
    assert surface["dense"]["rms_mm"] < 0.01 and surface["dense"]["beyond_5mm"] == 0.0
    assert surface["dense"]["coverage"] > 0.97
    assert surface["sparse"]["coverage"] < 0.5 * surface["dense"]["coverage"]


def test_surface_is_an_option_of_demo_replay_and_run():
    from lapreco_hil.cli.main import build_parser, main

    parser = build_parser()
    assert parser.parse_args(["demo", "--surface", "dense"]).surface == "dense"
    assert parser.parse_args(["replay", "s", "--out", "o", "--surface", "alpha"]).surface == "alpha"
    assert parser.parse_args(["run", "--grabber", "g", "--out", "o", "--surface", "dense"]).surface == "dense"
    assert parser.parse_args(["demo"]).surface is None  # the config's [surface] mode
    assert main(["demo", "--surface", "mesh"]) == 2


def test_a_live_run_fuses_keyframes_as_they_come_and_refuses_those_bundle_adjustment_moves(tmp_path, warp_cpu,
                                                                                             monkeypatch):
    """The live runtime's dense stage: keyframes reach it from the mapper's answers (their frames kept by the
    tracking stage until then), their depth maps are fused in the dense process during the run and taken out and put back when a
    local BA moves them; the outputs come from the final poses. The renderer's true depth stands in for stereo
    (the stereo itself is tested in test_dense_depth.py), so what is tested is the live plumbing."""
    from lapreco_hil.app.demo import run_demo

    # (picklable: the live run fuses in a process of its own)
    monkeypatch.setattr(dense_surface, "stereo_functions", lambda: (TrueDepth("apple", (192, 144)), nearest_views,
                                                                    None))
    report = run_demo(scene="apple", frames=40, resolution=(192, 144), out=str(tmp_path), device="cpu",
                      tracker="opencv", progress=False, runtime="live", surface="dense")
    assert report["runtime"] == "live" and report["surface"] == "dense" and report["surface_note"] is None
    dense = report["dense"]
    assert report["stage_ms"]["dense_keyframe"]["mean"] > 0  # fused while the run went, not only at its end
    live = report["live"]
    assert live["dense_keyframes"] > 0
    # every keyframe is fused in the end: live, or by the final build when the live stage had no time for it
    assert dense["keyframes_fused"] >= report["keyframes"] - 1 >= 3
    assert dense["keyframes_refused"] > 0  # local BA moved keyframes already fused
    assert pv.read(tmp_path / "dense.ply").n_points == dense["points"] > 1000
    surface = report["accuracy"]["surface"]
    # (a 40-frame 192x144 run: its final poses, not the fusion, set this; 0.4 mm on the CPU, 0.7 on CUDA)
    assert surface["dense"]["rms_mm"] < 1.0 and surface["dense"]["coverage"] > surface["sparse"]["coverage"]
