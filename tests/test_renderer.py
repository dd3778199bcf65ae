"""The Warp ray-casting renderer, on the CPU device: a rendered surface point projects where the camera
model says, the scope's field of view is dark outside its circle, and highlights move with the camera."""

import numpy as np
import pytest

from lapreco_hil.evaluation.accuracy import surface_distances
from lapreco_hil.geometry import transform_points


@pytest.fixture(scope="module")
def world(skull_world):
    return skull_world


def test_rendered_depth_backprojects_onto_the_true_surface_and_reprojects_to_its_pixel(world):
    t = world.now_ns()
    T = world.true_camera_pose(t)
    _, depth = world.render(t, 0)
    rows, cols = np.nonzero(depth > 0)
    pick = np.random.default_rng(0).choice(len(rows), 200, replace=False)
    uv = np.column_stack([cols[pick], rows[pick]]).astype(float)
    cam = world.camera
    ideal = cam.undistort_pixels(uv)
    rays = np.column_stack([(ideal[:, 0] - cam.cx) / cam.fx, (ideal[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))])
    Xc = rays * depth[rows[pick], cols[pick], None]
    Xw = transform_points(T, Xc)
    assert np.percentile(surface_distances(Xw, world.surface_mesh()), 95) < 2e-5  # 20 um: on the mesh
    np.testing.assert_allclose(cam.project(Xc), uv, atol=1e-3)


def test_field_of_view_is_circular_and_dark_outside(world):
    image, _ = world.render(world.now_ns(), 1)
    cam = world.camera
    yy, xx = np.mgrid[: cam.height, : cam.width]
    outside = np.hypot(xx - cam.cx, yy - cam.cy) > cam.fov_radius_px + 2
    assert outside.any()
    assert image[outside].mean() < 3  # sensor noise only
    assert image[~outside].mean() > 20


def test_highlight_moves_with_the_camera(world):
    """With the light at the scope tip, the brightest spot follows the camera, not the surface."""
    t0 = world.now_ns()
    t1 = t0 + 2_000_000_000
    bright = []
    for t in (t0, t1):
        img, _ = world.render(t, 2)
        g = img.astype(float).sum(2)
        bright.append(np.unravel_index(np.argmax(np.convolve(g.ravel(), np.ones(9), "same").reshape(g.shape)),
                                       g.shape))
    assert bright[0] != bright[1]


def test_noise_is_seeded_per_frame(world):
    t = world.now_ns()
    a, _ = world.render(t, 5)
    b, _ = world.render(t, 5)
    c, _ = world.render(t, 6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
