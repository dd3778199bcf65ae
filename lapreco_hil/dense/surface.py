"""The dense surface of a run: each keyframe's image kept, a depth map per reference keyframe by multi-view
stereo (``lapreco_hil.dense.depth``, or any function of the same signature), fused into a TSDF volume
(``lapreco_hil.dense.fusion``), meshed with colour.

Memory is bounded: a keyframe's undistorted image is kept JPEG-encoded in memory (``FusionConfig.jpeg_quality``)
and its fused depth map PNG-encoded (depth in 10 um steps, confidence in 1/255 steps: the map is fused as
stored, so taking it out again is exact); past ``keep_keyframes`` the oldest keyframes' images and maps are let
go (their part of the volume stays). The volume itself has its block cap.

Offline (``build``) every reference keyframe is fused once at the end with the final poses (a stereo scope's partner
views too, each a map of its own, where ``[depth] partner_maps_up_to`` says so). The incremental API
is for the live run: ``add_view`` as keyframes come, ``set_depth_ranges`` / ``fuse_pending`` when their poses
are refined, ``update_poses`` after each bundle adjustment. A fused keyframe whose new pose moves its fused points
by more than ``[fusion] refuse_shift_voxels`` is taken out with its old pose and put back with its new one (the
same depth map, re-placed) once its pose has settled: when a pose update no longer includes it (it left the
window bundle adjustment moves), or at the final build. Re-fusing at every nudge of the window was most of the
live stage's time (docs/dense.md, "Re-fusion").
"""

from __future__ import annotations

import logging
import time
from collections import Counter, OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable

import cv2
import numpy as np
import pyvista as pv

from lapreco_hil.camera import CameraModel, Rig, pinhole_canvas
from lapreco_hil.config import DepthConfig, PipelineConfig
from lapreco_hil.dense.coarse import without_coarse
from lapreco_hil.dense.fill import fill_holes
from lapreco_hil.dense.stereo_fill import fill_from, sgbm_depth
from lapreco_hil.dense.fusion import TsdfVolume
from lapreco_hil.dense.types import DepthMap, KeyframeView
from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import rotation_angle
from lapreco_hil.mapping.prediction import depth_span

log = logging.getLogger(__name__)

DepthFn = Callable[[KeyframeView, list, DepthConfig, str], DepthMap]
SourcesFn = Callable[[KeyframeView, list, int], list]
SURFACE_MODES = ("auto", "dense", "alpha")
DEPTH_UNIT_M = 1e-5  # a kept depth map's step: 10 um, up to 0.65 m
KEPT_STEPS = (DEPTH_UNIT_M, 255)  # a kept map: depth in DEPTH_UNIT_M steps (uint16), confidence in 1/255 (uint8)
CANDIDATE_FACTOR = 3  # decoded keyframe images cached: 3 x n views (and a few more)
CANDIDATE_POSES = 64  # the sources are chosen among the views this many nearest the reference (poses only)
# the final build's consistency check makes this many maps before fusing them (kept quantised: 3 bytes a pixel,
# 400 MB at 1080p), so that neighbours check each other
CONSISTENCY_CHUNK = 64


def stereo_functions() -> tuple[DepthFn | None, SourcesFn | None, str | None]:
    """Multi-view stereo's (compute_depth with a kept estimator, choose_sources), or (None, None, why) where it
    cannot be imported."""
    try:
        from lapreco_hil.dense.depth import KeptEstimator, choose_sources
    except ImportError as exc:
        return None, None, f"multi-view stereo is not available ({exc})"
    return KeptEstimator(), choose_sources, None


def same_rig_view(a, b) -> bool:
    """Whether two views (``KeyframeView`` or ``_View``) are one rig frame's: a reference keyframe and its stereo
    partners, or two partners of one reference."""
    return _rig_frame(a) == _rig_frame(b)


def _rig_frame(v) -> int:
    return v.reference if v.reference is not None else v.kf_id


def nearest_views(ref: KeyframeView, candidates: list, n: int) -> list:
    """The ``n`` candidates whose cameras are nearest the reference's (the views of its rig frame first: a reference
    keyframe's stereo partners, a partner's reference)."""
    c = ref.T_world_camera[:3, 3]
    return sorted(candidates, key=lambda v: (not same_rig_view(v, ref),
                                             np.linalg.norm(v.T_world_camera[:3, 3] - c)))[:n]


@dataclass
class DenseResult:
    """What a run's dense surface is: the mesh (with "RGB" and "Normals"), its surface points, and figures."""

    mesh: pv.PolyData
    points: np.ndarray  # (N, 3) metres, world
    normals: np.ndarray  # (N, 3)
    colours: np.ndarray  # (N, 3) uint8 RGB
    stats: dict = field(default_factory=dict)


