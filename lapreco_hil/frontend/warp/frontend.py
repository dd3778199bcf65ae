"""The Warp front-end object: owns its device buffers (allocated once, reused every frame) and turns a frame
into observations. Track bookkeeping (live counts, ids, compaction, the choice of new corners) stays on the
device, so on CUDA a frame is the grey conversion on the host, uploaded band by band as it is converted, then
two graph replays: the image stages (launched at once, so they run while the host prepares the frame's motion or
prior), then tracking, detection, and two small copies of the per-track results into pinned memory (the surviving
tracks' part first, so the host reads their colours while detection finishes). Images never come back: colours are
read on the host from the frame in hand, at each track's position in the distorted frame.

A frame that comes with a ``FrameMotion`` starts LK where the motion predicts each track (``warp/predict.py``);
its motion goes up to the device first, so it too is a graph replay (one tracking graph per kind of frame: buffer
parity, with or without a motion, LK's levels, the track budget, serving a rig). A frame without one aligns with
the last on the side stream beside its image stages (the global motion prior, ``_start_prior``). ``match_view``
brings this frame's tracker image back once and matches on the host (``frontend.epipolar``).

With a stereo rig (``match_view`` called) and fast image motion, a new track the drift check refuses at its first
step is judged again on the tracker image smoothed by ``TrackerConfig.rescue_smoothing_px``, as the OpenCV
front-end does (``_rescue_kernels``); a rig's frames are kinds of their own, so a mono run launches nothing more.
"""

from __future__ import annotations

import time
from typing import Callable, NamedTuple

import cv2
import numpy as np
import warp as wp

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.types import Frame, FrameMotion, Observations
from lapreco_hil.warp_device import device_lock, preload_kernels
from lapreco_hil.frontend import epipolar, stereo_depth, track_capacity
from lapreco_hil.frontend.image import (HIGHPASS_GAIN, LOG_OFFSET, prior_levels, pyramid_levels, shading_factor,
                                        shading_sigma_px, to_u8, tracker_image)
from lapreco_hil.frontend.drift import drift_smoothing_weights
from lapreco_hil.frontend.epipolar import FORWARD_BACKWARD_PX
from lapreco_hil.frontend.global_motion import (GOOD_CORRELATION, DistinctStarts, GlobalMotion, plausible,
                                                 reduced_maps)
from lapreco_hil.frontend.opencv import colors_at, undistort_view
from lapreco_hil.frontend.warp import consensus, corners, drift_check, global_motion, lk, predict, pyramid, tracks
from lapreco_hil.frontend.warp.graphs import CapturedLaunches
from lapreco_hil.frontend.warp.page_locked import bgr_to_grey, page_locked_source
from lapreco_hil.frontend.warp.tracks import RESULT_HEADER


# rounds of the parallel greedy selection; a corner still undecided after them is dropped (a chain of ever
# stronger neighbours longer than this): 8 leave next to none undecided (docs/benchmarks.md)
SELECTION_ROUNDS = 8
# LK gives up where the window's smaller gradient eigenvalue per pixel is below this. OpenCV's 1e-4 is in its
# own units (0-255 intensities, Scharr derivatives x32, scaled by 2^-20): about 1.5e-6 for [0, 1] intensities.
LK_MIN_EIG = 1.5e-6
LK_ITERATIONS = 30  # per pyramid level, as OpenCV's default criteria
LK_EPS = 0.01  # px: LK stops when a step is shorter, as OpenCV's default criteria
# px of a level above full resolution: there LK only has to start the next level inside its reach, so steps of
# a hundredth of a coarse pixel bought nothing (a quarter of LK's iterations, the same tracks: docs/benchmarks.md)
LK_COARSE_EPS = 0.05
DRIFT_ITERATIONS = 6  # Gauss-Newton steps of the drift check at most (it stops when converged)
COLOR_ROW = 64  # points per row of the colour remap
# the shading estimate's resolution: reduced by a power of two up to this, keeping its sigma at least this many
# pixels there (a sigma-3 Gaussian is sampled finely enough for bilinear upsampling)
SHADING_MAX_FACTOR = 8
SHADING_MIN_SIGMA_PX = 3.0
# frames of at least this many pixels go up in this many row bands, each copied while the next is converted
UPLOAD_BANDS = 4
UPLOAD_BANDS_FROM_PX = 1_000_000


class FrameKind(NamedTuple):
    """What makes one frame's kernels differ from another's: each kind is a CUDA graph of its own."""

    buffer: int  # the frame buffer's parity
    motion: bool  # a pose source's motion predicts the tracks
    lk_levels: int  # LK's pyramid levels (fewer where the prediction is sure)
    budget: int  # the frame's track budget (larger in fast motion)
    rig: bool  # a stereo rig's frame (the rescue's kernels follow)
    prior: bool  # without a motion, the tracks start from the global image motion


class ImageKind(NamedTuple):
    """What makes one frame's image stages differ from another's (a graph of their own, launched before the host
    prepares the frame's tracking)."""

    buffer: int  # the frame buffer's parity
    rig: bool  # a stereo rig's frame (the rescue's smoothed image follows)

