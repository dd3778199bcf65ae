"""The mapper: keyframes from robot motion and track loss, triangulation of tracks as they grow, local
robust bundle adjustment over a sliding window of keyframes with robot pose priors, and at the end a global
pass that labels inliers.

A live run can last as long as an operation, so the map in memory is bounded: past ``active_keyframes``
the oldest keyframes are retired in batches. Their frames get their final poses then, their landmarks are
labelled (inlier or not) and frozen into a flat archive, and their observations are let go; the final
global pass covers the active keyframes. A sequence shorter than that (an evaluation, a demo) is untouched.

Poses are T_world_camera; observations are undistorted pixels of the pinhole camera K.
"""

from __future__ import annotations

import collections
import functools
import itertools
import logging
import time
from dataclasses import dataclass, field
from operator import itemgetter

import numpy as np

from lapreco_hil.camera import Rig
from lapreco_hil.config import MapperConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.funnel import Funnel
from lapreco_hil.geometry import inv_T, rigid
from lapreco_hil.lookup import positions
from lapreco_hil.types import Observations, PosePrior
from lapreco_hil.mapping import bundle_adjustment as ba
from lapreco_hil.mapping.archive import LandmarkArchive
from lapreco_hil.mapping.keyframes import FrameRecord, Keyframe, PendingStructure, is_keyframe
from lapreco_hil.mapping.prediction import depth_span, depths_in_front
from lapreco_hil.mapping.resection import refine_pose, refine_poses
from lapreco_hil.mapping.retirement import Retirement, corrections_at
from lapreco_hil.mapping.robust import CAUCHY_K, TUKEY_C, RobustSchedule, RobustStage
from lapreco_hil.mapping.schur import final_ba_profile, final_pass_threads, solve_robust_schur
from lapreco_hil.mapping.triangulation import triangulate, widest_ray_angle_deg

log = logging.getLogger(__name__)

# views of a track used to triangulate it for the first time (bundle adjustment uses all of them)
TRIANGULATION_VIEWS = 6
# a track is triangulated once its end rays span this share of min_parallax_deg
PARALLAX_PRECHECK = 0.8
# live, a keyframe's new points are made in idle-time pieces of this many tracks (a frame that arrives waits
# for one piece at most, not for a whole keyframe's points)
TRIANGULATION_PIECE = 250
# before the first bundle adjustment, a new point's reprojection error may exceed the pixel gate by this many
# of its views' prior standard deviations (in pixels)
PRIOR_GATE_SIGMAS = 3.0
# with a stereo rig, a point seen by both eyes at this many instants is an inlier, and no point is one without:
# each instant's left-right match is a depth of its own, and the second instant is the second look that catches
# a mismatch
STEREO_INLIER_INSTANTS = 2


