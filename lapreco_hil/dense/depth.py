"""A depth map per keyframe by multi-view stereo: a plane sweep in inverse depth against a few neighbouring
keyframes with known poses, coarse to fine, in Warp (one code for the CPU and CUDA).

1. Each view to centred grey; the reference's field of view (``KeyframeView.mask``) and saturated specular
   highlights (near-white, low saturation, dilated) are excluded in every view, so a source's highlight spoils
   only that view's score. Prepared views stay on the device by kf_id (``[depth] cached_views``): a keyframe is
   the source of several others and is uploaded and prepared once.
2. Half resolution: fronto-parallel planes evenly spaced in inverse depth over the keyframe's landmark range (a
   configured default without one), spaced so that no source's image moves more than ``coarse_step_px`` between
   planes. Per plane and source, ZNCC over a window, its sums made per device (``DepthEstimator``'s ``sweep``):
   sliding along rows then columns on the CPU, per pixel from the window's taps on CUDA; a plane's score is the
   mean of its ``best_k`` best sources (an occluded or highlighted view drops out). Best
   plane, parabola through its neighbours, and the second-best local maximum for the margin.
3. Full resolution: ``fine_planes`` planes about the coarse depth (bilinear) spanning +-``fine_range_px`` of
   image motion, again with a parabola: sub-pixel depth at a fraction of a full-resolution sweep's cost.
4. Checks, in order, each counted in ``DepthMap.stats['funnel']`` (``FUNNEL``): in view (the mask), not a
   highlight, textured (ZNCC is undefined on flat windows), matched (best score and margin), in range (the best
   plane not at the range's end: the surface lies outside the landmarks' range), off edges (windows across a
   depth edge fatten the foreground), refined (the fine best not at its end), views agree (at least
   ``min_views`` sources each score the final depth well on their own: something that moved between the views,
   an instrument, fails it), supported (wrong matches come as specks and slivers, surfaces as regions), and,
   where the sources' own depth maps are given, geometry agrees (forward-backward through the source's map).

The steps are queued on the device and waited for once, when the map (or, left on the device, its funnel)
is read back: the host queues the next step while the device works (``DepthEstimator``'s ``profile`` waits at
each step's end, to time them).

``[depth] method = "patchmatch"`` replaces steps 3-4's fine sweep by slanted windows: the coarse depth refined
with a plane per pixel (red-black PatchMatch at half resolution, warp/patchmatch.py), scored at full resolution,
its support and depth edges measured against each pixel's plane (docs/dense.md, "Slanted windows").
"""

from __future__ import annotations

import hashlib
import logging
import math
import sys
import time
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.warp import patchmatch as pm
from lapreco_hil.dense.warp import plane_sweep as k
from lapreco_hil.dense.types import DepthMap, KeyframeView
from lapreco_hil.errors import ConfigError, ReconstructionError
from lapreco_hil.warp_device import device_lock, init_warp

log = logging.getLogger(__name__)

# pixels kept after each check, in order (a pixel's rejection code k: it failed FUNNEL[k + 1])
FUNNEL = ("pixels", "in_view", "not_highlight", "textured", "matched", "in_range", "off_edges", "refined",
          "views_agree", "supported", "geometry_agrees")
DEFAULT_SCENE_DEPTH_M = 0.1  # choose_sources' scene depth for a keyframe with no landmark range
PREFERRED_ANGLE_DEG = 5.0  # choose_sources ranks views by how close their triangulation angle is to this
SWEEPS = ("sliding", "windowed")  # how the window sums are made: DepthEstimator's ``sweep``
METHODS = ("sweep", "patchmatch")  # [depth] method
# rows per thread of the windowed sweep: long enough that the 2r rows summed before the first score are a small
# overhead, short enough for millions of threads at half 1080p; a multiple of 7 (sweep_window_ring's unrolled ring)
WINDOW_BAND_ROWS = 56
COUNT_SPAN = 64  # pixels of a row per thread of the funnel's histogram
# what a map asks of the device (``stats["device_ops"]``): kernel launches (memsets included), copies into and
# out of device arrays and their bytes (on the CPU device a write or read of the array's memory), waits for the
# device, and allocations (device buffers, and page-locked host ones on CUDA)
DEVICE_OPS = ("launches", "uploads", "uploaded_bytes", "downloads", "downloaded_bytes", "synchronisations",
              "allocations")
_ALL_IN_VIEW = object()  # the device's mask holds ones (a view without a mask)
# host buffers for depth maps an estimator keeps (page-locked from CUDA: 16.6 MB each at 1080p, and page-locking
# takes milliseconds: worth it for an estimator that makes many maps)
HOST_BUFFERS = 3


def window_radius(config: DepthConfig, n_src: int) -> int:
    """The ZNCC window's radius for a map of ``n_src`` sources. A plane's score is the mean of its ``best_k`` best
    sources' windows; with fewer sources than that (a two-view pair: one) the window grows until it holds as many
    samples as ``best_k`` windows of ``window_radius_px`` do (one view's score is as noisy as its samples are
    few): 11x11 for one source against two 7x7 (docs/dense.md, "Two views")."""
    r = config.window_radius_px
    used = min(config.best_k, n_src)
    while (2 * r + 1) ** 2 * used < (2 * config.window_radius_px + 1) ** 2 * config.best_k:
        r += 1
    return r


def _half_K(K: np.ndarray) -> np.ndarray:
    """Intrinsics of the 2x2-mean half-resolution image (pixel centres: x_half = (x + 0.5) / 2 - 0.5); of each
    of a stack of (..., 3, 3) intrinsics."""
    Kh = np.array(K, float)
    Kh[..., 0, 0] *= 0.5
    Kh[..., 1, 1] *= 0.5
    Kh[..., 0, 1] *= 0.5
    Kh[..., 0, 2] = (Kh[..., 0, 2] + 0.5) * 0.5 - 0.5
    Kh[..., 1, 2] = (Kh[..., 1, 2] + 0.5) * 0.5 - 0.5
    return Kh


def _homography_terms(ref: KeyframeView, sources: list[KeyframeView]) -> tuple[tuple, tuple]:
    """Per source, source pixel ~ A @ (x, y, 1) + rho * b for a fronto-parallel plane at inverse depth rho in the
    reference: ((A, b) at half resolution, (A, b) at full resolution), each (S, 3, 3) and (S, 3), every source
    at once (the same products as one source at a time, in a tenth of the time)."""
    K_ref = np.asarray(ref.K, float)
    K_src = np.stack([np.asarray(s.K, float) for s in sources])
    T_src_world = np.linalg.inv(np.stack([np.asarray(s.T_world_camera, float) for s in sources]))
    T_src_ref = T_src_world @ np.asarray(ref.T_world_camera, float)
    R, t = T_src_ref[:, :3, :3], T_src_ref[:, :3, 3:]
    return tuple((Ks @ R @ np.linalg.inv(Kr), (Ks @ t)[..., 0])
                 for Kr, Ks in ((_half_K(K_ref), _half_K(K_src)), (K_ref, K_src)))


def _max_shift_px(A: np.ndarray, b: np.ndarray, size: tuple[int, int], rho_lo: float, rho_hi: float) -> float:
    """The largest image motion in any source between the nearest and the farthest plane, over a grid of pixels
    (A, b: every source's homography terms)."""
    w, h = size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5))
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    p_lo = A @ pts + rho_lo * b[:, :, None]
    p_hi = A @ pts + rho_hi * b[:, :, None]
    ok = (p_lo[:, 2] > 1e-9) & (p_hi[:, 2] > 1e-9)
    if not ok.any():
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        d = p_hi[:, :2] / p_hi[:, 2:] - p_lo[:, :2] / p_lo[:, 2:]
    return float(np.max(np.hypot(d[:, 0], d[:, 1])[ok]))


