"""The live runtime's stages, each a small object run in a thread of its own by the supervisor: what it reads,
what it writes and what it counts are given to its constructor.

- ``Capture``: grabber -> the capture queue (newest ``capture_queue`` frames; older ones dropped and counted)
  and the record queue. Never blocks.
- ``Tracking``: capture queue -> pose prior + front-end -> the mapper (a shared-memory slot; with none free the
  frame is not mapped, counted). Takes every frame capture kept: LK needs consecutive frames.
- ``Results``: the mapper's messages -> latency, counters, free slots, the refined pose of the live view.
- ``Surface``: the mapper's map snapshot -> the live mesh every ``surface_period_s`` (or the dense surface's
  mesh), the textured view every ``view_period_s`` (no view: no live mesh).
- ``Dense``: keyframe images (kept by tracking until the mapper names its keyframes) and poses -> depth maps
  fused into the TSDF volume, re-fused when local BA moves a keyframe, its mesh every ``surface_period_s``; run
  in a process of its own (runtime/dense_process.py: ``DenseProcess`` is its stand-in in this process).
- ``Record``: the record queue -> the session recorder (drops counted there, so disk never stalls capture).
- ``RigCheck``: a stereo rig's extrinsics judged once against a live frame's images (``calib.rig_check``), off the
  capture path; a problem is said while the run goes on, not after a run of few points."""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lapreco_hil.errors import DeviceTimeoutError
from lapreco_hil.runtime.health import Condition
from lapreco_hil.mapping.prediction import TrackPoints, frame_motion
from lapreco_hil.frontend import partner_views
from lapreco_hil.runtime.messages import (BAWorkerReady, EndOfResults, FramePose, KeyframePoses, MapperReady,
                                          NewTrackPoints, SlotFree)
from lapreco_hil.runtime.metrics import LiveMetrics

if TYPE_CHECKING:
    from lapreco_hil.runtime.dense_process import DenseProcess

log = logging.getLogger(__name__)
BAD_TIME_SHOWN_S = 0.25  # frame times read as "refused" this long after the last refused frame
RETRY_KEYFRAMES = 4  # a live keyframe without a stereo source yet is tried again while this many wait


@dataclass
class StageLinks:
    """What the stages share: the run's events and the queues between them, under one condition."""

    stop: threading.Event = field(default_factory=threading.Event)  # the caller's Ctrl-C, or a fatal error
    capture_done: threading.Event = field(default_factory=threading.Event)
    finished: threading.Event = field(default_factory=threading.Event)  # the mapper's results are all in
    cond: threading.Condition = field(default_factory=threading.Condition)
    capture_q: collections.deque = field(default_factory=collections.deque)  # (Frame, arrival ns)
    record_q: collections.deque = field(default_factory=collections.deque)  # ("frame", Frame) / ("joints", list)
    disabled: set = field(default_factory=set)  # optional stages switched off after an error

    def notify(self) -> None:
        with self.cond:
            self.cond.notify_all()


class LatestView:
    """The newest tracked frame and its pose (the prior, then the refined one) for the live view."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frame = self._T = None

    def tracked(self, frame, T_world_camera: np.ndarray) -> None:
        with self._lock:
            self._frame, self._T = frame, T_world_camera

    def refined(self, seq: int, T_world_camera: np.ndarray) -> None:
        with self._lock:
            if self._frame is not None and self._frame.seq == seq:
                self._T = T_world_camera

    def get(self):
        with self._lock:
            return None if self._frame is None else (self._frame, self._T)


class RecentFrames:
    """The newest tracked frames by sequence number, until the mapper says which became keyframes (a few tens of
    milliseconds later); bounded, so frames it never names are let go."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._frames: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def add(self, frame) -> None:
        with self._lock:
            self._frames[frame.seq] = frame
            while len(self._frames) > self.capacity:
                self._frames.popitem(last=False)

    def take(self, seq: int):
        with self._lock:
            return self._frames.pop(seq, None)


