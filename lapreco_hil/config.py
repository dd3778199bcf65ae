"""Configuration: frozen dataclasses, loaded once from TOML and passed down (no global parameters).

A TOML file mirrors the dataclass tree: ``[tracker]``, ``[mapper]``, ``[surface]``... Every key is optional;
an unknown key, a value of the wrong type or a number outside its range is a :class:`ConfigError` naming the
file, the section and the key: ``config.toml: [mapper] window_keyframes = 0: must be >= 2``. Each numeric
field declares its range where it is defined, with :func:`ranged`.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

from lapreco_hil.errors import ConfigError


@dataclass(frozen=True)
class Range:
    """The values a numeric field accepts: finite, ``>= ge`` or ``> gt``, and ``<= le``."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None

    def problem(self, value: float) -> str | None:
        """What is wrong with ``value``, or None."""
        if not math.isfinite(value):
            return f"must be a finite number {self}"
        if (self.ge is not None and value < self.ge) or (self.gt is not None and value <= self.gt) \
                or (self.le is not None and value > self.le):
            return f"must be {self}"
        return None

    def __str__(self) -> str:
        low = f">= {self.ge:g}" if self.ge is not None else f"> {self.gt:g}" if self.gt is not None else ""
        high = f"<= {self.le:g}" if self.le is not None else ""
        return " and ".join(t for t in (low, high) if t)


def ranged(default, *, ge: float | None = None, gt: float | None = None, le: float | None = None):
    """A numeric dataclass field with its accepted range (checked when a configuration is loaded); for a tuple
    the range applies to each element."""
    return field(default=default, metadata={"range": Range(ge, gt, le)})


@dataclass(frozen=True)
class FewViewsConfig:
    """A sequence of at most ``frames`` frames (a calibrated stereo pair written as two frames, a v2 session of
    one rig frame) has no temporal tracking to sustain and each view is all there is: corners are detected
    denser there (the cost is a few milliseconds once, not per frame of a long run)."""

    frames: int = ranged(8, ge=0)  # 0: never
    max_features: int = ranged(4000, ge=1)
    min_distance_px: float = ranged(3.0, ge=0.0)
    quality_level: float = ranged(0.001, gt=0.0, le=1.0)