@dataclass
class _View:
    kf_id: int
    camera: int
    reference: int | None
    T_world_camera: np.ndarray
    jpeg: bytes
    depth_range: tuple[float, float] | None = None
    # once fused: the map as stored (PNG bytes), its K, the pose it is in the volume at, its integration number
    depth_png: bytes | None = None
    confidence_png: bytes | None = None
    K: np.ndarray | None = None
    T_fused: np.ndarray | None = None
    integration: int | None = None
    encoding: Future | None = None  # the map's PNG encoding, under way in the surface's encoder thread
    reach_m: float = 0.0  # the fused map's farthest point from the camera (its far depth along the corner ray)
    moving: bool = False  # the last pose update included it: bundle adjustment's window may move it again


class DenseSurface:
    """``camera``: the rig's camera 0 (its K is every view's K after undistortion, as in the mapper); ``rig``: a
    stereo scope's cameras (None: one camera). ``depth_fn`` / ``sources_fn``: compute_depth / choose_sources of
    lapreco_hil.dense.depth by default (a test may give the renderer's true depth to test fusion apart from
    stereo)."""

    def __init__(self, camera: CameraModel, config: PipelineConfig, device: str = "cpu", rig: Rig | None = None,
                 depth_fn: DepthFn | None = None, sources_fn: SourcesFn | None = None) -> None:
        if depth_fn is None:
            depth_fn, default_sources, why = stereo_functions()
            if depth_fn is None:
                raise ConfigError(f"[surface] mode = 'dense': {why}; use --surface alpha")
            sources_fn = sources_fn or default_sources
        self.depth_fn = depth_fn
        self.sources_fn = sources_fn or nearest_views
        self.camera = camera
        self.rig = rig if rig is not None and rig.is_stereo else None
        self.config = config
        self.device = device
        # the maps' pinhole camera: camera 0's K, on a canvas that holds every rig camera's whole field of view
        cameras = [camera] if self.rig is None else [camera, *self.rig.cameras[1:]]
        self.K, self.size = (pinhole_canvas(cameras, config.depth.canvas_max_pad)
                             if config.depth.full_field_of_view else (camera.K, (camera.width, camera.height)))
        self.volume = TsdfVolume(config.fusion, device)
        self.views: OrderedDict[int, _View] = OrderedDict()
        self._undistort: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._decoded: OrderedDict[int, np.ndarray] = OrderedDict()
        self.timings = {"depth_s": 0.0, "integration_s": 0.0, "meshing_s": 0.0}
        self.fused = 0  # depth maps fused (a keyframe's each; with a stereo scope's partner views', those too)
        self.partners_fused = 0  # ... of them, stereo partner views' (``[depth] partner_maps_up_to``)
        self.sgbm_filled = 0  # two-view maps whose holes semi-global matching filled (``[depth] two_view_sgbm``)
        self.refused = 0  # re-fusions after a pose update
        self.refused_final = 0  # ... of them by the final build
        self.refusions: Counter = Counter()  # kf_id -> its re-fusions
        self.depth_failures = 0
        # per map the final build fused after its consistency check: how many other maps it was checked against
        self.checked_against: list[int] = []
        self.without_sources: set[int] = set()  # keyframes no neighbour could serve as a stereo source for
        self.released = 0
        # one thread PNG-encodes the fused maps, so the fusing thread does not wait for it
        self._encoder = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dense-png")

    # --- images -------------------------------------------------------------------------------------------
    def _maps(self, camera: int):
        """cv2.remap maps from rig camera ``camera``'s distorted frame to the pinhole ``K`` (camera 0's), and the
        field of view in that undistorted image (bool)."""
        if camera not in self._undistort:
            cam = self.camera if camera == 0 else self.rig.cameras[camera]
            self._undistort[camera] = undistortion(cam, self.K, self.size)
        return self._undistort[camera]

    def add_view(self, kf_id: int, image_bgr: np.ndarray, T_world_camera: np.ndarray, camera: int = 0,
                 reference: int | None = None) -> None:
        """Keep a keyframe's image (the grabber's distorted BGR frame of rig camera ``camera``), undistorted to
        ``K``, JPEG-encoded; ``reference``: a stereo partner's reference keyframe (as Keyframe.reference)."""
        mx, my, _ = self._maps(camera)
        undistorted = cv2.remap(image_bgr, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        ok, jpeg = cv2.imencode(".jpg", undistorted, [cv2.IMWRITE_JPEG_QUALITY, int(self.config.fusion.jpeg_quality)])
        if not ok:
            raise ConfigError(f"keyframe {kf_id}: its image could not be JPEG-encoded ({image_bgr.shape})")
        self.views[kf_id] = _View(kf_id, camera, reference, np.array(T_world_camera, float), jpeg.tobytes())
        while len(self.views) > self.config.fusion.keep_keyframes:
            old_id, _ = self.views.popitem(last=False)
            self._decoded.pop(old_id, None)
            self.released += 1

    def _colour(self, kf_id: int) -> np.ndarray:
        """A kept view's undistorted RGB image (a few decoded ones cached)."""
        if kf_id in self._decoded:
            self._decoded.move_to_end(kf_id)
            return self._decoded[kf_id]
        bgr = cv2.imdecode(np.frombuffer(self.views[kf_id].jpeg, np.uint8), cv2.IMREAD_COLOR)
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        self._decoded[kf_id] = rgb
        while len(self._decoded) > CANDIDATE_FACTOR * max(self.config.depth.source_views,
                                                          self.config.depth.final_source_views) + 2:
            self._decoded.popitem(last=False)
        return rgb

    def keyframe_view(self, kf_id: int) -> KeyframeView:
        v = self.views[kf_id]
        return KeyframeView(kf_id, self._colour(kf_id), self.K.copy(), v.T_world_camera.copy(),
                            mask=self._maps(v.camera)[2], depth_range_m=v.depth_range, reference=v.reference)

    # --- poses and ranges ---------------------------------------------------------------------------------
    def set_depth_ranges(self, ranges: dict[int, tuple[float, float] | None]) -> None:
        for kf_id, r in ranges.items():
            if kf_id in self.views:
                self.views[kf_id].depth_range = r

    def update_poses(self, poses: dict[int, np.ndarray], settled: bool = False) -> int:
        """New refined poses of kept keyframes: after a local bundle adjustment, its window's (``settled``: final
        poses, the final build's). A fused keyframe is re-fused (taken out at the pose it was fused at, put back at
        its new one) once its pose has settled and only if the move shifts its fused points by more than ``[fusion]
        refuse_shift_voxels`` (``shift_bound``). Settled: this update leaves out a keyframe the previous one held
        (it left the window and bundle adjustment no longer moves it), or ``settled``. A keyframe still in the
        window waits, however far it moves: each window nudges it, and re-fusing at every nudge cost most of the
        live stage's time. Returns how many were re-fused."""
        settling = []
        for kf_id, T in poses.items():
            v = self.views.get(kf_id)
            if v is None:
                continue
            v.T_world_camera = np.array(T, float)
            v.moving = not settled
            if settled:
                settling.append(v)
        if not settled:
            for v in self.views.values():
                if v.moving and v.kf_id not in poses:
                    v.moving = False
                    settling.append(v)
        fc = self.config.fusion
        limit = fc.refuse_shift_voxels * fc.voxel_m
        moved = 0
        for v in settling:
            if v.T_fused is None or shift_bound(v.T_fused, v.T_world_camera, v.reach_m) <= limit:
                continue
            self._refuse(v)
            moved += 1
        self.refused += moved
        return moved

    def _refuse(self, v: _View) -> None:
        """Take a fused keyframe's kept map out at the pose it was fused at and put it back at its current one."""
        depth = self._stored_map(v)
        colour = self._colour(v.kf_id)
        t0 = time.perf_counter()
        self.volume.deintegrate(depth, colour, integration=v.integration, quantise=KEPT_STEPS)
        depth.T_world_camera = v.T_world_camera.copy()
        v.integration = self.volume.integrate(depth, colour, quantise=KEPT_STEPS)
        v.T_fused = v.T_world_camera.copy()
        self.timings["integration_s"] += time.perf_counter() - t0
        self.refusions[v.kf_id] += 1

    # --- fusion -------------------------------------------------------------------------------------------
    def _stored_map(self, v: _View) -> DepthMap:
        self._encoded(v)
        depth = cv2.imdecode(np.frombuffer(v.depth_png, np.uint8), cv2.IMREAD_UNCHANGED)
        conf = cv2.imdecode(np.frombuffer(v.confidence_png, np.uint8), cv2.IMREAD_UNCHANGED)
        return _dequantised(v.kf_id, depth, conf, v.K, v.T_fused.copy())

    @staticmethod
    def _encoded(v: _View) -> None:
        """Wait for the view's map to be PNG-encoded (if it is being)."""
        if v.encoding is not None:
            v.depth_png, v.confidence_png = v.encoding.result()
            v.encoding = None

    def _fuse_and_keep(self, v: _View, depth: DepthMap, colour: np.ndarray) -> None:
        """Fuse a new map as it will be kept (quantised on the device, ``KEPT_STEPS``) and keep that quantised
        map, PNG-encoded in the encoder thread (off the fusing thread: cv2 lets go of the GIL), so taking it
        out again later is exact."""
        if v.reference is not None and v.T_fused is None:
            self.partners_fused += 1
        v.integration = self.volume.integrate(depth, colour, quantise=KEPT_STEPS)
        d16, c8 = self.volume.quantised_map()
        v.K = np.array(depth.K, float)
        v.T_fused = np.array(depth.T_world_camera, float)
        v.reach_m = reach(v.K, d16)
        self._encoded(v)  # (a map made again for the same keyframe: the old encoding first)
        v.depth_png = v.confidence_png = None
        v.encoding = self._encoder.submit(_encode_pngs, d16, c8)

    def _sources(self, ref: KeyframeView, n: int | None = None) -> list[KeyframeView]:
        n = n or self.config.depth.source_views
        c = ref.T_world_camera[:3, 3]
        others = [v for v in self.views.values() if v.kf_id != ref.kf_id]
        others.sort(key=lambda v: (not same_rig_view(v, ref), np.linalg.norm(v.T_world_camera[:3, 3] - c)))
        # chosen on poses alone among many (an image stands in by its shape; only the chosen few are decoded): the
        # nearest keyframes are often too close for depth resolution, the best angle lies farther along the path
        w, h = self.size
        shape_only = np.broadcast_to(np.zeros((1, 1, 3), np.uint8), (h, w, 3))
        candidates = [KeyframeView(v.kf_id, shape_only, self.K, v.T_world_camera, reference=v.reference,
                                   depth_range_m=v.depth_range) for v in others[:CANDIDATE_POSES]]
        chosen = self.sources_fn(ref, candidates, n) if candidates else []
        return [self.keyframe_view(c.kf_id) for c in chosen]

    def _depth_map(self, ref: KeyframeView, sources: list[KeyframeView]):
        """(depth map, colour) of a reference keyframe: from a depth function that can leave its map on the device
        (``compute_on_device``, as KeptEstimator does), the map and the reference's colour as device arrays, so
        the volume fuses them without a trip through the host (the kept copy comes back quantised, a third of the
        bytes); else the function's map with the host colour."""
        on_device = getattr(self.depth_fn, "compute_on_device", None)
        if on_device is not None:
            depth, colour = on_device(ref, sources, self.config.depth, self.device)
            return depth, (ref.colour if colour is None else colour)
        return self.depth_fn(ref, sources, self.config.depth, self.device), ref.colour

    def fuse_pending(self, kf_ids=None, consistent: bool = False) -> int:
        """Depth maps for the kept reference keyframes not fused yet (or only ``kf_ids``), fused at their current
        poses. ``consistent`` (the final build): every map is made first, then each is fused with only the depths
        its neighbours' maps confirm (``_fuse_consistent``), where the depth function can check them and
        ``[depth] consistency_views`` asks for it; and a stereo scope's partner views get maps of their own too
        (their reference keyframe their first source; they check the reference maps and are checked by them),
        where ``[depth] partner_maps_up_to`` says so (``_partner_maps``). The live incremental fusion
        (``consistent`` False) makes the reference keyframes' maps alone. Returns how many were fused."""
        partners = consistent and self._partner_maps()
        todo = [v.kf_id for v in self.views.values() if (v.reference is None or partners) and v.T_fused is None
                and (kf_ids is None or v.kf_id in kf_ids)]
        check = getattr(self.depth_fn, "check_geometry", None)
        if consistent and check is not None and self.config.depth.consistency_views > 0:
            done = sum(self._fuse_consistent(todo[i:i + CONSISTENCY_CHUNK], check)
                       for i in range(0, len(todo), CONSISTENCY_CHUNK))
            self.fused += done
            return done
        done = 0
        for kf_id in todo:
            ref = self.keyframe_view(kf_id)
            sources = self._sources(ref)
            if not sources:  # no neighbour with a useful baseline (yet: a live run tries again later)
                self.without_sources.add(kf_id)
                continue
            self.without_sources.discard(kf_id)
            t0 = time.perf_counter()
            depth, colour = self._depth_map(ref, sources)
            t1 = time.perf_counter()
            self.timings["depth_s"] += t1 - t0
            if depth is None or not _has_depth(depth):
                self.depth_failures += 1
                continue
            self._fuse_and_keep(self.views[kf_id], depth, colour)
            self.timings["integration_s"] += time.perf_counter() - t1
            done += 1
        self.fused += done
        return done

    def _partner_maps(self) -> bool:
        """Whether the final build makes the stereo partner views' own depth maps too (``[depth]
        partner_maps_up_to``: at most that many reference keyframes kept)."""
        n = self.config.depth.partner_maps_up_to
        return n > 0 and sum(1 for v in self.views.values() if v.reference is None) <= n

    def _fuse_consistent(self, todo: list[int], check) -> int:
        """Multi-view geometric consistency: the maps of ``todo`` made first (kept quantised as they will be fused,
        3 bytes a pixel), then each fused with only the depths that ``[depth] consistency_min_views`` of its
        ``consistency_views`` nearest keyframes' maps (its sources first; a map of this batch, or one fused
        before) confirm forward-backward. Wrong depths rarely agree across views; right ones do."""
        cfg = self.config.depth
        made: dict[int, DepthMap] = {}  # kf_id -> its map as it will be kept
        chosen: dict[int, list[int]] = {}
        refs: dict[int, KeyframeView] = {}
        # ``[depth] final_geometric_pass``: every map of several sources made twice, the second time with its
        # sources' first-pass maps as PatchMatch's geometric term (ACMM); the first pass is the unchecked map (only
        # the second is kept). A map of one source (a stereo pair, a run of two keyframes) is made once: there the
        # one partner's map is what the left-right check tests, and the pairs were measured without it
        second_pass = (cfg.final_geometric_pass and cfg.method == "patchmatch"
                       and getattr(self.depth_fn, "unchecked", None) is not None)
        again: set[int] = set()  # the maps the second pass makes again
        for kf_id in todo:
            ref = self.keyframe_view(kf_id)
            sources = self._sources(ref, cfg.final_source_views)
            if not sources:
                self.without_sources.add(kf_id)
                continue
            self.without_sources.discard(kf_id)
            if ref.depth_range_m is not None and cfg.final_far_factor != 1.0:
                # (the sources stay chosen on the landmarks' range; the check vets what lies beyond it)
                near, far = ref.depth_range_m
                ref = replace(ref, depth_range_m=(near, far * cfg.final_far_factor))
            t0 = time.perf_counter()
            # with ``[depth] coarse_level``, holes of weak texture given a coarser map's depths, which the check vets
            coarse = getattr(self.depth_fn, "with_coarse_level", None) if cfg.coarse_level > 1 else None
            if second_pass and len(sources) > 1:
                # (a first pass for the geometric term: the unchecked map, every scored pixel's depth)
                depth = self.depth_fn.unchecked(ref, sources, cfg, self.device)
                again.add(kf_id)
            else:
                depth = (coarse or self.depth_fn)(ref, sources, cfg, self.device)
            self.timings["depth_s"] += time.perf_counter() - t0
            if depth is None or not _has_depth(depth):
                self.depth_failures += 1
                continue
            d16, c8 = _quantised(depth)  # (the estimator's host buffer is let go: it is reused for the next map)
            as_kept = _dequantised(kf_id, d16, c8, np.array(depth.K, float), np.array(depth.T_world_camera, float),
                                   depth.stats)
            made[kf_id] = as_kept
            chosen[kf_id] = [s.kf_id for s in sources]
            refs[kf_id] = ref
        if again:
            made = self._geometric_pass(made, chosen, {kf_id: refs[kf_id] for kf_id in made if kf_id in again})
        unfilled = made
        if cfg.consistency_fill_px > 0:
            # holes filled (a guess each): a filled depth is fused only where other maps confirm it, and it
            # confirms theirs in turn
            t0 = time.perf_counter()
            made = {kf_id: fill_holes(m, cfg.consistency_fill_px, cfg.consistency_fill_rel,
                                      cfg.consistency_fill_lines, cfg.consistency_fill_weight, self.device)
                    for kf_id, m in made.items()}
            self.timings["depth_s"] += time.perf_counter() - t0
        if cfg.two_view_sgbm:
            t0 = time.perf_counter()
            made = {kf_id: self._sgbm_filled(kf_id, m, chosen[kf_id]) for kf_id, m in made.items()}
            self.timings["depth_s"] += time.perf_counter() - t0
        done = 0
        stored: OrderedDict[int, DepthMap] = OrderedDict()  # kept maps of fused neighbours, decoded (a few)
        for kf_id, as_kept in made.items():
            v = self.views[kf_id]
            t0 = time.perf_counter()
            maps = [m for m in (self._map_of(n, made, stored) for n in self._neighbours(kf_id, chosen[kf_id], made))
                    if m is not None]
            if not maps:  # (a filled or coarse depth is never fused unconfirmed)
                as_kept = without_coarse(unfilled.get(kf_id, as_kept))
            checked = check(as_kept, maps, cfg, self.device, cfg.consistency_min_views) if maps else as_kept
            t1 = time.perf_counter()
            self.timings["depth_s"] += t1 - t0
            if not _has_depth(checked):
                self.depth_failures += 1
                continue
            self._fuse_and_keep(v, checked, self._colour(kf_id))
            self.checked_against.append(len(maps))
            self.timings["integration_s"] += time.perf_counter() - t1
            done += 1
        return done

    def _geometric_pass(self, first: dict[int, DepthMap], chosen: dict[int, list[int]],
                        refs: dict[int, KeyframeView]) -> dict[int, DepthMap]:
        """The maps of ``refs`` (unchecked first-pass maps in ``first``) made again with their sources' first-pass
        maps (of this batch, or, for a source fused before, its kept checked map) as PatchMatch's geometric term, with
        the coarse level where set; kept quantised as before, with the other maps of ``first`` as they are. A map
        whose second pass fails is left out."""
        cfg = self.config.depth
        fn = (getattr(self.depth_fn, "with_coarse_level", None) if cfg.coarse_level > 1 else None) or self.depth_fn
        stored: OrderedDict[int, DepthMap] = OrderedDict()
        out: dict[int, DepthMap] = {}
        for kf_id, made in first.items():
            ref = refs.get(kf_id)
            if ref is None:  # (a map made once)
                out[kf_id] = made
                continue
            geometry = {s: m for s in chosen[kf_id] if (m := self._map_of(s, first, stored)) is not None}
            sources = [self.keyframe_view(s) for s in chosen[kf_id]]
            t0 = time.perf_counter()
            depth = fn(ref, sources, cfg, self.device, geometry=geometry)
            self.timings["depth_s"] += time.perf_counter() - t0
            if depth is None or not _has_depth(depth):
                self.depth_failures += 1
                continue
            d16, c8 = _quantised(depth)
            out[kf_id] = _dequantised(kf_id, d16, c8, np.array(depth.K, float), np.array(depth.T_world_camera, float),
                                      depth.stats)
        return out

    def mesh_min_weight(self) -> float:
        """The weight a voxel needs to be meshed: ``[fusion] mesh_min_weight`` (single weak views leave no surface),
        or ``pair_mesh_min_weight`` where every fused map is a two-view final build's (each checked against exactly
        one other map: a stereo pair, a run of two keyframes). There the check has confirmed every fused depth by
        the only other view there is, and no surface can gather more than two maps' weight."""
        fc = self.config.fusion
        if self.checked_against and set(self.checked_against) == {1} and self.fused == len(self.checked_against):
            return fc.pair_mesh_min_weight
        return fc.mesh_min_weight

    def _sgbm_filled(self, kf_id: int, depth: DepthMap, sources: list[int]) -> DepthMap:
        """A two-view map (its first source its stereo partner, or the run's other keyframe) with its holes from
        semi-global matching against that view (``stereo_fill``); any other map as it is."""
        if not sources:
            return depth
        view, partner = self.views[kf_id], self.views[sources[0]]
        if not (same_rig_view(view, partner) or len(self.views) == 2):
            return depth
        cfg = self.config.depth
        near, far = view.depth_range or (cfg.default_near_m, cfg.default_far_m)
        if view.depth_range is not None:
            # the range the map itself searched (``final_far_factor``): a surface past the landmarks' far end has a
            # disparity below a search that stops there, and would be matched to the wrong one or none
            far *= cfg.final_far_factor
        other = sgbm_depth(self.keyframe_view(kf_id), self.keyframe_view(partner.kf_id), (near, far), cfg)
        if other is None:
            return depth
        self.sgbm_filled += 1
        return fill_from(depth, other)

    def _neighbours(self, kf_id: int, sources: list[int], made: dict) -> list[int]:
        """The keyframes whose maps check ``kf_id``'s: its sources, then the nearest others with a map (made in
        this batch or fused), up to ``[depth] consistency_views``."""
        n = self.config.depth.consistency_views
        c = self.views[kf_id].T_world_camera[:3, 3]
        others = [v for v in self.views.values() if v.kf_id != kf_id and v.kf_id not in sources
                  and (v.kf_id in made or v.T_fused is not None)]
        others.sort(key=lambda v: np.linalg.norm(v.T_world_camera[:3, 3] - c))
        return (sources + [v.kf_id for v in others])[:n]

    def _map_of(self, kf_id: int, made: dict, stored: OrderedDict) -> DepthMap | None:
        """A keyframe's map as made in this batch (its pose the one it was made at), or as kept once fused (PNG
        decoded, the last 2 x ``consistency_views`` of them kept in ``stored``)."""
        if kf_id in made:
            return made[kf_id]
        if kf_id in stored:
            stored.move_to_end(kf_id)
            return stored[kf_id]
        v = self.views.get(kf_id)
        if v is None or v.T_fused is None:
            return None
        depth = self._stored_map(v)
        depth.T_world_camera = v.T_world_camera.copy()  # (re-fused at its current pose by now)
        stored[kf_id] = depth
        while len(stored) > 2 * self.config.depth.consistency_views:
            stored.popitem(last=False)
        return depth

    def build(self, m) -> DenseResult:
        """Offline: every kept reference keyframe of a finished map (``MapResult``) fused at its final pose,
        with the depth range its landmarks span (and its stereo partners, ``fuse_pending``); the mesh and points."""
        return self.build_at(*final_poses_and_ranges(m))

    def build_at(self, poses: dict[int, np.ndarray], ranges: dict[int, tuple[float, float] | None]) -> DenseResult:
        """``build`` from the finished map's keyframe poses and depth ranges (``final_poses_and_ranges``): what a
        live run's dense process is sent."""
        self.refused_final += self.update_poses({k: T for k, T in poses.items() if k in self.views}, settled=True)
        self.set_depth_ranges(ranges)
        self.fuse_pending(consistent=True)
        return self.extract()

    def extract(self) -> DenseResult:
        t0 = time.perf_counter()
        mesh = self.volume.extract_mesh(self.mesh_min_weight())
        self.timings["meshing_s"] += time.perf_counter() - t0
        return dense_result(mesh, self.report(mesh))

    def report(self, mesh: pv.PolyData | None = None) -> dict:
        """report.json's ``dense``: points, triangles, keyframes fused, memory, timings."""
        vol = self.volume
        for v in self.views.values():
            self._encoded(v)
        kept = sum(len(v.jpeg) + len(v.depth_png or b"") + len(v.confidence_png or b"") for v in self.views.values())
        return {
            "points": int(mesh.n_points) if mesh is not None else None,
            "mesh_triangles": int(mesh.n_cells) if mesh is not None else None,
            "keyframes_fused": self.fused,
            "partner_maps_fused": self.partners_fused,  # (of them) stereo partner views' own maps
            "sgbm_filled_maps": self.sgbm_filled,  # (of them) two-view maps with holes from semi-global matching
            "keyframes_refused": self.refused,
            "keyframes_refused_final": self.refused_final,  # (of them) by the final build, at the final poses
            "refusions_per_keyframe": {"mean": self.refused / max(self.fused, 1),
                                       "max": max(self.refusions.values(), default=0)},
            "depth_maps_failed": self.depth_failures,
            "mesh_min_weight": self.mesh_min_weight(),  # (``pair_mesh_min_weight`` for a two-view final build)
            "keyframes_without_sources": len(self.without_sources),
            "keyframes_released": self.released,
            "voxel_mm": vol.voxel_m * 1e3,
            "memory": {"blocks": vol.blocks_in_use, "max_blocks": vol.max_blocks,
                       "peak_blocks": vol.stats.peak_blocks, "evicted_blocks": vol.stats.evicted_blocks,
                       "volume_mb": vol.memory_bytes / 2**20, "kept_images_mb": kept / 2**20},
            "timings_s": {**self.timings,
                          "depth_per_keyframe_s": self.timings["depth_s"] / max(self.fused, 1),
                          "integration_per_keyframe_s": self.timings["integration_s"] /
                          max(self.fused + self.refused, 1)},
        }


def _has_depth(depth: DepthMap) -> bool:
    if isinstance(depth.depth_m, np.ndarray):
        return bool(np.any(depth.depth_m > 0))
    return (depth.stats or {}).get("kept_pixels", 1) > 0  # a map on the device: its funnel's count


def shift_bound(T_from: np.ndarray, T_to: np.ndarray, reach_m: float) -> float:
    """The most a point within ``reach_m`` of the camera moves when the camera moves from ``T_from`` to ``T_to``
    (world_camera): the translation plus the rotation's angle x ``reach_m`` (|(R' - R) X| <= angle x |X|)."""
    return float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3])
                 + rotation_angle(T_from[:3, :3].T @ T_to[:3, :3]) * reach_m)