class Capture:
    def __init__(self, grabber, links: StageLinks, metrics: LiveMetrics, *, capture_queue: int, record_queue: int,
                 recording: bool, page_locked=None) -> None:
        self.grabber, self.links, self.metrics = grabber, links, metrics
        # a PageLockedFrames pool (the Warp front-end on CUDA): each frame is copied into page-locked memory here,
        # beside the tracking of the one before, so the tracking thread uploads it by one DMA
        self.page_locked = page_locked
        self.capture_queue, self.record_queue, self.recording = capture_queue, record_queue, recording
        self.bad_time_wall = 0.0  # when a frame was last refused for its time stamp

    def run(self) -> None:
        links, m = self.links, self.metrics
        last_seq = last_t = None
        while not links.stop.is_set():
            try:
                frame = self.grabber.read(timeout_s=0.5)
            except DeviceTimeoutError:
                m.add("capture_timeouts")
                continue
            if frame is None:
                return
            # the latency starts at capture: the grabber's host-clock stamp where it has one (time spent
            # queued in the grabber counts), else now
            arrival = frame.host_ns if frame.host_ns is not None else time.monotonic_ns()
            m.add("frames_in")
            if last_t is not None and frame.t_ns <= last_t:
                # a duplicated or backwards capture time would break pose interpolation and the map's order
                m.add("bad_timestamps")
                self.bad_time_wall = time.monotonic()
                continue
            last_t = frame.t_ns
            if last_seq is not None and frame.seq > last_seq + 1:
                m.add("dropped_source", frame.seq - last_seq - 1)  # gone before we could read them
            elif last_seq is None and frame.seq > 0:
                # the source numbered these before capture began (a grabber opened while the run started):
                # not the run's drops, but said, so that "in" is not read as all the source made
                m.add("passed_before_start", frame.seq)
            last_seq = frame.seq
            if self.page_locked is not None:
                staged = self.page_locked.stage(frame)
                m.add("frames_page_locked" if staged is not frame else "frames_not_page_locked")
                frame = staged
            with links.cond:
                if len(links.capture_q) >= self.capture_queue:
                    links.capture_q.popleft()
                    m.mark("dropped_capture")
                links.capture_q.append((frame, arrival))
                m.sample_depth("capture", len(links.capture_q))
                if self.recording and "record" not in links.disabled:
                    if len(links.record_q) >= self.record_queue:
                        links.record_q.popleft()
                        m.add("dropped_record")
                    links.record_q.append(("frame", frame))
                links.cond.notify_all()

    def frame_times_health(self) -> Condition:
        if time.monotonic() - self.bad_time_wall < BAD_TIME_SHOWN_S:
            return Condition("refused", False, f"{self.metrics.get('bad_timestamps')} frames refused: duplicated "
                             "or backwards time stamp", count_as="frame_times_refused")
        return Condition("ok", True)


class Tracking:
    """``frontend`` is set before the thread starts (LiveRun makes it before capture starts); ``submit(obs,
    prior, arrival_ns) -> bool`` hands a frame to the mapper."""

    def __init__(self, poses, links: StageLinks, metrics: LiveMetrics, latest: LatestView, coverage, submit, *,
                 device: str, degrade: bool, recording: bool, track_points: TrackPoints | None = None,
                 scene_depth_m: tuple[float, float] = (0.01, 0.3), offset_watch=None, rig=None,
                 recent: RecentFrames | None = None) -> None:
        self.poses, self.links, self.metrics, self.latest = poses, links, metrics, latest
        self.coverage, self.submit = coverage, submit
        self.device, self.degrade, self.recording = device, degrade, recording
        # pose-predicted tracking: the mapper's track points (None: tracks start where they were)
        self.track_points, self.scene_depth_m = track_points, scene_depth_m
        self.offset_watch = offset_watch  # the video-kinematics offset, watched (runtime/time_offset_watch.py)
        self.rig = rig  # a stereo scope: every frame's tracks are also found in the other cameras' images
        self.recent = recent  # the live dense surface's: frames until the mapper names its keyframes
        self.frontend = None
        self.tracks_lost = False
        self._prev = None  # the last tracked frame's (prior T_world_camera, observations)

    def run(self) -> None:
        if self.device and str(self.device).startswith("cuda"):
            import warp as wp

            with wp.ScopedDevice(self.device):
                self._loop()
        else:
            self._loop()

    def _next(self):
        links = self.links
        with links.cond:
            while not links.capture_q and not (links.capture_done.is_set() or links.stop.is_set()):
                links.cond.wait(0.1)
            return links.capture_q.popleft() if links.capture_q else None

    def _loop(self) -> None:
        links, m = self.links, self.metrics
        while (item := self._next()) is not None:
            frame, arrival = item
            t0 = time.perf_counter()
            samples = self.poses.poll()
            if self.recording and samples and "record" not in links.disabled:
                with links.cond:
                    links.record_q.append(("joints", samples))
                    links.cond.notify_all()
            if not self.poses.has_pose(frame.t_ns):
                m.add("frames_without_pose")  # no pose brackets it (counted by cause there): not mapped
                continue
            prior = self.poses.prior_at(frame.t_ns)
            t1 = time.perf_counter()
            motion = self._motion(prior.T_world_camera)
            try:
                obs = self.frontend.process(frame, motion)
            except Exception as exc:
                if self.degrade:
                    m.add("tracking_errors")
                    log.warning("tracking failed on frame %d (%s); frame skipped", frame.seq, exc)
                    continue
                raise
            t2 = time.perf_counter()
            if self.offset_watch is not None and motion is not None:
                self.offset_watch.observe(self._prev[1], obs, motion)
            self._prev = (prior.T_world_camera, obs)
            self.tracks_lost = len(obs) == 0
            self.coverage.update(obs.uv)
            m.time_stage("pose", t1 - t0)
            m.time_stage("frontend", t2 - t1)
            self.latest.tracked(frame, prior.T_world_camera)
            if self.recent is not None:
                self.recent.add(frame)
            views = partner_views(self.frontend, frame, self.rig)
            if not self.submit(obs, prior, arrival, views() if views is not None else ()):
                m.add("mapper_skipped")  # the mapper is a whole ring behind: this frame is not mapped
                continue
            m.add("frames_tracked")

    def _motion(self, T_world_camera):
        """Where the tracks should land in this frame (FrameMotion), from the previous frame's pose and the
        mapper's points; None for the first frame or without prediction."""
        if self.track_points is None or self._prev is None:
            return None
        T_prev, prev = self._prev
        known, depth = self.track_points.depths(prev.track_ids, T_prev)
        return frame_motion(T_prev, T_world_camera, known, depth, self.scene_depth_m)

    def front_end_health(self) -> Condition:
        """Tracks lost (smoke, blood, a lens against tissue), or spanning only part of the view."""
        if self.tracks_lost:
            return Condition("no tracks", False, count_as="tracks_lost")
        if self.coverage.partial:
            return Condition("partial view", False, f"tracks cover {self.coverage.share:.0%} of the view",
                             count_as="partial_view")
        return Condition("tracking", True)


