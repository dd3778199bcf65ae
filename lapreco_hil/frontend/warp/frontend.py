"""The Warp front-end object: owns its device buffers (allocated once, reused every frame) and turns a frame
into observations. Only small per-track arrays cross to the host in the steady state (positions, status,
colours, and the compact list of corner candidates when new features are needed); images stay on the device.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import warp as wp

from ...camera import CameraModel
from ...config import TrackerConfig
from ...types import Frame, Observations
from ...warp_device import device_lock
from . import kernels as K

MAX_CANDIDATES = 65536
# rounds of the parallel greedy selection; a corner still undecided after them is dropped (rare: a chain of
# ever stronger neighbours longer than this)
SELECTION_ROUNDS = 6
# LK gives up where the window's smaller gradient eigenvalue per pixel is below this. OpenCV's 1e-4 is in its
# own units (0-255 intensities, Scharr derivatives x32, scaled by 2^-20): about 1.5e-6 for [0, 1] intensities.
LK_MIN_EIG = 1.5e-6


class WarpFrontEnd:
    def __init__(self, camera: CameraModel, config: TrackerConfig, device: str | None = None) -> None:
        from ...warp_device import init_warp

        init_warp()
        self.camera = camera
        self.config = config
        self.device = wp.get_device(device)
        self.width, self.height = camera.width, camera.height
        W, H = self.width, self.height
        # pyramid layout: one flat array, per-level offsets
        self.levels = config.pyramid_levels + 1
        offs, ws, hs, total, w, h = [], [], [], 0, W, H
        for _ in range(self.levels):
            offs.append(total)
            ws.append(w)
            hs.append(h)
            total += w * h
            w, h = (w + 1) // 2, (h + 1) // 2
        self._lv = (offs, ws, hs)
        map_x, map_y = camera.undistort_maps()
        fov = cv2.remap(camera.fov_mask(margin_px=config.fov_margin_px), map_x, map_y, cv2.INTER_NEAREST,
                        borderValue=0)
        sigma = config.shading_sigma_px
        radius = int(np.ceil(3 * sigma)) if sigma > 0 else 7
        g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / max(sigma, 1.0)) ** 2)
        n = config.max_features
        with wp.ScopedDevice(self.device):
            self._remap = wp.array(np.stack([map_x, map_y], -1).astype(np.float32), dtype=wp.vec2)
            self._mask = wp.array(fov, dtype=wp.uint8)
            self._weights = wp.array((g / g.sum()).astype(np.float32), dtype=float)
            self._offs = wp.array(np.array(offs, np.int32), dtype=int)
            self._ws = wp.array(np.array(ws, np.int32), dtype=int)
            self._hs = wp.array(np.array(hs, np.int32), dtype=int)
            self._frame = wp.zeros((H, W, 3), dtype=wp.uint8)
            self._gray = wp.zeros((H, W), dtype=float)
            self._log = wp.zeros((H, W), dtype=float)
            self._tmp = wp.zeros((H, W), dtype=float)
            self._lit = wp.zeros((H, W), dtype=float)
            self._pyr = [wp.zeros(total, dtype=float) for _ in range(2)]  # current / previous, swapped
            self._gx = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._gy = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._eig = wp.zeros((H, W), dtype=float)
            self._max_eig = wp.zeros(1, dtype=float)
            self._occ = wp.zeros((H, W), dtype=wp.int32)
            self._cand_pos = wp.zeros(MAX_CANDIDATES, dtype=wp.vec2)
            self._cand_score = wp.zeros(MAX_CANDIDATES, dtype=float)
            self._cand_count = wp.zeros(1, dtype=wp.int32)
            self._pts = [wp.zeros(n, dtype=wp.vec2) for _ in range(2)]
            self._A = [wp.zeros(n, dtype=wp.mat22) for _ in range(2)]
            self._patches = [wp.zeros((n, K.PATCH * K.PATCH), dtype=float) for _ in range(2)]
            self._lk_pts = wp.zeros(n, dtype=wp.vec2)
            self._status = wp.zeros(n, dtype=wp.int32)
            self._error = wp.zeros(n, dtype=float)
            self._keep = wp.zeros(n, dtype=wp.int32)
            self._residual = wp.zeros(n, dtype=float)
            self._slot = wp.zeros(n, dtype=wp.int32)
            self._colors = wp.zeros(n, dtype=wp.vec3)
            cell = max(config.min_distance_px, 1.0) / np.sqrt(2.0)
            self._grid = (float(cell), int(np.ceil(W / cell)) + 1, int(np.ceil(H / cell)) + 1)
            self._best = wp.zeros(self._grid[1] * self._grid[2], dtype=float)
            self._winner = wp.zeros(self._grid[1] * self._grid[2], dtype=wp.int32)
            self._sel_keys = wp.zeros(2 * MAX_CANDIDATES, dtype=float)  # radix sort needs twice the room
            self._sel_values = wp.zeros(2 * MAX_CANDIDATES, dtype=wp.int32)
            self._n_sel = wp.zeros(1, dtype=wp.int32)
            self._n_dev = wp.zeros(1, dtype=wp.int32)
            self._state = [wp.zeros(MAX_CANDIDATES, dtype=wp.int32) for _ in range(2)]
        with wp.ScopedDevice("cpu"):
            # frames arrive in host memory; a pinned staging buffer makes the upload one DMA
            self._staging = wp.zeros((H, W, 3), dtype=wp.uint8, pinned=self.device.is_cuda)
        self.use_graphs = True
        self.profile = False  # synchronise at stage ends to time each stage (benchmarks)
        self._marks: dict[str, float] = {}
        self._graphs = [None, None]
        self._prepared = [False, False]
        self._detect_graphs = [None, None]
        self._detected = [False, False]
        self._cur = 0  # which of the double buffers holds the current pyramid / track state
        self._has_prev = False
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0
        self._lit_min = float(np.log1p(config.min_brightness))

    @property
    def n_tracks(self) -> int:
        return len(self._ids)

    # --- image stages -----------------------------------------------------------------------------------------
    def _launch(self, kernel, dim, inputs):
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def _upload(self, image: np.ndarray) -> None:
        if image.shape != (self.height, self.width, 3) or image.dtype != np.uint8:
            raise ValueError(f"frame is {image.shape} {image.dtype}; the front-end was built for "
                             f"{self.height}x{self.width}x3 uint8")
        self._staging.numpy()[...] = image
        wp.copy(self._frame, self._staging)

    def _prepare(self) -> None:
        """The image stages for the current buffers: on CUDA one graph replay (captured on the second use of
        each buffer, once every kernel module is loaded), elsewhere plain launches."""
        cur = self._cur
        if not self.device.is_cuda or not self.use_graphs or not self._prepared[cur]:
            self._prepare_kernels()
            self._prepared[cur] = True
            return
        if self._graphs[cur] is None:
            with wp.ScopedCapture(device=self.device) as capture:
                self._prepare_kernels()
            self._graphs[cur] = capture.graph
        wp.capture_launch(self._graphs[cur])

    def _prepare_kernels(self) -> None:
        """Undistort, remove shading, build the pyramid and its gradients into the current buffers."""
        cfg = self.config
        H, W = self.height, self.width
        self._launch(K.undistort_gray, (H, W), [self._frame, self._remap, self._gray])
        self._launch(K.log_image, (H, W), [self._gray, self._log])
        self._launch(K.blur_1d, (H, W), [self._log, self._weights, 1, 0, self._tmp])
        self._launch(K.blur_1d, (H, W), [self._tmp, self._weights, 0, 1, self._lit])
        pyr, gx, gy = self._pyr[self._cur], self._gx[self._cur], self._gy[self._cur]
        if cfg.shading_sigma_px > 0:
            self._launch(K.to_level0, (H, W), [self._log, self._lit, 1.0, 1, pyr])
        else:
            self._launch(K.to_level0, (H, W), [self._gray, self._lit, 1.0 / 255.0, 0, pyr])
        offs, ws, hs = self._lv
        for l in range(1, self.levels):
            self._launch(K.pyr_down, (hs[l], ws[l]), [pyr, offs[l - 1], ws[l - 1], hs[l - 1], offs[l], ws[l], hs[l]])
        for l in range(self.levels):
            self._launch(K.sobel, (hs[l], ws[l]), [pyr, offs[l], ws[l], hs[l], gx, gy])

    # --- tracking -----------------------------------------------------------------------------------------------
    def _track(self) -> np.ndarray:
        """LK from the previous pyramid, the drift check (or LK's own verdict) and the field-of-view test, then
        compaction into the current buffers on the device; one read-back (the keep flags, which the host
        needs for the track ids)."""
        cfg = self.config
        n = self.n_tracks
        prev, cur = 1 - self._cur, self._cur
        wp.launch_tiled(K.lk_track, dim=[n], inputs=[
            self._pyr[prev], self._gx[prev], self._gy[prev], self._pyr[cur], self._offs, self._ws, self._hs,
            self.levels, cfg.window_px, 30, 0.01, LK_MIN_EIG, self._pts[prev], n, self._lk_pts, self._status,
            self._error], block_dim=64, device=self.device)
        self._sync_for_profile("lk")
        if cfg.drift_check:
            wp.launch_tiled(K.drift_check, dim=[n], inputs=[
                self._pyr[cur], self._gx[cur], self._gy[cur], self.width, self.height, self._patches[prev],
                self._A[prev], self._lk_pts, self._status, self._mask, n, 6, cfg.drift_max_residual, 1.6, 3.0,
                self._pts[prev], self._keep, self._residual], block_dim=64, device=self.device)
        else:
            self._launch(K.lk_keep, n, [self._lk_pts, self._status, self._mask, n, self._pts[prev], self._keep])
        wp.utils.array_scan(self._keep, self._slot, inclusive=False)
        self._launch(K.scatter_tracks, (n, K.PATCH * K.PATCH), [
            self._keep, self._slot, self._pts[prev], self._A[prev], self._patches[prev], self._pts[cur],
            self._A[cur], self._patches[cur]])
        keep = self._keep.numpy()[:n] == 1
        self._ids = self._ids[keep]
        return keep

    def _sync_for_profile(self, name: str) -> None:
        """Per-stage times need the device synchronised at stage ends; the steady state does without."""
        if self.profile:
            wp.synchronize_device(self.device)
            self._marks[name] = time.perf_counter()

    # --- detection ----------------------------------------------------------------------------------------------
    def _candidate_kernels(self) -> None:
        """Occupancy around live tracks, Shi-Tomasi response, local maxima, and the greedy minimum-distance
        selection, into (keys, values, count) on the device."""
        cfg = self.config
        H, W = self.height, self.width
        cur = self._cur
        self._occ.zero_()
        r = int(np.ceil(cfg.min_distance_px))
        self._launch(K.occupancy, (cfg.max_features, (2 * r + 1) ** 2),
                     [self._pts[cur], self._n_dev, float(cfg.min_distance_px), self._occ])
        lit_min = self._lit_min if cfg.min_brightness > 0 else -1e30
        self._max_eig.zero_()
        self._launch(K.min_eigenvalue, (H, W), [self._gx[cur], self._gy[cur], W, H, cfg.block_size, self._mask,
                                                 self._lit, lit_min, self._occ, self._eig, self._max_eig])
        self._cand_count.zero_()
        self._launch(K.corner_candidates, (H, W), [
            self._eig, self._max_eig, cfg.quality_level, self._mask, self._lit, lit_min, self._occ,
            cfg.block_size // 2 + 1, self._cand_pos, self._cand_score, self._cand_count])
        cell, gw, gh = self._grid
        self._best.fill_(-1.0e30)
        self._winner.fill_(-1)
        self._n_sel.zero_()
        self._launch(K.cell_best, MAX_CANDIDATES, [self._cand_pos, self._cand_score, self._cand_count, cell, gw,
                                                    self._best])
        self._launch(K.cell_winner, MAX_CANDIDATES, [self._cand_pos, self._cand_score, self._cand_count, cell, gw,
                                                      self._best, self._winner])
        self._launch(K.selection_init, MAX_CANDIDATES, [self._cand_pos, self._cand_count, cell, gw, self._winner,
                                                         self._state[0]])
        for rnd in range(SELECTION_ROUNDS):
            self._launch(K.selection_round, MAX_CANDIDATES, [
                self._cand_pos, self._cand_score, self._cand_count, cell, gw, gh, self._winner,
                float(cfg.min_distance_px), self._state[rnd % 2], self._state[(rnd + 1) % 2]])
        self._launch(K.selection_collect, MAX_CANDIDATES, [self._cand_score, self._state[SELECTION_ROUNDS % 2],
                                                            self._sel_keys, self._sel_values, self._n_sel])

    def _detect(self) -> int:
        cfg = self.config
        n = self.n_tracks
        want = cfg.max_features - n
        if want <= 0:
            return 0
        cur = self._cur
        self._n_dev.fill_(n)  # the graph reads the live-track count from the device
        # everything up to the selection count has a fixed shape: one graph replay per buffer on CUDA
        if not self.device.is_cuda or not self.use_graphs or not self._detected[cur]:
            self._candidate_kernels()
            self._detected[cur] = True
        else:
            if self._detect_graphs[cur] is None:
                with wp.ScopedCapture(device=self.device) as capture:
                    self._candidate_kernels()
                self._detect_graphs[cur] = capture.graph
            wp.capture_launch(self._detect_graphs[cur])
        m = int(self._n_sel.numpy()[0])  # the one number the host needs
        W, H = self.width, self.height
        k = min(m, want)
        if k == 0:
            return 0
        wp.utils.radix_sort_pairs(self._sel_keys, self._sel_values, m)
        self._launch(K.append_tracks, k, [self._cand_pos, self._sel_values, n, self._pts[cur]])
        self._launch(K.sample_patches, (k, K.PATCH * K.PATCH), [self._pyr[cur], W, H, self._pts[cur], n,
                                                                 self._patches[cur], self._A[cur]])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + k)])
        self._next_id += k
        return k

    # --- the frame ----------------------------------------------------------------------------------------------
    def process(self, frame: Frame) -> Observations:
        with device_lock(self.device):
            return self._process(frame)

    def _process(self, frame: Frame) -> Observations:
        cfg = self.config
        self._marks = {}
        t0 = time.perf_counter()
        self._cur = 1 - self._cur
        self._upload(frame.image)
        self._sync_for_profile("upload")
        self._prepare()
        self._sync_for_profile("prepare")
        if self._has_prev and self.n_tracks:
            self._track()
        else:
            self._ids = self._ids[:0]
        self._sync_for_profile("track")
        n_new = 0
        if self.n_tracks < cfg.redetect_below * cfg.max_features:
            n_new = self._detect()
        n = self.n_tracks
        if n:
            self._launch(K.gather_colors, n, [self._frame, self._remap, self._pts[self._cur], n, self._colors])
            uv = self._pts[self._cur].numpy()[:n].astype(np.float64)
            colors = np.clip(np.round(self._colors.numpy()[:n]), 0, 255).astype(np.uint8)
        else:
            uv, colors = np.zeros((0, 2)), np.zeros((0, 3), np.uint8)
        t_end = time.perf_counter()
        self._has_prev = True
        timings = {"total": t_end - t0}
        if self.profile:
            m = self._marks
            timings.update({"upload": m["upload"] - t0, "prepare": m["prepare"] - m["upload"],
                            "lk": m.get("lk", m["prepare"]) - m["prepare"],
                            "drift_check": m["track"] - m.get("lk", m["prepare"]), "detect": t_end - m["track"]})
        return Observations(frame.seq, frame.t_ns, self._ids.copy(), uv, colors, n_new, timings)