def reach(K: np.ndarray, d16: np.ndarray) -> float:
    """How far from the camera a kept map's points lie at most (metres): its far depth along the image's corner
    ray that leaves the axis most."""
    far = float(d16.max(initial=0)) * DEPTH_UNIT_M
    h, w = d16.shape
    corners = np.linalg.solve(K, np.array([[0.0, w - 1.0, 0.0, w - 1.0], [0.0, 0.0, h - 1.0, h - 1.0], [1.0] * 4]))
    return far * float(np.linalg.norm(corners, axis=0).max())


def _quantised(depth: DepthMap) -> tuple[np.ndarray, np.ndarray]:
    """A host map as the volume quantises it to keep it (``KEPT_STEPS``, tsdf's ``prepare_map``): depth in
    DEPTH_UNIT_M steps (uint16, 0 where none or beyond its range), confidence in 1/255 (0 where no depth)."""
    d = np.nan_to_num(np.asarray(depth.depth_m, np.float64), nan=0.0)
    q = np.where(d > 0, np.floor(d / DEPTH_UNIT_M + 0.5), 0.0)
    d16 = np.where(q < 65536, q, 0).astype(np.uint16)
    c = np.nan_to_num(np.asarray(depth.confidence, np.float64), nan=0.0)
    c8 = np.where((d16 > 0) & (c > 0), np.floor(np.minimum(c, 1.0) * 255.0 + 0.5), 0).astype(np.uint8)
    return d16, c8