class Results:
    def __init__(self, messages, slot_freed, metrics: LiveMetrics, latest: LatestView, progress=None,
                 track_points: TrackPoints | None = None, dense: "DenseProcess | None" = None,
                 recent: RecentFrames | None = None) -> None:
        self.messages, self.slot_freed = messages, slot_freed  # a queue of the mapper's messages
        self.metrics, self.latest, self.progress = metrics, latest, progress
        self.track_points = track_points
        self.dense, self.recent = dense, recent  # the live dense surface, and the frames it takes keyframes from

    def run(self) -> None:
        m = self.metrics
        while True:
            msg = self.messages.get()
            if isinstance(msg, EndOfResults):
                return
            if isinstance(msg, SlotFree):
                self.slot_freed(msg.slot)
            elif isinstance(msg, FramePose):
                m.frame_done(msg.arrival_ns, msg.done_ns)
                m.add("frames_processed")
                if msg.is_keyframe:
                    m.add("keyframes")
                    if self.dense is not None:
                        frame = self.recent.take(msg.seq)
                        if frame is not None:
                            self.dense.keyframe(msg.keyframe_id, frame, msg.T_world_camera)
                        else:
                            m.add("dense_keyframes_missed")  # its frame was let go before the mapper named it
                m.set("local_ba_skipped", msg.local_ba_skipped)
                m.set("resection_skipped", msg.resection_skipped)
                self.latest.refined(msg.seq, msg.T_world_camera)
                if self.progress is not None:
                    self.progress.update(1)
            elif isinstance(msg, KeyframePoses):
                if self.dense is not None:
                    self.dense.poses(msg)
            elif isinstance(msg, NewTrackPoints):
                if self.track_points is not None:
                    self.track_points.update(msg.track_ids, msg.points)
            elif not isinstance(msg, (MapperReady, BAWorkerReady)):  # (when the start stopped waiting for them)
                log.error("unexpected message from the mapper: %r", msg)


