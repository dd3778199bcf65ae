"""The OpenCV front-end: undistort (remap), pyramidal Lucas-Kanade (started where the camera motion predicts,
when it is known; without it, the tracks' consensus: ``frontend.consensus``), Shi-Tomasi with a minimum distance to live tracks and the scope's field-of-view mask. It is
the seed paper's CPU baseline.

With a stereo rig (``match_view`` called) and fast image motion, a new track the drift check refuses at its first
step is judged again on the tracker image smoothed by ``TrackerConfig.rescue_smoothing_px`` against its first
patch taken there, and once kept it stays registered there (``_drift_check``)."""

from __future__ import annotations

import time

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.types import Frame, FrameMotion, Observations
from lapreco_hil.frontend import consensus, epipolar, stereo_depth
from lapreco_hil.frontend.global_motion import GlobalMotion
from lapreco_hil.frontend.drift import AffineDriftCheck, drift_image, gradients
from lapreco_hil.frontend.image import prior_levels, pyramid_levels, tracker_image


class OpenCVFrontEnd:
    def __init__(self, camera: CameraModel, config: TrackerConfig) -> None:
        self.camera = camera
        self.config = config
        self._map_x, self._map_y = camera.undistort_maps()
        fov = camera.fov_mask(margin_px=config.fov_margin_px)
        # the mask in undistorted coordinates: a pixel is usable if its source lies inside the field of view
        self.mask = cv2.remap(fov, self._map_x, self._map_y, cv2.INTER_NEAREST, borderValue=0)
        self._prev: np.ndarray | None = None
        self._prev_float: np.ndarray | None = None
        self._last: tuple[int, int] = (0, 0)  # the last processed frame's (seq, t_ns)
        self._depth_range = FrameMotion(np.eye(4)).depth_range_m  # the last motion's, for match_view
        self._views: dict[CameraModel, tuple[np.ndarray, np.ndarray]] = {}  # other cameras' undistortion maps
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0
        self._stereo_prior = (self._ids, self._pts, None)  # the last frame's tracks and motion, for match_view
        self.drift = (AffineDriftCheck(config.drift_patch_px, max_residual=config.drift_max_residual)
                      if config.drift_check else None)
        self._ref = np.zeros((0, config.drift_patch_px**2), np.float32)
        self._A = np.zeros((0, 2, 2))
        # the rescue's state, per track: its first patch on the smoothed image (kept only with a rig), drift checks
        # passed, and whether it is registered on the smoothed image; _rig: match_view was called (a stereo rig)
        self._ref_smooth = np.zeros((0, config.drift_patch_px**2), np.float32)
        self._age = np.zeros(0, np.int32)
        self._smoothed = np.zeros(0, bool)
        self._rig = False
        self.levels = pyramid_levels(config, camera.width, camera.height)
        self._prior_levels = prior_levels(config, camera.width, camera.height)  # LK from the global prior
        self._lk = epipolar.lk_params(config.window_px, self.levels)
        # frames without a pose prediction: the image motion from a dense alignment (frontend.global_motion),
        # and the tracks' consensus homography of the last frame (a seed of the next alignment)
        self._global = GlobalMotion(camera.width, camera.height) if config.global_motion_prior else None
        self._consensus_H: np.ndarray | None = None

    def _inside(self, pts: np.ndarray) -> np.ndarray:
        xi = np.clip(np.round(pts[:, 0]).astype(int), 0, self.camera.width - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(int), 0, self.camera.height - 1)
        inb = (pts[:, 0] >= 0) & (pts[:, 0] < self.camera.width) & (pts[:, 1] >= 0) & (pts[:, 1] < self.camera.height)
        return inb & (self.mask[yi, xi] > 0)

    def _predict(self, motion: FrameMotion, depth: np.ndarray, intensity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each track starts LK in the new frame (NaN: not found along its epipolar line, so lost), and
        which were searched along their line (no depth known)."""
        self._depth_range = motion.depth_range_m
        guess = epipolar.predict(self._pts.astype(np.float64), depth, self._prev_float, intensity, self.camera.K,
                                 np.asarray(motion.T_cur_prev, np.float64), motion.depth_range_m)
        return guess, ~np.isfinite(depth)

    def process(self, frame: Frame, motion: FrameMotion | None = None) -> Observations:
        cfg = self.config
        self._stereo_prior = (self._ids, self._pts, motion)  # (arrays replaced, never written in place)
        depth = (epipolar.start_depths(self._pts, self._ids, motion, self.camera.K,
                                       (self.camera.width, self.camera.height)) if motion is not None else None)
        given = motion is not None
        if depth is None:
            motion = None  # a small motion: tracked as without one
        budget, lk_levels = cfg.max_features, self.levels
        if motion is not None:
            size = (self.camera.width, self.camera.height)
            budget, lk_levels = epipolar.prediction_plan(cfg, self.levels, size, self._pts, self._ids, depth, motion,
                                                         self.camera.K)
        t0 = time.perf_counter()
        color = cv2.remap(frame.image, self._map_x, self._map_y, cv2.INTER_LINEAR)
        gray = cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
        # too dark to carry texture (the cavity beyond the light's reach): no detections there
        lit = cv2.blur(gray, (15, 15)) >= cfg.min_brightness
        # only a frame without a motion is aligned (with the last frame, when that had none either); a small one
        # given by the pose source is not: the image barely moved, the tracks start where they were
        prior = None
        if self._global is not None:
            if not given:
                prior = self._global.estimate(gray, () if self._consensus_H is None else (self._consensus_H,))
            else:
                self._global.forget()
        self._consensus_H = None
        gray, intensity = tracker_image(gray, cfg, self.levels)
        t1 = time.perf_counter()
        n_lk = 0
        searched = np.zeros(len(self._pts), bool)
        levels = self.levels
        before = self._pts  # each track's position in the previous frame (the rescue's forward-backward check)
        fast = False  # the tracks moved at least fast_motion_px (median LK step): the rescue's frames
        if self._prev is not None and len(self._pts):
            pts = self._pts.reshape(-1, 1, 2)
            if motion is None:
                guess = None
                if prior is not None:
                    # every track starts where the frame's image motion puts it (LK on the levels that reach the
                    # prior's error from there)
                    guess = cv2.perspectiveTransform(pts.astype(np.float64), prior).astype(np.float32)
                    levels = self._prior_levels
                nxt, status, err = self._track(gray, pts, guess, levels)
                predicted = np.ones(len(pts), bool)
            else:
                guess, searched = self._predict(motion, depth, intensity)
                predicted = np.isfinite(guess).all(axis=1)
                guess = np.where(predicted[:, None], guess, self._pts).astype(np.float32).reshape(-1, 1, 2)
                levels = lk_levels
                nxt, status, err = self._track(gray, pts, guess, levels)
            nxt = nxt.reshape(-1, 2)
            tracked = (status.ravel() == 1) & (err.ravel() < cfg.max_lk_error)
            if motion is None and cfg.consensus_px > 0:
                self._consensus_H = consensus.homography(self._pts, nxt, tracked, cfg.consensus_px)
                nxt, tracked = consensus.retrack_to(self._consensus_H, self._pts, nxt, tracked, cfg.consensus_px,
                                                    lambda rows, starts: self._track_again(gray, rows, starts))
            keep = predicted & tracked & self._inside(nxt)
            if searched.any():
                # a match found along its epipolar line (a wide baseline) must track back to where it was
                back = epipolar.lk_params(cfg.window_px, levels)
                keep &= ~searched | epipolar.tracks_back(gray, self._prev, nxt, self._pts, back)
            n_lk = int(keep.sum())
            before = self._pts[keep]
            steps = np.linalg.norm(nxt[keep] - before, axis=1)
            fast = len(steps) > 0 and float(np.median(steps)) >= cfg.fast_motion_px
            self._filter(keep, nxt)
            searched = searched[keep]
        t2 = time.perf_counter()
        registered = drift_image(intensity, cfg.drift_smoothing_px) if self.drift is not None else intensity
        smoothed = drift_image(intensity, cfg.rescue_smoothing_px) if self._rescues() else None
        if self.drift is not None and len(self._pts):
            back = epipolar.lk_params(cfg.window_px, levels)
            positions, keep = self._drift_check(registered, smoothed, searched, self._rig and fast,
                                                lambda uv, rows: epipolar.tracks_back(gray, self._prev, uv,
                                                                                      before[rows], back))
            anew = searched & ~keep
            if anew.any():
                # across a wide baseline the first patch's affine model may no longer hold (perspective, the
                # light): a match verified forward and backward that the drift check refused starts a new
                # reference where LK put it
                positions[anew] = self._pts[anew]
                keep[anew] = self._inside(self._pts[anew])
                self._ref[anew] = self.drift.reference_patches(registered, self._pts[anew])
                self._A[anew] = np.eye(2)
                self._smoothed[anew] = False
            self._filter(keep, positions)
            self._age += 1
        t_drift = time.perf_counter()
        n_new = 0
        if len(self._pts) < cfg.redetect_below * budget:
            mask = self.mask.copy()
            mask[~lit] = 0
            for x, y in self._pts:
                cv2.circle(mask, (int(round(x)), int(round(y))), int(cfg.min_distance_px), 0, -1)
            want = budget - len(self._pts)
            corners = cv2.goodFeaturesToTrack(gray, maxCorners=want, qualityLevel=cfg.quality_level,
                                              minDistance=cfg.min_distance_px, mask=mask, blockSize=cfg.block_size)
            if corners is not None:
                corners = corners.reshape(-1, 2)
                n_new = len(corners)
                self._pts = np.vstack([self._pts, corners]).astype(np.float32)
                self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n_new)])
                self._next_id += n_new
                if self.drift is not None:
                    self._ref = np.vstack([self._ref, self.drift.reference_patches(registered, corners)])
                    self._A = np.concatenate([self._A, np.repeat(np.eye(2)[None], n_new, 0)])
                    self._age = np.concatenate([self._age, np.zeros(n_new, np.int32)])
                    self._smoothed = np.concatenate([self._smoothed, np.zeros(n_new, bool)])
                    if smoothed is not None:
                        self._ref_smooth = np.vstack([self._ref_smooth,
                                                      self.drift.reference_patches(smoothed, corners)])
        t3 = time.perf_counter()
        self._prev, self._prev_float = gray, intensity
        self._last = (frame.seq, frame.t_ns)
        funnel = {"corners": n_new, "after_lk": n_lk, "after_drift_check": len(self._pts) - n_new}
        return Observations(frame.seq, frame.t_ns, self._ids.copy(), self._pts.astype(np.float64),
                            colors_at(color, self._pts), n_new,
                            {"undistort": t1 - t0, "track": t2 - t1, "drift_check": t_drift - t2,
                             "detect": t3 - t_drift}, funnel=funnel)

    def match_view(self, image: np.ndarray, camera: CameraModel, T_other_this: np.ndarray,
                   camera_index: int = 1) -> Observations:
        """The live tracks of the last processed frame found in another camera's simultaneous image (see
        ``epipolar.match_across``): undistorted pixels of ``camera``'s K, the same ids, its colours."""
        seq, t_ns = self._last
        empty = Observations(seq, t_ns, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3), np.uint8),
                             camera=camera_index)
        if not self._rig:
            self._rig = True
            if self._rescues() and self._prev_float is not None:
                # the live tracks' first patches on the smoothed image: only those found in this frame can be
                # rescued (at their first step), and their first patches are this frame's
                self._ref_smooth = self.drift.reference_patches(
                    drift_image(self._prev_float, self.config.rescue_smoothing_px), self._pts)
        if self._prev is None or len(self._pts) == 0:
            return empty
        color = undistort_view(image, camera, self._views)
        other_u8, other_float = tracker_image(cv2.cvtColor(color, cv2.COLOR_BGR2GRAY), self.config, self.levels)
        pts = self._pts.astype(np.float64)
        search = (stereo_depth.search_ranges(pts, stereo_depth.carried_depths(
            self._ids, *stereo_depth.known_depths(*self._stereo_prior), self.camera.K),
            (self.camera.width, self.camera.height), self._depth_range) if self.config.stereo_depth_prior else None)
        uv, found = epipolar.match_across(self._prev, self._prev_float, other_u8, other_float, pts, self.camera.K,
                                          camera.K, np.asarray(T_other_this, np.float64), self._depth_range, self._lk,
                                          self.config.drift_max_residual, search)
        return Observations(seq, t_ns, self._ids[found].copy(), uv[found], colors_at(color, uv[found]),
                            camera=camera_index)

    def _track(self, gray: np.ndarray, pts: np.ndarray, guess: np.ndarray | None = None, levels: int | None = None):
        """Pyramidal LK of ``pts`` from the previous image into ``gray`` (from ``guess`` when given) on ``levels``
        pyramid levels (None: the front-end's): ``coarse_window_px`` on the levels from ``coarse_from_level`` up
        (LK on those levels' images), then ``window_px`` on the finer ones from where the coarse levels put each
        track (the Warp kernel's per-level window, in two calls)."""
        cfg = self.config
        k, levels = cfg.coarse_from_level, self.levels if levels is None else levels
        flags = 0 if guess is None else cv2.OPTFLOW_USE_INITIAL_FLOW
        if k > levels or cfg.coarse_window_px == cfg.window_px:
            return cv2.calcOpticalFlowPyrLK(self._prev, gray, pts, guess, flags=flags,
                                            **dict(self._lk, maxLevel=levels))
        prev_k, cur_k = self._prev, gray
        for _ in range(k):
            prev_k, cur_k = cv2.pyrDown(prev_k), cv2.pyrDown(cur_k)
        scale = float(2**k)
        coarse, st_coarse, err = cv2.calcOpticalFlowPyrLK(
            prev_k, cur_k, pts / scale, None if guess is None else guess / scale, flags=flags,
            winSize=(cfg.coarse_window_px, cfg.coarse_window_px), maxLevel=levels - k, criteria=self._lk["criteria"])
        if k == 0:
            return coarse, st_coarse, err
        nxt, st, err = cv2.calcOpticalFlowPyrLK(self._prev, gray, pts, (coarse * scale).astype(np.float32),
                                                flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **dict(self._lk, maxLevel=k - 1))
        return nxt, st & st_coarse, err

    def _track_again(self, gray: np.ndarray, rows: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The consensus's second try (``frontend.consensus``): LK of the tracks ``rows`` from ``starts`` on the
        finest levels; their positions and whether LK tracked them."""
        nxt, status, err = self._track(gray, self._pts[rows].reshape(-1, 1, 2), starts.reshape(-1, 1, 2),
                                       consensus.RETRACK_MAX_LEVEL)
        return nxt.reshape(-1, 2), (status.ravel() == 1) & (err.ravel() < self.config.max_lk_error)

    def _rescues(self) -> bool:
        """Whether new tracks may be rescued (``_drift_check``): a rig, the drift check, a smoothing."""
        return self._rig and self.drift is not None and self.config.rescue_smoothing_px > 0

    def _drift_check(self, registered: np.ndarray, smoothed: np.ndarray | None, searched: np.ndarray,
                     rescue: bool, tracks_back) -> tuple[np.ndarray, np.ndarray]:
        """Each track's registered position (float32) and whether the drift check keeps it. A track registers
        on ``registered`` against its first patch, or, once rescued, on ``smoothed`` against its first patch
        there. With ``rescue`` (a rig, and a frame whose tracks moved at least ``fast_motion_px``), a new track
        refused at its first step (not one searched along its epipolar line: those start a new reference) is
        rescued when the smoothed check keeps it and LK from its registered position lands back where it was
        (``tracks_back(uv, rows)``: bool per row). Why: Shi-Tomasi picks a low-contrast corner partly where the
        sensor noise made one; that noise is in the first patch and not in the next frame, so the residual
        refuses tracks LK put right. Only at fast motion: there the texture leaves the view within a few frames
        and a refused track is a lost point, while at slow motion a corner found again nearby next frame
        replaces it. Only with a rig: its point is an inlier only when both eyes agree on its depth at two
        instants (``mapper.STEREO_INLIER_INSTANTS``); a mono point has no other judge, and the points of the
        tracks it adds were less accurate in mono (docs/results.md, session 17)."""
        n = len(self._pts)
        if smoothed is None or not (rescue or self._smoothed.any()):
            reg = self.drift.register(registered, *gradients(registered), self._ref, self._A,
                                      self._pts.astype(np.float64))
            self._A = reg.A
            return reg.positions.astype(np.float32), reg.keep & self._inside(reg.positions)
        positions = self._pts.copy()
        keep = np.zeros(n, bool)
        plain = ~self._smoothed
        if plain.any():
            reg = self.drift.register(registered, *gradients(registered), self._ref[plain], self._A[plain],
                                      self._pts[plain].astype(np.float64))
            positions[plain], self._A[plain] = reg.positions, reg.A
            keep[plain] = reg.keep & self._inside(reg.positions)
        again = self._smoothed | (rescue & (self._age == 0) & ~keep & ~searched)
        if again.any():
            # a rescued track's shape is its own; a new one starts from the identity (its plain fit was refused)
            A0 = np.where(self._smoothed[again][:, None, None], self._A[again], np.eye(2)[None])
            reg = self.drift.register(smoothed, *gradients(smoothed), self._ref_smooth[again], A0,
                                      self._pts[again].astype(np.float64))
            positions[again], self._A[again] = reg.positions, reg.A
            kept = reg.keep & self._inside(reg.positions)
            new = kept & ~self._smoothed[again]
            rows = np.flatnonzero(again)[new]
            if len(rows):
                kept[new] = tracks_back(positions[rows], rows)
            keep[again] = kept
            self._smoothed[again] = True
        return positions, keep

    def _filter(self, keep: np.ndarray, positions: np.ndarray) -> None:
        self._pts, self._ids = positions[keep], self._ids[keep]
        if self.drift is not None:
            self._ref, self._A = self._ref[keep], self._A[keep]
            self._age, self._smoothed = self._age[keep], self._smoothed[keep]
            if len(self._ref_smooth) == len(keep):
                self._ref_smooth = self._ref_smooth[keep]


def colors_at(color: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """RGB of an undistorted BGR image at the nearest pixel of each position."""
    h, w = color.shape[:2]
    xi = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    return color[yi, xi, ::-1].copy()


def undistort_view(image: np.ndarray, camera: CameraModel, maps: dict) -> np.ndarray:
    """Another camera's BGR frame undistorted with its own model (its maps cached in ``maps``, by camera)."""
    if image.ndim != 3 or image.shape[:2] != (camera.height, camera.width) or image.dtype != np.uint8:
        raise ConfigError(f"view image is {image.shape} {image.dtype}; its camera is {camera.height}x"
                         f"{camera.width}x3 uint8")
    if camera not in maps:
        maps[camera] = camera.undistort_maps()
    map_x, map_y = maps[camera]
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)