def _dequantised(kf_id: int, d16: np.ndarray, c8: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                 stats: dict | None = None) -> DepthMap:
    """A kept map (``_quantised``) back in metres and [0, 1] confidence."""
    return DepthMap(kf_id, d16.astype(np.float32) * np.float32(DEPTH_UNIT_M),
                    c8.astype(np.float32) / np.float32(255.0), K, T_world_camera, stats)


def _encode_pngs(d16: np.ndarray, c8: np.ndarray) -> tuple[bytes, bytes]:
    return cv2.imencode(".png", d16)[1].tobytes(), cv2.imencode(".png", c8)[1].tobytes()


def undistortion(camera: CameraModel, K: np.ndarray | None = None, size: tuple[int, int] | None = None):
    """cv2.remap maps from ``camera``'s distorted frame to the pinhole ``K`` (default: its own) at ``size``, and its
    field of view in that undistorted image (bool H x W: the lens's region, nothing outside the frame, nothing past
    a fold of the lens model: ``CameraModel.seen_region``)."""
    mx, my = camera.undistort_maps(K, size)
    return mx, my, camera.seen_region(mx, my)


def final_poses_and_ranges(m) -> tuple[dict[int, np.ndarray], dict[int, tuple[float, float] | None]]:
    """A finished map's (``MapResult``) keyframe poses and the depths each one's inlier landmarks span."""
    poses = {int(k.id): np.asarray(k.T_world_camera, float) for k in m.keyframes}
    return poses, depth_ranges(m.keyframes, m.landmark_ids, m.points, m.inlier)


