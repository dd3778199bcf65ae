"""A dense surface from two views only (a stereo pair, or a two-frame session): the renderer's liver seen by a
simulated stereo scope (5.5 mm baseline, 90 mm away, as a real laparoscope's pair) through the final build's path,
each map filled and checked against the other's; and the ZNCC window that grows when a map has fewer sources than
a score combines. Warp's CPU device by default (LAPRECO_TEST_DEVICE=cuda:0 runs them on CUDA)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import DepthConfig, PipelineConfig
from lapreco_hil.dense.types import KeyframeView

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
SIZE = (720, 576)
FOCAL_PX = 700.0
BASELINE_M = 0.0055


def _render_pair(scene_name: str, eye: tuple[float, float, float]):
    """(camera, left and right BGR images, their true depths, T_world_left, T_world_right): a stereo scope at
    ``eye`` looking at the scene's centre."""
    from lapreco_hil.geometry import look_at
    from lapreco_hil.simulators.world.renderer import Renderer
    from lapreco_hil.simulators.world.scenes import build_scene

    w, h = SIZE
    camera = CameraModel(w, h, FOCAL_PX, FOCAL_PX, (w - 1) / 2, (h - 1) / 2)
    scene = build_scene(scene_name, 0)
    renderer = Renderer(scene.vertices, scene.faces, scene.face_material, list(scene.materials), camera,
                        device=DEVICE)
    T_left = look_at(np.array(eye), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    T_right = T_left.copy()
    T_right[:3, 3] += T_left[:3, 0] * BASELINE_M  # along the left camera's x
    left, depth_left = renderer.render(T_left, seed=1)
    right, depth_right = renderer.render(T_right, seed=2)
    return camera, left, right, depth_left, depth_right, T_left, T_right


@pytest.fixture(scope="module")
def liver_pair(warp_cpu):
    return _render_pair("liver", (-0.02, 0.0, 0.09))


@pytest.fixture(scope="module")
def skull_pair(warp_cpu):
    """The skull's sparse dots on smooth bone: little texture, as a smooth silicone phantom's."""
    return _render_pair("skull", (0.02, -0.01, 0.08))


def _range(depth: np.ndarray) -> tuple[float, float]:
    z = depth[depth > 0]
    return float(np.percentile(z, 1)) * 0.9, float(np.percentile(z, 99)) * 1.1


def test_a_map_from_one_source_scores_a_window_as_large_as_two_sources_windows():
    from lapreco_hil.dense.depth import window_radius

    config = DepthConfig()
    assert (config.window_radius_px, config.best_k) == (3, 2)
    assert window_radius(config, 4) == 3 and window_radius(config, 2) == 3
    assert window_radius(config, 1) == 5  # 121 samples against 2 x 49
    assert window_radius(dataclasses.replace(config, best_k=1), 1) == 3
    assert window_radius(dataclasses.replace(config, best_k=3), 1) == 6  # 169 against 3 x 49
    assert window_radius(dataclasses.replace(config, best_k=3), 2) == 4  # 2 x 81 against 3 x 49


def test_one_sources_map_with_the_grown_window_is_denser_and_no_less_accurate(skull_pair):
    """The same pair with the window a one-source map gets (11x11) and with the 7x7 of a multi-view map (best_k 1
    keeps it): measured on the CPU 36% more pixels within 1 mm of the true depth (171 192 against 126 001), the
    share beyond 1 mm 16.9 -> 15.2% (the liver's richer texture: 3% more, 2.5 -> 1.8%)."""
    from lapreco_hil.dense.depth import DepthEstimator

    camera, left, right, depth_left, _, T_left, T_right = skull_pair
    K = camera.K
    near_far = _range(depth_left)
    ref = KeyframeView(0, left[:, :, ::-1].copy(), K, T_left, None, near_far)
    src = KeyframeView(1, right[:, :, ::-1].copy(), K, T_right, None, near_far)
    results = []
    for best_k in (2, 1):
        config = dataclasses.replace(DepthConfig(), best_k=best_k)
        depth_map = DepthEstimator(config, DEVICE).compute(ref, [src])
        kept = depth_map.valid & (depth_left > 0)
        err = np.abs(depth_map.depth_m - depth_left)[kept] * 1e3
        results.append((depth_map.stats["window_radius_px"], int(np.count_nonzero(err < 1.0)), np.mean(err > 1.0)))
    (r_grown, good_grown, bad_grown), (r_small, good_small, bad_small) = results
    assert (r_grown, r_small) == (5, 3)
    assert good_grown > 1.05 * good_small
    assert bad_grown <= bad_small


def test_a_stereo_pair_makes_a_surface_that_covers_most_of_what_both_see(liver_pair):
    """The final build of the two views (each map filled, then checked against the other's): most of the surface
    both views see lies within 1 mm of a fused point, and hardly any fused point lies beyond 5 mm of the true
    surface (issue 22's two-view target: at most 0.5%). Measured on the CPU: 88.6% covered, none beyond 5 mm."""
    from lapreco_hil.dense.surface import DenseSurface
    from scipy.spatial import cKDTree

    camera, left, right, depth_left, depth_right, T_left, T_right = liver_pair
    dense = DenseSurface(camera, PipelineConfig(), DEVICE)
    dense.add_view(0, left, T_left)
    dense.add_view(1, right, T_right)
    poses = {0: T_left, 1: T_right}
    result = dense.build_at(poses, {0: _range(depth_left), 1: _range(depth_right)})
    assert dense.fused == 2
    # the true surface: the left view's pixels the right view sees too (their true depths, back-projected)
    K = camera.K
    v, u = np.nonzero(depth_left > 0)
    z = depth_left[v, u]
    X_left = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
    X_world = (T_left[:3, :3] @ X_left).T + T_left[:3, 3]
    X_right = (np.linalg.inv(T_right) @ np.c_[X_world, np.ones(len(X_world))].T)[:3]
    uv = (K @ X_right)[:2] / X_right[2]
    iu, iv = np.round(uv).astype(int)
    inside = (iu >= 0) & (iu < SIZE[0]) & (iv >= 0) & (iv < SIZE[1])
    seen = np.zeros(len(z), bool)
    seen[inside] = np.abs(depth_right[iv[inside], iu[inside]] - X_right[2, inside]) < 1e-3
    truth = X_world[seen]
    points = result.points
    assert len(points) > 1000
    covered = cKDTree(points).query(truth)[0] < 1e-3
    beyond = cKDTree(X_world).query(points)[0] > 5e-3
    assert covered.mean() >= 0.8, covered.mean()
    assert beyond.mean() <= 0.005, beyond.mean()