def _spread(seen: list, n: int) -> list:
    """At most n of a track's views, evenly spread, always the first and the last."""
    m = len(seen)
    if m <= n:
        return seen
    return [seen[(i * (m - 1) + (n - 1) // 2) // (n - 1)] for i in range(n)]  # distinct: m > n


def _distinct(values: np.ndarray) -> np.ndarray:
    """np.unique of an integer array by a sort (numpy's hashed unique took 3 ms on a window's 45k ids; this 0.4), or
    by a count where the values span no more than their number (a window's keyframe ids)."""
    if len(values) and int(values.max()) - int(values.min()) < len(values):
        lo = int(values.min())
        return (np.flatnonzero(np.bincount(values - lo)) + lo).astype(values.dtype, copy=False)
    s = np.sort(values)
    return s[np.concatenate([[True], s[1:] != s[:-1]])] if len(s) else s


@dataclass(frozen=True)
class MapperSchedule:
    """When the mapper does its heavier work: inline, as an offline run does (``offline``), or spread over a
    live run's idle moments so that no frame waits for it (``live``)."""

    # local BA is asked of a worker process (``local_ba_wanted``, ``local_ba_job``) while frames go on being
    # mapped, instead of being solved inline
    defer_local_ba: bool = False
    # frames settled at a retirement get a fresh pose refinement against the map; live they keep the
    # interpolated keyframe correction (hundreds at once would stall the frames waiting; each was refined as
    # it came)
    resect_on_retire: bool = True
    # keyframes retire one at a time in idle moments (``maintain``), not a batch in the middle of a frame;
    # ``add`` still retires a batch if the map gets a whole batch over its bound (no idle time for that long)
    defer_retirement: bool = False
    # a keyframe's new points are triangulated (and its local BA asked for) in the next idle moment, so its
    # pose is published first and the frames behind it do not wait for its structure
    defer_triangulation: bool = False
    # with ``defer_local_ba``: a keyframe's local BA is wanted as soon as it is added, on the landmarks that exist
    # (its own new points, made in idle moments while the worker solves, join the next window), not after them
    local_ba_before_points: bool = False

    @classmethod
    def offline(cls) -> MapperSchedule:
        """Everything inline, in frame order: evaluations, demos, replays."""
        return cls()

    @classmethod
    def live(cls, ba_worker: bool, local_ba_before_points: bool = False) -> MapperSchedule:
        """A live run: structure and retirement in idle moments, local BA in a worker process if there is one
        (else inline, in idle moments after the keyframe's points)."""
        return cls(defer_local_ba=ba_worker, resect_on_retire=False, defer_retirement=True,
                   defer_triangulation=True, local_ba_before_points=ba_worker and local_ba_before_points)


@dataclass(frozen=True)
class ProblemScope:
    """Which part of the map a bundle adjustment covers: the landmarks seen by keyframes from ``points_from``
    on, with their observations in keyframes from ``views_from`` on, keyframe by keyframe (a local window), or
    with every observation of them, landmark by landmark (``every_view``: the final pass; every keyframe from
    ``points_from`` on joins, free). Keyframes before the first active one join fixed."""

    points_from: int
    views_from: int
    every_view: bool = False


@dataclass
class MapResult:
    keyframes: list[Keyframe]
    frames: list[FrameRecord]
    frame_poses: np.ndarray  # (F, 4, 4) refined T_world_camera of every frame
    landmark_ids: np.ndarray
    points: np.ndarray  # (N, 3)
    colors: np.ndarray  # (N, 3) uint8
    inlier: np.ndarray  # (N,) bool
    observations: int
    inlier_observations: int
    stats: dict = field(default_factory=dict)


def local_schedule(config: MapperConfig) -> RobustSchedule:
    """The robust schedule of a local BA (the live BA worker solves with it too)."""
    return RobustSchedule((RobustStage("cauchy", CAUCHY_K, config.local_cauchy_iterations),
                           RobustStage("tukey", TUKEY_C, config.local_tukey_iterations)),
                          sigma_floor_px=config.sigma_floor_px)


BA_SOLVERS = {"schur": solve_robust_schur, "gtsam": ba.solve_robust}


def ba_solver(config: MapperConfig):
    """The robust BA solver ``[mapper] ba_solver`` names: ``solve(problem, schedule) -> BAResult`` (the Schur
    solver's kernels on ``[mapper] ba_device``)."""
    if config.ba_solver not in BA_SOLVERS:
        raise ConfigError(f"[mapper] ba_solver = '{config.ba_solver}': use {' or '.join(BA_SOLVERS)}")
    device = config.ba_device
    if device not in ("auto", "cpu", "numpy") and not device.startswith("cuda"):
        raise ConfigError(f"[mapper] ba_device = '{device}': use auto, cpu, numpy, cuda or cuda:N")
    if device == "auto":
        from lapreco_hil.warp_device import resolve_device

        device = resolve_device("auto")
    if config.ba_solver == "schur" and device != "cpu":
        return functools.partial(solve_robust_schur, device=device)
    return BA_SOLVERS[config.ba_solver]


class Mapper:
    def __init__(self, K: np.ndarray, config: MapperConfig, schedule: MapperSchedule | None = None,
                 rig: Rig | None = None) -> None:
        self.K = np.asarray(K, float)
        self.config = config
        # a stereo scope: each keyframe's partner views join as keyframes of their own, tied to it
        self.rig = rig if rig is not None and rig.is_stereo else None
        self.funnel = Funnel.for_rig() if self.rig is not None else Funnel()
        # a rig: each active track searched for in a partner view -> found there yet (let go at retirement, when
        # one never found and never a candidate is counted in _without_partner)
        self._partnered: dict[int, bool] = {}
        self._without_partner = 0
        self._tried: set[int] = set()  # tracks tried for a point (active ones: let go at retirement)
        self.image_motion_px: list[float] = []  # per frame: the median track displacement from the frame before
        self.schedule = schedule if schedule is not None else MapperSchedule.offline()
        self.keyframes: list[Keyframe] = []
        self.frames: list[FrameRecord] = []
        self.tracks: dict[int, list[tuple[int, np.ndarray]]] = {}  # track id -> [(keyframe id, uv)]
        self.landmarks: dict[int, np.ndarray] = {}  # track id -> X
        self.landmark_colors: dict[int, np.ndarray] = {}
        self.archive = LandmarkArchive()
        self.retirement = Retirement(config)
        self.tracks_seen = 0
        self._local_ba_wanted = False
        self._corrected = False  # a bundle adjustment has refined a keyframe's pose (the triangulation gate)
        self._untriangulated: list[PendingStructure] = []  # oldest first
        self.structured: list[int] = []  # keyframes whose deferred points are now made (the live mapper drains it)
        self.ba_times: list[float] = []
        self.ba_iterations: list[int] = []
        self.last_sigma_px = float("nan")
        self.solve_ba = ba_solver(config)
        self.local_schedule = local_schedule(config)
        self.final_schedule = RobustSchedule(
            (RobustStage("cauchy", CAUCHY_K, config.final_cauchy_iterations),
             RobustStage("tukey", TUKEY_C, config.final_tukey_iterations)), sigma_floor_px=config.sigma_floor_px)

    @property
    def first_active(self) -> int:
        """Keyframes before this one are retired."""
        return self.retirement.first_active

    @property
    def _local_ba_before_points(self) -> bool:
        return self.schedule.defer_local_ba and self.schedule.local_ba_before_points

    @property
    def local_ba_wanted(self) -> bool:
        """A keyframe's local BA waits to be taken (``local_ba_job``) by the worker (deferred local BA)."""
        return self._local_ba_wanted

    # --- per frame -----------------------------------------------------------------------------------------
    def add(self, obs: Observations, prior: PosePrior, local_ba: bool = True, resect: bool = True,
            partners=None) -> bool:
        """Take one frame's observations and pose prior; returns True if it became a keyframe.
        A live run that is behind passes ``local_ba=False`` (this keyframe's local BA is deferred to the next)
        and ``resect=False`` (a non-keyframe takes its prior with the last keyframe's correction instead of a
        pose refinement; ``finish`` refines every frame anyway). With a stereo rig, ``partners`` gives the
        frame's tracks as the other cameras saw them at the same instant (Observations with ``camera`` set, in
        that camera's pinhole pixels), or a callable returning them, called only for a keyframe."""
        self.funnel.add(obs.funnel)
        self.funnel.add({"frames": 1})
        self._measure_motion(obs)
        is_kf = is_keyframe(self._last_reference(), obs, prior, self.K, self.config)
        if is_kf and len(self._untriangulated) >= 2:
            self._structure_step(None)  # no idle moment for two keyframes: the oldest one's points now
        record = FrameRecord(obs.frame_seq, obs.t_ns, prior.T_world_camera, prior.cov,
                             len(self.keyframes) if is_kf else None, obs.track_ids.copy(), obs.uv.copy())
        self.frames.append(record)
        if not is_kf:
            predicted = self._predict_pose(prior)
            record.T_refined = self._resect(record, predicted) if resect else predicted
            return False
        # A keyframe starts from its prior with the last keyframe's correction: good when bundle adjustment
        # has refined that keyframe. Live, with local BA solved a few hundred milliseconds late, it has not; the
        # keyframe is then refined against the map first, as any frame is (from the prediction alone most of
        # its new points failed the reprojection test, and were tried again at every keyframe).
        predicted = self._predict_pose(prior)
        stale = bool(self.keyframes) and not self.keyframes[-1].refined
        kf = Keyframe(len(self.keyframes), obs.frame_seq, obs.t_ns, prior,
                      self._resect(record, predicted) if resect and stale else predicted,
                      obs.track_ids.copy(), obs.uv.copy(), obs.colors.copy())
        self.keyframes.append(kf)
        retirement = self.retirement
        self._note_views(kf)
        record.T_refined = kf.T_world_camera
        if self.rig is not None and partners is not None:
            views = list(partners() if callable(partners) else partners)
            for view in views:
                self._add_partner(kf, view)
            self._count_partners(kf, views)
        self._untriangulated.append(PendingStructure(kf.id, local_ba and not self._local_ba_before_points))
        if local_ba and self._local_ba_before_points and len(self.keyframes) >= 2:
            self._local_ba_wanted = True  # its points follow in idle moments, while the worker solves
        if not self.schedule.defer_triangulation:
            self._triangulate_pending()
        cutoff = retirement.batch_due(len(self.keyframes), deferred=self.schedule.defer_retirement)
        if cutoff is not None:
            self._retire(cutoff)
        return True

    def _note_views(self, kf: Keyframe) -> None:
        """Keyframe ``kf``'s view of each of its tracks, appended to the track (one loop over a keyframe's
        thousands of tracks, its bookkeeping for retirement handed over at once)."""
        tracks, retired, kid = self.tracks, self.retirement.retired_tracks, kf.id
        kept, before = [], []
        for tid, uv in zip(kf.track_ids.tolist(), kf.uv):
            if tid in retired:
                continue  # its landmark is final
            seen = tracks.get(tid)
            if seen is None:
                tracks[tid] = [(kid, uv)]
                before.append(None)
            else:
                before.append(seen[-1][0])
                seen.append((kid, uv))
            kept.append(tid)
        self.tracks_seen += before.count(None)
        self.retirement.seen_in(kid, kept, before)

    def _measure_motion(self, obs: Observations) -> None:
        """How far the image moved since the previous frame: the median displacement of the tracks both saw
        (what a fast scope motion does to tracking: report.json's ``image_motion_px``)."""
        prev = self.frames[-1] if self.frames else None
        if prev is None or prev.track_ids is None or not len(obs):
            return
        _, ia, ib = np.intersect1d(prev.track_ids, obs.track_ids, assume_unique=True, return_indices=True)
        if len(ia):
            self.image_motion_px.append(float(np.median(np.linalg.norm(obs.uv[ib] - prev.uv[ia], axis=1))))

    def _last_reference(self) -> Keyframe | None:
        """The newest camera-0 keyframe (keyframes are chosen by the rig's reference camera)."""
        for kf in reversed(self.keyframes):
            if kf.reference is None:
                return kf
        return None

    def _add_partner(self, kf: Keyframe, view: Observations) -> None:
        """A stereo partner's view of keyframe ``kf``: a keyframe of its own at the rig's extrinsic from
        ``kf``, its pixels re-expressed with camera 0's K, its tracks joined to the same track ids (their
        points get depth from this very keyframe: the baseline is the parallax)."""
        T_cam0_cam = self.rig.T_cam0_cam[view.camera]
        K_cam = self.rig.cameras[view.camera].K
        uv = view.uv
        if len(uv):
            rays = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_cam).T
            uv = (rays @ self.K.T)[:, :2] / (rays @ self.K.T)[:, 2:3]
        prior = PosePrior(rigid(kf.prior.T_world_camera @ T_cam0_cam), kf.prior.cov, kf.t_ns)
        partner = Keyframe(len(self.keyframes), kf.frame_seq, kf.t_ns, prior,
                           rigid(kf.T_world_camera @ T_cam0_cam), view.track_ids.copy(), uv,
                           view.colors.copy(), reference=kf.id, camera=view.camera, T_cam0_cam=T_cam0_cam)
        self.keyframes.append(partner)
        for tid, p in zip(partner.track_ids.tolist(), partner.uv):
            seen = self.tracks.get(tid)
            if seen is None or self.retirement.is_retired(tid):
                continue  # only the reference camera's tracks (the partner view adds their other eye)
            self.retirement.seen(tid, partner.id, seen[-1][0])
            seen.append((partner.id, p))

    def _count_partners(self, kf: Keyframe, views: list[Observations]) -> None:
        """The funnel's left-right matching: keyframe ``kf``'s active tracks searched for in its partner views,
        and those found there, each track counted once (the first time it is searched, and found)."""
        found = set(itertools.chain.from_iterable(v.track_ids.tolist() for v in views))
        partnered, tracks = self._partnered, self.tracks
        searched = matched = 0
        for tid in kf.track_ids.tolist():
            if tid not in tracks:
                continue  # retired: its point is final
            before = partnered.get(tid)
            hit = tid in found
            if before is None:
                searched += 1
            if hit and not before:
                matched += 1
            partnered[tid] = bool(before) or hit
        self.funnel.add({"partner_searched": searched, "partner_matched": matched})

    def _unpartnered(self, track_ids) -> int:
        """How many of ``track_ids`` were searched for in a partner view, never found and never a candidate (let
        go here: the funnel's ``without_partner``)."""
        partnered, tried = self._partnered, self._tried
        return sum(1 for t in track_ids if partnered.pop(t, True) is False and t not in tried)

    def track_depths(self, track_ids: np.ndarray, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The depth (z in the camera at ``T_world_camera``) of each of ``track_ids`` that has a landmark:
        (ids, depths) for pose-predicted tracking."""
        ids = [t for t in np.asarray(track_ids).tolist() if t in self.landmarks]
        return depths_in_front(ids, np.array([self.landmarks[t] for t in ids]), T_world_camera)

    def _landmarks_of(self, track_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sorted distinct ids of ``track_ids`` that have a landmark, their points (M, 3)): one dict look-up per
        distinct id, then any subset is found by ``_lookup`` (keyframes of a window share most of their tracks)."""
        landmarks = self.landmarks
        known = np.array([t for t in _distinct(track_ids).tolist() if t in landmarks], np.int64)
        return known, np.array(list(map(landmarks.__getitem__, known.tolist())), float).reshape(-1, 3)

    @staticmethod
    def _lookup(track_ids: np.ndarray, known: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ids of ``track_ids`` (in their order) that are in ``known`` (sorted), and their points."""
        if not len(known):
            return np.zeros(0, np.int64), np.zeros((0, 3))
        rows = np.minimum(np.searchsorted(known, track_ids), len(known) - 1)
        found = known[rows] == track_ids
        return track_ids[found], points[rows[found]]

    def newest_reference_poses(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, T_world_camera (K, 4, 4), depth spans (K, 2), NaN where unknown) of the newest ``n`` reference
        keyframes: what the live dense surface needs after a local BA."""
        kfs = [kf for kf in self.keyframes[max(self.first_active, len(self.keyframes) - 2 * n):]
               if kf.reference is None][-n:]
        spans = np.full((len(kfs), 2), np.nan)
        if kfs:
            # the window's landmarks looked up once, not once per keyframe that sees them
            known, points = self._landmarks_of(np.concatenate([kf.track_ids for kf in kfs]).astype(np.int64))
            for i, kf in enumerate(kfs):
                ids, X = self._lookup(np.asarray(kf.track_ids, np.int64), known, points)
                span = depth_span(depths_in_front(ids, X, kf.T_world_camera)[1])
                if span is not None:
                    spans[i] = span
        return (np.array([kf.id for kf in kfs], np.int64),
                np.array([kf.T_world_camera for kf in kfs]).reshape(-1, 4, 4), spans)

    def _triangulate_pending(self) -> None:
        while self._untriangulated:
            self._structure_step(None)

    def _structure_step(self, limit: int | None) -> None:
        """The oldest pending keyframe's new points, at most ``limit`` candidate tracks of them (None: all);
        once they are all done, its local BA (asked of the worker, or run here)."""
        pending = self._untriangulated[0]
        if pending.tracks is None:
            kf = self.keyframes[pending.kf_id]
            pending.tracks = self._triangulation_candidates(kf)
            pending.colors = self._colors_in(kf, pending.tracks)
            if limit is not None:
                return  # choosing them was this piece of work
        n = len(pending.tracks) if limit is None else limit
        self._triangulate_tracks(pending.tracks[:n], pending.colors)
        del pending.tracks[:n]
        if pending.tracks:
            return
        self._untriangulated.pop(0)
        if self.schedule.defer_triangulation:
            self.structured.append(pending.kf_id)
        if len(self.keyframes) >= 2 and pending.local_ba:
            if self.schedule.defer_local_ba:
                self._local_ba_wanted = True  # the live mapper hands it to its BA worker (local_ba_job)
            else:
                self._local_ba()

    @staticmethod
    def _colors_in(kf: Keyframe, tracks: list[int]) -> dict[int, np.ndarray]:
        """The colour of each of ``tracks`` (some of the keyframe's) in keyframe ``kf``: looked up, not a
        dictionary of all its thousands of tracks (most are no candidate)."""
        return dict(zip(tracks, kf.colors[positions(kf.track_ids, np.asarray(tracks, np.int64))[0]]))

    def maintain(self) -> str | None:
        """Idle-time work for a live mapper, one short piece per call: a keyframe's deferred triangulation
        (``TRIANGULATION_PIECE`` tracks at a time, then its local BA), else retiring the oldest keyframe if the
        map is over its bound. Returns what it did ("triangulate", "retire"), None when nothing was due (call
        again while it works and nothing waits)."""
        if self._untriangulated:
            self._structure_step(TRIANGULATION_PIECE)
            return "triangulate"
        cutoff = self.retirement.one_due(len(self.keyframes))
        if cutoff is None:
            return None
        self._retire(cutoff)
        return "retire"

    # --- bounded memory ------------------------------------------------------------------------------------
    def _retire(self, cutoff: int) -> None:
        """Retire keyframes before ``cutoff``: final poses for the frames before it, landmarks seen only by
        retired keyframes labelled and archived, their observations let go."""
        self._triangulate_pending()
        retirement = self.retirement
        # the frames settled here lie before keyframe ``cutoff``
        kt, corr = retirement.corrections(self.keyframes, upto=cutoff)
        self._settle_frames(retirement.take_frames(self.frames, self.keyframes[cutoff].t_ns), kt, corr,
                            resect=self.schedule.resect_on_retire)
        retired = retirement.take_tracks(cutoff)
        with_point = [t for t in retired if t in self.landmarks]
        if with_point:
            # their observations flattened once (point j's views in order), no tuple per view
            seen_by = [self.tracks[t] for t in with_point]
            flat = list(itertools.chain.from_iterable(seen_by))
            obs_kf = np.fromiter(map(itemgetter(0), flat), np.int64, len(flat))
            obs_point = np.repeat(np.arange(len(with_point)), np.fromiter(map(len, seen_by), np.int64, len(seen_by)))
            kf_ids, obs_pose = np.unique(obs_kf, return_inverse=True)
            points = np.array([self.landmarks[t] for t in with_point])
            poses = np.array([self.keyframes[k].T_world_camera for k in kf_ids.tolist()])
            r = ba.residual_vectors(self.K, poses, points, obs_pose, obs_point,
                                    np.array(list(map(itemgetter(1), flat))))
            sigma = self.last_sigma_px if np.isfinite(self.last_sigma_px) else self.config.sigma_floor_px
            good = np.linalg.norm(r, axis=1) <= self.final_schedule.inlier_threshold_px(sigma)
            centres = poses[obs_pose][:, :3, 3]
            inlier = self._inlier_points(obs_point, good, len(with_point), len(kf_ids),
                                         self._is_reference(obs_kf), self._is_reference(kf_ids).sum(),
                                         points, centres, self._instants(obs_kf))
            self.archive.add(np.array(with_point, np.int64), points,
                             np.array([self.landmark_colors[t] for t in with_point], np.uint8), inlier)
            self.archive.observations += int(len(good))
            self.archive.inlier_observations += int(good.sum())
        if self._partnered:
            self._without_partner += self._unpartnered(retired)
        # (C-level loops over the retired tracks, a thousand or more a keyframe)
        self._tried.difference_update(retired)
        collections.deque(map(self.tracks.pop, retired), maxlen=0)
        collections.deque(map(self.landmarks.pop, retired, itertools.repeat(None)), maxlen=0)
        collections.deque(map(self.landmark_colors.pop, retired, itertools.repeat(None)), maxlen=0)
        empty = np.zeros(0, np.int64)
        for kf in retirement.take_keyframes_to_empty(self.keyframes, cutoff):
            kf.track_ids, kf.uv, kf.colors = empty, np.zeros((0, 2)), np.zeros((0, 3), np.uint8)
        retirement.advance(cutoff)
        log.debug("retired keyframes before %d: %d landmarks archived, %d active", cutoff, len(with_point),
                  len(self.landmarks))

    def _is_reference(self, kf_ids: np.ndarray) -> np.ndarray:
        """Whether each keyframe is a reference (camera 0) view, not a stereo partner."""
        unique, inverse = np.unique(np.asarray(kf_ids, np.int64), return_inverse=True)
        return np.array([self.keyframes[k].reference is None for k in unique.tolist()], bool)[inverse]

    def _instants(self, kf_ids: np.ndarray) -> np.ndarray | None:
        """The instant of each keyframe: its own id for a reference keyframe, its reference's for a partner (None
        without a rig: every keyframe is its own instant)."""
        if self.rig is None:
            return None
        kfs = self.keyframes
        unique, inverse = np.unique(np.asarray(kf_ids, np.int64), return_inverse=True)
        return np.array([k if kfs[k].reference is None else kfs[k].reference for k in unique.tolist()],
                        np.int64)[inverse]

    def _inlier_points(self, obs_point: np.ndarray, good: np.ndarray, n_points: int, n_views: int,
                       reference_obs: np.ndarray | None = None, n_reference_views: int | None = None,
                       points: np.ndarray | None = None, obs_centres: np.ndarray | None = None,
                       obs_instant: np.ndarray | None = None) -> np.ndarray:
        """A landmark is an inlier with enough inlier observations, making up enough of its observations; with a
        stereo rig, in enough of the reference camera's keyframes too (where there are that many): a stereo match
        seen at one instant only has the rig's 5 mm baseline and no second look to catch a mismatch. Given each
        observation's instant (``obs_instant``), a point seen by both eyes at STEREO_INLIER_INSTANTS instants
        (every one of those observations an inlier) is an inlier too: two left-right depths and the temporal
        pair must agree; and no point is an inlier without that (or both eyes at every instant, in a map of fewer
        instants): one eye's views agree as well on a feature only that eye sees so (where an occluding contour
        crosses the tissue behind it, the two eyes see that crossing at different places). Given the ``points``
        and each observation's camera centre, two inlier instants whose rays meet at least
        ``two_view_parallax_deg`` apart also make an inlier."""
        cfg = self.config
        counts = np.bincount(obs_point[good], minlength=n_points)
        totals = np.bincount(obs_point, minlength=n_points)
        # a point cannot be seen more often than there are keyframes (a two-view stereo pair: 2)
        min_obs = min(cfg.min_inlier_observations, n_views)
        enough = counts >= min_obs
        instants = good if reference_obs is None or self.rig is None else good & reference_obs
        wide = np.zeros(n_points, bool)
        if points is not None and cfg.two_view_parallax_deg > 0:
            angle = widest_ray_angle_deg(points, obs_point[instants], obs_centres[instants], n_points)
            wide = (np.bincount(obs_point[instants], minlength=n_points) >= 2) & (angle >= cfg.two_view_parallax_deg)
        stereo = np.zeros(n_points, bool)
        confirmed = np.ones(n_points, bool)
        if self.rig is not None and reference_obs is not None and obs_instant is not None:
            both = self._stereo_instants(obs_point, good, reference_obs, obs_instant, n_points)
            stereo = both >= STEREO_INLIER_INSTANTS
            # both eyes look at nearly the same field: a point the other eye does not confirm at as many instants
            # (every instant, in a map of fewer) is a feature one eye alone sees so, as on an occluding contour
            confirmed = both >= min(STEREO_INLIER_INSTANTS, int(n_reference_views if n_reference_views is not None
                                                                else STEREO_INLIER_INSTANTS))
        ok = (enough | wide | stereo) & (counts >= cfg.min_inlier_fraction * totals) & confirmed
        if self.rig is not None and reference_obs is not None:
            in_reference = np.bincount(obs_point[good & reference_obs], minlength=n_points)
            ok &= (in_reference >= min(cfg.min_inlier_observations, int(n_reference_views))) | wide | stereo
        return ok

    @staticmethod
    def _stereo_instants(obs_point: np.ndarray, good: np.ndarray, reference_obs: np.ndarray,
                         obs_instant: np.ndarray, n_points: int) -> np.ndarray:
        """Per point, the instants at which both its reference view and a partner view are inliers."""
        span = int(obs_instant.max()) + 1 if len(obs_instant) else 1
        key = obs_point.astype(np.int64) * span + obs_instant
        both = np.intersect1d(key[good & reference_obs], key[good & ~reference_obs])  # (distinct keys)
        return np.bincount(both // span, minlength=n_points)

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The map as it stands, for the live surface: archived inliers, then every active landmark."""
        return next(self.map_points_in_pieces(None))  # (in one piece, its only step is the map)

    def map_points_in_pieces(self, piece: int | None):
        """``map_points`` as a generator that gathers ``piece`` active landmarks per step (None: all at once),
        yielding None after each step and the map (points, colours) at the end: the live mapper gathers its
        snapshot in idle moments (a large map takes milliseconds in one go). Landmarks that BA moves meanwhile
        are taken where they are when their piece is gathered; landmarks retired meanwhile are left out."""
        _, apts, acols, ain = self.archive.arrays()
        ids = list(self.landmarks)
        step = len(ids) if piece is None else piece
        pts, cols = [apts[ain]], [acols[ain]]
        for start in range(0, len(ids), max(step, 1)):
            chunk = [t for t in ids[start:start + step] if t in self.landmarks]
            pts.append(np.array([self.landmarks[t] for t in chunk]).reshape(-1, 3))
            cols.append(np.array([self.landmark_colors[t] for t in chunk], np.uint8).reshape(-1, 3))
            if start + step < len(ids):
                yield None
        yield np.concatenate(pts), np.concatenate(cols)

    def _resection_points(self, record: FrameRecord) -> tuple[np.ndarray, np.ndarray]:
        """(landmarks, pixels) of the frame's tracks that have a point, thinned to ``resection_max_points``."""
        landmarks, ids = self.landmarks, record.track_ids.tolist()
        known = [i for i, t in enumerate(ids) if t in landmarks]
        cap = self.config.resection_max_points
        if cap and len(known) > cap:  # a 6-DoF pose with a prior is settled long before 2000 points
            known = known[:: -(-len(known) // cap)]
        pts = np.array([landmarks[ids[i]] for i in known]).reshape(-1, 3)
        return pts, record.uv[known].reshape(-1, 2)

    def _resect(self, record: FrameRecord, T_init: np.ndarray) -> np.ndarray:
        """The frame's pose refined against the current map (its prior where it sees too few landmarks)."""
        pts, uv = self._resection_points(record)
        if len(pts) < 6:
            return T_init
        T, _ = refine_pose(record.T_prior, record.cov, pts, uv, self.K, self._resection_sigma_px(), T_init=T_init)
        return T

    def _resection_sigma_px(self) -> float:
        """The pixel noise a frame's resection assumes: the last bundle adjustment's, 1 px before there is one."""
        return self.last_sigma_px if np.isfinite(self.last_sigma_px) else 1.0

    def _predict_pose(self, prior: PosePrior) -> np.ndarray:
        """Start a new keyframe from its prior corrected like the previous keyframe (robot errors drift
        slowly, so the last correction is the best guess)."""
        last = self._last_reference()
        if last is None:
            return prior.T_world_camera.copy()
        correction = last.T_world_camera @ inv_T(last.prior.T_world_camera)
        return rigid(correction @ prior.T_world_camera)

    # --- structure -----------------------------------------------------------------------------------------
    def _triangulation_candidates(self, kf: Keyframe) -> list[int]:
        """The keyframe's tracks that have no point yet and whose views now span (nearly) enough parallax."""
        cands = [t for t in kf.track_ids.tolist() if t not in self.landmarks and len(self.tracks.get(t, ())) >= 2]
        return self._wide_enough(cands)

    def _triangulate_tracks(self, cands: list[int], color_of: dict[int, np.ndarray]) -> None:
        """New points for ``cands``, from their views so far, coloured by ``color_of``."""
        cfg = self.config
        cands = [t for t in cands if t in self.tracks and t not in self.landmarks]  # (retired or made since)
        if not cands:
            return
        # A track that has not yet had the parallax for a point is seen in every keyframe since it started: its
        # first and last views (the parallax) and a few evenly between are enough for the initial point, which
        # bundle adjustment then refines with all of them (every view made triangulation a keyframe's main cost).
        views = [_spread(self.tracks[t], TRIANGULATION_VIEWS) for t in cands]
        counts = np.fromiter(map(len, views), np.int64, len(views))
        V = int(counts.max())
        uv = np.zeros((len(cands), V, 2))
        seen = np.zeros((len(cands), V), bool)
        poses = np.tile(np.eye(4), (len(cands), V, 1, 1))  # each track's own views (unused slots: identity)
        # every view flattened once (track n's j-th view at row n, column j), no Python loop per view
        flat = list(itertools.chain.from_iterable(views))
        rows = np.repeat(np.arange(len(cands)), counts)
        cols = np.arange(len(flat)) - np.repeat(np.cumsum(counts) - counts, counts)
        kfs = np.fromiter(map(itemgetter(0), flat), np.int64, len(flat))
        uv[rows, cols] = np.array(list(map(itemgetter(1), flat)))
        seen[rows, cols] = True
        kf_ids, which = np.unique(kfs, return_inverse=True)
        poses[rows, cols] = np.array([self.keyframes[k].T_world_camera for k in kf_ids.tolist()])[which]
        if self._corrected:
            res = triangulate(uv, seen, poses, self.K, cfg.min_parallax_deg, cfg.max_reprojection_px)
            valid = res.valid
        else:
            # No bundle adjustment has corrected a pose yet: the views are the pose source's own, whose error
            # (compliance, backlash; at 1080p tens of pixels) the pixel gate alone would call a bad point, and
            # the map would never start. The gate widens by what the views' prior covariances make of a pixel;
            # the first local BA then corrects the poses, and every later point meets the plain gate.
            res = triangulate(uv, seen, poses, self.K, cfg.min_parallax_deg, np.inf)
            count = seen.sum(axis=1)
            last = poses[np.arange(len(cands)), count - 1]
            z = np.einsum("ni,ni->n", res.points - last[:, :3, 3], last[:, :3, 2])  # depth in the newest view
            rot2, trans2 = self._prior_sigma2(kf_ids)
            rot2_n, trans2_n = rot2[which].reshape(-1), trans2[which].reshape(-1)
            owner = rows
            worst_rot2, worst_trans2 = np.zeros(len(cands)), np.zeros(len(cands))
            np.maximum.at(worst_rot2, owner, rot2_n)
            np.maximum.at(worst_trans2, owner, trans2_n)
            sigma_px = self.K[0, 0] * np.sqrt(worst_rot2 + worst_trans2 / np.maximum(z, 1e-6) ** 2)
            valid = res.valid & (res.max_error_px <= cfg.max_reprojection_px + PRIOR_GATE_SIGMAS * sigma_px)
        first_try = [t not in self._tried for t in cands]  # the funnel counts tracks, not attempts
        self._tried.update(cands)
        self.funnel.add({"candidates": sum(first_try), "triangulated": int(valid.sum())})
        for n in np.flatnonzero(valid):
            t = cands[n]
            self.landmarks[t] = res.points[n]
            self.landmark_colors[t] = color_of[t]

    def _prior_sigma2(self, kf_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per keyframe, the variance of its prior's rotation (rad^2) and translation (m^2) across the optical
        axis: what moves its image points."""
        covs = np.array([self.keyframes[k].prior.cov for k in kf_ids.tolist()]).reshape(-1, 6, 6)
        return covs[:, 0, 0] + covs[:, 1, 1], covs[:, 3, 3] + covs[:, 4, 4]

    def _wide_enough(self, cands: list[int]) -> list[int]:
        """The candidates whose first and last viewing rays already span (nearly) the parallax a new point
        needs. Most tracks wait several keyframes for it; this costs a dot product each, triangulating them
        cost most of a keyframe's time at 2000 tracks. (The margin covers the noise in the two rays.)"""
        if not cands:
            return cands
        seen = [self.tracks[t] for t in cands]
        first, last = list(map(itemgetter(0), seen)), list(map(itemgetter(-1), seen))
        k0 = np.fromiter(map(itemgetter(0), first), np.int64, len(cands))
        k1 = np.fromiter(map(itemgetter(0), last), np.int64, len(cands))
        uv0 = np.array(list(map(itemgetter(1), first)))
        uv1 = np.array(list(map(itemgetter(1), last)))
        kf_ids, which = np.unique(np.concatenate([k0, k1]), return_inverse=True)
        R = np.array([self.keyframes[k].T_world_camera[:3, :3] for k in kf_ids.tolist()])[which]
        Kinv = np.linalg.inv(self.K)

        def world_rays(uv, R_):
            r = np.einsum("nij,nj->ni", R_, np.column_stack([uv, np.ones(len(uv))]) @ Kinv.T)
            return r / np.linalg.norm(r, axis=1, keepdims=True)

        n = len(cands)
        cos = np.sum(world_rays(uv0, R[:n]) * world_rays(uv1, R[n:]), axis=1)
        wide = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) >= PARALLAX_PRECHECK * self.config.min_parallax_deg
        return [t for t, w in zip(cands, wide.tolist()) if w]

    # --- bundle adjustment ---------------------------------------------------------------------------------
    def _problem(self, scope: ProblemScope) -> ba.BAProblem | None:
        """The bundle adjustment of ``scope`` (None when it holds no landmark). Built from the keyframes' own
        arrays, vectorised: a local window at 2000 tracks holds tens of thousands of observations, built while
        frames wait."""
        reach = self.keyframes[scope.views_from:]
        tids = np.concatenate([kf.track_ids for kf in reach]) if reach else np.zeros(0, np.int64)
        uvs = np.concatenate([kf.uv for kf in reach]) if reach else np.zeros((0, 2))
        kfi = np.repeat(np.array([kf.id for kf in reach], np.int64), [len(kf.track_ids) for kf in reach])
        point_ids, points = self._landmarks_of(tids[kfi >= scope.points_from])
        if not len(point_ids):
            return None
        obs_point = None
        free = np.zeros(0, np.int64)
        if scope.every_view:
            # every view of each landmark (retired keyframes' too: their arrays may be gone, the tracks keep them)
            # (hundreds of thousands of views in a long map's final pass: flattened once, no tuple per view)
            seen_by = [self.tracks[t] for t in point_ids.tolist()]
            obs = list(itertools.chain.from_iterable(seen_by))
            kfi = np.fromiter(map(itemgetter(0), obs), np.int64, len(obs))
            tids = np.repeat(point_ids, [len(s) for s in seen_by])
            uvs = np.concatenate(list(map(itemgetter(1), obs))).reshape(-1, 2)
            free = np.arange(scope.points_from, len(self.keyframes))
        else:  # the window's observations of its points (one look-up finds both which and where)
            rows, found = positions(point_ids, tids, keys_sorted=True)
            keep = np.flatnonzero(found)  # (taken by index: cheaper than four boolean selections)
            tids, uvs, kfi, obs_point = tids.take(keep), uvs.take(keep, axis=0), kfi.take(keep), rows.take(keep)
        seen = _distinct(kfi)
        first_active = self.first_active
        kf_ids = np.concatenate([np.union1d(free, seen[seen >= first_active]), seen[seen < first_active]])
        index = np.zeros(len(self.keyframes), np.int64)
        index[kf_ids] = np.arange(len(kf_ids))
        chosen = [self.keyframes[k] for k in kf_ids.tolist()]
        has_prior, tie_pairs, tie_T, tie_covs = self._rig_ties(chosen, index, kf_ids)
        return ba.BAProblem(
            K=self.K, pose_ids=kf_ids, poses=np.array([k.T_world_camera for k in chosen]),
            fixed=(kf_ids < first_active) | self._poses_held(),
            prior_poses=np.array([k.prior.T_world_camera for k in chosen]),
            prior_covs=np.array([k.prior.cov for k in chosen]), point_ids=point_ids, points=points,
            obs_pose=index[kfi], obs_point=np.searchsorted(point_ids, tids) if obs_point is None else obs_point,
            obs_uv=uvs, has_prior=has_prior,
            tie_pairs=tie_pairs, tie_T=tie_T, tie_covs=tie_covs)

    def _poses_held(self) -> bool:
        """Whether the map is too few instants for bundle adjustment to move its poses
        (``hold_poses_up_to_views``): its points are refined, its poses stay as given."""
        return sum(1 for k in self.keyframes if k.reference is None) <= self.config.hold_poses_up_to_views

    def _rig_ties(self, chosen: list[Keyframe], index: np.ndarray, kf_ids: np.ndarray):
        """Which of a problem's poses have their own prior, and the ties of stereo partners to their reference
        keyframes (the rig's extrinsic within its calibrated uncertainty). A partner whose reference is not
        in the problem keeps a prior of its own (the reference's, carried through the extrinsic)."""
        in_problem = set(kf_ids.tolist())
        has_prior = np.array([k.reference is None or k.reference not in in_problem for k in chosen], bool)
        ties = [(int(index[k.reference]), i) for i, k in enumerate(chosen)
                if k.reference is not None and k.reference in in_problem]
        if not ties:
            return has_prior, np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6, 6))
        rig = self.rig
        cov = np.diag([rig.sigma_rotation_rad**2] * 3 + [rig.sigma_translation_m**2] * 3)
        tie_T = np.array([chosen[j].T_cam0_cam for _, j in ties])
        return has_prior, np.array(ties, np.int64), tie_T, np.repeat(cov[None], len(ties), 0)

    def _local_scope(self) -> ProblemScope:
        """The newest ``window_keyframes`` keyframes and their landmarks, with every observation of those
        landmarks in the ``2 x window`` keyframes before the window. Those co-visible older keyframes join as
        free variables with their robot priors (a soft edge): holding them fixed would carry their errors
        into every later window; only retired ones stay fixed."""
        n, w = len(self.keyframes), self.config.window_keyframes * (len(self.rig) if self.rig else 1)
        return ProblemScope(points_from=max(self.first_active, n - w), views_from=max(0, n - 3 * w))

    def _apply(self, problem: ba.BAProblem, result: ba.BAResult) -> None:
        for i, k in enumerate(problem.pose_ids.tolist()):
            if not problem.fixed[i] and k >= self.first_active:  # (a worker's result may outlive a keyframe)
                self.keyframes[k].T_world_camera = result.poses[i]
                self.keyframes[k].refined = True
        landmarks = self.landmarks
        for t, X in zip(problem.point_ids.tolist(), result.points):
            if t in landmarks:
                landmarks[t] = X
        self._corrected |= any(self.keyframes[k].refined for k in problem.pose_ids.tolist()
                               if k < len(self.keyframes))
        self.ba_times.append(result.seconds)
        self.ba_iterations.append(result.iterations)
        self.last_sigma_px = result.stats.get("sigma_px", self.last_sigma_px)

    def _local_ba(self) -> None:
        problem = self._problem(self._local_scope())
        if problem is not None:
            self._apply(problem, self.solve_ba(problem, self.local_schedule))

    def local_ba_job(self) -> tuple[ba.BAProblem, dict] | None:
        """The newest window's local BA for a worker to solve (``ba_solver(config)(problem, local_schedule)``),
        and the ticket ``apply_local_ba`` needs; None when there is nothing to adjust."""
        self._local_ba_wanted = False
        problem = self._problem(self._local_scope())
        if problem is None:
            return None
        last = len(self.keyframes) - 1
        return problem, {"last_kf": last, "T_last": self.keyframes[last].T_world_camera.copy()}

    def apply_local_ba(self, problem: ba.BAProblem, result: ba.BAResult, ticket: dict) -> None:
        """A worker's local BA, solved on the map as it was when the job left: its keyframes and landmarks
        take the result (unless retired since), and keyframes added meanwhile move with the newest solved
        one (they were predicted from its old correction)."""
        self._apply(problem, result)
        last = ticket["last_kf"]
        shift = rigid(self.keyframes[last].T_world_camera @ inv_T(ticket["T_last"]))
        for kf in self.keyframes[last + 1:]:
            kf.T_world_camera = rigid(shift @ kf.T_world_camera)

    # --- end of sequence -----------------------------------------------------------------------------------
    def finish(self) -> MapResult:
        self._triangulate_pending()
        cfg = self.config
        t0 = time.perf_counter()
        # the final pass: every active keyframe, its landmarks with all their observations
        final = ProblemScope(points_from=self.first_active, views_from=self.first_active, every_view=True)
        problem = self._problem(final) if self.first_active < len(self.keyframes) else None
        ids = np.array(sorted(self.landmarks), dtype=np.int64)
        inlier = np.zeros(len(ids), bool)
        n_obs = n_inlier_obs = 0
        threshold = float("nan")
        reprojection = {}
        if problem is not None:
            if cfg.final_global_ba:
                result = self._solve_final(problem)
                self._apply(problem, result)
                good = result.stats["inlier_obs"]
                threshold = result.stats["inlier_threshold_px"]
                e = result.residuals_px
            else:
                r = ba.residual_vectors(problem.K, problem.poses, problem.points, problem.obs_pose,
                                        problem.obs_point, problem.obs_uv)
                threshold = self.final_schedule.inlier_threshold_px(ba.pixel_sigma(problem, r, self.final_schedule))
                e = np.linalg.norm(r, axis=1)
                good = e <= threshold
            reference_pose = self._is_reference(problem.pose_ids)
            poses, points = (result.poses, result.points) if cfg.final_global_ba else (problem.poses, problem.points)
            ok = self._inlier_points(problem.obs_point, good, len(problem.point_ids), len(problem.pose_ids),
                                     reference_pose[problem.obs_pose], int(reference_pose.sum()),
                                     points, poses[problem.obs_pose][:, :3, 3],
                                     None if self.rig is None else self._instants(problem.pose_ids)[problem.obs_pose])
            kept = e[ok[problem.obs_point] & np.isfinite(e)]  # every view of the inlier points
            if len(kept):
                reprojection = {"median_px": float(np.median(kept)), "p95_px": float(np.percentile(kept, 95)),
                                "observations": int(len(kept))}
            in_problem = dict(zip(problem.point_ids.tolist(), ok))
            inlier = np.array([in_problem.get(t, False) for t in ids.tolist()], bool)
            n_obs, n_inlier_obs = int(len(good)), int(good.sum())
        points = np.array([self.landmarks[t] for t in ids.tolist()]).reshape(-1, 3)
        colors = np.array([self.landmark_colors[t] for t in ids.tolist()], np.uint8).reshape(-1, 3)
        aids, apts, acols, ain = self.archive.arrays()
        ids, points = np.concatenate([aids, ids]), np.concatenate([apts, points])
        colors, inlier = np.concatenate([acols, colors]), np.concatenate([ain, inlier])
        n_obs += self.archive.observations
        n_inlier_obs += self.archive.inlier_observations
        self.funnel.counts["inliers"] = int(inlier.sum())
        if self.rig is not None:  # the active tracks' share too (every attempt at a point is over)
            active = sum(1 for t, found in self._partnered.items() if not found and t not in self._tried)
            self.funnel.counts["without_partner"] = self._without_partner + active
        stats = {
            "keyframes": sum(1 for k in self.keyframes if k.reference is None),
            "partner_views": sum(1 for k in self.keyframes if k.reference is not None),
            "funnel": self.funnel.as_dict(),
            "retired_keyframes": self.first_active,
            "tracks": self.tracks_seen,
            "landmarks": int(len(ids)),
            "archived_landmarks": len(self.archive),
            "inliers": int(inlier.sum()),
            "outliers": int((~inlier).sum()),
            "local_ba_runs": len(self.ba_times) - (1 if problem is not None and cfg.final_global_ba else 0),
            "local_ba_mean_s": float(np.mean(self.ba_times[:-1])) if len(self.ba_times) > 1 else 0.0,
            "final_ba_s": time.perf_counter() - t0,
            "final_ba": final_ba_profile(problem, result) if problem is not None and cfg.final_global_ba else None,
            "pixel_sigma_mad": self.last_sigma_px,
            "inlier_threshold_px": float(threshold) if problem is not None else None,
            "reprojection": reprojection,
            "image_motion_px": ({"median": float(np.median(self.image_motion_px)),
                                 "p95": float(np.percentile(self.image_motion_px, 95))} if self.image_motion_px
                                else {}),
        }
        t1 = time.perf_counter()
        frame_poses = self._frame_poses()
        stats["frame_poses_s"] = time.perf_counter() - t1
        return MapResult(self.keyframes, self.frames, frame_poses, ids, points, colors, inlier, n_obs,
                         n_inlier_obs, stats)

    def _solve_final(self, problem: ba.BAProblem) -> ba.BAResult:
        """The final pass, its camera system (thousands wide for a long map) on ``[mapper] final_ba_threads``
        BLAS threads (docs/benchmarks.md, session 11)."""
        if self.config.ba_solver == "schur":
            return solve_robust_schur(problem, self.final_schedule, device=self.config.ba_device,
                                      blas_threads=self.config.final_ba_threads or final_pass_threads())
        return self.solve_ba(problem, self.final_schedule)

    def _frame_poses(self) -> np.ndarray:
        """Every frame's refined pose against the final map: keyframes from the global BA, the others by
        pose-only refinement started from the keyframe corrections interpolated in time (the corrections alone
        leave the live demo's frames 1.8x closer to the truth than raw FK instead of 5x)."""
        if not self.keyframes:
            return np.array([f.T_prior for f in self.frames])
        kt, corr = self.retirement.corrections(self.keyframes)
        self._settle_frames(self.retirement.take_frames(self.frames), kt, corr)
        return np.array([f.T_refined for f in self.frames])

    def _settle_frames(self, frames: list[FrameRecord], kt: np.ndarray, corr: list[np.ndarray],
                       resect: bool = True) -> None:
        """Frames' final poses: a keyframe's own, else its prior with the keyframe corrections interpolated in
        time, refined against the map (unless ``resect`` is off; all frames at once, ``refine_poses``); their
        observations are then let go."""
        others = []
        for f in frames:
            if f.keyframe is not None:
                f.T_refined = self.keyframes[f.keyframe].T_world_camera
            else:
                others.append(f)
        if others:
            C = corrections_at(kt, corr, np.array([f.t_ns for f in others], np.int64))
            for f, c in zip(others, C):
                f.T_refined = c @ f.T_prior
        if resect and others:
            chosen = [self._resection_points(f) for f in others]
            refined = refine_poses(np.array([f.T_prior for f in others]), np.array([f.cov for f in others]),
                                   [pts for pts, _ in chosen], [uv for _, uv in chosen], self.K,
                                   self._resection_sigma_px(),
                                   T_inits=np.array([f.T_refined for f in others]))
            for f, T in zip(others, refined):
                f.T_refined = T
        for f in frames:
            f.track_ids = f.uv = f.cov = None
