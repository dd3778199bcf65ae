"""Alpha-shape meshing of the inlier landmarks (the seed, after Wengert, used CGAL's alpha shapes; VTK's
Delaunay with an alpha radius computes the same complex)."""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour."""
    if len(points) < 2:
        return 0.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def alpha_shape(points: np.ndarray, colors: np.ndarray | None, alpha_factor: float) -> pv.PolyData:
    """Boundary of the alpha complex with alpha = alpha_factor x median point spacing; empty if < 4 points.
    Per-point colours (uint8 RGB) are carried onto the mesh vertices as 'RGB'."""
    if len(points) < 4:
        return pv.PolyData()
    cloud = pv.PolyData(np.asarray(points, dtype=np.float64))
    if colors is not None:
        cloud.point_data["RGB"] = np.asarray(colors, np.uint8)
    alpha = alpha_factor * point_spacing(points)
    volume = cloud.delaunay_3d(alpha=alpha, tol=1e-6)
    surface = volume.extract_surface(algorithm="dataset_surface", pass_pointid=False, pass_cellid=False).triangulate().clean()
    return surface


def thin_points(points: np.ndarray, colors: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points``, spread evenly over the cloud: one point per voxel, the voxel grown until few
    enough remain (the live surface's cost grows faster than linearly with its points)."""
    if len(points) <= max_points:
        return points, colors
    lo = points.min(axis=0)
    extent = float(np.max(points.max(axis=0) - lo)) or 1.0
    voxel = extent / max(max_points, 1) ** (1 / 2)  # a surface: points scale with area
    keep = np.arange(len(points))
    for _ in range(30):
        cells = np.floor((points - lo) / voxel).astype(np.int64)
        dims = cells.max(axis=0) + 1
        _, keep = np.unique((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2], return_index=True)
        if len(keep) <= max_points:
            break
        voxel *= 1.25
    keep = np.sort(keep[:max_points])
    return points[keep], colors[keep]