@dataclass(frozen=True)
class TrackerConfig:
    max_features: int = ranged(800, ge=1)
    min_distance_px: float = ranged(8.0, ge=0.0)
    quality_level: float = ranged(0.01, gt=0.0, le=1.0)
    block_size: int = ranged(7, ge=3)
    window_px: int = ranged(21, ge=3)
    # LK's window on the pyramid levels from coarse_from_level up: wider there, so that LK alone (no pose
    # prediction) holds a large motion on periodic or sparse texture (docs/benchmarks.md, session 11)
    coarse_window_px: int = ranged(31, ge=3)
    coarse_from_level: int = ranged(4, ge=0)
    # LK's pyramid levels above full resolution, or "auto": from the image's size and expected_motion_px
    # (frontend.image.pyramid_levels)
    pyramid_levels: int | str = ranged("auto", ge=0)
    # the image motion per frame (px) LK must reach without a pose prediction ("auto" levels)
    expected_motion_px: float = ranged(80.0, gt=0.0)
    # "auto" levels stop where the coarsest level's shorter side would fall below this (px)
    pyramid_min_coarsest_px: float = ranged(32.0, gt=0.0)
    max_lk_error: float = ranged(30.0, gt=0.0)
    fov_margin_px: float = ranged(12.0, ge=0.0)
    # re-detect when fewer than this share of max_features is alive
    redetect_below: float = ranged(0.9, ge=0.0, le=1.0)
    # at fast scope motion a track lives few keyframes (each frame is one), so a point seen at three instants
    # needs more tracks per frame: a frame whose pose prediction moves the tracks at least fast_motion_px
    # (median) keeps up to fast_features_scale x max_features (1: never; docs/results.md, "Fast motion")
    fast_motion_px: float = ranged(25.0, gt=0.0)
    fast_features_scale: float = ranged(1.5, ge=1.0)
    # LK on frames with a pose prediction skips the coarse-window levels the prediction's uncertainty does not
    # need (frontend.image.predicted_levels; docs/frontend-real-frames.md); opt-in: the tracking bench's
    # figures with the defaults (docs/benchmarks.md) were measured without it
    reduced_predicted_levels: bool = False
    # log-domain high-pass against moving shading (0 = track raw intensities, as the seed's baseline did): the
    # Gaussian's sigma in pixels of the coarsest pyramid level (x 2^levels at full resolution)
    shading_sigma_px: float = ranged(3.0, ge=0.0)
    # no new features where the local mean grey level is below this (0-255)
    min_brightness: float = ranged(20.0, ge=0.0, le=255.0)
    # Zinsser drift check: affine + gain/bias registration of each track's first patch
    drift_check: bool = True
    drift_patch_px: int = ranged(13, ge=3)
    drift_max_residual: float = ranged(0.75, gt=0.0)
    # the drift check registers on the tracker image smoothed by a Gaussian of this sigma (px; 0: unsmoothed): at
    # 0.8, more tracks kept on low-contrast texture at fast motion, but less accurate points (docs/results.md, s15)
    drift_smoothing_px: float = ranged(0.0, ge=0.0)
    # with a stereo rig (both front-ends), a new track the drift check refuses at its first step is judged again
    # on the tracker image smoothed by this sigma (px; 0: never) and stays registered there once kept: more tracks
    # live to be confirmed by both eyes at fast motion (frontend/opencv, frontend/warp; docs/results.md, s17)
    rescue_smoothing_px: float = ranged(0.8, ge=0.0)
    # a stereo match unclear over the map's whole depth range is searched again near the depth the map gives its
    # track (frontend/stereo_depth): more matches on smooth tissue, a few gross ones more (docs/results.md, s15)
    stereo_depth_prior: bool = True
    # start each track where the pose source's motion says it lands (FrameMotion); off: where it was
    predict: bool = True
    # without a pose prediction, a track off the RANSAC homography of the frame's LK steps by more than this (px),
    # or lost, is tracked again from where the homography puts it (frontend.consensus; 0: never)
    consensus_px: float = ranged(3.0, ge=0.0)
    # without a pose prediction, every track starts LK where the frame's image motion puts it: a homography from a
    # dense alignment of the whole frame at low resolution (frontend.global_motion; off: where it was)
    global_motion_prior: bool = True
    few_views: FewViewsConfig = field(default_factory=FewViewsConfig)

    def for_frames(self, frames: int | None) -> "TrackerConfig":
        """This configuration for a sequence of ``frames`` frames (None: unknown, a live run): denser corners
        for a few views (``few_views``)."""
        few = self.few_views
        if frames is None or frames > few.frames:
            return self
        return dataclasses.replace(self, max_features=max(self.max_features, few.max_features),
                                   min_distance_px=min(self.min_distance_px, few.min_distance_px),
                                   quality_level=min(self.quality_level, few.quality_level))


@dataclass(frozen=True)
class PriorConfig:
    """Joint-space 1-sigma error of the robot's reported joints (compliance, backlash, encoder),
    mapped to a camera-pose covariance through the manipulator Jacobian, plus a floor for what the
    joints do not explain (hand-eye, scope bending)."""

    joint_sigma: tuple[float, ...] = ranged((0.0035, 0.0035, 0.0003, 0.0035), ge=0.0)  # rad, rad, m, rad
    floor_rot_sigma_rad: float = ranged(0.0005, gt=0.0)
    floor_trans_sigma_m: float = ranged(0.0002, gt=0.0)