def depth_ranges(keyframes, landmark_ids: np.ndarray, points: np.ndarray, inlier: np.ndarray,
                 min_points: int = 8) -> dict[int, tuple[float, float] | None]:
    """Per keyframe, the depths its inlier landmarks span (``mapping.prediction.depth_span``: 2nd to 98th
    percentile with a margin); None where it sees fewer than ``min_points`` of them (its observations let go, or
    too few)."""
    lm = dict(zip(np.asarray(landmark_ids)[inlier].tolist(), np.asarray(points)[inlier]))
    out = {}
    for kf in keyframes:
        ids = [t for t in np.asarray(kf.track_ids).tolist() if t in lm] if kf.track_ids is not None else []
        if not ids:
            out[kf.id] = None
            continue
        X = np.array([lm[t] for t in ids])
        T = kf.T_world_camera
        out[kf.id] = depth_span(((X - T[:3, 3]) @ T[:3, :3])[:, 2], min_points)
    return out


def dense_result(mesh, stats: dict) -> DenseResult:
    """A DenseResult of a TSDF mesh: its vertices as the dense points, with their normals and colours."""
    if mesh.n_points:
        points = np.asarray(mesh.points, float)
        normals = np.asarray(mesh.point_data["Normals"], float)
        colours = np.asarray(mesh.point_data["RGB"], np.uint8)
    else:
        points, normals, colours = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return DenseResult(mesh, points, normals, colours, stats)