class Surface:
    def __init__(self, snapshot, camera, config, out_dir, links: StageLinks, metrics: LiveMetrics,
                 latest: LatestView, dense: "DenseProcess | None" = None) -> None:
        self.snapshot, self.camera, self.config, self.out_dir = snapshot, camera, config, out_dir
        self.links, self.metrics, self.latest = links, metrics, latest
        self.dense = dense  # the live dense surface: its mesh is the live one
        self.mesh = None

    def run(self) -> None:
        from lapreco_hil.surface.mesh import alpha_shape, thin_points
        from lapreco_hil.runtime.live_view import LiveView

        rt, m = self.config.runtime, self.metrics
        view = LiveView(self.camera, self.out_dir, rt.view_period_s) if rt.view_period_s > 0 and \
            self.out_dir is not None else None
        version = -1
        next_mesh = next_view = time.monotonic()
        try:
            while not self.links.stop.wait(0.02) and not self.links.finished.is_set():
                now = time.monotonic()
                if self.dense is not None:
                    self.mesh = self.dense.mesh  # (rebuilt by the dense stage)
                elif view is not None and now >= next_mesh:
                    # (the live view is the mesh's one reader: without it nothing is rebuilt, a full alpha shape
                    # every couple of seconds held the GIL from tracking for 200 ms at 1080p)
                    # until the first mesh exists, look again soon: the view should show it as soon as there is one
                    next_mesh = now + (rt.surface_period_s if self.mesh is not None else min(rt.surface_period_s, 0.1))
                    v, pts, cols = self.snapshot.read()
                    if v != version and len(pts) >= 4:
                        t0 = time.perf_counter()
                        pts, cols = thin_points(pts, cols, rt.surface_max_points)
                        self.mesh = alpha_shape(pts, cols, self.config.surface.alpha_factor)
                        m.time_stage("surface", time.perf_counter() - t0)
                        m.add("surface_rebuilds")
                        version = v
                if view is not None and now >= next_view and self.mesh is not None:
                    next_view = now + rt.view_period_s
                    latest = self.latest.get()
                    if latest is not None:
                        t0 = time.perf_counter()
                        view.render(self.mesh, *latest)
                        m.time_stage("view", time.perf_counter() - t0)
                        m.add("views")
        finally:
            if view is not None:
                view.close()


class Dense:
    """The live dense surface's schedule (``[surface] mode = "dense"``, lapreco_hil.dense.surface.DenseSurface),
    run in the dense process (runtime/dense_process.py, which feeds it and reports for it). Keyframes come with
    their frame; a keyframe's depth map is made and fused once a newer keyframe exists (its neighbours on both
    sides, the mapper's depth span for it by then), and taken out and put back when local BA moves it. The mesh
    is extracted every ``period_s`` for the live view (None: no view wants it; meshing the whole volume takes a
    CPU second, so then only the final outputs mesh it).

    The stage is busy at most ``busy_share`` of the wall time: after each keyframe it rests in proportion, and
    when several keyframes are ready it fuses the newest (what the live view wants) and leaves the older ones to
    the final build."""

    def __init__(self, surface, links: StageLinks, metrics: LiveMetrics, *, period_s: float | None,
                 device: str, busy_share: float = 1.0) -> None:
        self.surface, self.links, self.metrics = surface, links, metrics
        self.period_s, self.device, self.busy_share = period_s, device, busy_share
        self.mesh = None
        self._inbox: collections.deque = collections.deque()  # ("keyframe", id, frame, T) | ("poses", msg)
        self._cond = threading.Condition()
        self.order: list[int] = []  # keyframe ids as they came

    def keyframe(self, kf_id: int, frame, T_world_camera: np.ndarray) -> None:
        with self._cond:
            self._inbox.append(("keyframe", kf_id, frame, T_world_camera))
            self._cond.notify()

    def poses(self, msg: KeyframePoses) -> None:
        with self._cond:
            self._inbox.append(("poses", msg))
            self._cond.notify()

    def run(self) -> None:
        from lapreco_hil.warp_device import device_lock

        m = self.metrics
        next_mesh = time.monotonic() + (self.period_s or 0.0)
        rest_until = 0.0  # no keyframe is fused before this (monotonic s): the stage's busy share
        while not self.links.stop.is_set() and not self.links.finished.is_set():
            with self._cond:
                if not self._inbox:
                    self._cond.wait(0.05)
                items = list(self._inbox)
                self._inbox.clear()
            for item in items:
                self._take(item)
            # every keyframe but the newest has a neighbour on each side by now: its depth map; one that has no
            # source view yet is tried again while it is among the newest few
            ready = self.order[:-1]
            if ready and time.monotonic() >= rest_until:
                t0 = time.perf_counter()
                # the newest first; the older ones (the stage had no time for them) wait for the final build
                newest, older = ready[-1], ready[:-1]
                fused = self.surface.fuse_pending({newest})
                m.add("dense_left_to_final", sum(k not in self.surface.without_sources for k in older))
                waiting = [k for k in ready if k in self.surface.without_sources][-RETRY_KEYFRAMES:]
                self.order = waiting + self.order[-1:]
                took = time.perf_counter() - t0
                rest_until = time.monotonic() + took * (1.0 / self.busy_share - 1.0)
                if fused:
                    m.time_stage("dense_keyframe", took / fused)
                    m.add("dense_keyframes", fused)
            now = time.monotonic()
            if self.period_s is not None and now >= next_mesh and self.surface.fused:
                next_mesh = now + self.period_s
                t0 = time.perf_counter()
                with device_lock(self.device):
                    self.mesh = self.surface.extract().mesh
                m.time_stage("dense_mesh", time.perf_counter() - t0)

    def _take(self, item) -> None:
        if item[0] == "keyframe":
            _, kf_id, frame, T = item
            self.surface.add_view(kf_id, frame.image, T)
            self.order.append(kf_id)
        else:
            msg = item[1]
            spans = {int(k): (None if not np.all(np.isfinite(r)) else (float(r[0]), float(r[1])))
                     for k, r in zip(msg.keyframe_ids, msg.depth_ranges)}
            self.surface.set_depth_ranges(spans)
            self.metrics.add("dense_refused", self.surface.update_poses(dict(zip(msg.keyframe_ids.tolist(),
                                                                                 msg.poses))))

    def finish(self, poses: dict, ranges: dict):
        """The run's dense surface from its final map's keyframe poses and depth ranges
        (``dense.surface.final_poses_and_ranges``): every kept keyframe at its final pose; a DenseResult."""
        from lapreco_hil.warp_device import device_lock

        for item in self._inbox:  # keyframes that came after the stage stopped (the final poses replace updates)
            if item[0] == "keyframe":
                self._take(item)
        self._inbox.clear()
        with device_lock(self.device):
            return self.surface.build_at(poses, ranges)