@dataclass(frozen=True)
class MapperConfig:
    keyframe_translation_m: float = ranged(0.002, ge=0.0)
    keyframe_rotation_rad: float = ranged(0.02, ge=0.0)
    keyframe_track_ratio: float = ranged(0.7, ge=0.0, le=1.0)
    keyframe_parallax_deg: float = ranged(1.0, ge=0.0)
    min_parallax_deg: float = ranged(2.0, gt=0.0)
    max_reprojection_px: float = ranged(3.0, gt=0.0)
    window_keyframes: int = ranged(8, ge=2)
    # the seed's robust schedule: Cauchy then Tukey, MAD scale re-estimated before each stage
    local_cauchy_iterations: int = ranged(3, ge=0)
    local_tukey_iterations: int = ranged(3, ge=0)
    final_cauchy_iterations: int = ranged(15, ge=0)
    final_tukey_iterations: int = ranged(15, ge=0)
    sigma_floor_px: float = ranged(0.2, gt=0.0)
    # a landmark is an inlier with at least this many inlier observations, making up at least this share
    min_inlier_observations: int = ranged(3, ge=2)
    min_inlier_fraction: float = ranged(0.5, ge=0.0, le=1.0)
    # ...or with two inlier observations (instants) whose rays meet at least this wide (degrees; 0: never):
    # with the robot's poses known such a pair fixes the depth, and a fast scan sees many points at two instants
    # only; 4 degrees keeps the fast runs' accuracy (2.5 cost it: docs/results.md, "Fast motion")
    two_view_parallax_deg: float = ranged(4.0, ge=0.0)
    final_global_ba: bool = True
    # live, with a BA worker: a keyframe's local BA is asked for as soon as it is added (with the points that
    # exist), not after its new points are made; those then join the next window (docs/benchmarks.md, session 12)
    local_ba_before_points: bool = False
    # the robust BA's solver, local and final: "schur" (numpy, the reduced camera system: lapreco_hil.mapping.schur)
    # or "gtsam" (GTSAM's LM, the reference); the same schedule and answers (docs/benchmarks.md)
    ba_solver: str = "schur"
    # where the Schur solver's per-observation kernels run: "auto" (CUDA where Warp sees one, else the CPU),
    # "cpu" (Warp's CPU device), "cuda"/"cuda:N" (the landmarks are then eliminated on the GPU too) or "numpy"
    ba_device: str = "auto"
    # BLAS threads of the final pass's camera system (thousands wide for a long map); 0: every core of a machine
    # of 8 or more, one on a smaller one (on 2 shared cores OpenBLAS's spinning threads made it 7x slower)
    final_ba_threads: int = ranged(0, ge=0)
    # bounded memory for long runs: past this many keyframes the oldest ``retire_batch`` are retired (their
    # landmarks labelled and frozen, their observations let go); 0 keeps every keyframe active
    active_keyframes: int = ranged(400, ge=0)
    # a map of at most this many instants (reference keyframes) keeps its poses as given: two views cannot tell a
    # calibrated relative pose's error from the images' own systematic errors (a lens model's residual, an
    # interlaced sensor's rows), and hundreds of points would turn the pair to fit the latter
    hold_poses_up_to_views: int = ranged(2, ge=0)
    # (near, far) metres: where tissue can be before the map knows (a track with no depth yet is searched along
    # its epipolar line over this range)
    scene_depth_m: tuple[float, float] = ranged((0.01, 0.3), gt=0.0)
    # a frame's pose is refined against at most this many of its landmarks, evenly spread (0 = all)
    resection_max_points: int = ranged(400, ge=0)
    retire_batch: int = ranged(100, ge=1)