class WarpFrontEnd:
    def __init__(self, camera: CameraModel, config: TrackerConfig, device: str | None = None) -> None:
        from lapreco_hil.warp_device import init_warp

        init_warp()
        self.camera = camera
        self.config = config
        self.device = wp.get_device(device)
        self.width, self.height = camera.width, camera.height
        W, H = self.width, self.height
        # pyramid layout: one flat array, per-level offsets
        self.pyramid_levels = pyramid_levels(config, W, H)  # above full resolution
        self.levels = self.pyramid_levels + 1  # with full resolution
        self._lk_levels = self.levels  # LK's this frame: fewer where a pose prediction starts the tracks
        self._prior_lk_levels = prior_levels(config, W, H) + 1  # ... or the global motion prior (with full resolution)
        self._budget = config.max_features  # the tracks this frame keeps (track_budget)
        self._sigma = shading_sigma_px(config, self.pyramid_levels)
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
        # the shading estimate (the log image blurred with sigma) is taken at a reduced resolution, with sigma /
        # factor: the largest power of two that leaves sigma a few pixels there
        sigma = max(self._sigma, 1.0)
        factor = max(shading_factor(sigma, SHADING_MAX_FACTOR, SHADING_MIN_SIGMA_PX), 2)
        low_sigma = sigma / factor
        radius = int(np.ceil(3 * low_sigma))
        g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / low_sigma) ** 2)
        self._low = (-(-W // factor), -(-H // factor), factor)
        hw, hh, _ = self._low
        n = track_capacity(config)  # slots: max_features, more on frames of fast motion (track_budget)
        with wp.ScopedDevice(self.device):
            self._remap = wp.array(np.stack([map_x, map_y], -1).astype(np.float32), dtype=wp.vec2)
            self._mask = wp.array(fov, dtype=wp.uint8)
            self._weights = wp.array((g / g.sum()).astype(np.float32), dtype=float)
            self._offs = wp.array(np.array(offs, np.int32), dtype=int)
            self._ws = wp.array(np.array(ws, np.int32), dtype=int)
            self._hs = wp.array(np.array(hs, np.int32), dtype=int)
            self._frame = wp.zeros((H, W), dtype=wp.uint8)  # the distorted frame's grey levels
            # a page-locked frame comes up whole, then is converted here (allocated where it can come: CUDA)
            self._frame_bgr = wp.zeros((H, W, 3), dtype=wp.uint8) if self.device.is_cuda else None
            self._log = wp.zeros((H, W), dtype=float)
            self._lit = wp.zeros((H, W), dtype=float)  # the shading level (blurred log), full resolution
            self._low_log, self._low_tmp, self._low_lit = (wp.zeros(hw * hh, dtype=float) for _ in range(3))
            self._pyr = [wp.zeros(total, dtype=float) for _ in range(2)]  # current / previous, swapped
            # level 0 smoothed for the drift check (drift.drift_image), its gradients, and the blur's scratch
            self._drift_weights = wp.array(drift_smoothing_weights(config.drift_smoothing_px), dtype=float)
            smoothed = W * H if self._drift_weights.shape[0] > 1 else 1
            self._drift_img, self._drift_gx, self._drift_gy, self._drift_tmp = (wp.zeros(smoothed, dtype=float)
                                                                                for _ in range(4))
            # the rescue (a rig's): level 0 smoothed by rescue_smoothing_px, its gradients, the blur's scratch; per
            # track, its first patch there and its state (drift_check.TRACK_*); which slots each drift check
            # registers, and the frame's (moved at least fast_motion_px, tracked) counts
            self._rescue_on = config.drift_check and config.rescue_smoothing_px > 0
            self._rig = False  # match_view was called
            self._rescue_weights = wp.array(drift_smoothing_weights(config.rescue_smoothing_px), dtype=float)
            rescue_px, slots = (W * H, n) if self._rescue_on else (1, 1)
            self._rescue_img, self._rescue_gx, self._rescue_gy, self._rescue_tmp = (
                wp.zeros(rescue_px, dtype=float) for _ in range(4))
            self._ref_smooth = [wp.zeros((slots, drift_check.PATCH * drift_check.PATCH), dtype=float)
                                for _ in range(2)]
            self._rescue_state = [wp.zeros(slots, dtype=wp.int32) for _ in range(2)]
            self._plain, self._again = wp.zeros(slots, dtype=wp.int32), wp.zeros(slots, dtype=wp.int32)
            self._fast_counts = wp.zeros(2, dtype=wp.int32)
            self._gx = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._gy = [wp.zeros(total, dtype=float) for _ in range(2)]
            self._eig = wp.zeros((H, W), dtype=float)
            self._rows = wp.zeros(H * W, dtype=wp.vec3)  # the structure tensor's horizontal sums
            self._max_eig = wp.zeros(1, dtype=float)
            self._occ = wp.zeros((H, W), dtype=wp.int32)  # occupied where it holds the detection's stamp
            self._stamp = wp.zeros(1, dtype=wp.int32)
            self._pts = [wp.zeros(n, dtype=wp.vec2) for _ in range(2)]
            self._A = [wp.zeros(n, dtype=wp.mat22) for _ in range(2)]
            self._steps = [wp.zeros(n, dtype=wp.vec2) for _ in range(2)]  # each track's motion in its last frame
            self._patches = [wp.zeros((n, drift_check.PATCH * drift_check.PATCH), dtype=float) for _ in range(2)]
            self._lk_pts = wp.zeros(n, dtype=wp.vec2)
            self._status = wp.zeros(n, dtype=wp.int32)
            self._error = wp.zeros(n, dtype=float)
            self._keep = wp.zeros(n, dtype=wp.int32)
            self._residual = wp.zeros(n, dtype=float)
            self._slot = wp.zeros(n, dtype=wp.int32)
            # a frame's results, packed for their copies to the host (pack_results)
            self._packed = (wp.zeros(n, dtype=wp.vec4), wp.zeros(n + RESULT_HEADER, dtype=wp.int32))
            # pose-predicted starts (FrameMotion): each slot's own depth as the host sends it (<= 0: none) and
            # its start depth (borrowed, settled; <= 0: none), the start positions, the epipolar sweep's scratch,
            # and whether LK starts from them (0 in every captured graph)
            self._own_depth = wp.zeros(n, dtype=float)
            self._depth = wp.zeros(n, dtype=float)
            # the frame's motion (T_cur_prev; 1 / near, 1 / far), read by the prediction kernels from the device
            # so that a captured graph replays them for any motion
            self._motion_T = wp.zeros(1, dtype=wp.mat44)
            self._inverse_range = wp.zeros(1, dtype=wp.vec2)
            self._guess = wp.zeros(n, dtype=wp.vec2)
            self._use_guess = wp.zeros(1, dtype=wp.int32)
            self._sweep_scores = wp.zeros((n, predict.SWEEP_SAMPLES), dtype=float)
            self._sweep_cand = wp.zeros((n, predict.SWEEP_SAMPLES), dtype=wp.vec2)
            self._sweep_found = wp.zeros(n, dtype=wp.int32)  # 1: the sweep's match was clear
            self._n_tracked = wp.zeros(1, dtype=wp.int32)
            # the forward-backward check of tracks found along their epipolar line: LK back, its verdict, and
            # the positions LK gave (the drift check moves them; a verified wide-baseline match keeps LK's)
            self._back_pts = wp.zeros(n, dtype=wp.vec2)
            self._back_status = wp.zeros(n, dtype=wp.int32)
            self._back_error = wp.zeros(n, dtype=float)
            self._searched = wp.zeros(n, dtype=wp.int32)
            self._back_needed = wp.zeros(n, dtype=wp.int32)  # the slots LK tracks back (swept ones)
            self._every_slot = wp.empty(0, dtype=wp.int32)
            self._at_lk = wp.zeros(n, dtype=wp.vec2)
            self._one = wp.ones(1, dtype=wp.int32)
        self._consensus = consensus.ConsensusBuffers(n, W, H, self.device)
        # frames without a pose prediction: the image motion from the host's dense alignment of the frame
        # (frontend.global_motion), sent up before the frame's tracking graph; _prior: this frame's tracks start
        # from it
        self._global = GlobalMotion(W, H) if config.global_motion_prior else None
        # the frames' alignment images and ECC from the first seeds on the device; the host's seeds for the rest
        self._align = None if self._global is None else global_motion.AlignmentImages(
            W, H, self._global.factor, reduced_maps(map_x, map_y, self._global.factor), self.device)
        self._align_has_prev = False  # the last frame's alignment image was made (it had no motion)
        self._aligning = None  # the seed whose ECC _start_prior launched for this frame, if any
        # frames whose prior came from the device's ECC, from the host's seeds, or from neither (no prior)
        self.prior_aligned = {"device": 0, "host": 0, "none": 0}
        self._prior = False
        self._consensus_H: np.ndarray | None = None  # the last frame's consensus (pixels), a seed of the next
        with wp.ScopedDevice(self.device):
            self._prior_H = wp.zeros(1, dtype=wp.mat33)
        with wp.ScopedDevice(self.device):
            cell = max(config.min_distance_px, 1.0) / np.sqrt(2.0)
            self._grid = (float(cell), int(np.ceil(W / cell)) + 1, int(np.ceil(H / cell)) + 1)
            n_cells = self._grid[1] * self._grid[2]
            self._cell_key = wp.zeros(n_cells, dtype=wp.uint64)  # zero between detections (cell_init clears it)
            self._cells = wp.zeros(n_cells, dtype=wp.vec3)  # each cell's strongest corner: (x, y, score)
            self._cell_state = wp.zeros(n_cells, dtype=wp.int32)  # -1 out, 0 undecided, 1 selected
            self._hist = wp.zeros(corners.SCORE_BINS, dtype=wp.int32)
            self._cut = wp.zeros(2, dtype=wp.int32)
            self._taken = wp.zeros(2, dtype=wp.int32)
            self._take_scratch = corners.TakeScratch(n_cells, self.device)
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
            # each frame's results come back into pinned buffers (two copies inside the frame's graph, see
            # pack_results): the surviving tracks after tracking, all tracks after detection
            self._out_kept, self._out_all = ((wp.zeros(n, dtype=wp.vec4, pinned=pinned),
                                              wp.zeros(n + RESULT_HEADER, dtype=wp.int32, pinned=pinned))
                                             for _ in range(2))
            # a frame's motion goes up from here (the slots' own depths, T_cur_prev, the inverse depth range); the
            # previous frame's copies are done by then (each frame ends waiting for its results)
            self._motion_up = (wp.zeros(n, dtype=float, pinned=pinned), wp.zeros(1, dtype=wp.mat44, pinned=pinned),
                               wp.zeros(1, dtype=wp.vec2, pinned=pinned))
            # a frame's image motion goes up from here; the consensus's homography and its inliers come back here
            self._prior_up = wp.zeros(1, dtype=wp.mat33, pinned=pinned)
            self._consensus_out = (wp.zeros(1, dtype=wp.mat33, pinned=pinned), wp.zeros(1, dtype=wp.int32, pinned=pinned))
        # numpy views of the pinned buffers, made once (pinned memory does not move)
        self._staging_np = self._staging.numpy()
        self._kept_np, self._all_np = (tuple(a.numpy() for a in out) for out in (self._out_kept, self._out_all))
        self._motion_up_np = tuple(a.numpy() for a in self._motion_up)
        self._prior_up_np = self._prior_up.numpy()
        self._consensus_out_np = tuple(a.numpy() for a in self._consensus_out)
        # events the host waits on: the surviving tracks' results are in, the frame's results are in
        self._tracked = wp.Event(self.device) if self.device.is_cuda else None
        self._done = wp.Event(self.device) if self.device.is_cuda else None
        self.frames_page_locked = 0  # frames that came up by the page-locked path (``page_locked``)
        # the corner response and selection run beside tracking, at high priority: theirs is a chain of short
        # launches, which should not queue behind the blocks of LK and the drift check
        self._side_stream = wp.Stream(self.device, priority=-1) if self.device.is_cuda else None
        self.profile = False  # synchronise at stage ends to time each stage (benchmarks); no graphs then
        self._marks: dict[str, float] = {}
        # one CUDA graph per kind of frame: (buffer parity, with a motion, LK's levels, the track budget, the
        # rescue's launches: a rig's frames, the prior)
        self._graphs = CapturedLaunches(self.device, "front-end")
        # and one per kind of image stages: they run while the host prepares the frame's motion or prior
        self._image_graphs = CapturedLaunches(self.device, "front-end image stages")
        self._cur = 0  # which of the double buffers holds the current pyramid / track state
        self._n_tracks = 0
        self._lit_min = float(np.log(config.min_brightness + LOG_OFFSET))
        # the OpenCV baseline's LK error (TrackerConfig.max_lk_error) is in the 8-bit units of the image it
        # tracks: HIGHPASS_GAIN per unit of the log high-pass, or 255 for plain intensity in [0, 1]
        self._lk_error_units = HIGHPASS_GAIN if self._sigma > 0 else 255.0
        self._motion: FrameMotion | None = None  # this frame's, while it is processed
        self._depth_range = FrameMotion(np.eye(4)).depth_range_m  # the last motion's, for match_view
        self._last = (0, 0, np.zeros(0, np.int64), np.zeros((0, 2)))  # the last frame's seq, t_ns, ids, uv
        self._stereo_prior = (self._last[2], self._last[3], None)  # the last frame's tracks and motion, for match_view
        self._views: dict[CameraModel, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def n_tracks(self) -> int:
        return self._n_tracks

    # --- image stages -----------------------------------------------------------------------------------------
    def _stage_image(self, image: np.ndarray, motion: FrameMotion | None = None) -> None:
        """The frame's grey levels up and its image stages queued (``_image_kernels``); for a frame without a
        motion, its alignment image and ECC from the last frame's motion first, on the side stream
        (``_start_prior``): both run while the host goes on."""
        self._to_staging(image)
        beside = self._start_prior(motion)
        self._launch_image_stages()
        if beside:  # what follows on the main stream (the next frame's upload among it) waits for the alignment
            wp.get_stream(self.device).wait_stream(self._side_stream)

    def _launch_image_stages(self) -> None:
        self._image_graphs.run(ImageKind(self._cur, self._rescuing()), self._image_kernels, graphs=not self.profile)

    def _to_staging(self, image: np.ndarray) -> None:
        """The frame's grey levels into the pinned staging buffer and on to the device, band by band: each band's
        copy runs while the host converts the next (the frame's graph starts after the last on the same
        stream)."""
        if image.shape != (self.height, self.width, 3) or image.dtype != np.uint8:
            raise ValueError(f"frame is {image.shape} {image.dtype}; the front-end was built for "
                             f"{self.height}x{self.width}x3 uint8")
        source = page_locked_source(image)
        if source is not None:
            # a frame the capture thread put in page-locked memory: one DMA, the grey levels made here
            if self._frame_bgr is None:
                self._frame_bgr = wp.zeros(source.shape, dtype=wp.uint8, device=self.device)
            wp.copy(self._frame_bgr, source)
            bgr_to_grey(self._frame_bgr, self._frame, self.device)
            self.frames_page_locked += 1
            return
        W, H = self.width, self.height
        bands = UPLOAD_BANDS if W * H >= UPLOAD_BANDS_FROM_PX else 1
        for b in range(bands):
            r0, r1 = H * b // bands, H * (b + 1) // bands
            cv2.cvtColor(image[r0:r1], cv2.COLOR_BGR2GRAY, dst=self._staging_np[r0:r1])
            wp.copy(self._frame, self._staging, r0 * W, r0 * W, (r1 - r0) * W)

    def _colors_at(self, image: np.ndarray, src: np.ndarray) -> np.ndarray:
        """RGB under each track: the distorted frame sampled bilinearly at the track's source position (computed
        on the device from the undistortion map), border replicated; one remap of (x, y) pairs."""
        n = len(src)
        if n == 0:
            return np.zeros((0, 3), np.uint8)
        # in rows of COLOR_ROW points: cv2.remap is faster on short rows than on one long one
        rows = -(-n // COLOR_ROW)
        xy = np.empty((rows * COLOR_ROW, 2), np.float32)
        xy[:n] = src
        xy[n:] = xy[n - 1]
        bgr = cv2.remap(image, xy.reshape(rows, COLOR_ROW, 2), None, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n]
        return np.ascontiguousarray(bgr[:, ::-1])

    def _prepare_kernels(self) -> None:
        """Undistort, remove shading, build the pyramid and its gradients into the current buffers."""
        dev = self.device
        hw, hh, factor = self._low
        pyramid.undistort_log(self._frame, self._remap, self._log, dev)
        pyramid.box_mean(self._log, self._low_log, hw, hh, factor, dev)
        pyramid.blur_1d(self._low_log, hw, hh, self._weights, 1, 0, self._low_tmp, dev)
        pyramid.blur_1d(self._low_tmp, hw, hh, self._weights, 0, 1, self._low_lit, dev)
        pyr, gx, gy = self._pyr[self._cur], self._gx[self._cur], self._gy[self._cur]
        pyramid.level0(self._log, self._low_lit, hw, hh, factor, self._sigma > 0, pyr, self._lit,
                       dev)
        offs, ws, hs = self._lv
        for l in range(1, self.levels):
            pyramid.pyr_down(pyr, offs[l - 1], ws[l - 1], hs[l - 1], offs[l], ws[l], hs[l], dev)
        pyramid.sobel_levels(pyr, self._offs, self._ws, self._hs, self.levels, gx, gy, dev)
        if self.config.drift_check and self._drift_weights.shape[0] > 1:
            self._smoothed_level0(self._drift_weights, self._drift_tmp, self._drift_img, self._drift_gx,
                                  self._drift_gy)
        if self._rescuing():
            self._rescue_image_kernels()

    def _smoothed_level0(self, weights, tmp, img, gx, gy) -> None:
        """``img`` <- level 0 of the current frame blurred by ``weights`` (``drift.drift_image``), with its
        gradients ``gx``, ``gy``."""
        dev, W, H = self.device, self.width, self.height
        pyramid.blur_1d(self._pyr[self._cur], W, H, weights, 1, 0, tmp, dev)
        pyramid.blur_1d(tmp, W, H, weights, 0, 1, img, dev)
        pyramid.sobel_levels(img, self._offs, self._ws, self._hs, 1, gx, gy, dev)

    def _rescuing(self) -> bool:
        """Whether this frame may rescue new tracks (``_rescue_kernels``): a rig, the drift check, a smoothing."""
        return self._rig and self._rescue_on

    def _rescue_image_kernels(self) -> None:
        """Level 0 of the current frame smoothed by ``rescue_smoothing_px`` (``drift.drift_image``) and its
        gradients: the image a rescued track registers on."""
        self._smoothed_level0(self._rescue_weights, self._rescue_tmp, self._rescue_img, self._rescue_gx,
                              self._rescue_gy)

    def _drift_images(self) -> tuple:
        """(image, gx, gy) the drift check registers on in the current frame: level 0 smoothed
        (``drift.drift_image``), or level 0 itself without smoothing."""
        if self._drift_weights.shape[0] > 1:
            return self._drift_img, self._drift_gx, self._drift_gy
        cur = self._cur
        return self._pyr[cur], self._gx[cur], self._gy[cur]

    # --- tracking -----------------------------------------------------------------------------------------------
    def _lk_kernels(self) -> None:
        """Pyramidal LK of the previous buffers' tracks into the current image. The launch covers every slot;
        kernels read the live count from the device, so the shapes are fixed (a graph)."""
        cfg = self.config
        prev, cur = 1 - self._cur, self._cur
        lk.lk_track(self._pyr[prev], self._gx[prev], self._gy[prev], self._pyr[cur], self._offs, self._ws, self._hs,
                    self._lk_levels, cfg.window_px, LK_ITERATIONS, LK_EPS, LK_MIN_EIG,
                    cfg.max_lk_error / self._lk_error_units, self._pts[prev], self._count[prev],
                    self._guess, self._use_guess, self._lk_pts, self._status, self._error, self.device,
                    coarse_win=cfg.coarse_window_px, coarse_from=cfg.coarse_from_level, coarse_eps=LK_COARSE_EPS,
                    only=self._every_slot)
        if self._motion is None and cfg.consensus_px > 0:
            self._consensus_kernels()
        tracks.count_tracked(self._lk_pts, self._status, self._mask, self._count[prev], self._n_tracked, self.device)
        if self._motion is not None:
            # LK back into the previous image from where the swept tracks landed (only they are checked: the
            # tracks started at a depth skip it, most of a live run's)
            predict.swept_and_tracked(self._depth, self._status, self._count[prev], self._back_needed, self.device)
            self._lk_back()
            predict.forward_backward(self._depth, self._pts[prev], self._back_pts, self._back_status,
                                     self._count[prev], self._status, self._searched, self.device)
            wp.copy(self._at_lk, self._lk_pts)
        if self._rescuing():
            # whether the frame is one of fast motion (the rescue's), from LK's steps after its checks
            drift_check.count_fast(self._lk_pts, self._pts[prev], self._status, self._mask, self._count[prev],
                                   cfg.fast_motion_px, self._fast_counts, self.device)
            if self._motion is None:
                wp.copy(self._at_lk, self._lk_pts)  # where a new track's rescue starts
        self._sync_for_profile("lk")

    def _consensus_kernels(self) -> None:
        """Without a motion: the tracks' RANSAC homography, and the tracks off it or lost tracked again from
        where it puts them on the two finest levels (LK's blocks of the others return at once), each taking the
        position that agrees better with it (``frontend.consensus``). (No conditional node: the corner selection
        on the side stream is not joined yet, and a capture cannot pause for one.)"""
        cfg, b = self.config, self._consensus
        prev, cur = 1 - self._cur, self._cur
        consensus.find_consensus(b, self._pts[prev], self._lk_pts, self._status, self._count[prev], cfg.consensus_px,
                                 self.device)
        if self._global is not None:
            for dst, src in zip(self._consensus_out, (b.best, b.agreed)):
                wp.copy(dst, src)
        lk.lk_track(self._pyr[prev], self._gx[prev], self._gy[prev], self._pyr[cur], self._offs, self._ws, self._hs,
                    min(consensus.RETRACK_LEVELS, self._lk_levels), cfg.window_px, LK_ITERATIONS, LK_EPS, LK_MIN_EIG,
                    cfg.max_lk_error / self._lk_error_units, self._pts[prev], self._count[prev], b.guess, self._one,
                    b.re_pts, b.re_status, b.re_error, self.device, coarse_eps=LK_COARSE_EPS, only=b.again)
        consensus.take_closer(b, cfg.consensus_px, self._lk_pts, self._status, self._error, self.device)

    def _lk_back(self) -> None:
        """LK from where the tracks landed back into the previous image, from where they were, for the slots
        ``_back_needed`` flags (the forward-backward checks: the swept tracks', the rescued new ones')."""
        cfg = self.config
        prev, cur = 1 - self._cur, self._cur
        lk.lk_track(self._pyr[cur], self._gx[cur], self._gy[cur], self._pyr[prev], self._offs, self._ws, self._hs,
                    self._lk_levels, cfg.window_px, LK_ITERATIONS, LK_EPS, LK_MIN_EIG,
                    cfg.max_lk_error / self._lk_error_units, self._lk_pts, self._count[prev],
                    self._pts[prev], self._one, self._back_pts, self._back_status, self._back_error, self.device,
                    coarse_eps=LK_COARSE_EPS, only=self._back_needed)

    def _predict_kernels(self, motion: FrameMotion) -> None:
        """Each track's start in this frame from the camera motion (projection at its depth or the epipolar
        sweep on pyramid level 1), then LK starts there."""
        offs, ws, hs = self._lv
        level = min(epipolar.SWEEP_LEVEL, self.levels - 1)
        prev, cur = 1 - self._cur, self._cur
        predict.borrow_and_settle(self._pts[prev], self._count[prev], self._own_depth, self.camera.K, self._motion_T,
                                  self._inverse_range, (self.width, self.height), self._depth, self.device)
        predict.predict_starts(self._pyr[prev], self._pyr[cur], offs[level], ws[level], hs[level], level,
                               self._pts[prev], self._count[prev], self._depth, self.camera.K, self._motion_T,
                               self._inverse_range, self._sweep_scores, self._sweep_cand, self._guess,
                               self._sweep_found, self.device)

    def _keep_kernels(self) -> None:
        """The drift check (or LK's own verdict) and the field-of-view test, then compaction of the surviving
        tracks into the current buffers, all on the device: the host learns nothing until the end."""
        cfg = self.config
        prev, cur = 1 - self._cur, self._cur
        dev = self.device
        rescuing = self._rescuing()
        if cfg.drift_check:
            img, gx, gy = self._drift_images()
            if rescuing:
                drift_check.plain_slots(self._rescue_state[prev], self._count[prev], self._plain, dev)
            drift_check.drift_check(
                img, gx, gy, self.width, self.height, self._patches[prev],
                self._A[prev], self._lk_pts, self._status, self._mask, self._count[prev], DRIFT_ITERATIONS,
                cfg.drift_max_residual, 1.6, 3.0, self._keep, self._residual, dev,
                only=self._plain if rescuing else self._every_slot)
            if rescuing:
                self._rescue_kernels()
            if self._motion is not None:
                drift_check.reanchor(img, self.width, self.height, self._searched, self._at_lk,
                                     self._count[prev], self._mask, self._lk_pts, self._patches[prev], self._A[prev],
                                     self._keep, dev)
                if rescuing:
                    drift_check.reanchored_plain(self._searched, self._count[prev], self._rescue_state[prev], dev)
        else:
            tracks.lk_keep(self._lk_pts, self._status, self._mask, self._count[prev], self._keep, dev)
        tracks.compact_tracks(
            self._keep, self._slot, self._lk_pts, self._pts[prev], self._A[prev], self._patches[prev], self._ids[prev],
            self._pts[cur], self._steps[cur], self._A[cur], self._patches[cur], self._ids[cur], dev)
        if rescuing:
            tracks.compact_rescue(self._keep, self._slot, self._rescue_state[prev], self._ref_smooth[prev],
                                  self._rescue_state[cur], self._ref_smooth[cur], dev)
        redetect_below = int(np.ceil(cfg.redetect_below * self._budget))
        tracks.count_kept(self._keep, self._slot, self._count[cur], redetect_below, self._detect_flag, self._n_new,
                          dev)
        self._sync_for_profile("track")

    def _rescue_kernels(self) -> None:
        """After the drift check of the plain tracks (all but the rescued ones): the rescued tracks, and on a
        frame of fast motion the new tracks it refused (not those found along their epipolar line: those are
        anchored anew), registered on the rescue-smoothed image against their first patch there; a new one kept
        there must also track back (LK from its registered position into the previous image) within
        FORWARD_BACKWARD_PX of where it was. Why, and why only with a rig at fast motion: see the OpenCV
        front-end's ``_drift_check``."""
        cfg = self.config
        prev = 1 - self._cur
        dev = self.device
        state = self._rescue_state[prev]
        drift_check.rescue_candidates(state, self._keep, self._searched if self._motion is not None else None,
                                      self._fast_counts, self._count[prev], self._at_lk, self._lk_pts,
                                      self._A[prev], self._again, dev)
        drift_check.drift_check(
            self._rescue_img, self._rescue_gx, self._rescue_gy, self.width, self.height, self._ref_smooth[prev],
            self._A[prev], self._lk_pts, self._status, self._mask, self._count[prev], DRIFT_ITERATIONS,
            cfg.drift_max_residual, 1.6, 3.0, self._keep, self._residual, dev, only=self._again)
        drift_check.rescue_back_needed(state, self._again, self._keep, self._back_needed, dev)
        self._lk_back()
        drift_check.rescue_verdict(self._back_needed, self._back_pts, self._back_status, self._pts[prev],
                                   self._again, self._count[prev], FORWARD_BACKWARD_PX, self._keep, state, dev)

    def _sync_for_profile(self, name: str) -> None:
        """Per-stage times need the device synchronised at stage ends; the steady state does without."""
        if self.profile:
            wp.synchronize_device(self.device)
            self._marks[name] = time.perf_counter()

    # --- detection ----------------------------------------------------------------------------------------------
    def _occupancy(self, buffer: int, ahead: float, which: int) -> None:
        """Stamp the discs around the live tracks of a track buffer, each moved on by ``ahead`` times its last
        step (``which``: see ``corners._occupancy``)."""
        corners.occupancy(self._pts[buffer], self._steps[buffer], ahead, self._count[buffer],
                          float(self.config.min_distance_px), self._stamp, which, self._occ, self.device)

    def _selection_start(self) -> None:
        """A new detection's stamps, and the occupancy discs around where the tracks are predicted in this
        frame: where each will be if it moves as in its last frame. That leaves less room between the discs
        the selection avoids and those the corners are checked against when taken (around the tracks' new
        positions, ``corners._free_now``) than the previous positions would. It needs nothing from the frame, so on
        CUDA it runs beside the image stages."""
        corners.selection_begin(self._stamp, self._max_eig, self.device)
        self._occupancy(1 - self._cur, 1.0, 0)

    def _selection_kernels(self) -> None:
        """The Shi-Tomasi response of the current frame (the structure tensor's smaller eigenvalue) and its best
        value where corners may start, local maxima (each cell of side min_distance / sqrt(2) keeps its
        strongest) and the greedy minimum-distance selection, away from the occupancy discs. It needs nothing
        from tracking, so on CUDA it runs beside LK and the drift check."""
        cfg = self.config
        H, W = self.height, self.width
        cur, dev = self._cur, self.device
        lit_min = self._lit_min if cfg.min_brightness > 0 else -1e30
        corners.structure_rows(self._gx[cur], self._gy[cur], W, H, cfg.block_size, self._rows, dev)
        corners.min_eigenvalue(self._rows, W, H, cfg.block_size, self._mask, self._lit, lit_min, self._occ,
                               self._stamp, self._eig, self._max_eig, dev)
        cell, gw, gh = self._grid
        corners.corner_candidates(self._eig, self._max_eig, cfg.quality_level, self._mask, self._lit, lit_min,
                                  self._occ, self._stamp, cfg.block_size // 2 + 1, cell, gw, self._cell_key, dev)
        corners.cell_init(self._cell_key, self._eig, self._cells, self._cell_state, self._hist, dev)
        for _ in range(SELECTION_ROUNDS):
            corners.selection_round(self._cells, gw, gh, float(cfg.min_distance_px), self._cell_state, dev)

    def _detect_kernels(self, beside_tracking: bool) -> None:
        """New tracks in the free slots: the strongest selected corners (a score histogram picks them, no sort)
        that no surviving track has come near, and their first patches for the drift check. The selection ran
        beside tracking on CUDA; elsewhere it runs here, only on frames that need new corners."""
        cur, dev = self._cur, self.device
        count = self._count[cur]
        if not beside_tracking:
            self._selection_start()
            self._selection_kernels()
        self._occupancy(cur, 0.0, 1)
        corners.score_histogram(self._cells, self._cell_state, self._max_eig, self._occ, self._stamp, self._hist, dev)
        corners.score_threshold(self._hist, count, self._budget, self._cut, self._taken, dev)
        corners.take_corners(self._cells, self._cell_state, self._max_eig, self._cut, self._occ, self._stamp, count,
                             self._next_id, self._taken, self._pts[cur], self._ids[cur], self._take_scratch, dev)
        drift_check.sample_patches(self._drift_images()[0], self.width, self.height, self._pts[cur], count,
                                   self._taken, self._patches[cur], self._A[cur], self._steps[cur], dev)
        if self._rescuing():
            drift_check.sample_rescue_patches(self._rescue_img, self.width, self.height, self._pts[cur], count,
                                              self._taken, self._ref_smooth[cur], self._rescue_state[cur], dev)
        tracks.commit_new_tracks(self._taken, count, self._n_new, self._next_id, dev)

    # --- the frame ----------------------------------------------------------------------------------------------
    def _image_kernels(self) -> None:
        """A frame's image stages once its grey levels are on the device (one CUDA graph per ``ImageKind``),
        launched before the host prepares the frame's tracking (the motion's start depths, the plan, the prior),
        so the two overlap. On CUDA the corner selection's occupancy discs run beside them on a second stream."""
        side = self._side
        self._sync_for_profile("upload")
        if side is not None:
            main = wp.get_stream(self.device)
            side.wait_stream(main)
            with wp.ScopedStream(side, sync_enter=False):
                self._selection_start()
        self._prepare_kernels()
        if side is not None:
            main.wait_stream(side)  # (a graph's streams join before it ends)

    def _frame_kernels(self) -> None:
        """A frame once its image stages are queued (one CUDA graph per ``FrameKind``): the tracks' starts,
        tracking, the surviving tracks' results into pinned memory (then the ``tracked`` event: the host reads their
        colours while the rest runs), new corners when too few tracks are left (a conditional node), and every
        track's results into a second set of pinned buffers.

        On CUDA the corner response and the greedy selection run on a second stream beside tracking (they need
        nothing from it). They are wasted on frames that need no new corners, which costs GPU time but no
        latency."""
        side = self._side
        main = wp.get_stream(self.device) if side is not None else None
        if self._motion is not None:
            self._predict_kernels(self._motion)
        elif self._prior:
            predict.prior_starts(self._prior_H, self._pts[1 - self._cur], self._count[1 - self._cur], self._guess,
                                 self.device)
        self._sync_for_profile("prepare")
        if side is not None:
            side.wait_stream(main)
            with wp.ScopedStream(side, sync_enter=False):
                self._selection_kernels()
        self._lk_kernels()
        self._keep_kernels()
        self._copy_results(self._out_kept)
        if self._tracked is not None:
            wp.record_event(self._tracked, external=True)  # a node the host can wait on, inside a graph
        if side is not None:
            main.wait_stream(side)
        wp.capture_if(self._detect_flag, on_true=lambda: self._detect_kernels(beside_tracking=side is not None))
        self._copy_results(self._out_all)
        if self._done is not None:
            wp.record_event(self._done, external=True)

    def _copy_results(self, out: tuple) -> None:
        cur = self._cur
        tracks.pack_results(self._pts[cur], self._ids[cur], self._count[cur], self._n_new, self._n_tracked,
                            self._remap, *self._packed, self.device)
        for dst, src in zip(out, self._packed):
            wp.copy(dst, src)

    def warm_up(self, rig: bool = False) -> None:
        """Compile every kernel and capture the graph of every kind of frame on black frames (no corners, so no
        tracks are left behind): without a motion, and with one for each track budget (and each of LK's level
        counts where the prediction may reduce them). A live run's first frames then wait for no compile, and
        no frame mid-run for a capture: the first frame of fast motion (the larger budget) once paid for its
        kind's eager launches and capture while frames queued behind it. With ``rig`` (a stereo run: its frames
        are a rig's from its first ``match_view`` on) and the rescue on CUDA, a rig's kinds too."""
        preload_kernels("lapreco_hil.frontend.warp", self.device)  # the motion path's kernels too
        black = np.zeros((self.height, self.width, 3), np.uint8)
        budgets = sorted({self.config.max_features, track_capacity(self.config)})
        lk_levels = range(1, self.levels + 1) if self.config.reduced_predicted_levels else [self.levels]
        still = FrameMotion(np.eye(4))
        serving = self._rig
        seq = 0
        try:
            for serving_rig in ([False, True] if rig and self._rescue_on and self.device.is_cuda and self.use_graphs
                                else [self._rig]):
                self._rig = serving_rig
                for k in range(4):  # both buffer parities, eager then captured
                    self.process(Frame(black, seq, seq))
                    seq += 1
                for k in range(4 if self._global is not None else 0):  # without a motion, from the image motion
                    with device_lock(self.device):
                        self._warm_prior_frame(Frame(black, seq, seq))
                    seq += 1
                for budget in budgets:
                    for levels in lk_levels:
                        for k in range(4):
                            with device_lock(self.device):
                                self._warm_motion_frame(Frame(black, seq, seq), still, budget, levels)
                            seq += 1
        finally:
            self._rig = serving
            if self._global is not None:  # the black frames are no one's previous frame
                self._global = GlobalMotion(self.width, self.height)
                self._align_has_prev = False
                self._consensus_H = None
                self.prior_aligned = dict.fromkeys(self.prior_aligned, 0)

    def _warm_prior_frame(self, frame: Frame) -> None:
        """One frame of the kind without a motion whose tracks start from the image motion (the identity here):
        launched, or captured on the kind's second use."""
        self._marks = {}
        self._cur = cur = 1 - self._cur
        self._to_staging(frame.image)
        if self._align is not None:  # the alignment's graphs too (each parity's, captured on its second use)
            self._align.make(self._frame)
            self._align.align(np.eye(3))
        self._aligning = None
        self._launch_image_stages()
        self._use_prior(np.eye(3))
        try:
            self._process_frame(frame, time.perf_counter(), cur)
        finally:
            self._clear_prior()

    def _warm_motion_frame(self, frame: Frame, motion: FrameMotion, budget: int, lk_levels: int) -> None:
        """One frame of the kind (a motion, ``budget`` tracks, ``lk_levels`` LK levels) whatever its motion
        would choose: launched, or captured on the kind's second use (``_process_frame``)."""
        self._marks = {}
        self._cur = cur = 1 - self._cur
        self._stage_image(frame.image, motion)
        try:
            self._set_motion(motion, epipolar.OwnStartDepths(np.zeros(0), np.zeros(0)))
            self._budget, self._lk_levels = budget, lk_levels
            self._process_frame(frame, time.perf_counter(), cur)
        finally:
            self._clear_motion()

    def _clear_motion(self) -> None:
        """Back to a frame without a motion: LK from the tracks' last positions, all levels, the usual budget."""
        self._use_guess.fill_(0)
        self._motion = None
        self._lk_levels = self.levels
        self._budget = self.config.max_features

    @property
    def use_graphs(self) -> bool:
        """Whether frames replay CUDA graphs (False off CUDA, after a failed capture, or when switched off)."""
        return self._graphs.enabled and self._image_graphs.enabled

    @use_graphs.setter
    def use_graphs(self, on: bool) -> None:
        self._graphs.enabled = self._image_graphs.enabled = bool(on) and self.device.is_cuda

    def process(self, frame: Frame, motion: FrameMotion | None = None) -> Observations:
        with device_lock(self.device):
            return self._process(frame, motion)

    def _set_motion(self, motion: FrameMotion | None, depths: epipolar.OwnStartDepths | None = None) -> None:
        """The frame's motion to the device: each slot's own depth (``depths``: ``epipolar.own_start_depths``;
        the device borrows the others' from their neighbours), the flag that makes LK start from the predicted
        positions, LK's pyramid levels for the prediction's uncertainty and the frame's track budget
        (``epipolar.prediction_plan``). The depths and the motion go up through pinned buffers, and the
        prediction kernels read them there (a captured graph replays them)."""
        self._motion = motion
        self._lk_levels = self.levels
        self._budget = self.config.max_features
        if motion is None:
            return
        _, _, ids, uv = self._last
        depth = depths.depth
        self._budget, lk_levels = epipolar.prediction_plan(self.config, self.pyramid_levels, (self.width, self.height),
                                                           uv, ids, depths.plan, motion, self.camera.K,
                                                           depths.moved_sq, depths.terms)
        self._lk_levels = lk_levels + 1  # (with full resolution)
        self._depth_range = motion.depth_range_m
        depth_up, T_up, range_up = self._motion_up_np
        depth_up[:] = 0.0
        depth_up[:len(depth)] = np.nan_to_num(depth, nan=0.0)
        T_up[:], range_up[:] = predict.motion_params(motion.T_cur_prev, motion.depth_range_m)
        for target, source in zip((self._own_depth, self._motion_T, self._inverse_range), self._motion_up):
            wp.copy(target, source)
        self._use_guess.fill_(1)

    def _process(self, frame: Frame, motion: FrameMotion | None = None) -> Observations:
        self._marks = {}
        t0 = time.perf_counter()
        self._cur = cur = 1 - self._cur
        self._stage_image(frame.image, motion)
        self._stereo_prior = (self._last[2], self._last[3], motion)  # (arrays replaced, never written in place)
        try:
            depths = None
            if motion is not None and self._n_tracks > 0:
                _, _, ids, uv = self._last
                depths = epipolar.own_start_depths(uv, ids, motion, self.camera.K, (self.width, self.height))
            # (a small motion: the frame's captured graph replays, as without a motion)
            self._set_motion(motion if depths is not None else None, depths)
            self._set_prior(motion)
            return self._process_frame(frame, t0, cur)
        finally:
            if self._motion is not None:
                self._clear_motion()
            if self._prior:
                self._clear_prior()

    def _start_prior(self, motion: FrameMotion | None) -> bool:
        """For a frame without a motion (and the prior on): the alignment image, then ECC from the last frame's
        motion, launched without waiting (``_set_prior`` collects them). On CUDA they go on the side stream once
        the frame is up, so they run beside the image stages: neither needs the other. Whether they went there."""
        self._aligning = None
        if self._global is None or motion is not None:
            return False
        first = self._global.last if self._align_has_prev and plausible(self._global.last) else None

        def launches():
            self._align.make(self._frame)
            if first is not None:
                self._align.launch_align(self._global.to_alignment(first))

        beside = self._on_side(launches)
        self._aligning = first
        return beside

    @property
    def _side(self):
        """The second stream for work beside the main one (CUDA), or None: off CUDA, and when profiling (stage
        times need one stream)."""
        return self._side_stream if not self.profile else None

    def _on_side(self, launches: Callable[[], None]) -> bool:
        """``launches()`` on the side stream after the main stream's work so far (CUDA; else where they are):
        whether they went there."""
        side = self._side
        if side is None:
            launches()
            return False
        side.wait_stream(wp.get_stream(self.device))
        with wp.ScopedStream(side, sync_enter=False):
            launches()
        return True

    def _set_prior(self, motion: FrameMotion | None) -> None:
        """A frame without a motion: its image motion from a dense alignment with the last frame
        (``frontend.global_motion``), and LK starts every track from it (``predict.prior_starts``). The frame's
        alignment image is made on the device from its grey levels, and ECC runs there from the last frame's
        motion and the tracks' consensus (``warp.global_motion``); a frame those seeds do not align well goes to
        the host's other seeds, with the two alignment images brought down. A frame with a motion costs nothing
        here (the next has no prior), a small one included (the pose source says the image barely moved: the
        tracks start where they were)."""
        if self._global is None:
            return
        if motion is not None:
            self._global.forget()
            self._align_has_prev = False
            return
        has_prev, self._align_has_prev = self._align_has_prev, True  # (its image was made: _start_prior)
        if not has_prev:
            self._global.forget()
            return
        seeds = () if self._consensus_H is None else (self._consensus_H,)
        H, tried = self._device_prior(seeds)
        if H is not None:
            self.prior_aligned["device"] += 1
        else:  # the host's other seeds, the device's alignments competing as they are
            H = self._global.estimate_images(*self._align.download(), seeds, aligned=tuple(tried))
            self.prior_aligned["host" if H is not None else "none"] += 1
        if H is None or self._n_tracks == 0:
            return
        self._use_prior(H)

    def _device_prior(self, seeds: tuple[np.ndarray, ...]) -> tuple[np.ndarray | None, list[tuple]]:
        """The frame's motion (full-resolution pixels) from ECC on the device, started from the last frame's
        motion, then from each seed, taken where it aligns well (``GOOD_CORRELATION``; else None), and the
        alignments made: (start, correlation, homography or None), alignment pixels."""
        tried: list[tuple] = []
        starts = DistinctStarts((self._align.h, self._align.w))
        for seed in (self._global.last, *seeds):
            if not plausible(seed):
                continue
            H0 = self._global.to_alignment(seed)
            if not starts.new(H0):
                continue
            if self._aligning is None or seed is not self._aligning:  # (else launched by _start_prior)
                self._on_side(lambda: self._align.launch_align(H0))
            rho, H = self._align.collect()
            tried.append((H0, rho, H))
            if H is not None and plausible(H) and rho >= GOOD_CORRELATION:
                full = self._global.to_full(H)
                self._global.took(full)
                return full, tried
        return None, tried

    def _use_prior(self, H: np.ndarray) -> None:
        """This frame's tracks start where the homography H (pixels, previous frame -> this one) puts them: H up
        through its pinned buffer, LK from the guesses, the prior's kind of frame."""
        self._prior_up_np[0] = H / H[2, 2]
        wp.copy(self._prior_H, self._prior_up)
        self._use_guess.fill_(1)
        self._prior = True
        self._lk_levels = self._prior_lk_levels

    def _clear_prior(self) -> None:
        """Back to a frame without the prior: LK from the tracks' last positions, all levels."""
        self._prior = False
        self._use_guess.fill_(0)
        self._lk_levels = self.levels

    def _read_consensus(self) -> np.ndarray | None:
        """The homography (pixels) of the frame's tracks' consensus, when the frame found one (a seed of the next
        frame's alignment)."""
        if self._global is None or self._motion is not None or self.config.consensus_px <= 0:
            return None
        best, agreed = self._consensus_out_np
        if int(agreed[0]) <= 0:
            return None
        cx, cy, s = self._consensus.frame
        N = np.array([[1.0 / s, 0.0, -cx / s], [0.0, 1.0 / s, -cy / s], [0.0, 0.0, 1.0]])
        H = np.linalg.inv(N) @ np.asarray(best[0], np.float64) @ N
        return H / H[2, 2] if np.isfinite(H).all() and abs(H[2, 2]) > 1e-12 else None

    def _process_frame(self, frame: Frame, t0: float, cur: int) -> Observations:
        # On CUDA a frame is one graph replay per kind of frame, captured on the kind's second use (once every
        # kernel module is loaded and the scan's scratch exists); elsewhere, and when profiling, launches.
        kind = FrameKind(cur, self._motion is not None, self._lk_levels, self._budget, self._rescuing(), self._prior)
        self._graphs.run(kind, self._frame_kernels, graphs=not self.profile)
        # the surviving tracks' results and colours are read while detection runs (new tracks only append)
        if self._tracked is not None:
            wp.synchronize_event(self._tracked)
        per_track, counts_ids = self._kept_np
        kept = int(counts_ids[0])
        kept_uv = per_track[:kept, :2].astype(np.float64)
        kept_ids = counts_ids[RESULT_HEADER:RESULT_HEADER + kept].astype(np.int64)
        kept_colors = self._colors_at(frame.image, per_track[:kept, 2:])
        if self._done is not None:
            wp.synchronize_event(self._done)  # an event on the frame's stream: cheaper than the whole device
        else:
            wp.synchronize_device(self.device)
        per_track, counts_ids = self._all_np
        n, n_new, n_tracked = int(counts_ids[0]), int(counts_ids[1]), int(counts_ids[2])
        self._consensus_H = self._read_consensus()
        self._n_tracks = n
        uv = np.concatenate([kept_uv, per_track[kept:n, :2]])
        ids = np.concatenate([kept_ids, counts_ids[RESULT_HEADER + kept:RESULT_HEADER + n]])
        colors = np.concatenate([kept_colors, self._colors_at(frame.image, per_track[kept:n, 2:])])
        t_end = time.perf_counter()
        timings = {"total": t_end - t0}
        if self.profile:
            m = self._marks
            timings.update({"upload": m["upload"] - t0, "prepare": m["prepare"] - m["upload"],
                            "lk": m["lk"] - m["prepare"], "drift_check": m["track"] - m["lk"],
                            "detect": t_end - m["track"]})
        self._last = (frame.seq, frame.t_ns, ids, uv)
        funnel = {"corners": n_new, "after_lk": n_tracked, "after_drift_check": kept}
        return Observations(frame.seq, frame.t_ns, ids, uv, colors, n_new, timings, funnel=funnel)

    def match_view(self, image: np.ndarray, camera: CameraModel, T_other_this: np.ndarray,
                   camera_index: int = 1) -> Observations:
        """The live tracks of the last processed frame found in another camera's simultaneous image: this
        frame's tracker image comes back from the device once, then the epipolar sweep, LK and the
        forward-backward check of ``epipolar.match_across`` run on the host."""
        seq, t_ns, ids, uv = self._last
        if not self._rig:
            self._start_rig()
        if len(ids) == 0:
            return Observations(seq, t_ns, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3), np.uint8),
                                camera=camera_index)
        with device_lock(self.device):
            this = self._pyr[self._cur].numpy()[: self.width * self.height].reshape(self.height, self.width)
        shading = self._sigma > 0
        this_u8 = to_u8(this) if shading else np.clip(this * 255.0 + 0.5, 0, 255).astype(np.uint8)
        color = undistort_view(image, camera, self._views)
        other_u8, other_float = tracker_image(cv2.cvtColor(color, cv2.COLOR_BGR2GRAY), self.config,
                                             self.pyramid_levels)
        lk_params = epipolar.lk_params(self.config.window_px, self.pyramid_levels)
        search = (stereo_depth.search_ranges(uv, stereo_depth.carried_depths(
            ids, *stereo_depth.known_depths(*self._stereo_prior), self.camera.K), (self.width, self.height),
            self._depth_range) if self.config.stereo_depth_prior else None)
        found_uv, found = epipolar.match_across(this_u8, this, other_u8, other_float, uv, self.camera.K, camera.K,
                                                np.asarray(T_other_this, np.float64), self._depth_range, lk_params,
                                                self.config.drift_max_residual, search)
        return Observations(seq, t_ns, ids[found].copy(), found_uv[found], colors_at(color, found_uv[found]),
                            camera=camera_index)

    def _start_rig(self) -> None:
        """The front-end serves a rig from now on: its frames may rescue new tracks. The live tracks' first
        patches on the smoothed image are this frame's (only those found in it can be rescued, at their first
        step), and those found in it are new. (Under the device's lock: a frame in progress on another thread
        sees the rig from its start or not at all.)"""
        with device_lock(self.device):
            self._rig = True
            if not self._rescue_on:
                return
            cur = self._cur
            self._rescue_image_kernels()
            drift_check.rescue_start(self._rescue_img, self.width, self.height, self._pts[cur], self._count[cur],
                                     self._n_new, self._ref_smooth[cur], self._rescue_state[cur], self.device)
