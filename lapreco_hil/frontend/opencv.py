"""The OpenCV front-end: undistort (remap), pyramidal Lucas-Kanade, Shi-Tomasi with a minimum distance to
live tracks and the scope's field-of-view mask. It is the seed paper's CPU baseline."""

from __future__ import annotations

import time

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.types import Frame, Observations
from lapreco_hil.frontend.drift import AffineDriftCheck


def remove_shading(gray: np.ndarray, sigma_px: float) -> np.ndarray:
    """Log-domain high-pass (float32): image = albedo x shading, and the scope-tip light makes the shading move
    with the camera, which breaks brightness constancy and makes tracks drift. Subtracting the blurred log
    image keeps the texture (albedo) and drops the smooth shading."""
    log = np.log1p(gray.astype(np.float32))
    return log - cv2.GaussianBlur(log, (0, 0), sigma_px)


# 8-bit levels per unit of the log high-pass when the baseline tracks it as an 8-bit image
HIGHPASS_GAIN = 96.0


def to_u8(high: np.ndarray) -> np.ndarray:
    return np.clip(high * HIGHPASS_GAIN + 128.0, 0, 255).astype(np.uint8)


class OpenCVFrontEnd:
    def __init__(self, camera: CameraModel, config: TrackerConfig) -> None:
        self.camera = camera
        self.config = config
        self._map_x, self._map_y = camera.undistort_maps()
        fov = camera.fov_mask(margin_px=config.fov_margin_px)
        # the mask in undistorted coordinates: a pixel is usable if its source lies inside the field of view
        self.mask = cv2.remap(fov, self._map_x, self._map_y, cv2.INTER_NEAREST, borderValue=0)
        self._prev: np.ndarray | None = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0
        self.drift = (AffineDriftCheck(config.drift_patch_px, max_residual=config.drift_max_residual)
                      if config.drift_check else None)
        self._ref = np.zeros((0, config.drift_patch_px**2), np.float32)
        self._A = np.zeros((0, 2, 2))
        w = config.window_px
        self._lk = dict(winSize=(w, w), maxLevel=config.pyramid_levels,
                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))

    def _inside(self, pts: np.ndarray) -> np.ndarray:
        xi = np.clip(np.round(pts[:, 0]).astype(int), 0, self.camera.width - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(int), 0, self.camera.height - 1)
        inb = (pts[:, 0] >= 0) & (pts[:, 0] < self.camera.width) & (pts[:, 1] >= 0) & (pts[:, 1] < self.camera.height)
        return inb & (self.mask[yi, xi] > 0)

    def process(self, frame: Frame, motion=None) -> Observations:
        cfg = self.config
        t0 = time.perf_counter()
        color = cv2.remap(frame.image, self._map_x, self._map_y, cv2.INTER_LINEAR)
        gray = cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
        # too dark to carry texture (the cavity beyond the light's reach): no detections there
        lit = cv2.blur(gray, (15, 15)) >= cfg.min_brightness
        if cfg.shading_sigma_px > 0:
            intensity = remove_shading(gray, cfg.shading_sigma_px)
            gray = to_u8(intensity)
        else:
            intensity = gray.astype(np.float32) / 255.0
        t1 = time.perf_counter()
        if self._prev is not None and len(self._pts):
            nxt, status, err = cv2.calcOpticalFlowPyrLK(self._prev, gray, self._pts.reshape(-1, 1, 2), None,
                                                        **self._lk)
            nxt = nxt.reshape(-1, 2)
            keep = (status.ravel() == 1) & (err.ravel() < cfg.max_lk_error) & self._inside(nxt)
            self._filter(keep, nxt)
        t2 = time.perf_counter()
        if self.drift is not None and len(self._pts):
            gx = cv2.Sobel(intensity, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
            gy = cv2.Sobel(intensity, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
            reg = self.drift.register(intensity, gx, gy, self._ref, self._A, self._pts.astype(np.float64))
            self._A = reg.A
            keep = reg.keep & self._inside(reg.positions)
            self._filter(keep, reg.positions.astype(np.float32))
        t_drift = time.perf_counter()
        n_new = 0
        if len(self._pts) < cfg.redetect_below * cfg.max_features:
            mask = self.mask.copy()
            mask[~lit] = 0
            for x, y in self._pts:
                cv2.circle(mask, (int(round(x)), int(round(y))), int(cfg.min_distance_px), 0, -1)
            want = cfg.max_features - len(self._pts)
            corners = cv2.goodFeaturesToTrack(gray, maxCorners=want, qualityLevel=cfg.quality_level,
                                              minDistance=cfg.min_distance_px, mask=mask, blockSize=cfg.block_size)
            if corners is not None:
                corners = corners.reshape(-1, 2)
                n_new = len(corners)
                self._pts = np.vstack([self._pts, corners]).astype(np.float32)
                self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n_new)])
                self._next_id += n_new
                if self.drift is not None:
                    self._ref = np.vstack([self._ref, self.drift.reference_patches(intensity, corners)])
                    self._A = np.concatenate([self._A, np.repeat(np.eye(2)[None], n_new, 0)])
        t3 = time.perf_counter()
        self._prev = gray
        xi = np.clip(np.round(self._pts[:, 0]).astype(int), 0, self.camera.width - 1)
        yi = np.clip(np.round(self._pts[:, 1]).astype(int), 0, self.camera.height - 1)
        colors = color[yi, xi, ::-1].copy()
        return Observations(frame.seq, frame.t_ns, self._ids.copy(), self._pts.astype(np.float64), colors, n_new,
                            {"undistort": t1 - t0, "track": t2 - t1, "drift_check": t_drift - t2,
                             "detect": t3 - t_drift})

    def _filter(self, keep: np.ndarray, positions: np.ndarray) -> None:
        self._pts, self._ids = positions[keep], self._ids[keep]
        if self.drift is not None:
            self._ref, self._A = self._ref[keep], self._A[keep]