@dataclass(frozen=True)
class DepthConfig:
    """Multi-view stereo per keyframe (lapreco_hil.dense.depth)."""

    # "sweep": the plane sweep's fronto-parallel windows, coarse to fine; "patchmatch": its coarse depth refined
    # per pixel with slanted windows (a plane per pixel, red-black PatchMatch at half resolution; the default since
    # session 17: more coverage on the simulated scenes, docs/dense.md)
    method: str = "patchmatch"
    # the live dense stage's method (a live run's keyframes, fused as they come): the sweep, measured live on the H100
    # (9.5 ms a 1080p map, no frame dropped); PatchMatch's cost beside a live run on a GPU is not measured yet
    live_method: str = "sweep"
    source_views: int = ranged(4, ge=1)  # neighbouring keyframes (and the stereo partner) each depth map uses
    # the sweep's range where the keyframe's sparse landmarks give none (metres along the optical axis)
    default_near_m: float = ranged(0.02, gt=0.0)
    default_far_m: float = ranged(0.30, gt=0.0)
    # ZNCC window (2r+1)^2 at both levels: 7x7; a map of fewer sources than best_k scores a larger one at full
    # resolution, as many samples as best_k windows (dense.depth.window_radius: 11x11 for a two-view pair)
    window_radius_px: int = ranged(3, ge=1)
    coarse_step_px: float = ranged(1.0, gt=0.0)  # plane spacing of the half-resolution sweep: at most this shift
    min_planes: int = ranged(8, ge=3)  # the half-resolution sweep's planes, whatever the baseline
    max_planes: int = ranged(96, ge=3)  # ... and their cap (a wider spacing beyond it): bounds time and memory
    fine_planes: int = ranged(4, ge=3)  # planes of the full-resolution refinement about the coarse depth ...
    fine_range_px: float = ranged(0.75, gt=0.0)  # ... spanning this image motion (half-resolution pixels) each way
    best_k: int = ranged(2, ge=1)  # a plane's score: mean ZNCC of its k best source views (an occluded view drops out)
    min_zncc: float = ranged(0.6, ge=-1.0, le=1.0)  # the best score a pixel needs to get a depth
    # planes a pixel must score on (the rest fall outside the sources): the best of a few is no match
    min_scored_fraction: float = ranged(0.3, ge=0.0, le=1.0)
    min_margin: float = ranged(0.05, ge=0.0)  # best minus the second local maximum: repeated texture is ambiguous
    # bend of the coarse depth between a pixel and its neighbours a window away (as image motion, half-resolution
    # pixels) beyond which it sits on a depth edge, where windows fatten the foreground
    max_depth_jump_px: float = ranged(2.0, gt=0.0)
    edge_min_zncc: float = ranged(0.3, ge=-1.0, le=1.0)  # ... counting the neighbours that match at least this well
    margin_scale: float = ranged(0.3, gt=0.0)  # the margin at which the confidence's uniqueness factor reaches 1
    # a window scores on the pixels usable in both views (not excluded, inside): at least this fraction of it
    min_valid_fraction: float = ranged(0.6, gt=0.0, le=1.0)
    min_texture: float = ranged(0.008, ge=0.0)  # window standard deviation (grey / 255): below it ZNCC is noise
    view_min_zncc: float = ranged(0.5, ge=-1.0, le=1.0)  # a source view agrees with the depth at this score
    min_views: int = ranged(2, ge=1)  # source views that must agree (capped at the views there are): moving things fail
    # a depth needs this share of its neighbours (radius in pixels) within this relative depth: specks and thin
    # slivers (wrong matches along silhouettes and folds) go, surfaces stay
    support_radius_px: int = ranged(3, ge=1)
    min_support: float = ranged(0.5, ge=0.0, le=1.0)
    support_max_rel: float = ranged(0.02, gt=0.0)
    geometric_max_px: float = ranged(1.0, gt=0.0)  # forward-backward through a source's depth map: reprojection
    geometric_max_rel: float = ranged(0.01, gt=0.0)  # ... and relative depth difference
    geometric_min_views: int = ranged(1, ge=1)  # source depth maps that must agree (capped at those given)
    # the dense surface's final build (offline, and the keyframes a live run leaves to it) makes every map first,
    # then keeps of each the depths that ``consistency_min_views`` of the maps of its ``consistency_views`` nearest
    # keyframes (its sources first) confirm forward-backward (0: no such check; docs/dense.md, "Session 17")
    consistency_views: int = ranged(7, ge=0)  # (8 before the coarse level, session 24)
    # (3 with 4 sources; 2 since the final build's 8 sources lead the neighbours: each a view at a useful angle)
    consistency_min_views: int = ranged(2, ge=1)
    # ... after filling each map's holes of up to ``consistency_fill_px`` pixels (0: none) where at least
    # ``consistency_fill_lines`` of its row, column and diagonals bridge them between depths within
    # ``consistency_fill_rel`` (inverse depth), at ``consistency_fill_weight`` of their confidence; the check vets
    # the filled depths like any other (lapreco_hil.dense.fill; docs/dense.md, "Session 17, second pass")
    consistency_fill_px: int = ranged(48, ge=0)
    consistency_fill_rel: float = ranged(0.04, gt=0.0)
    consistency_fill_lines: int = ranged(1, ge=1, le=4)
    consistency_fill_weight: float = ranged(0.5, gt=0.0, le=1.0)
    # ... and, before the filling, each map's pixels whose window was too flat or match too weak take the depth of a
    # map of its views reduced by ``coarse_level`` (2: half, 4: quarter; 0: none), the same window spanning more of
    # the scene, where that map's four depths about the pixel agree within ``coarse_max_rel`` (inverse depth), at
    # ``coarse_weight`` of its confidence; vetted by the check like any other (dense/coarse.py; docs/dense.md,
    # "Session 24")
    coarse_level: int = ranged(2, ge=0)
    coarse_max_rel: float = ranged(0.02, gt=0.0)
    coarse_weight: float = ranged(0.5, gt=0.0, le=1.0)
    # ... and each map's range reaches this factor past its landmarks' far end: surface behind the last landmarks
    # (the liver's far omentum) gets depths, vetted by the check (docs/dense.md, "Session 24: the far range and
    # more views")
    final_far_factor: float = ranged(1.25, ge=1.0)
    # ... from this many source views (``source_views`` live, for its cost): where few of four neighbours see a
    # surface, best_k of more may; at most 8 score per pixel (patchmatch) (docs/dense.md, "Session 24: the far range
    # and more views")
    final_source_views: int = ranged(8, ge=1)
    # ... and, method "patchmatch", made a second time with the first pass's maps of its sources (every scored
    # pixel's depth, unchecked, as ACMM's) as a geometric term (ACMM's geometric consistency): each source's score
    # of a plane less ``geometric_pass_weight`` x its forward-backward reprojection error through that source's map
    # (full-resolution pixels, at most ``geometric_pass_tau_px``; ACMM's 0.2 and 3), so that pixels whose windows
    # barely tell planes apart take the one the neighbours' maps agree on. Off: it adds coverage on both simulated
    # scenes but takes the liver's RMS past 0.5 mm, and doubles the final build's depth time (docs/dense.md,
    # "Session 26")
    final_geometric_pass: bool = False
    geometric_pass_weight: float = ranged(0.2, ge=0.0)
    geometric_pass_tau_px: float = ranged(3.0, gt=0.0)
    # a stereo scope's partner views (rig camera >= 1) get depth maps of their own in the final build, filled,
    # checked and fused as the reference keyframes' are, when the run keeps at most this many reference keyframes
    # (0: never; the live incremental fusion is reference-only; docs/dense.md, "Two views")
    partner_maps_up_to: int = ranged(1000, ge=0)
    # the final build's two-view maps (a stereo partner's, or a run of two keyframes) get their holes from OpenCV's
    # semi-global matching against that one partner (dense/stereo_fill.py), checked left-right as every depth is
    # (docs/dense.md, "Two views")
    two_view_sgbm: bool = True
    # the depth maps' pinhole image holds the whole field of view: a barrel lens undistorted at the frame's size
    # and K loses its outer band (a fifth of the image on a real 720x576 scope), so the canvas grows to hold it,
    # by at most ``canvas_max_pad`` of the frame's width and height on each side (docs/dense.md, "The canvas")
    full_field_of_view: bool = True
    canvas_max_pad: float = ranged(0.25, ge=0.0, le=1.0)
    highlight_value: float = ranged(0.97, gt=0.0, le=1.0)  # a saturated highlight: max(RGB) at least this ...
    highlight_saturation: float = ranged(0.15, ge=0.0, le=1.0)  # ... and (max - min) / max at most this
    highlight_dilate_px: int = ranged(3, ge=0)  # its halo (bloom, a window that overlaps it) is excluded too
    # keyframes whose prepared images (grey at full and half resolution) stay on the device to be sources again:
    # a keyframe is the source of several others (about 10 MB each at 1080p; at least the views of one depth map)
    cached_views: int = ranged(12, ge=1)
    # method "patchmatch": checkerboard iterations, each trying the neighbours' planes and perturbations
    patchmatch_iterations: int = ranged(3, ge=1)
    # its window at half resolution: (2r+1)^2 pixels sampled every ``step`` (r=3, step 2: 16 taps over 7x7); at
    # full resolution the sweep's window_radius_px, every pixel
    patchmatch_window_radius_px: int = ranged(3, ge=1)
    patchmatch_window_step_px: int = ranged(2, ge=1)
    patchmatch_far_px: int = ranged(5, ge=3)  # the far neighbours' distance (odd: the other colour of the board)
    # the steepest slant tried, as the slope tan(angle between surface and image plane): 5 is 79 degrees
    patchmatch_max_slope: float = ranged(5.0, gt=0.0)
    # the first iteration's perturbation: image motion (half-resolution pixels) and slope; halved each iteration
    patchmatch_perturb_px: float = ranged(4.0, gt=0.0)
    patchmatch_perturb_slope: float = ranged(1.0, gt=0.0)
    # a depth within the window's reach departing from a pixel's plane by more than this (relative) marks a depth
    # edge, where windows fatten the foreground
    patchmatch_edge_rel: float = ranged(0.03, gt=0.0)
    patchmatch_edge_slope: float = ranged(0.5, ge=0.0)  # ... plus a slope error of this over their distance
    patchmatch_edge_min: int = ranged(7, ge=1)  # ... at least this many of them (a stray wrong depth is no edge)
    # a depth's confidence x cos(angle between its ray and its plane's normal) to this power: fusion weighs grazing
    # depths less (0: not at all)
    patchmatch_angle_weight: float = ranged(0.5, ge=0.0)
    patchmatch_refine_px: float = ranged(0.5, gt=0.0)  # full resolution: a parabola through +-this image motion
    patchmatch_seed: int = ranged(0, ge=0)  # its random numbers (a map is repeatable on one device)


