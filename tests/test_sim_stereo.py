"""The simulated stereo scope (``sim://SCENE?stereo=1``): camera 1 is rendered where the rig's extrinsic puts
it, with its own intrinsics; camera 0, the ground truth and the mono path are what they were."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import transform_points
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot

W, H = 480, 360


def _grabber(query: str = "", warp_device: str = "cpu"):
    g = open_grabber(f"sim://skull?width={W}&height={H}&device={warp_device}{query}", DeviceContext())
    g.open()
    return g


def _visible_points(depth: np.ndarray, camera, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(pixels, camera-frame points) of ``n`` surface points camera 0 sees, in the middle of its view."""
    rows, cols = np.nonzero(depth > 0)
    central = np.hypot(cols - camera.cx, rows - camera.cy) < 0.45 * camera.fov_radius_px
    rows, cols = rows[central], cols[central]
    pick = np.random.default_rng(seed).choice(len(rows), n, replace=False)
    uv = np.column_stack([cols[pick], rows[pick]]).astype(float)
    ideal = camera.undistort_pixels(uv)
    rays = np.column_stack([(ideal[:, 0] - camera.cx) / camera.fx, (ideal[:, 1] - camera.cy) / camera.fy,
                            np.ones(n)])
    return uv, rays * depth[rows[pick], cols[pick], None]


def _match(left: np.ndarray, right: np.ndarray, uv0: np.ndarray, guess: np.ndarray, half: int = 8,
           search: int = 5) -> tuple[np.ndarray, float]:
    """Where the left image's patch about pixel uv0 (integer) lies in the right image near ``guess``: sub-pixel
    (parabola through the correlation peak), with its normalised correlation."""
    x0, y0 = (int(v) for v in uv0)
    patch = left[y0 - half: y0 + half + 1, x0 - half: x0 + half + 1]
    gx, gy = (int(round(v)) for v in guess)
    area = right[gy - half - search: gy + half + search + 1, gx - half - search: gx + half + search + 1]
    score = cv2.matchTemplate(area, patch, cv2.TM_CCOEFF_NORMED)
    py, px = np.unravel_index(np.argmax(score), score.shape)
    sub = []
    for axis, p in ((1, px), (0, py)):
        line = score[py, :] if axis == 1 else score[:, px]
        if 0 < p < len(line) - 1:
            a, b, c = line[p - 1], line[p], line[p + 1]
            sub.append(p + 0.5 * (a - c) / (a - 2 * b + c))
        else:
            sub.append(float(p))
    return np.array([gx - search + sub[0], gy - search + sub[1]]), float(score[py, px])