def surface_mode(config: PipelineConfig, live: bool = False, device: str = "cpu") -> str:
    """The surface a run makes: "dense" or "alpha" (``[surface] mode = "auto"``: dense offline and live on a CUDA
    device, where the dense stage's own process keeps up beside tracking; alpha live on the CPU, where it cannot:
    docs/dense.md, "Live")."""
    mode = config.surface.mode
    if mode not in SURFACE_MODES:
        raise ConfigError(f"[surface] mode = '{mode}': use auto, dense or alpha")
    if mode == "auto":
        return "alpha" if live and not str(device).startswith("cuda") else "dense"
    return mode


def dense_functions_for(config: PipelineConfig, live: bool = False,
                        device: str = "cpu") -> tuple[tuple[DepthFn, SourcesFn] | None, str | None]:
    """The run's (depth function, sources function) when its surface is dense (``surface_mode``; None for alpha),
    or (None, why) with one warning when multi-view stereo is not there: the run then makes the alpha shape."""
    if surface_mode(config, live, device) == "alpha":
        return None, None
    depth_fn, sources_fn, why = stereo_functions()
    if depth_fn is None:
        note = f"dense surface off: {why}; the alpha shape instead"
        log.warning(note)
        return None, note
    return (depth_fn, sources_fn), None


def dense_surface_for(camera: CameraModel, config: PipelineConfig, device: str, rig: Rig | None = None,
                      live: bool = False) -> tuple[DenseSurface | None, str | None]:
    """The run's DenseSurface when its surface is dense (``dense_functions_for``), else (None, why or None)."""
    functions, note = dense_functions_for(config, live, device)
    if functions is None:
        return None, note
    return DenseSurface(camera, config, device, rig, *functions), None