@dataclass(frozen=True)
class FusionConfig:
    """The truncated signed distance volume (lapreco_hil.dense.fusion)."""

    voxel_m: float = ranged(0.0005, gt=0.0)
    # half the band about the surface a depth map updates, in voxels: wider than the maps' depth noise
    truncation_voxels: float = ranged(4.0, ge=1.0)
    # the memory cap: 8^3-voxel blocks (10 KiB each); past it the blocks unused for longest are dropped
    max_blocks: int = ranged(16384, ge=8)
    # a voxel with less weight (1 = one view at full confidence) is unobserved for meshing: single weak views
    # leave no surface
    mesh_min_weight: float = ranged(0.5, ge=0.0)
    # ... but in a two-view final build (a stereo pair, a run of two keyframes: every fused map checked against the
    # one other map) a voxel needs only this: each fused depth is already confirmed by the only other view there is,
    # and two filled, coarse or semi-global depths (a fraction of a match's confidence) rarely sum to mesh_min_weight
    # (docs/dense.md, "Session 25")
    pair_mesh_min_weight: float = ranged(0.0, ge=0.0)
    # a fused keyframe whose pose update moves its fused points (at most: translation + rotation x its farthest
    # point's distance) more than this many voxels is taken out and fused again at its new pose, once its pose
    # has settled (a pose update no longer includes it: it left bundle adjustment's window; docs/dense.md)
    refuse_shift_voxels: float = ranged(0.25, ge=0.0)
    # keyframes whose images and depth maps are kept (compressed, in memory) to be sources and re-fused;
    # the oldest are let go past it (their part of the volume stays where it was fused)
    keep_keyframes: int = ranged(400, ge=2)
    jpeg_quality: int = ranged(95, ge=50, le=100)  # the kept keyframe images (JPEG in memory)

    # keys of older configurations and what replaced them (loading one is a ConfigError that says so)
    retired: typing.ClassVar[dict[str, str]] = {
        "refuse_translation_m": "refuse_shift_voxels (the largest move of a keyframe's fused points, in voxels; "
                                "default 0.25)",
        "refuse_rotation_rad": "refuse_shift_voxels (the largest move of a keyframe's fused points, in voxels; "
                               "default 0.25)",
    }