@pytest.mark.parametrize("right_focal_scale", [1.0, 1.02])
def test_the_right_view_shows_a_surface_point_where_the_rig_projects_it(warp_cpu, right_focal_scale):
    g = _grabber(f"&stereo=1&baseline_mm=5&right_focal_scale={right_focal_scale}", warp_cpu)
    frame = g.read()
    rig = g.rig
    cam0, cam1 = rig.cameras
    assert rig.is_stereo and rig.baseline_m() == pytest.approx(0.005)
    assert cam1.fx == pytest.approx(cam0.fx * right_focal_scale) and cam1.cx == cam0.cx
    np.testing.assert_allclose(rig.T_cam0_cam[1][:3, 3], [0.005, 0.0, 0.0])  # to the right, along camera 0's x
    # the visible surface of camera 0 (its depth, the renderer's), on the true surface
    T_world_cam0 = g.ground_truth.camera_pose(frame.t_ns)
    (_, depth0), (_, depth1) = g.world.render_rig(frame.t_ns, frame.seq, rig)
    uv0, X0 = _visible_points(depth0, cam0, 200)
    X1 = transform_points(np.linalg.inv(rig.T_cam0_cam[1]), X0)
    uv1 = cam1.project(X1)
    # camera 1's depth where the rig puts the point is the point's depth in camera 1 (bilinear between pixel
    # centres; a few points sit on a fold of the skull where that blends two surfaces)
    sampled = cv2.remap(depth1, uv1[:, None, 0].astype(np.float32), uv1[:, None, 1].astype(np.float32),
                        cv2.INTER_LINEAR).ravel()
    off = np.abs(sampled - X1[:, 2])
    assert np.median(off) < 1e-5 and np.percentile(off, 90) < 5e-5, off
    if right_focal_scale == 1.0:
        # rectified by construction (parallel cameras, one lens): the disparity of the ideal pinhole pixels is
        # baseline x f / depth, and rows agree
        d = cam0.undistort_pixels(uv0) - cam1.undistort_pixels(uv1)
        np.testing.assert_allclose(d[:, 0], 0.005 * cam0.fx / X0[:, 2], atol=1e-6)
        np.testing.assert_allclose(d[:, 1], 0.0, atol=1e-6)
        assert np.median(d[:, 0]) > 10  # (a disparity a camera-0 render at the same pose would miss)
    # the right IMAGE shows the left image's texture there: each patch found within 0.5 px of where the rig says
    left = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY).astype(np.float32)
    right = cv2.cvtColor(frame.views[0], cv2.COLOR_BGR2GRAY).astype(np.float32)
    errors = []
    for p0, p1 in zip(uv0, uv1):
        window = np.s_[int(p0[1]) - 8: int(p0[1]) + 9, int(p0[0]) - 8: int(p0[0]) + 9]
        patch, patch_depth = left[window], depth0[window]
        # a patch locates its centre by correlation where it has texture and lies on a smooth piece of surface
        # (not across a fold, where the two viewpoints see different things)
        if patch.std() < 6 or patch_depth.min() <= 0 or patch_depth.std() > 0.01 * patch_depth.mean():
            continue
        found, score = _match(left, right, p0, p1)
        if score > 0.9:
            errors.append(np.linalg.norm(found - p1))
    assert len(errors) >= 15
    # (measured: median 0.15 px, 90th percentile 0.39 px; a baseline off by 10 % moves them by over 1 px)
    assert np.median(errors) < 0.25 and np.percentile(errors, 90) < 0.5, np.round(errors, 2)


def test_stereo_keeps_camera_0_the_ground_truth_and_the_mono_path(warp_cpu):
    mono = _grabber("", warp_cpu)
    stereo = _grabber("&stereo=1", warp_cpu)
    for _ in range(2):
        a, b = mono.read(), stereo.read()
        assert a.views == () and len(b.views) == 1
        np.testing.assert_array_equal(a.image, b.image)  # camera 0 renders exactly what the mono scope does
        assert (a.t_ns, a.seq) == (b.t_ns, b.seq)
        np.testing.assert_array_equal(mono.ground_truth.camera_pose(a.t_ns), stereo.ground_truth.camera_pose(b.t_ns))
        assert np.mean(np.abs(b.views[0].astype(int) - b.image.astype(int))) > 5  # another viewpoint
    assert len(mono.rig) == 1 and mono.rig.cameras[0] == mono.camera == stereo.rig.cameras[0]
    assert stereo.rig.baseline_m() == pytest.approx(0.005)  # the default baseline


@pytest.mark.parametrize("optics", [0, 30])
def test_both_cameras_look_along_the_scope_s_viewing_angle(warp_cpu, optics):
    ctx = DeviceContext()
    robot = open_robot(f"sim://skull?width={W}&height={H}&device={warp_cpu}&optics={optics}", ctx)
    g = open_grabber(f"sim://skull?width={W}&height={H}&device={warp_cpu}&optics={optics}&stereo=1", ctx)
    assert robot.world is g.world
    T_tip_cam0 = robot.description.T_tip_camera
    for T_cam0_cam in g.rig.T_cam0_cam:
        axis = (T_tip_cam0 @ T_cam0_cam)[:3, 2]  # the camera's optical axis in the scope tip's frame
        assert np.degrees(np.arccos(np.clip(axis @ [0.0, 0.0, 1.0], -1, 1))) == pytest.approx(optics, abs=1e-9)


def test_stereo_url_errors_are_one_line(warp_cpu):
    ctx = DeviceContext()
    for query, words in (("baseline_mm=5", "baseline_mm= describes a stereo scope; add stereo=1"),
                         ("stereo=1&baseline_mm=90", "baseline_mm must be in 0.5..30 mm, got 90"),
                         ("stereo=maybe", "'stereo=maybe' must be true or false"),
                         ("optics=90", "optics must be in 0..70 deg, got 90")):
        with pytest.raises(ConfigError) as info:
            open_grabber(f"sim://skull?device={warp_cpu}&{query}", ctx)
        assert words in str(info.value) and "\n" not in str(info.value), query
