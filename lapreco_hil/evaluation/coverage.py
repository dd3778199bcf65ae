"""How much of a true surface the cameras saw, and how much of that a reconstruction covers: samples spread by
area over the true surface, the ones some camera had in view, and the share of those with a reconstructed point
within a radius. One function for the sparse points (``lapreco evaluate``, after ICP) and the dense surface.

"In view" is what the real camera sees (``camera_view``): a ray its distortion model projects into its own image,
inside its field of view. A pinhole image of the same K and size (what the app undistorts to) leaves out the
outer band of a barrel-distorted frame, and a surface seen only there would not count against a reconstruction.
"""

from __future__ import annotations

import cv2
import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from lapreco_hil.camera import CameraModel, pinhole_canvas

# the samples' own z-buffer, each sample splatted over a disc 4 sample spacings wide (a gap in the front surface's
# samples would let a hidden one show through); a sample within 3 splat radii (a 72-degree slope) of the nearest
# depth at its pixel is visible. Checked against the renderer's exact visibility in docs/dense.md
OCCLUSION_SPLAT_SPACINGS = 4.0
OCCLUSION_SLOPE = 3.0


def sample_surface(surface: pv.PolyData, spacing_m: float, max_points: int = 300_000, seed: int = 0) -> np.ndarray:
    """Points spread uniformly by area over the surface, about ``spacing_m`` apart."""
    tri = surface.triangulate()
    faces = tri.faces.reshape(-1, 4)[:, 1:]
    v = np.asarray(tri.points, float)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    n = int(min(max_points, max(1000, area.sum() / spacing_m**2)))
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(area), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * a[idx] + (s * (1 - r2))[:, None] * b[idx] + (s * r2)[:, None] * c[idx]
    return pts


# the canvas of camera_view grows by at most this share of the image's size on each side (a lens model whose edge
# rays undistort to enormous angles would otherwise ask for a canvas of millions of pixels)
CANVAS_MAX_PAD = 1.0


def camera_view(camera: CameraModel) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """What ``camera`` sees, as a pinhole image (``visible_samples``' K, size and mask): the camera's focal
    lengths, a size that holds its whole field of view undistorted, and a mask of the rays it sees (projected
    with its distortion into its image, inside its field of view, before any fold of the lens model:
    ``CameraModel.seen_region``). A camera without distortion is its own image and field of view."""
    fov = camera.fov_mask() > 0
    if not np.any(camera.dist_array):
        return camera.K, (camera.width, camera.height), fov
    K, size = pinhole_canvas([camera], CANVAS_MAX_PAD)
    map_x, map_y = camera.undistort_maps(K, size)
    return K, size, camera.seen_region(map_x, map_y)


def visible_samples(samples: np.ndarray, poses: np.ndarray, K: np.ndarray, size: tuple,
                    near_m: float = 0.01, far_m: float = 0.3, max_views: int = 60, mask: np.ndarray | None = None,
                    occlusion_m: float | None = None, spacing_m: float | None = None) -> np.ndarray:
    """Which true-surface samples some camera had in view: in front of it, inside the pinhole image of ``K``
    and ``size`` (and inside ``mask``, bool H x W, where given: the scope's field of view), within range. A real
    camera's view is ``camera_view(camera)``'s K, size and mask. With ``occlusion_m`` (and the
    samples' ``spacing_m``) a sample farther than that, plus the slope allowance, behind the nearest sample in
    its z-buffer cell is hidden; without, surfaces hidden behind others count as visible and the coverage is a
    lower bound."""
    seen = np.zeros(len(samples), bool)
    step = max(1, len(poses) // max_views)
    w, h = size
    for T in poses[::step]:
        R, t = T[:3, :3], T[:3, 3]
        pc = (samples - t) @ R
        z = pc[:, 2]
        ok = (z > near_m) & (z < far_m)
        uv = pc[ok, :2] / z[ok, None] @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx, uv = np.flatnonzero(ok)[inside], uv[inside]
        if mask is not None:
            keep = mask[uv[:, 1].astype(int), uv[:, 0].astype(int)]
            idx, uv = idx[keep], uv[keep]
        if occlusion_m is not None and len(idx):
            zi = z[idx]
            spacing_px = spacing_m * K[0, 0] / float(np.median(zi))
            radius_px = max(1, int(np.ceil(0.5 * OCCLUSION_SPLAT_SPACINGS * spacing_px)))
            px = np.clip(uv.astype(np.int64), 0, [w - 1, h - 1])
            zbuf = np.full((h, w), np.inf, np.float32)
            np.minimum.at(zbuf, (px[:, 1], px[:, 0]), zi.astype(np.float32))
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2)
            nearest = cv2.erode(zbuf, disc, borderType=cv2.BORDER_REPLICATE)[px[:, 1], px[:, 0]]
            allowance = occlusion_m + OCCLUSION_SLOPE * radius_px * nearest / K[0, 0]
            idx = idx[zi <= nearest + allowance]
        seen[idx] = True
    return seen


def covered_fraction(points: np.ndarray, samples: np.ndarray, radius_m: float) -> float:
    """The share of ``samples`` with one of ``points`` within ``radius_m``."""
    if len(samples) == 0:
        return float("nan")
    if len(points) == 0:
        return 0.0
    d, _ = cKDTree(np.asarray(points, float)).query(samples, distance_upper_bound=radius_m)
    return float(np.mean(np.isfinite(d)))
