"""Semi-global matching (OpenCV's StereoSGBM) for a two-view depth map's holes: a stereo scope's pair, or a session
of two frames. The project's own depth maps (``dense.depth``) keep a depth only where a window's ZNCC is strong and
no depth edge is near; on a pair with one source that leaves much of the surface empty. SGBM's path costs carry a
depth across weak texture; its depths only enter the holes of the map, at a lower confidence, and the final build's
left-right consistency check (``fuse_pending(consistent=True)``) keeps only those the other view's map confirms.

The two views are undistorted to one pinhole ``K`` (``KeyframeView``); they are rectified for their relative pose
here, matched, and the disparity is taken back to the reference view's own pixels (nearest disparity sample: no
interpolation across depth edges)."""

from __future__ import annotations

import cv2
import numpy as np

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.types import DepthMap, KeyframeView

SGBM_CONFIDENCE = 0.3  # a filled depth's confidence (fusion weight); the project's own depths carry their ZNCC
SGBM_BLOCK_PX = 5
# a disparity below this (px) is too far to tell from infinity, or SGBM's "no match"
MIN_DISPARITY_PX = 0.5
# SGBM's errors gather at depth edges (a window across a silhouette takes the foreground's disparity): no depth
# within EDGE_PX of a disparity step over EDGE_STEP_PX, or of a pixel without a disparity (on the rendered pairs of
# docs/dense.md, "Two views": beyond 5 mm of the truth 2.0 -> 0.1% of its depths)
EDGE_PX = 6
EDGE_STEP_PX = 1.0


def highlights(colour: np.ndarray, config: DepthConfig) -> np.ndarray:
    """Saturated specular highlights (``[depth] highlight_*``, as the depth maps exclude them): they move with the
    light, so no two views agree on them."""
    c = np.asarray(colour, np.float32) / 255.0
    top, bottom = c.max(axis=2), c.min(axis=2)
    flat = (top - bottom) <= config.highlight_saturation * np.maximum(top, 1e-6)
    mask = ((top >= config.highlight_value) & flat).astype(np.uint8)
    r = config.highlight_dilate_px
    if r > 0 and mask.any():
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)


def sgbm_depth(ref: KeyframeView, src: KeyframeView, depth_range_m: tuple[float, float],
               config: DepthConfig | None = None) -> DepthMap | None:
    """``ref``'s depth (z in its camera, metres; 0 where unknown) from SGBM against ``src``, searched over the
    disparities of ``depth_range_m`` (near, far), none on ``ref``'s highlights; None when the two views have no
    side-by-side baseline to rectify."""
    config = config or DepthConfig()
    K = np.asarray(ref.K, float)
    h, w = ref.colour.shape[:2]
    T_src_ref = np.linalg.inv(np.asarray(src.T_world_camera, float)) @ np.asarray(ref.T_world_camera, float)
    baseline = float(np.linalg.norm(T_src_ref[:3, 3]))
    if baseline <= 0.0 or not np.isfinite(baseline):
        return None
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(K, np.zeros(5), K, np.zeros(5), (w, h), T_src_ref[:3, :3],
                                                T_src_ref[:3, 3], flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        return None  # a vertical baseline: rectified rows would be columns (not a side-by-side pair)
    f = float(P1[0, 0])
    grey = []
    for view, R, P in ((ref, R1, P1), (src, R2, P2)):
        mx, my = cv2.initUndistortRectifyMap(K, None, R, P, (w, h), cv2.CV_32FC1)
        image = cv2.remap(np.ascontiguousarray(view.colour), mx, my, cv2.INTER_LINEAR)
        grey.append(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    near, far = depth_range_m
    d_max = f * baseline / max(near, 1e-4)
    d_min = f * baseline / max(far, near + 1e-4)
    # SGBM searches [min, min + num): num a multiple of 16; ref on the left unless src lies to its left
    ref_left = P2[0, 3] < 0
    lo = max(int(np.floor(d_min)) - 2, 0)
    num = int(np.ceil((d_max - lo + 2) / 16.0)) * 16
    if num <= 0 or num > w:
        num = min(max(num, 16), (w // 16) * 16)
    sgbm = cv2.StereoSGBM_create(lo, num, SGBM_BLOCK_PX, P1=8 * SGBM_BLOCK_PX ** 2, P2=32 * SGBM_BLOCK_PX ** 2,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1,
                                 mode=cv2.STEREO_SGBM_MODE_HH)
    a, b = grey
    if ref_left:
        disparity = sgbm.compute(a, b).astype(np.float32) / 16.0
    else:  # mirrored, the reference becomes the left view
        disparity = sgbm.compute(a[:, ::-1].copy(), b[:, ::-1].copy()).astype(np.float32)[:, ::-1] / 16.0
    # each reference pixel's place in the rectified image, and the disparity there
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T @ R1.T
    Kr = P1[:3, :3]
    pr = rays @ Kr.T
    ur, vr = pr[..., 0] / pr[..., 2], pr[..., 1] / pr[..., 2]
    valid = (disparity > MIN_DISPARITY_PX).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * EDGE_PX + 1, 2 * EDGE_PX + 1))
    spread = cv2.dilate(disparity, kernel) - cv2.erode(np.where(valid > 0, disparity, 1e6).astype(np.float32), kernel)
    disparity = np.where((cv2.erode(valid, kernel) > 0) & (spread <= EDGE_STEP_PX), disparity, 0.0).astype(np.float32)
    d = cv2.remap(disparity, ur.astype(np.float32), vr.astype(np.float32), cv2.INTER_NEAREST,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    ok = (d > MIN_DISPARITY_PX) & (rays[..., 2] > 0)
    z_rect = np.where(ok, f * baseline / np.where(ok, d, 1.0), 0.0)
    # the point on the pixel's ray at that depth in the rectified frame, back in the reference camera (R1^T x)
    X_rect = rays / np.where(ok, rays[..., 2], 1.0)[..., None] * z_rect[..., None]
    z = (X_rect @ R1)[..., 2]
    inside = ok & (z >= near) & (z <= far)
    if ref.mask is not None:
        inside &= np.asarray(ref.mask, bool)
    inside &= ~highlights(ref.colour, config)
    depth = np.where(inside, z, 0.0).astype(np.float32)
    confidence = np.where(inside, SGBM_CONFIDENCE, 0.0).astype(np.float32)
    return DepthMap(ref.kf_id, depth, confidence, K, np.asarray(ref.T_world_camera, float),
                    {"sgbm_depths": int(np.count_nonzero(depth)), "sgbm_disparities": [lo, lo + num]})


def fill_from(depth: DepthMap, other: DepthMap) -> DepthMap:
    """``depth`` with its holes taken from ``other`` (same view and size), at ``other``'s confidence."""
    hole = (depth.depth_m <= 0) & (other.depth_m > 0)
    stats = dict(depth.stats or {})
    stats["sgbm_filled"] = int(np.count_nonzero(hole))
    return DepthMap(depth.kf_id, np.where(hole, other.depth_m, depth.depth_m).astype(np.float32),
                    np.where(hole, other.confidence, depth.confidence).astype(np.float32), depth.K,
                    depth.T_world_camera, stats)