class Record:
    def __init__(self, recorder, links: StageLinks) -> None:
        self.recorder, self.links = recorder, links

    def run(self) -> None:
        links = self.links
        while True:
            with links.cond:
                while not links.record_q and not links.finished.is_set():
                    links.cond.wait(0.1)
                if not links.record_q:
                    return
                kind, item = links.record_q.popleft()
            if kind == "frame":
                self.recorder.add_frame(item)
            else:
                self.recorder.add_joints(item)


class RigCheck:
    """A stereo rig's extrinsics against the newest tracked frame's images, as a replay checks its first frame:
    the rig inverted, in the wrong unit or not fitting at all is said at the start of the run. A frame too poor in
    features to judge (a dark first second, the scope in its trocar) is passed over for a later one, up to
    ``tries`` frames ``period_s`` apart. Never fails the run: a check that cannot run is logged."""

    def __init__(self, rig, latest: LatestView, links: StageLinks, source: str, *, first_after_s: float = 0.5,
                 period_s: float = 1.0, tries: int = 5) -> None:
        self.rig, self.latest, self.links, self.source = rig, latest, links, source
        self.first_after_s, self.period_s, self.tries = first_after_s, period_s, tries
        self.fits: list[dict] | None = None  # one summary per judged pair; None: no frame could be judged

    def run(self) -> None:
        wait_s = self.first_after_s
        for _ in range(self.tries):
            stopped = self.links.stop.wait(wait_s)  # a run shorter than the wait: its last frame is judged
            wait_s = self.period_s
            if self._judge(self.latest.get()) or stopped:
                return

    def _judge(self, newest) -> bool:
        """True once the check has run (judged, or could not run); False: no frame to judge yet."""
        from lapreco_hil.calib.rig_check import check_rig

        if newest is None or 1 + len(newest[0].views) < len(self.rig):
            return False
        frame = newest[0]
        images = (np.array(frame.image),) + tuple(np.array(v) for v in frame.views)  # its slot is reused
        try:
            fits = check_rig(self.rig, images)
        except Exception as exc:  # (an image OpenCV cannot read): the run goes on unchecked
            log.warning("%s: the stereo rig could not be checked: %s: %s", self.source, type(exc).__name__, exc)
            return True
        if not fits:
            return False
        self.fits = [dict(fit.summary(), frame_seq=int(frame.seq)) for fit in fits]
        for fit in fits:
            if fit.problem:
                log.warning("%s: %s", self.source, fit.problem)
        return True
