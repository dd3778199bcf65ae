"""The Warp front-end object: owns its device buffers (allocated once, reused every frame) and turns a frame
into observations. Track bookkeeping (live counts, ids, compaction, the choice of new corners) stays on the
device, so on CUDA a frame is the upload, one graph replay and one read-back of the per-track results (positions
and ids) into pinned memory; images never come back (colours are read on the host, from the frame in hand).
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np
import warp as wp

from ...camera import CameraModel
from ...config import TrackerConfig
from ...types import Frame, Observations
from ...warp_device import device_lock
from . import kernels as K

log = logging.getLogger(__name__)

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
        self._map_x, self._map_y = map_x, map_y  # the host reads each track's colour through them
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
            self._frame = wp.zeros((H, W), dtype=wp.uint8)  # the distorted frame's grey levels
            self._gray = wp.zeros((H, W), dtype=float)
            self._log = wp.zeros((H, W), dtype=float)
            self._tmp = wp.zeros((H, W), dtype=float)
            self._lit = wp.zeros((H, W), dtype=float)
            # flat views for the separable blur, which walks a flat index
            self._log_flat, self._tmp_flat, self._lit_flat = (a.flatten() for a in (self._log, self._tmp, self._lit))
            self._pyr = [wp.zeros(total, dtype=float) for _ in range(2)]  # current / previous, swapped
            self._gx = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._gy = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._eig = wp.zeros((H, W), dtype=float)
            self._rows = wp.zeros(H * W, dtype=wp.vec3)  # the structure tensor's horizontal sums
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
            cell = max(config.min_distance_px, 1.0) / np.sqrt(2.0)
            self._grid = (float(cell), int(np.ceil(W / cell)) + 1, int(np.ceil(H / cell)) + 1)
            self._best = wp.zeros(self._grid[1] * self._grid[2], dtype=float)
            self._winner = wp.zeros(self._grid[1] * self._grid[2], dtype=wp.int32)
            self._state = [wp.zeros(MAX_CANDIDATES, dtype=wp.int32) for _ in range(2)]
            self._hist = wp.zeros(K.SCORE_BINS, dtype=wp.int32)
            self._cut = wp.zeros(2, dtype=wp.int32)
            self._taken = wp.zeros(2, dtype=wp.int32)
            # track bookkeeping lives on the device, so a frame needs no read-back until its results
            self._ids = [wp.zeros(n, dtype=wp.int32) for _ in range(2)]
            self._count = [wp.zeros(1, dtype=wp.int32) for _ in range(2)]  # live tracks in each buffer
            self._next_id = wp.zeros(1, dtype=wp.int32)
            self._n_new = wp.zeros(1, dtype=wp.int32)
            self._detect_flag = wp.zeros(1, dtype=wp.int32)
        pinned = self.device.is_cuda
        with wp.ScopedDevice("cpu"):
            # Frames arrive in host memory as BGR. Only grey levels go up: OpenCV converts straight into a pinned
            # staging buffer (one third of the bytes, then one DMA); the colours the map needs are read on the
            # host at the tracks, after the frame.
            self._staging = wp.zeros((H, W), dtype=wp.uint8, pinned=pinned)
            # each frame's results come back in one go, into pinned buffers (copies inside the frame's graph)
            self._out_counts = wp.zeros(2, dtype=wp.int32, pinned=pinned)
            self._out_pts = wp.zeros(n, dtype=wp.vec2, pinned=pinned)
            self._out_ids = wp.zeros(n, dtype=wp.int32, pinned=pinned)
        self._staging_np = self._staging.numpy()
        self.use_graphs = True
        self.profile = False  # synchronise at stage ends to time each stage (benchmarks); no graphs then
        self._marks: dict[str, float] = {}
        self._graphs = [None, None]  # one CUDA graph per frame, per buffer parity
        self._runs = [0, 0]
        self._cur = 0  # which of the double buffers holds the current pyramid / track state
        self._n_tracks = 0
        self._lit_min = float(np.log1p(config.min_brightness))

    @property
    def n_tracks(self) -> int:
        return self._n_tracks

    # --- image stages -----------------------------------------------------------------------------------------
    def _launch(self, kernel, dim, inputs):
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def _upload(self, image: np.ndarray) -> None:
        if image.shape != (self.height, self.width, 3) or image.dtype != np.uint8:
            raise ValueError(f"frame is {image.shape} {image.dtype}; the front-end was built for "
                             f"{self.height}x{self.width}x3 uint8")
        cv2.cvtColor(image, cv2.COLOR_BGR2GRAY, dst=self._staging_np)
        wp.copy(self._frame, self._staging)

    def _colors_at(self, image: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """RGB under each track: its undistorted position mapped back into the distorted frame, sampled
        bilinearly (a 1 x N remap)."""
        if len(uv) == 0:
            return np.zeros((0, 3), np.uint8)
        x = np.clip(np.round(uv[:, 0]).astype(int), 0, self.width - 1)
        y = np.clip(np.round(uv[:, 1]).astype(int), 0, self.height - 1)
        mx, my = self._map_x[y, x][None, :], self._map_y[y, x][None, :]
        bgr = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        return np.ascontiguousarray(bgr[:, ::-1])

    def _prepare_kernels(self) -> None:
        """Undistort, remove shading, build the pyramid and its gradients into the current buffers."""
        cfg = self.config
        H, W = self.height, self.width
        self._launch(K.undistort_gray, (H, W), [self._frame, self._remap, self._gray])
        self._launch(K.log_image, (H, W), [self._gray, self._log])
        self._launch(K.blur_1d, (H, W), [self._log_flat, W, H, self._weights, 1, 0, self._tmp_flat])
        self._launch(K.blur_1d, (H, W), [self._tmp_flat, W, H, self._weights, 0, 1, self._lit_flat])
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
    def _track_kernels(self) -> None:
        """LK from the previous buffers' tracks, the drift check (or LK's own verdict) and the field-of-view test,
        then compaction into the current buffers, all on the device. Launches cover every slot; kernels read the
        live count from the device, so the shapes are fixed (a graph) and the host learns nothing until the end."""
        cfg = self.config
        n = cfg.max_features
        prev, cur = 1 - self._cur, self._cur
        wp.launch_tiled(K.lk_track, dim=[n], inputs=[
            self._pyr[prev], self._gx[prev], self._gy[prev], self._pyr[cur], self._offs, self._ws, self._hs,
            self.levels, cfg.window_px, 30, 0.01, LK_MIN_EIG, self._pts[prev], self._count[prev], self._lk_pts,
            self._status, self._error], block_dim=64, device=self.device)
        self._sync_for_profile("lk")
        if cfg.drift_check:
            wp.launch_tiled(K.drift_check, dim=[n], inputs=[
                self._pyr[cur], self._gx[cur], self._gy[cur], self.width, self.height, self._patches[prev],
                self._A[prev], self._lk_pts, self._status, self._mask, self._count[prev], 6, cfg.drift_max_residual,
                1.6, 3.0, self._pts[prev], self._keep, self._residual], block_dim=64, device=self.device)
        else:
            self._launch(K.lk_keep, n, [self._lk_pts, self._status, self._mask, self._count[prev], self._pts[prev],
                                        self._keep])
        wp.utils.array_scan(self._keep, self._slot, inclusive=False)
        self._launch(K.scatter_tracks, (n, K.PATCH * K.PATCH), [
            self._keep, self._slot, self._pts[prev], self._A[prev], self._patches[prev], self._ids[prev],
            self._pts[cur], self._A[cur], self._patches[cur], self._ids[cur]])
        redetect_below = int(np.ceil(cfg.redetect_below * n))
        self._launch(K.count_kept, 1, [self._keep, self._slot, self._count[cur], redetect_below, self._detect_flag,
                                       self._n_new])
        self._sync_for_profile("track")

    def _sync_for_profile(self, name: str) -> None:
        """Per-stage times need the device synchronised at stage ends; the steady state does without."""
        if self.profile:
            wp.synchronize_device(self.device)
            self._marks[name] = time.perf_counter()

    # --- detection ----------------------------------------------------------------------------------------------
    def _detect_kernels(self) -> None:
        """Occupancy around live tracks, Shi-Tomasi response, local maxima, the greedy minimum-distance selection,
        and the strongest of the selected corners into the free slots (a score histogram picks them, no sort);
        their first patches for the drift check."""
        cfg = self.config
        H, W = self.height, self.width
        cur = self._cur
        count = self._count[cur]
        self._occ.zero_()
        r = int(np.ceil(cfg.min_distance_px))
        self._launch(K.occupancy, (cfg.max_features, (2 * r + 1) ** 2),
                     [self._pts[cur], count, float(cfg.min_distance_px), self._occ])
        lit_min = self._lit_min if cfg.min_brightness > 0 else -1e30
        self._max_eig.zero_()
        self._launch(K.structure_rows, (H, W), [self._gx[cur], self._gy[cur], W, H, cfg.block_size, self._rows])
        self._launch(K.min_eigenvalue, (H, W), [self._rows, W, H, cfg.block_size, self._mask, self._lit, lit_min,
                                                 self._occ, self._eig, self._max_eig])
        self._cand_count.zero_()
        self._launch(K.corner_candidates, (H, W), [
            self._eig, self._max_eig, cfg.quality_level, self._mask, self._lit, lit_min, self._occ,
            cfg.block_size // 2 + 1, self._cand_pos, self._cand_score, self._cand_count])
        cell, gw, gh = self._grid
        self._best.fill_(-1.0e30)
        self._winner.fill_(-1)
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
        selected = self._state[SELECTION_ROUNDS % 2]
        self._hist.zero_()
        self._taken.zero_()
        self._launch(K.score_histogram, MAX_CANDIDATES, [self._cand_score, selected, self._max_eig, self._hist])
        self._launch(K.score_threshold, 1, [self._hist, count, cfg.max_features, self._cut, self._n_new])
        self._launch(K.take_corners, MAX_CANDIDATES, [self._cand_pos, self._cand_score, selected, self._max_eig,
                                                       self._cut, count, self._next_id, self._taken, self._pts[cur],
                                                       self._ids[cur]])
        self._launch(K.sample_patches, (cfg.max_features, K.PATCH * K.PATCH), [
            self._pyr[cur], W, H, self._pts[cur], count, self._n_new, self._patches[cur], self._A[cur]])
        self._launch(K.commit_new_tracks, 1, [count, self._n_new, self._next_id])

    # --- the frame ----------------------------------------------------------------------------------------------
    def _frame_kernels(self) -> None:
        """Everything after the upload: image stages, tracking, detection when too few tracks are left (a
        conditional node inside the graph), and the copies of the results into pinned host memory."""
        cur = self._cur
        self._prepare_kernels()
        self._sync_for_profile("prepare")
        self._track_kernels()
        wp.capture_if(self._detect_flag, on_true=self._detect_kernels)
        wp.copy(self._out_counts, self._count[cur], count=1)
        wp.copy(self._out_counts, self._n_new, dest_offset=1, count=1)
        wp.copy(self._out_pts, self._pts[cur])
        wp.copy(self._out_ids, self._ids[cur])

    def warm_up(self) -> None:
        """Compile every kernel and capture both frame graphs on black frames (no corners, so no tracks are
        left behind), so a live run's first frames do not wait tens of seconds for them."""
        black = np.zeros((self.height, self.width, 3), np.uint8)
        for k in range(4):  # both buffer parities, eager then captured
            self.process(Frame(black, k, k))

    def process(self, frame: Frame) -> Observations:
        with device_lock(self.device):
            return self._process(frame)

    def _process(self, frame: Frame) -> Observations:
        self._marks = {}
        t0 = time.perf_counter()
        self._cur = cur = 1 - self._cur
        self._upload(frame.image)
        self._sync_for_profile("upload")
        # On CUDA the frame is one graph replay per buffer parity, captured on the buffer's second use (once
        # every kernel module is loaded and the scan's scratch exists); elsewhere, and when profiling, launches.
        if self.device.is_cuda and self.use_graphs and not self.profile and self._runs[cur] >= 1:
            if self._graphs[cur] is None:
                try:
                    with wp.ScopedCapture(device=self.device) as capture:
                        self._frame_kernels()
                    self._graphs[cur] = capture.graph
                except Exception as exc:  # e.g. a driver without conditional graph nodes (CUDA < 12.4)
                    log.warning("front-end: CUDA graph capture failed (%s); launching kernels one by one", exc)
                    self.use_graphs = False
            if self._graphs[cur] is not None:
                wp.capture_launch(self._graphs[cur])
            else:
                self._frame_kernels()
        else:
            self._frame_kernels()
        self._runs[cur] += 1
        wp.synchronize_device(self.device)
        n, n_new = (int(v) for v in self._out_counts.numpy())
        self._n_tracks = n
        uv = self._out_pts.numpy()[:n].astype(np.float64)
        ids = self._out_ids.numpy()[:n].astype(np.int64)
        colors = self._colors_at(frame.image, uv)
        t_end = time.perf_counter()
        timings = {"total": t_end - t0}
        if self.profile:
            m = self._marks
            timings.update({"upload": m["upload"] - t0, "prepare": m["prepare"] - m["upload"],
                            "lk": m["lk"] - m["prepare"], "drift_check": m["track"] - m["lk"],
                            "detect": t_end - m["track"]})
        return Observations(frame.seq, frame.t_ns, ids, uv, colors, n_new, timings)