@dataclass(frozen=True)
class SurfaceConfig:
    # "dense": multi-view stereo fused in a TSDF volume, meshed; "alpha": the seed's alpha shape on the sparse map;
    # "auto": dense where it keeps up: offline (replay, sequential demo) and live on a CUDA device (the dense
    # stage in a process of its own); alpha live on the CPU, where it takes the cores tracking needs
    # (docs/dense.md, "Live")
    mode: str = "auto"
    alpha_factor: float = ranged(4.0, gt=0.0)  # alpha = factor x median nearest-neighbour distance
    render_width: int = ranged(1024, ge=16)
    render_height: int = ranged(768, ge=16)


@dataclass(frozen=True)
class RuntimeConfig:
    """The live runtime's queues and rates (lapreco_hil/runtime)."""

    capture_queue: int = ranged(4, ge=1)  # frames between capture and tracking; the oldest is dropped when full
    # observation slots in shared memory between tracking and the mapper process: enough to hold the frames
    # that arrive during one local BA (about a second at 60 fps), which the mapper then catches up on cheaply
    mapper_slots: int = ranged(128, ge=1)
    mapper_backlog_skip_ba: int = ranged(2, ge=0)  # local BA is deferred while more frames than this wait for the mapper
    # local BA in a worker process of its own, on the newest window, while the mapper goes on mapping frames
    # ("on"), or run by the mapper between frames, deferred while frames wait ("off"). "auto": on with 4 or
    # more CPU cores: on 2 cores a third busy process takes the time tracking needs (docs/benchmarks.md)
    ba_worker: str = "auto"
    max_tracks: int = ranged(4096, ge=1)
    max_landmarks: int = ranged(200_000, ge=1)
    surface_period_s: float = ranged(2.0, gt=0.0)  # live mesh rebuild
    surface_max_points: int = ranged(15_000, ge=4)  # the live mesh is built on at most this many points, evenly thinned
    view_period_s: float = ranged(0.0, ge=0.0)  # live textured view to PNG (0 = off)
    # the live dense stage's share of the wall time at most: in its own process it still shares the cores and
    # the GPU with tracking; keyframes it has no time for are fused by the final build (docs/dense.md, "Live")
    dense_busy_share: float = ranged(0.5, gt=0.0, le=1.0)
    record_queue: int = ranged(64, ge=1)
    # the front-end reports a "partial view" while its tracks span less than this share of the view they
    # normally span (an instrument or blood over part of the scope's view)
    partial_view_below: float = ranged(0.6, ge=0.0, le=1.0)