@dataclass
class _Sweep:
    """The device buffers of one sweep level (allocated once per image size and source count)."""

    rows: object  # (h, w) vec3: reference window row sums
    std: object  # (h, w) reference window standard deviation, 0 where not textured
    base: object  # (h, w) inverse depth each plane offsets
    sums: object  # (S, P, h, w) vec6 window row sums: the sliding sweep's (None for the windowed one)
    samples: object  # (S, P, h, w) warped source grey: the windowed sweep's (the sliding one samples into zncc)
    zncc: object  # (S, P, h, w)
    plane: object
    best: object
    second: object


def _fingerprint(view: KeyframeView) -> bytes:
    """What tells a cached view's image from another with the same kf_id: a digest of every 16th pixel of every
    16th row of the colour and the mask, 0.07 ms at 1080p (a keyframe's image does not change;
    ``DepthEstimator.forget`` is for a caller whose does). Not taken when the view brings the very arrays its
    cached entry was prepared from (``_CachedView``)."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(repr(view.colour.shape).encode())
    digest.update(np.ascontiguousarray(view.colour[::16, ::16]).tobytes())
    if view.mask is not None:
        digest.update(np.ascontiguousarray(view.mask[::16, ::16], np.uint8).tobytes())
    return digest.digest()


def _no_referent() -> None:
    return None


def _ref(array):
    """A weak reference to ``array`` (None for None; one that refers to nothing for an object that takes none)."""
    if array is None:
        return None
    try:
        return weakref.ref(array)
    except TypeError:
        return _no_referent


def _refers_to(ref, array) -> bool:
    """Whether ``ref`` (``_ref``'s) refers to ``array`` itself (both None: True)."""
    return ref is None if array is None else (ref is not None and ref() is array)


class _CachedView(NamedTuple):
    """A prepared view in the device cache: its slot, its image's fingerprint, and weak references to the colour
    and mask arrays it was prepared from (a view that brings these same arrays is not fingerprinted again)."""

    slot: int
    fingerprint: bytes
    colour: object
    mask: object


class DepthEstimator:
    """Computes depth maps on one device, reusing its buffers from one keyframe to the next (they are made again
    only when the image size or the number of source views changes), and keeping the last ``cached_views``
    keyframes' prepared images there: a keyframe is the source of several others, and is prepared once.

    ``sweep`` picks how the window sums are made (see plane_sweep's docstring): "sliding" (the CPU's default) or
    "windowed" (CUDA's); both give the same depth maps up to float rounding. Depth maps come out in
    ``host_buffers`` kept host buffers (page-locked from CUDA), each reused once no map refers to it (0: a new
    pageable buffer per map, for an estimator that makes one map); or, with ``compute(..., on_device=True)``, stay
    on the device for a caller that uses them there (the TSDF volume fuses them with no trip through the host;
    ``view_colour`` gives a cached view's colour there too).

    A map's steps are queued on the device's current stream and waited for once, at its read-back; ``profile``
    (a benchmark's switch) waits at each step's end instead, so that ``stats["times_ms"]`` times the steps
    themselves (else each step's figure is the host's time to queue it, and the last one's includes the wait).
    ``stats["device_ops"]`` counts what the device was asked for the map (``DEVICE_OPS``)."""

    def __init__(self, config: DepthConfig, device: str, sweep: str | None = None,
                 host_buffers: int = HOST_BUFFERS, profile: bool = False) -> None:
        self.wp = init_warp()
        self.config = config
        self.device = device
        self.profile = profile
        self._cuda = self.wp.get_device(device).is_cuda
        if sweep is None:
            sweep = "windowed" if self._cuda else "sliding"
        if sweep not in SWEEPS:
            raise ConfigError(f"DepthEstimator sweep {sweep!r} is none of {', '.join(SWEEPS)}")
        self.sweep = sweep
        self.ops = dict.fromkeys(DEVICE_OPS, 0)  # the current (or last) map's
        self._commands: dict[tuple, tuple] = {}  # recorded launches (``_launch``)
        self._shape: tuple | None = None
        self._check_shape: tuple | None = None
        self._view_shape: tuple | None = None
        self._cached: OrderedDict[int, _CachedView] = OrderedDict()  # kf_id -> its cached view, LRU first
        self._mask_of = None  # what the device's mask holds: _ALL_IN_VIEW, a weak reference to a host mask, None
        self._host_buffers: list[tuple[object, np.ndarray]] = []
        self._host_refs = 0
        self._keep_host_buffers = host_buffers
        self._pinned = False
        self._host_counts = None
        self._staging: list = []  # page-locked upload buffers (colour, mask): (warp array, its numpy view, event)
        if config.default_near_m >= config.default_far_m:
            raise ConfigError(f"[depth] default_near_m {config.default_near_m} must be less than "
                              f"default_far_m {config.default_far_m}")
        for name in ("method", "live_method"):
            if getattr(config, name) not in METHODS:
                raise ConfigError(f"[depth] {name} {getattr(config, name)!r} is none of {', '.join(METHODS)}")
        if config.patchmatch_far_px % 2 == 0:
            raise ConfigError(f"[depth] patchmatch_far_px {config.patchmatch_far_px} must be odd (a neighbour "
                              "of the other colour of the checkerboard)")
        if config.min_planes > config.max_planes:
            raise ConfigError(f"[depth] min_planes {config.min_planes} must not exceed max_planes "
                              f"{config.max_planes}")

    def forget(self, kf_id: int | None = None) -> None:
        """Drop a keyframe's prepared image from the device cache (without ``kf_id``: all of them, and the uploaded
        mask): for a caller that changes a keyframe's image (or, with no ``kf_id``, a mask) in place, since a view
        that brings the same arrays is taken as unchanged; and for timing the preparation."""
        if kf_id is None:
            self._mask_of = None
            self._cached.clear()
        else:
            self._cached.pop(kf_id, None)

    # --- what the device is asked (counted in ``ops``) -----------------------------------------------------
    def _alloc(self, shape, dtype):
        self.ops["allocations"] += 1
        self._commands.clear()  # (recorded launches hold the arrays they were recorded with: let old ones go)
        return self.wp.zeros(shape, dtype=dtype, device=self.device)

    def _alloc_host(self, shape, dtype, pinned: bool):
        """A host array for transfers (page-locked: an allocation the driver makes, counted as the device's)."""
        if pinned:
            self.ops["allocations"] += 1
        return self.wp.empty(shape, dtype=dtype, device="cpu", pinned=pinned)

    def _launch(self, kernel, dim, inputs: list) -> None:
        """Launch by a command recorded at the first launch with these arrays (``wp.launch(record_cmd=True)``),
        setting again only the values that changed since its last launch: a replay costs a fraction of a
        launch's argument packing (most of a map's values are the config's)."""
        key = (id(kernel), dim, *(id(a) if isinstance(a, self.wp.array) else None for a in inputs))
        recorded = self._commands.get(key)
        if recorded is None:
            command = self.wp.launch(kernel, dim=dim, device=self.device, inputs=inputs, record_cmd=True)
            # (the inputs kept with the command keep its arrays, and so the ids in its key, alive)
            self._commands[key] = (command, list(inputs))
        else:
            command, last = recorded
            for i, value in enumerate(inputs):
                if isinstance(value, self.wp.array) or (type(value) in (int, float, bool)
                                                        and type(last[i]) is type(value) and last[i] == value):
                    continue
                command.set_param_at_index(i, value)
                last[i] = value
        command.launch()
        self.ops["launches"] += 1

    def _fill(self, array, value) -> None:
        array.fill_(value)
        self.ops["launches"] += 1  # (a memset)

    def _copy_in(self, target, source, nbytes: int) -> None:
        self.wp.copy(target, source)
        self.ops["uploads"] += 1
        self.ops["uploaded_bytes"] += int(nbytes)

    def _copy_out(self, target, source) -> None:
        self.wp.copy(target, source)
        self.ops["downloads"] += 1
        self.ops["downloaded_bytes"] += int(source.capacity)

    def _synchronize(self) -> None:
        """Wait for this estimator's work: the device's current stream (not the device's other streams: the
        front-end's, say)."""
        if self._cuda:
            self.wp.synchronize_stream(self.wp.get_stream(self.device))
        self.ops["synchronisations"] += 1

    def _event(self):
        return self.wp.get_stream(self.device).record_event() if self._cuda else None

    # --- buffers ----------------------------------------------------------------------------------------------
    def _sweep_buffers(self, h: int, w: int, n_src: int, n_planes: int) -> _Sweep:
        sliding = self.sweep == "sliding"
        volume = (n_src, n_planes, h, w)
        return _Sweep(
            rows=self._alloc((h, w), self.wp.vec3), std=self._alloc((h, w), float),
            base=self._alloc((h, w), float),
            sums=self._alloc(volume, k.vec6) if sliding else None,
            samples=None if sliding else self._alloc(volume, float),
            zncc=self._alloc(volume, float),
            plane=self._alloc((h, w), float),
            best=self._alloc((h, w), float), second=self._alloc((h, w), float))

    def _ensure_checks(self, h: int, w: int) -> None:
        """The output and geometric-check buffers (all that ``check_geometry`` needs)."""
        if self._check_shape == (h, w):
            return
        wp = self.wp
        self.out = self._alloc((2, h, w), float)  # depth, confidence: one download
        self.depth = self.out[0]
        self.confidence = self.out[1]
        self.code = self._alloc((h, w), wp.uint8)
        self.counts = self._alloc(k.CODE_KEPT + 1, int)
        self.agree = self._alloc((h, w), int)
        self.supported = self._alloc((h, w), wp.uint8)
        self.src_depth = self._alloc((h, w), float)
        # host buffers that depth maps are downloaded into and handed out as they are (page-locked from CUDA: a
        # download at the bus's speed, and no copy on the host), each reused once no depth map uses it any more
        self._host_buffers = []
        self._pinned = self._cuda
        # the funnel's counts come back into a kept page-locked buffer (the map's one small read-back)
        self._host_counts = self._alloc_host(k.CODE_KEPT + 1, int, pinned=True) if self._cuda else None
        self._check_shape = (h, w)

    def _ensure_views(self, h: int, w: int, n_views: int) -> None:
        """The prepared-view cache: colour, grey at full and half resolution and each pixel's state, one slot per
        view (the colour kept so that a depth map's reference can be fused from the device)."""
        slots = max(self.config.cached_views, n_views)
        if self._view_shape is not None and self._view_shape[:2] == (h, w) and self._view_shape[2] >= n_views:
            return
        wp = self.wp
        self.colour = self._alloc((slots, h, w, 3), wp.uint8)
        self.mask = self._alloc((h, w), wp.uint8)
        self.highlight_flags = self._alloc((h, w), wp.uint8)  # the highlight pixels themselves
        self.highlight = self._alloc((h, w), wp.uint8)  # dilated: what is excluded
        self.full_grey = self._alloc((slots, h, w), float)
        self.half_grey = self._alloc((slots, h // 2, w // 2), float)
        self.state = self._alloc((slots, h, w), wp.uint8)
        # each slot's arrays, made once (indexing makes a new array each time)
        self._slot_arrays = [(self.colour[i], self.full_grey[i], self.half_grey[i], self.state[i])
                             for i in range(slots)]
        self._staging = []
        if self._cuda and self._keep_host_buffers > 0:
            for shape in ((h, w, 3), (h, w)):  # colour, mask
                host = self._alloc_host(shape, wp.uint8, pinned=True)
                self._staging.append((host, host.numpy(), None))
        self._cached.clear()
        self._mask_of = None
        self._view_shape = (h, w, slots)

    def _ensure(self, h: int, w: int, n_src: int, n_planes: int) -> None:
        """Buffers for this size and source count, and a coarse cost volume of at least ``n_planes`` planes (grown
        in steps of 16: the volume is the sweep's largest buffer)."""
        self._ensure_checks(h, w)
        self._ensure_views(h, w, n_src + 1)
        shape = (h, w, n_src)
        if self._shape == shape:
            if self.coarse.zncc.shape[1] < n_planes:
                self.coarse = self._sweep_buffers(h // 2, w // 2, n_src, 16 * math.ceil(n_planes / 16))
            return
        wp = self.wp
        self.coarse = self._sweep_buffers(h // 2, w // 2, n_src, 16 * math.ceil(n_planes / 16))
        # the refinement uses the fine level's window statistics only: no cost volume
        fine_planes = self.config.fine_planes if self.config.method == "sweep" else 0
        self.fine = self._sweep_buffers(h, w, n_src, fine_planes)
        self._ensure_parameters(n_src)
        if self.config.method == "patchmatch":
            self.pm_plane = self._alloc((h // 2, w // 2), wp.vec3)  # inverse depth and its gradient
            self.pm_score = self._alloc((h // 2, w // 2), float)
            self.pm_full_plane = self._alloc((h, w), wp.vec3)
            self.pm_unchecked = self._alloc((h, w), float)  # every scored pixel's depth (``unchecked_depth``)
        self._shape = shape

    def _ensure_parameters(self, n_src: int) -> None:
        """A map's small parameters, one device allocation uploaded in one copy: the plane homographies' terms A
        (mat33) and b (vec3), the coarse level's sources then the fine level's, and the sources' cache slots
        (int32). On CUDA they are written into a kept page-locked host twin; on the CPU device into the array."""
        wp = self.wp
        a_end, b_end = 18 * n_src, 24 * n_src
        self._parameters = self._alloc(25 * n_src, wp.float32)

        def part(start: int, n: int, dtype):
            return wp.array(ptr=self._parameters.ptr + 4 * start, shape=(n,), dtype=dtype,
                            device=self._parameters.device)

        self.A_c, self.A_f = part(0, n_src, wp.mat33), part(9 * n_src, n_src, wp.mat33)
        self.b_c, self.b_f = part(a_end, n_src, wp.vec3), part(a_end + 3 * n_src, n_src, wp.vec3)
        self.src_slots = part(b_end, n_src, wp.int32)
        self._parameters_host = self._alloc_host(25 * n_src, wp.float32, pinned=True) if self._cuda else None
        host = (self._parameters_host if self._cuda else self._parameters).numpy()
        self._parameters_event = None  # the last upload from the host twin (reused once it is read)
        self._host_A = host[:a_end].reshape(2 * n_src, 3, 3)
        self._host_b = host[a_end:b_end].reshape(2 * n_src, 3)
        self._host_slots = host[b_end:].view(np.int32)

    def _write_terms(self, terms: tuple) -> None:
        """The homography terms into the parameters' host side (waiting, on CUDA, for its last upload)."""
        if self._parameters_event is not None:
            self.wp.synchronize_event(self._parameters_event)
            self._parameters_event = None
        (A_c, b_c), (A_f, b_f) = terms
        n = len(A_c)
        self._host_A[:n] = A_c
        self._host_A[n:] = A_f
        self._host_b[:n] = b_c
        self._host_b[n:] = b_f

    def _upload_parameters(self, slots: list[int]) -> None:
        self._host_slots[:] = slots
        if self._cuda:
            self._copy_in(self._parameters, self._parameters_host, self._parameters.capacity)
            self._parameters_event = self._event()
        else:  # written in place: the CPU device's array is host memory
            self.ops["uploads"] += 1
            self.ops["uploaded_bytes"] += self._parameters.capacity

    # --- steps ------------------------------------------------------------------------------------------------
    def _slots(self, views: list[KeyframeView]) -> tuple[list[int], list[int]]:
        """Each view's slot in the prepared-view cache, preparing those that are not there (or whose image
        changed; the least recently used others make room), and the kf_ids it prepared."""
        needed = {v.kf_id for v in views}
        slots, prepared = [], []
        for view in views:
            entry = self._cached.get(view.kf_id)
            if entry is None or not (_refers_to(entry.colour, view.colour) and _refers_to(entry.mask, view.mask)):
                fingerprint = _fingerprint(view)
                if entry is None or entry.fingerprint != fingerprint:
                    slot = entry.slot if entry is not None else self._free_slot(needed)
                    self._prepare(view, slot)
                    prepared.append(view.kf_id)
                else:
                    slot = entry.slot
                entry = _CachedView(slot, fingerprint, _ref(view.colour), _ref(view.mask))
                self._cached[view.kf_id] = entry
            self._cached.move_to_end(view.kf_id)
            slots.append(entry.slot)
        return slots, prepared

    def _free_slot(self, needed: set) -> int:
        used = {entry.slot for entry in self._cached.values()}
        free = [i for i in range(self._view_shape[2]) if i not in used]
        if free:
            return free[0]
        victim = next(kf_id for kf_id in self._cached if kf_id not in needed)
        return self._cached.pop(victim).slot

    def _prepare(self, view: KeyframeView, slot: int) -> None:
        """Upload one view's colour and mask into its cache slot: grey with the field of view and dilated
        highlights excluded, its half-resolution mean, and why each pixel may not be used. The device's mask is
        uploaded only when the view brings another mask array than the last one (a camera's keyframes share
        one; like an image, a mask is not changed in place)."""
        cfg = self.config
        h, w = view.colour.shape[:2]
        colour, grey, half_grey, state = self._slot_arrays[slot]
        self._upload(0, colour, view.colour)
        if view.mask is None:
            if self._mask_of is not _ALL_IN_VIEW:
                self._fill(self.mask, 1)
                self._mask_of = _ALL_IN_VIEW
        elif self._mask_of is _ALL_IN_VIEW or not _refers_to(self._mask_of, view.mask):
            self._upload(1, self.mask, view.mask)
            self._mask_of = _ref(view.mask)
        self._launch(k.prepare_view, (h, w), [colour, self.mask, cfg.highlight_value, cfg.highlight_saturation,
                                              grey, self.highlight_flags])
        self._fill(self.highlight, 0)
        self._launch(k.dilate_scatter, (h, w), [self.highlight_flags, cfg.highlight_dilate_px, self.highlight])
        self._launch(k.exclude, (h, w), [self.mask, self.highlight, grey, state])
        self._launch(k.half_mean, (h // 2, w // 2), [grey, half_grey])

    def _upload(self, index: int, target, data: np.ndarray) -> None:
        """``data`` (cast to uint8) into the device array ``target``: on CUDA, for an estimator that keeps host
        buffers, through kept page-locked staging buffer ``index`` (a copy at the bus's speed that the GPU makes
        while the host goes on; a pageable one is staged by the driver, at a third of that), each reused once its
        last upload has been read."""
        if not self._staging:
            data = np.ascontiguousarray(data, np.uint8)
            self._copy_in(target, self.wp.array(data, dtype=self.wp.uint8, device="cpu", copy=False), data.nbytes)
            return
        host, array, uploaded = self._staging[index]
        if uploaded is not None:
            self.wp.synchronize_event(uploaded)
        np.copyto(array, data, casting="unsafe")
        self._copy_in(target, host, array.nbytes)
        self._staging[index] = (host, array, self._event())

    def _window_stats(self, level: _Sweep, ref, r: int) -> None:
        h, w = ref.shape
        self._launch(k.window_rows, (h, w), [ref, r, level.rows])
        self._launch(k.window_cols, (h, w), [level.rows, r, self.config.min_texture, self.config.min_valid_fraction,
                                             level.std])

    def _sweep(self, level: _Sweep, ref, src, A, b, rho0: float, drho: float, n_planes: int, n_src: int,
               min_scored: int, r: int) -> None:
        cfg = self.config
        h, w = ref.shape
        sample_into = level.zncc if self.sweep == "sliding" else level.samples
        self._launch(k.warp_samples, (n_src, h, w),
                     [ref, src, self.src_slots, A, b, level.base, rho0, drho, n_planes, sample_into])
        if self.sweep == "sliding":
            # the samples are in the ZNCC volume, which the column pass overwrites once the rows have summed them
            self._launch(k.sweep_rows, (n_src, n_planes, h), [ref, level.zncc, r, level.sums])
            self._launch(k.sweep_cols, (n_src, n_planes, w),
                         [level.sums, level.std, r, cfg.min_texture, cfg.min_valid_fraction, level.zncc])
        else:
            dim = (n_src, n_planes, math.ceil(h / WINDOW_BAND_ROWS), w)
            if r == k.RING_RADIUS:
                self._launch(k.sweep_window_ring, dim, [ref, level.samples, level.std, WINDOW_BAND_ROWS,
                                                        cfg.min_texture, cfg.min_valid_fraction, level.zncc])
            else:
                self._launch(k.sweep_window, dim, [ref, level.samples, level.std, r, WINDOW_BAND_ROWS,
                                                   cfg.min_texture, cfg.min_valid_fraction, level.zncc])
        self._launch(k.select_plane, (h, w), [level.zncc, n_src, n_planes, min(cfg.best_k, n_src), min_scored,
                                              level.plane, level.best, level.second])

    def _step(self, times: dict, name: str, t0: float, waited: bool = False) -> float:
        """A step's end: its time since ``t0`` (with ``profile``, once the device has done it; ``waited``: the
        step waited already)."""
        if self.profile and not waited:
            self._synchronize()
        t1 = time.perf_counter()
        times[name] = round((t1 - t0) * 1000.0, 3)
        return t1

    # --- the depth map ----------------------------------------------------------------------------------------
    def compute(self, ref: KeyframeView, sources: list[KeyframeView],
                source_depths: dict[int, DepthMap] | None = None, on_device: bool = False,
                geometry: dict[int, DepthMap] | None = None) -> DepthMap:
        """The depth map of ``ref`` against ``sources`` (see the module's docstring); ``source_depths`` (kf_id ->
        that source's own depth map) adds the forward-backward check for the sources it holds. ``on_device``: the
        map's depth and confidence are left on the device, as Warp arrays that this estimator's next ``compute``
        or ``check_geometry`` overwrites (only the funnel's counts come back; ``stats["kept_pixels"]`` says
        whether it has any depth). Either way the device has finished the map when it returns. ``geometry``
        (kf_id -> a source's map from a first pass; method "patchmatch", ``[depth] geometric_pass_weight`` > 0):
        PatchMatch scores each plane with the sources' reprojection errors through those maps too (ACMM's
        geometric consistency; warp/patchmatch.py), ``stats["geometry_sources"]`` says which sources had one."""
        # Warp's current stream is one per device for the whole process: take turns with the other threads
        # that drive this device (a CUDA graph capture in the front-end must not catch these launches)
        with device_lock(self.device):
            return self._compute(ref, sources, source_depths, on_device, geometry)

    def view_colour(self, kf_id: int):
        """A cached view's colour on the device ((H, W, 3) uint8 Warp array, as uploaded), or None when it is not
        cached; valid until the view leaves the cache (a later ``compute``)."""
        entry = self._cached.get(kf_id)
        return None if entry is None else self._slot_arrays[entry.slot][0]

    def _compute(self, ref: KeyframeView, sources: list[KeyframeView],
                 source_depths: dict[int, DepthMap] | None, on_device: bool = False,
                 geometry: dict[int, DepthMap] | None = None) -> DepthMap:
        cfg = self.config
        if not sources:
            raise ReconstructionError(f"keyframe {ref.kf_id}: a depth map needs at least one source view")
        w, h = ref.size
        for view in sources:
            if view.size != (w, h):
                raise ReconstructionError(f"keyframe {view.kf_id} is {view.size[0]}x{view.size[1]}, keyframe "
                                          f"{ref.kf_id} {w}x{h}: multi-view stereo needs views of one size")
            if view.kf_id == ref.kf_id:
                raise ReconstructionError(f"keyframe {ref.kf_id} is among its own source views")
        if len({v.kf_id for v in sources}) != len(sources):
            raise ReconstructionError(f"keyframe {ref.kf_id}: source views {[v.kf_id for v in sources]} repeat "
                                      "a keyframe")
        if w < 16 or h < 16:
            raise ReconstructionError(f"keyframe {ref.kf_id}: {w}x{h} is too small for multi-view stereo")
        n_src = len(sources)
        self.ops = dict.fromkeys(DEVICE_OPS, 0)
        times: dict[str, float] = {}
        t0 = time.perf_counter()
        near, far = ref.depth_range_m or (cfg.default_near_m, cfg.default_far_m)
        near, far = max(float(near), 1e-4), float(far)
        if far <= near:
            raise ReconstructionError(f"keyframe {ref.kf_id}: depth_range_m {ref.depth_range_m} is empty")
        rho_lo, rho_hi = 1.0 / far, 1.0 / near
        # the new reference (and any source not cached) goes to the device first: the device prepares it while
        # the host works out the planes
        self._ensure_checks(h, w)
        self._ensure_views(h, w, n_src + 1)
        slots, prepared = self._slots([ref] + list(sources))
        t0 = self._step(times, "prepare_ms", t0)

        K_ref = np.asarray(ref.K, float)
        terms = _homography_terms(ref, sources)
        shift = _max_shift_px(*terms[0], (w // 2, h // 2), rho_lo, rho_hi)
        n_planes = int(np.clip(math.ceil(shift / cfg.coarse_step_px) + 1, cfg.min_planes, cfg.max_planes))
        self._ensure(h, w, n_src, n_planes)
        drho_c = (rho_hi - rho_lo) / (n_planes - 1)
        step_px = max(shift, 1e-6) / (n_planes - 1)  # the largest image motion from one coarse plane to the next
        drho_f = 2.0 * cfg.fine_range_px / step_px * drho_c / (cfg.fine_planes - 1)
        rho0_f = -0.5 * (cfg.fine_planes - 1) * drho_f
        # every source's plane homographies and cache slot go up in one small copy
        self._write_terms(terms)
        self._upload_parameters(slots[1:])
        A_c, A_f, b_c, b_f = self.A_c, self.A_f, self.b_c, self.b_f
        fine, coarse = self.fine, self.coarse
        _, ref_full, ref_half, ref_state = self._slot_arrays[slots[0]]
        # the full-resolution window grows for few sources (``window_radius``); the coarse one stays, since a wider
        # coarse window fattens the foreground further across depth edges
        r = window_radius(cfg, n_src)
        self._window_stats(coarse, ref_half, cfg.window_radius_px)
        self._window_stats(fine, ref_full, r)
        t0 = self._step(times, "setup_ms", t0)

        # (the coarse level's base inverse depth stays 0: its planes lie at rho_lo + i drho_c)
        self._sweep(coarse, ref_half, self.half_grey, A_c, b_c, rho_lo, drho_c, n_planes, n_src,
                    max(3, math.ceil(cfg.min_scored_fraction * n_planes)), cfg.window_radius_px)
        t0 = self._step(times, "coarse_sweep_ms", t0)

        if cfg.method == "patchmatch":
            with_geometry = self._geometry(ref, sources, geometry or {}, A_f, b_f)
            t0 = self._patchmatch(times, t0, ref_state, ref_half, ref_full, A_c, b_c, A_f, b_f, n_src, rho_lo,
                                  rho_hi, drho_c, step_px, K_ref, ref.kf_id, r)
        else:
            self._launch(k.upsample_rho, (h, w), [coarse.plane, rho_lo, drho_c, 0.5 * (rho_lo + rho_hi), fine.base])
            self._sweep(fine, ref_full, self.full_grey, A_f, b_f, rho0_f, drho_f, cfg.fine_planes, n_src,
                        cfg.fine_planes, r)
            t0 = self._step(times, "fine_sweep_ms", t0)

            self._launch(k.finalise, (h, w),
                         [ref_state, ref_full, fine.std, coarse.plane, coarse.best, coarse.second, n_planes,
                          cfg.window_radius_px, cfg.max_depth_jump_px / step_px, cfg.edge_min_zncc, fine.base,
                          fine.zncc, n_src, fine.plane, fine.best, cfg.fine_planes, rho0_f, drho_f, cfg.min_zncc,
                          cfg.min_margin, cfg.margin_scale, cfg.view_min_zncc, cfg.min_views, self.depth,
                          self.confidence, self.code])
            self._launch(k.support, (h, w), [self.depth, self.code, cfg.support_radius_px, cfg.support_max_rel,
                                             cfg.min_support, self.supported])
            self._launch(k.apply_support, (h, w), [self.supported, self.depth, self.confidence, self.code])
        given = [s for s in sources if source_depths and s.kf_id in source_depths]
        if given:
            self._geometric(ref.kf_id, ref.K, ref.T_world_camera, [source_depths[s.kf_id] for s in given])
        self._fill(self.counts, 0)
        self._launch(k.count_codes, (h, math.ceil(w / COUNT_SPAN)), [self.code, COUNT_SPAN, self.counts])
        t0 = self._step(times, "checks_ms", t0)

        out, counts = self._download(with_map=not on_device)
        if on_device:
            out = (self.depth, self.confidence)
        funnel = {name: int(counts[i:].sum()) for i, name in enumerate(FUNNEL)}
        if not given:
            funnel.pop("geometry_agrees")
        self._step(times, "download_ms", t0, waited=True)
        times["total_ms"] = round(sum(times.values()), 3)
        stats = {"funnel": funnel, "times_ms": times, "profiled": self.profile, "device_ops": dict(self.ops),
                 "method": cfg.method, "planes": n_planes, "depth_range_m": (near, far), "window_radius_px": r,
                 "sources": [s.kf_id for s in sources], "geometric_sources": [s.kf_id for s in given],
                 "prepared": prepared, "kept_pixels": list(funnel.values())[-1]}
        if cfg.method == "patchmatch" and with_geometry:
            stats["geometry_sources"] = with_geometry
        log.debug("depth map of keyframe %d: %s, %.1f ms", ref.kf_id, funnel, times["total_ms"])
        return DepthMap(ref.kf_id, out[0], out[1], np.array(ref.K, float), np.array(ref.T_world_camera, float),
                        stats)

    def _geometry(self, ref: KeyframeView, sources: list[KeyframeView], maps: dict[int, DepthMap], A_f,
                  b_f) -> list[int]:
        """The PatchMatch kernels' geometric term (``pm.Geometry``, at half and full resolution): the sources'
        first-pass maps uploaded and the terms that carry a source pixel back into the reference; its weight 0
        (off) without maps or with ``geometric_pass_weight`` 0. The kf_ids of the sources with a map."""
        wp = self.wp
        cfg = self.config
        h, w = ref.size[1], ref.size[0]
        n = min(len(sources), pm.MAX_SOURCES)
        given = [s.kf_id for s in sources[:n] if s.kf_id in maps] if cfg.geometric_pass_weight > 0 else []
        shape = (n, h, w) if given else (1, 1, 1)  # (off: a placeholder the kernels do not read)
        if getattr(self, "_geo_shape", None) != (shape, n):
            self.geo_depth = self._alloc(shape, float)
            self.geo_C = self._alloc(n, wp.mat33)
            self.geo_c = self._alloc(n, wp.vec3)
            self._geo_shape = (shape, n)
            self._geo = [pm.Geometry(), pm.Geometry()]  # half, full resolution
        for geo, scale, offset in zip(self._geo, (2.0, 1.0), (0.5, 0.0)):
            geo.weight = float(cfg.geometric_pass_weight) if given else 0.0
            geo.tau = float(cfg.geometric_pass_tau_px)
            geo.scale, geo.offset = scale, offset
            geo.depth, geo.A, geo.b, geo.C, geo.c = self.geo_depth, A_f, b_f, self.geo_C, self.geo_c
        if not given:
            return []
        K_ref = np.asarray(ref.K, float)
        C = np.zeros((n, 3, 3), np.float32)
        c = np.zeros((n, 3), np.float32)
        depths = np.zeros((n, h, w), np.float32)  # a source without a map: no depth (the largest error)
        for i, s in enumerate(sources[:n]):
            T_ref_src = np.linalg.inv(np.asarray(ref.T_world_camera, float)) @ np.asarray(s.T_world_camera, float)
            C[i] = K_ref @ T_ref_src[:3, :3] @ np.linalg.inv(np.asarray(s.K, float))
            c[i] = K_ref @ T_ref_src[:3, 3]
            if s.kf_id in maps:
                if maps[s.kf_id].depth_m.shape != (h, w):
                    raise ReconstructionError(f"keyframe {s.kf_id}'s map is {maps[s.kf_id].depth_m.shape}, keyframe "
                                              f"{ref.kf_id} is {w}x{h}: the geometric term needs one size")
                depths[i] = maps[s.kf_id].depth_m
        self._assign(self.geo_depth, depths)
        self._assign_typed(self.geo_C, C, wp.mat33)
        self._assign_typed(self.geo_c, c, wp.vec3)
        return given

    def _assign_typed(self, target, values: np.ndarray, dtype) -> None:
        values = np.ascontiguousarray(values, np.float32)
        self._copy_in(target, self.wp.array(values, dtype=dtype, device="cpu", copy=False), values.nbytes)

    def _patchmatch(self, times: dict, t0: float, ref_state, ref_half, ref_full, A_c, b_c, A_f, b_f, n_src: int,
                    rho_lo: float, rho_hi: float, drho_c: float, step_px: float, K_ref: np.ndarray,
                    kf_id: int, r_full: int) -> float:
        """The coarse sweep's depth refined per pixel with slanted windows (``[depth] method = "patchmatch"``:
        warp/patchmatch.py): initialised from the sweep, red-black propagation and perturbation at half
        resolution, then each plane scored and refined at full resolution into the depth, confidence and funnel
        code (the checks that follow are the sweep's)."""
        wp = self.wp
        cfg = self.config
        h, w = ref_full.shape
        hc, wc = ref_half.shape
        focal_half = float(_half_K(K_ref)[0, 0])
        n = min(n_src, pm.MAX_SOURCES)  # the first (best) sources
        k_best = min(cfg.best_k, n)
        rho_per_px = drho_c / max(step_px, 1e-9)  # inverse depth per half-resolution pixel of image motion (at most)
        r, step = cfg.patchmatch_window_radius_px, cfg.patchmatch_window_step_px
        common = [self.src_slots, None, None, n, k_best, r, step, cfg.min_texture, cfg.min_valid_fraction]
        half = list(common)
        half[1:3] = [A_c, b_c]
        seed = (cfg.patchmatch_seed * 7919 + kf_id) % (2 ** 31 - 1)
        self._launch(pm.init_planes, (hc, wc),
                     [self.coarse.plane, rho_lo, drho_c, rho_lo, rho_hi, focal_half, cfg.patchmatch_max_slope,
                      cfg.patchmatch_perturb_slope, seed, ref_half, self.coarse.std, self.half_grey, *half,
                      self.pm_plane, self.pm_score, self._geo[0]])
        for it in range(cfg.patchmatch_iterations):
            shrink = 0.5 ** it
            for parity in (0, 1):
                self._launch(pm.propagate, (hc, (wc + 1) // 2),
                             [parity, it, seed, cfg.patchmatch_far_px, rho_lo, rho_hi, focal_half,
                              cfg.patchmatch_max_slope, cfg.patchmatch_perturb_px * rho_per_px * shrink,
                              cfg.patchmatch_perturb_slope * shrink, ref_half, self.coarse.std, self.half_grey,
                              *half, self.pm_plane, self.pm_score, self._geo[0]])
        t0 = self._step(times, "patchmatch_ms", t0)
        full = list(common)
        full[5:7] = [r_full, 1]
        full[1:3] = [A_f, b_f]
        # a full-resolution pixel's image motion is twice a half-resolution one's for the same inverse depth
        self._launch(pm.finalise_planes, (h, w),
                     [ref_state, ref_full, self.fine.std, self.pm_plane, self.full_grey, *full, rho_lo, rho_hi,
                      0.5 * drho_c, 0.5 * cfg.patchmatch_refine_px * rho_per_px, cfg.min_zncc, cfg.view_min_zncc,
                      cfg.min_views, self.depth, self.confidence, self.code, self.pm_full_plane,
                      wp.mat33(*K_ref.ravel()), wp.mat33(*np.linalg.inv(K_ref).ravel()), cfg.patchmatch_angle_weight,
                      self._geo[1], self.pm_unchecked])
        # support against the pixel's plane; the depth-edge check reaches as far as the half-resolution window does
        self._launch(pm.plane_support, (h, w),
                     [self.depth, self.pm_full_plane, cfg.support_radius_px, cfg.support_max_rel, cfg.min_support,
                      2 * cfg.patchmatch_window_radius_px, cfg.patchmatch_edge_rel, cfg.patchmatch_edge_slope,
                      float(K_ref[0, 0]), cfg.patchmatch_edge_min, self.supported])
        self._launch(pm.apply_plane_support, (h, w), [self.supported, self.depth, self.confidence, self.code])
        return t0

    def _download(self, with_map: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
        """(2, H, W) depth and confidence (``with_map``; else None), and the funnel codes' histogram, as host
        arrays of their own, after one wait."""
        array = None
        if with_map:
            host, array = self._host_buffer()
            self._copy_out(host, self.out)
        if self._host_counts is not None:
            self._copy_out(self._host_counts, self.counts)
            counts = self._host_counts
        else:  # the CPU device's array is host memory
            counts = self.counts
            self.ops["downloads"] += 1
            self.ops["downloaded_bytes"] += counts.capacity
        self._synchronize()
        return array, counts.numpy().copy()

    def _host_buffer(self) -> tuple[object, np.ndarray]:
        """A host (2, H, W) buffer no depth map uses: a kept one whose array nothing outside this estimator refers
        to (a depth map's arrays are views of it), else a new kept one up to ``host_buffers``, else a new one that
        is handed out and not kept."""
        for entry in self._host_buffers:
            if sys.getrefcount(entry[1]) <= self._host_refs:
                return entry
        if len(self._host_buffers) < self._keep_host_buffers:
            buffer = self._alloc_host(self.out.shape, float, pinned=self._pinned)
            entry = (buffer, buffer.numpy())
            self._host_buffers.append(entry)
            self._host_refs = sys.getrefcount(entry[1])  # this estimator's own references (the same each time)
            return entry
        buffer = self.wp.empty(self.out.shape, dtype=float, device="cpu")
        return buffer, buffer.numpy()

    def _assign(self, target, values: np.ndarray) -> None:
        """A host float array into the device's (a pageable copy: the geometric check's inputs)."""
        values = np.ascontiguousarray(values, np.float32)
        self._copy_in(target, self.wp.array(values, dtype=float, device="cpu", copy=False), values.nbytes)

    def unchecked_depth(self) -> np.ndarray:
        """(H, W) float32 of the last ``compute`` (method "patchmatch"): every scored pixel's depth before the
        checks (0 where none), the first-pass map of the geometric term (``compute(..., geometry=)``)."""
        return self.pm_unchecked.numpy().copy()

    def rejection_codes(self) -> np.ndarray:
        """(H, W) uint8 of the last ``compute``, for diagnostics: code k < len(FUNNEL) - 1 means the pixel failed
        the check ``FUNNEL[k + 1]`` (0: outside the mask, 1: a highlight, ...); len(FUNNEL) - 1: kept."""
        return self.code.numpy().copy()

    def check_geometry(self, depth_map: DepthMap, source_maps: list[DepthMap],
                       min_views: int | None = None) -> DepthMap:
        """``depth_map`` with only the depths that at least ``min_views`` (``geometric_min_views`` by default;
        capped at the maps given) of ``source_maps`` (other keyframes' own depth maps: its sources', or any
        neighbour's) confirm forward-backward; the funnel gains ``geometry_agrees``."""
        if not source_maps:
            return depth_map
        with device_lock(self.device):
            return self._check_geometry(depth_map, source_maps, min_views)

    def _check_geometry(self, depth_map: DepthMap, source_maps: list[DepthMap],
                        min_views: int | None = None) -> DepthMap:
        h, w = depth_map.depth_m.shape
        self.ops = dict.fromkeys(DEVICE_OPS, 0)
        self._ensure_checks(h, w)
        t0 = time.perf_counter()
        self._assign(self.depth, depth_map.depth_m)
        self._assign(self.confidence, depth_map.confidence)
        self._geometric(depth_map.kf_id, depth_map.K, depth_map.T_world_camera, source_maps, min_views)
        (depth, confidence), _ = self._download()
        stats = dict(depth_map.stats or {})
        stats["funnel"] = dict(stats.get("funnel", {}), geometry_agrees=int(np.count_nonzero(depth > 0)))
        stats["geometric_sources"] = [m.kf_id for m in source_maps]
        stats["times_ms"] = dict(stats.get("times_ms", {}),
                                 geometry_ms=round((time.perf_counter() - t0) * 1000.0, 3))
        stats["geometry_device_ops"] = dict(self.ops)
        return DepthMap(depth_map.kf_id, depth, confidence, depth_map.K, depth_map.T_world_camera, stats)

    def _geometric(self, kf_id: int, K_ref, T_world_ref, maps: list[DepthMap], min_views: int | None = None) -> None:
        """Keep the depths on the device that at least ``min_views`` (``geometric_min_views``) of the given depth
        maps confirm."""
        wp = self.wp
        cfg = self.config
        h, w = self.depth.shape
        K_ref = np.asarray(K_ref, float)
        self._fill(self.agree, 0)
        for dm in maps:
            if dm.depth_m.shape != (h, w):
                raise ReconstructionError(f"depth map of keyframe {dm.kf_id} is {dm.depth_m.shape}, keyframe "
                                          f"{kf_id}'s ({h}, {w}): the geometric check needs one size")
            T_src_ref = np.linalg.inv(np.asarray(dm.T_world_camera, float)) @ np.asarray(T_world_ref, float)
            self._assign(self.src_depth, dm.depth_m)
            K_src = np.asarray(dm.K, float)
            self._launch(k.geometric_agreement, (h, w),
                         [self.depth, wp.mat33(*np.linalg.inv(K_ref).ravel()), wp.mat33(*K_ref.ravel()),
                          wp.mat33(*T_src_ref[:3, :3].ravel()), wp.vec3(*T_src_ref[:3, 3]), wp.mat33(*K_src.ravel()),
                          wp.mat33(*np.linalg.inv(K_src).ravel()), self.src_depth, cfg.geometric_max_px,
                          cfg.geometric_max_rel, self.agree])
        need = cfg.geometric_min_views if min_views is None else min_views
        self._launch(k.apply_agreement, (h, w), [self.agree, min(need, len(maps)), self.depth,
                                                 self.confidence, self.code])


def compute_depth(ref: KeyframeView, sources: list[KeyframeView], config: DepthConfig, device: str,
                  source_depths: dict[int, DepthMap] | None = None) -> DepthMap:
    """The depth map of ``ref`` against ``sources`` (see the module's docstring); ``source_depths`` (kf_id ->
    that source's own depth map) adds the forward-backward geometric check for the sources it holds. For many
    keyframes keep one :class:`DepthEstimator`: it reuses its device buffers."""
    return DepthEstimator(config, device, host_buffers=0).compute(ref, sources, source_depths)


class KeptEstimator:
    """``compute_depth`` with one DepthEstimator kept (per config and device): a keyframe is prepared on the
    device once and serves as a source of its neighbours' maps from the cache, and the buffers (page-locked on
    CUDA) are reused. A dense surface keeps one for its life."""

    def __init__(self) -> None:
        self._estimator: DepthEstimator | None = None
        self._key: tuple[DepthConfig, str] | None = None
        self._coarse: DepthEstimator | None = None  # the coarse level's (``with_coarse_level``)
        self._coarse_key: tuple[DepthConfig, str] | None = None

    def __call__(self, ref: KeyframeView, sources: list[KeyframeView], config: DepthConfig, device: str,
                 source_depths: dict[int, DepthMap] | None = None,
                 geometry: dict[int, DepthMap] | None = None) -> DepthMap:
        return self._kept(config, device).compute(ref, sources, source_depths, geometry=geometry)

    def unchecked(self, ref: KeyframeView, sources: list[KeyframeView], config: DepthConfig,
                  device: str) -> DepthMap:
        """A first pass for the geometric term: the map of every scored pixel's depth before the checks
        (``DepthEstimator.unchecked_depth``; confidence 1 where it has one)."""
        estimator = self._kept(config, device)
        made = estimator.compute(ref, sources)
        depth = estimator.unchecked_depth()
        return DepthMap(ref.kf_id, depth, (depth > 0).astype(np.float32), made.K, made.T_world_camera, made.stats)

    def with_coarse_level(self, ref: KeyframeView, sources: list[KeyframeView], config: DepthConfig,
                          device: str, geometry: dict[int, DepthMap] | None = None) -> DepthMap:
        """The depth map, its holes that a flat window or a weak match left given the depth of a map made the same
        way from the views reduced by ``[depth] coarse_level`` (lapreco_hil.dense.coarse; its own kept estimator),
        marked in ``stats["coarse_taken"]``: for the final build, whose consistency check vets them. ``geometry``:
        the sources' first-pass maps, for the full-resolution map's geometric term (``DepthEstimator.compute``)."""
        from lapreco_hil.dense.coarse import coarse_config, coarse_into_holes, reduced_view

        estimator = self._kept(config, device)
        full = estimator.compute(ref, sources, geometry=geometry)
        factor = config.coarse_level
        w, h = ref.size
        if factor < 2 or min(w, h) // factor < 16:
            return full
        codes = estimator.rejection_codes()
        if self._coarse_key != (config, str(device)):
            # (its texture threshold scaled to the reduced image's noise: ``coarse_config``)
            self._coarse = DepthEstimator(coarse_config(config), device, host_buffers=0)
            self._coarse_key = (config, str(device))
        coarse = self._coarse.compute(reduced_view(ref, factor), [reduced_view(s, factor) for s in sources])
        return coarse_into_holes(full, codes, coarse, factor, config.coarse_max_rel, config.coarse_weight, device)

    def compute_on_device(self, ref: KeyframeView, sources: list[KeyframeView], config: DepthConfig,
                          device: str):
        """The depth map with its depth and confidence left on the device (``DepthEstimator.compute``'s
        ``on_device``), and the reference's colour there: (DepthMap, (H, W, 3) uint8 Warp array). Both are the
        estimator's buffers, valid until its next map."""
        estimator = self._kept(config, device)
        depth_map = estimator.compute(ref, sources, on_device=True)
        return depth_map, estimator.view_colour(ref.kf_id)

    def check_geometry(self, depth_map: DepthMap, maps: list[DepthMap], config: DepthConfig, device: str,
                       min_views: int) -> DepthMap:
        """``DepthEstimator.check_geometry`` on the kept estimator: the depths of ``depth_map`` that at least
        ``min_views`` of the other keyframes' ``maps`` confirm."""
        return self._kept(config, device).check_geometry(depth_map, maps, min_views)

    def _kept(self, config: DepthConfig, device: str) -> DepthEstimator:
        if self._key != (config, str(device)):
            self._estimator, self._key = DepthEstimator(config, device), (config, str(device))
        return self._estimator


def compute_depths(views: list[KeyframeView], config: DepthConfig, device: str,
                   estimator: DepthEstimator | None = None) -> dict[int, DepthMap]:
    """Depth maps of every view against its ``choose_sources`` neighbours, each then checked forward-backward
    against its sources' own depth maps (views with no useful neighbour get none)."""
    estimator = estimator or DepthEstimator(config, device)
    chosen = {v.kf_id: choose_sources(v, views, config.source_views) for v in views}
    raw = {v.kf_id: estimator.compute(v, chosen[v.kf_id]) for v in views if chosen[v.kf_id]}
    return {kf_id: estimator.check_geometry(dm, [raw[s.kf_id] for s in chosen[kf_id] if s.kf_id in raw])
            for kf_id, dm in raw.items()}


def highlight_mask(colour: np.ndarray, config: DepthConfig | None = None, device: str = "cpu") -> np.ndarray:
    """(H, W) bool: saturated specular highlights (near-white, low saturation), dilated by
    ``highlight_dilate_px``: the pixels that multi-view stereo leaves out in every view."""
    wp = init_warp()
    cfg = config or DepthConfig()
    h, w = colour.shape[:2]
    with device_lock(device), wp.ScopedDevice(device):
        colour_d = wp.array(np.ascontiguousarray(colour, np.uint8))
        mask = wp.ones((h, w), dtype=wp.uint8)
        grey = wp.zeros((h, w), dtype=float)
        flags = wp.zeros((h, w), dtype=wp.uint8)
        dilated = wp.zeros((h, w), dtype=wp.uint8)
        wp.launch(k.prepare_view, dim=(h, w), inputs=[colour_d, mask, cfg.highlight_value, cfg.highlight_saturation,
                                                      grey, flags])
        wp.launch(k.dilate_scatter, dim=(h, w), inputs=[flags, cfg.highlight_dilate_px, dilated])
        return dilated.numpy().astype(bool)


def _centre(view: KeyframeView) -> np.ndarray:
    return np.asarray(view.T_world_camera, float)[:3, 3]


def choose_sources(ref: KeyframeView, candidates: list[KeyframeView], n: int) -> list[KeyframeView]:
    """Up to ``n`` neighbours of ``ref`` for multi-view stereo, best first: a stereo partner (same rig reference)
    first, then views whose triangulation angle at the scene depth lies between 2 and 30 degrees and that see
    much of what ``ref`` sees, ranked by overlap times closeness of the angle to PREFERRED_ANGLE_DEG (wide enough for
    depth resolution, narrow enough that windows still look alike)."""
    near, far = ref.depth_range_m or (DEFAULT_SCENE_DEPTH_M, DEFAULT_SCENE_DEPTH_M)
    z = 0.5 * (near + far)
    w, h = ref.size
    K_inv = np.linalg.inv(np.asarray(ref.K, float))
    xs, ys = np.meshgrid(np.linspace(0.1, 0.9, 5) * (w - 1), np.linspace(0.1, 0.9, 5) * (h - 1))
    rays = K_inv @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    T_wr = np.asarray(ref.T_world_camera, float)
    points = T_wr[:3, :3] @ (rays / rays[2] * z) + T_wr[:3, 3:4]
    centre_point = T_wr[:3, :3] @ (K_inv @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0]) * z) + T_wr[:3, 3]
    partners, ranked = [], []
    ref_group = ref.reference if ref.reference is not None else ref.kf_id
    for cand in candidates:
        if cand.kf_id == ref.kf_id:
            continue
        cand_group = cand.reference if cand.reference is not None else cand.kf_id
        if ref_group == cand_group:
            partners.append(cand)
            continue
        a = centre_point - _centre(ref)
        c = centre_point - _centre(cand)
        angle = math.degrees(math.acos(np.clip(a @ c / (np.linalg.norm(a) * np.linalg.norm(c) + 1e-12), -1, 1)))
        if not 2.0 <= angle <= 30.0:
            continue
        T_cw = np.linalg.inv(np.asarray(cand.T_world_camera, float))
        pc = T_cw[:3, :3] @ points + T_cw[:3, 3:4]
        front = pc[2] > 1e-6
        uv = np.asarray(cand.K, float) @ pc
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uv[0] / uv[2], uv[1] / uv[2]
        cw, ch = cand.size
        overlap = float(np.mean(front & (u >= 0) & (u <= cw - 1) & (v >= 0) & (v <= ch - 1)))
        if overlap < 0.3:
            continue
        ranked.append((overlap * math.exp(-math.log(angle / PREFERRED_ANGLE_DEG) ** 2 / (2 * 0.6 ** 2)), cand))
    ranked.sort(key=lambda item: -item[0])
    return (partners + [c for _, c in ranked])[:n]
