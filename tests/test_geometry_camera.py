import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.geometry import interpolate_pose, inv_T, look_at, make_T, pose_error, to_tum
from lapreco_hil.geometry import Rotation


def random_pose(rng):
    return make_T(Rotation.from_rotvec(rng.normal(0, 1, 3)).as_matrix(), rng.normal(0, 0.1, 3))


def test_inverse_and_interpolation_endpoints(rng):
    T0, T1 = random_pose(rng), random_pose(rng)
    np.testing.assert_allclose(T0 @ inv_T(T0), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T0, T1, 0.0), T0, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T0, T1, 1.0), T1, atol=1e-12)


def test_interpolation_midpoint_is_half_the_relative_rotation(rng):
    T0 = random_pose(rng)
    step = make_T(Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix(), [0.02, 0.0, 0.0])
    mid = interpolate_pose(T0, T0 @ step, 0.5)
    rel = inv_T(T0) @ mid
    assert Rotation.from_matrix(rel[:3, :3]).as_rotvec() == pytest.approx([0, 0, 0.2], abs=1e-12)


def test_tum_line_order_is_t_xyz_then_quaternion_xyzw():
    T = make_T(Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix(), [1, 2, 3])
    fields = [float(v) for v in to_tum(1_500_000_000, T).split()]
    assert fields[:4] == [1.5, 1, 2, 3]
    assert fields[4:] == pytest.approx([0, 0, np.sqrt(0.5), np.sqrt(0.5)], abs=1e-9)


def test_a_tum_lines_time_is_its_integer_nanoseconds_exactly():
    """A ROS bag's wall-clock stamp (1.77e18 ns) written as t * 1e-9 came out 166 ns off in float64."""
    line = to_tum(1765432100123456789, np.eye(4))
    assert line.split()[0] == "1765432100.123456789"
    assert to_tum(-1_500_000_001, np.eye(4)).split()[0] == "-1.500000001"


def test_look_at_gives_an_opencv_camera():
    T = look_at(np.array([0.0, 0, 0]), np.array([0.0, 0, 1]), np.array([0.0, -1, 0]))
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-12)
    assert pose_error(T, T) == (0.0, 0.0)


def paper_distort(xu, yu, k, t, p):
    """The seed paper's equations (1)-(4), written out independently of OpenCV."""
    r2 = xu**2 + yu**2
    radial = k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    dx = radial * xu + 2 * t[0] * xu * yu + t[1] * (3 * xu**2 + yu**2) + p[0] * r2
    dy = radial * yu + t[0] * (xu**2 + 3 * yu**2) + 2 * t[1] * xu * yu + p[1] * r2
    return xu + dx, yu + dy


def test_paper_model_is_the_opencv_subset(rng):
    k, t, p = (-0.28, 0.09, -0.012), (0.0006, -0.0004), (0.0008, -0.0006)
    cam = CameraModel.from_paper_model(640, 480, 450.0, 452.0, 321.0, 238.0, k=k, t=t, p=p)
    pts = np.column_stack([rng.uniform(-0.6, 0.6, 50), rng.uniform(-0.45, 0.45, 50), np.ones(50)])
    uv = cam.project(pts)
    xd, yd = paper_distort(pts[:, 0], pts[:, 1], k, t, p)
    np.testing.assert_allclose(uv[:, 0], 450.0 * xd + 321.0, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], 452.0 * yd + 238.0, atol=1e-9)


def test_undistort_pixels_inverts_projection(rng):
    cam = CameraModel.from_paper_model(640, 480, 450.0, 450.0, 320.0, 240.0, k=(-0.28, 0.09, -0.012),
                                       t=(0.0006, -0.0004), p=(0.0008, -0.0006))
    pts = np.column_stack([rng.uniform(-0.5, 0.5, 100), rng.uniform(-0.4, 0.4, 100), np.ones(100)])
    ideal = pts[:, :2] * 450.0 + [320.0, 240.0]
    np.testing.assert_allclose(cam.undistort_pixels(cam.project(pts)), ideal, atol=1e-6)
    map_x, map_y = cam.undistort_maps()
    assert map_x.shape == (480, 640) and map_x.dtype == np.float32
    assert cv2.remap(np.ones((480, 640), np.uint8), map_x, map_y, cv2.INTER_NEAREST).shape == (480, 640)