@dataclass(frozen=True)
class PipelineConfig:
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)


def _build(cls, data: dict, where: str, source: str):
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key in getattr(cls, "retired", {}):
            raise ConfigError(f"{source}: {_key(where, key)}: replaced by {cls.retired[key]}; remove it")
        if key not in fields:
            raise ConfigError(f"{source}: {_key(where, key)}: unknown key (known: {', '.join(sorted(fields))})")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: '{where}{key}' must be a table [{where}{key}]")
            kwargs[key] = _build(hint, value, f"{where}{key}.", source)
            continue
        kwargs[key] = _coerce(value, hint, fields[key].metadata.get("range"), f"{_key(where, key)} = {value!r}",
                              source)
    return cls(**kwargs)


def _key(where: str, key: str) -> str:
    """'[mapper] window_keyframes' (TOML's section and key)."""
    return f"[{where.rstrip('.')}] {key}" if where else key


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _coerce(value, hint, accepted: Range | None, name: str, source: str):
    origin = typing.get_origin(hint)
    if origin is tuple:
        if not isinstance(value, list) or not all(_is_number(v) for v in value):
            raise ConfigError(f"{source}: {name}: must be a list of numbers")
        for v in value:
            if accepted is not None and (problem := accepted.problem(float(v))):
                raise ConfigError(f"{source}: {name}: each value {problem}")
        return tuple(float(v) for v in value)
    if hint == int | str:  # a whole number or "auto"
        if value == "auto":
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f'{source}: {name}: must be a whole number {accepted} or "auto"')
        hint = int
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {name}: must be true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {name}: must be a whole number{f' {accepted}' if accepted else ''}")
    elif hint is float:
        if not _is_number(value):
            raise ConfigError(f"{source}: {name}: must be a number{f' {accepted}' if accepted else ''}")
        value = float(value)
    elif hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {name}: must be a string")
        return value
    if accepted is not None and (problem := accepted.problem(value)):
        raise ConfigError(f"{source}: {name}: {problem}")
    return value


def config_from_dict(data: dict, source: str = "<config>") -> PipelineConfig:
    return _build(PipelineConfig, data, "", source)


def load_config(path: str | Path | None) -> PipelineConfig:
    """Load a TOML configuration; ``None`` gives the defaults."""
    if path is None:
        return PipelineConfig()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror}); check the path") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); save the config as UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc}); fix the file") from None
    return config_from_dict(data, str(path))
