"""The mapper in its own process, and its local BA in another. GTSAM's optimiser holds the GIL for the whole
solve (docs/benchmarks.md, "Runtime notes"), so a
local BA in a thread would stall whatever else runs in that process: capture and tracking in the main
process, and the per-frame work (keyframe choice, triangulation, pose refinement) in the mapper. So frames
are mapped as they come while the BA worker solves the newest window; when its result is back the mapper
applies it and hands over the newest window again (BA runs on the newest keyframes only, as often as it can).
A keyframe's pose is published as soon as it is resected; its new points (and the local BA that follows them)
wait for the mapper's next idle moment, so the frames queued behind a keyframe do not wait for its structure.

Observations arrive through shared memory (ObservationRing), slot numbers and refined poses through queues;
BA problems and results (numpy arrays) through the worker's queues; the final map goes back through a pipe.
Every message is a small frozen dataclass (runtime/messages.py). Both processes end when the main process
dies, however it dies (``die_with_parent``)."""

from __future__ import annotations

import functools
import gc
import logging
import os
import queue
import signal
import sys
import threading
import time
import traceback

from multiprocessing.connection import wait as wait_for_any

import numpy as np

from lapreco_hil.runtime.messages import (BAJob, BAResult, BAWorkerReady, EndOfFrames, EndOfJobs, FinalMap,
                                          FramePose, KeyframePoses, MapperFailed, MapperReady, NewTrackPoints,
                                          SlotFree)

log = logging.getLogger(__name__)

SNAPSHOT_PERIOD_S = 0.5  # the map for the live surface is published at most this often
SNAPSHOT_PIECE = 2500  # landmarks gathered per idle moment for it (a frame that arrives waits for one piece)
YOUNG_GC_PERIOD_S = 1.0  # the mapper's idle-time garbage collection (IdleTimeGC)
# Frames first: a BA result is applied, the next BA job built and sent, the map snapshot gathered (each a few
# to tens of milliseconds) when no frame waits, or after this long without such a moment (a long backlog)
HOUSEKEEPING_MAX_DELAY_S = 0.25
_IDLE = object()  # no frame waiting


class IdleTimeGC:
    """Garbage collection in the mapper's idle moments only. The mapper holds every active track's views, a
    few hundred thousand small objects into a run, and CPython's automatic full collections walk them all,
    pauses that grow with the map and stall the frames waiting (docs/benchmarks.md, "Runtime notes"). The mapper makes almost no reference cycles (under a thousand objects unreachable
    after a whole session), so in its process automatic collection is off and the young generations, where
    short-lived cycles are, are collected when no frame waits. Reference counting frees everything else as
    before."""

    def __init__(self, period_s: float = YOUNG_GC_PERIOD_S, clock=time.monotonic) -> None:
        self.period_s, self.clock = period_s, clock
        self._next = clock() + period_s
        self._was_enabled = gc.isenabled()
        self.collected = 0  # unreachable objects found by the idle-time collections

    def start(self) -> "IdleTimeGC":
        gc.disable()
        return self

    def stop(self) -> None:
        if self._was_enabled:
            gc.enable()

    __enter__ = start

    def __exit__(self, *exc) -> None:
        self.stop()

    def collect_if_due(self) -> bool:
        """Collect the young generations if the period has passed; True when it did."""
        now = self.clock()
        if now < self._next:
            return False
        self.collected += gc.collect(1)
        self._next = now + self.period_s
        return True


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent(parent_pid: int) -> None:
    """End this process when ``parent_pid`` (the main process) dies, even by kill -9: on Linux the kernel sends
    SIGKILL (prctl PR_SET_PDEATHSIG); elsewhere a thread watches the parent pid. A parent that died before this
    call is caught by the pid check. (No cleanup is needed here: the shared memory and semaphores belong to the
    main process, and multiprocessing's resource tracker unlinks them once every process of the run is gone.)"""
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
        if armed:
            if os.getppid() != parent_pid:
                os._exit(1)
            return

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.25)
        os._exit(1)

    threading.Thread(target=watch, name="parent watch", daemon=True).start()


def ba_worker_main(schedule, jobs_q, results_q, parent_pid: int, mapper_config, ready_q=None) -> None:
    """Process body: solve each BAJob until EndOfJobs arrives; errors go back, never lost. ``ready_q``: where
    BAWorkerReady goes once the solver is loaded (the main process holds capture until then)."""
    die_with_parent(parent_pid)
    from lapreco_hil.mapping.mapper import ba_solver

    solve = ba_solver(mapper_config)
    if mapper_config.ba_solver == "schur" and mapper_config.ba_device != "numpy":
        # compiled now, not in the first window (which the live schedule would then defer)
        from lapreco_hil.warp_device import preload_kernels, resolve_device

        preload_kernels("lapreco_hil.mapping.schur_kernels", resolve_device(mapper_config.ba_device))
        if resolve_device(mapper_config.ba_device).startswith("cuda"):  # (the final pass's camera system's)
            from lapreco_hil.mapping import dense_cholesky, schur

            dense_cholesky.load(schur.DEVICE_TILE, resolve_device(mapper_config.ba_device))
        # this process's windows' device buffers (and a GPU's page-locked mirrors), kept from one to the next
        from lapreco_hil.mapping.schur_kernels import SchurWorkspace

        solve = functools.partial(solve, workspace=SchurWorkspace())

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    if ready_q is not None:
        ready_q.put(BAWorkerReady())
    while True:
        job = jobs_q.get()
        if isinstance(job, EndOfJobs):
            return
        started_ns, t0 = time.monotonic_ns(), time.perf_counter()
        try:
            solved, error = solve(job.problem, schedule), ""
        except Exception:
            solved, error = None, traceback.format_exc()
        results_q.put(BAResult(job.job_id, solved, error, time.perf_counter() - t0, started_ns, time.monotonic_ns()))


class _BAClient:
    """The mapper's side of the worker: one job in flight at a time, and its round trip timed (what decides how
    many keyframes' BA is deferred: a keyframe that arrives while a job is in flight waits for the next one)."""

    def __init__(self, jobs_q, results_q, clock=None) -> None:
        self.jobs_q, self.results_q = jobs_q, results_q
        self.clock = clock  # a StageClock for the round trip's legs, or None
        self.in_flight = None  # (job id, problem, ticket, submitted at (monotonic ns))
        self._next_id = 0
        self.runs = self.failed = 0
        self.solve_s: list[float] = []  # the worker's time per solve
        self.keyframes_in_flight = 0  # keyframes added while the job now in flight is out
        self.keyframes_per_flight: list[int] = []  # per collected job

    def submit(self, job) -> None:
        problem, ticket = job
        self.in_flight = (self._next_id, problem, ticket, time.monotonic_ns())
        self.jobs_q.put(BAJob(self._next_id, problem))
        self._next_id += 1

    def keyframe_added(self) -> None:
        if self.in_flight is not None:
            self.keyframes_in_flight += 1

    def result_ready(self) -> bool:
        """Whether the job in flight has its answer waiting (a poll of the result pipe, microseconds)."""
        return self.in_flight is not None and not self.results_q.empty()

    def collect(self, mapper, timeout_s: float = 0.0) -> bool:
        """Apply the finished job, if there is one (waiting up to ``timeout_s``); True when one was."""
        if self.in_flight is None:
            return False
        try:
            reply: BAResult = self.results_q.get(timeout=timeout_s) if timeout_s else self.results_q.get_nowait()
        except queue.Empty:
            return False
        now = time.monotonic_ns()
        self.solve_s.append(reply.solve_s)
        _, problem, ticket, submitted_ns = self.in_flight
        self.in_flight = None
        self.keyframes_per_flight.append(self.keyframes_in_flight)
        self.keyframes_in_flight = 0
        if self.clock is not None and reply.done_ns:
            # submitted -> collected, and its legs: to the worker (queue, pickling, the worker's previous
            # answer), and how long the answer waited for the mapper to collect it
            self.clock.add("local_ba_in_flight", (now - submitted_ns) * 1e-9)
            self.clock.add("local_ba_to_worker", (reply.started_ns - submitted_ns) * 1e-9)
            self.clock.add("local_ba_result_waited", (now - reply.done_ns) * 1e-9)
        if not reply.error:
            mapper.apply_local_ba(problem, reply.solved, ticket)
            self.runs += 1
        else:  # a failed local BA loses one refinement, not the run: the next window covers it
            self.failed += 1
            log.error("local BA %d failed in the worker:\n%s", reply.job_id, reply.error)
        return True


def mapper_main(ring_name: str, ring_slots: int, max_tracks: int, snap_name: str, max_points: int, snap_lock,
                K: np.ndarray, mapper_config, backlog_skip_ba: int, ready_q, done_q, final_conn, parent_pid: int,
                ba_jobs_q=None, ba_results_q=None, ring_cameras: int = 1, rig=None,
                keyframe_poses: bool = False) -> None:
    """Process body: take SlotReady messages until EndOfFrames, then finish the map and send it (FinalMap, or
    MapperFailed). With BA queues, local BA goes to the worker; without, it runs here (deferred while frames
    wait). ``keyframe_poses``: after each local BA, send the newest keyframes' poses (KeyframePoses, for the
    live dense surface)."""
    die_with_parent(parent_pid)
    from lapreco_hil.mapping.mapper import Mapper, MapperSchedule
    from lapreco_hil.runtime.shm import MapSnapshot, ObservationRing

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle: it ends the run cleanly
    ring = ObservationRing(ring_slots, max_tracks, name=ring_name, cameras=ring_cameras)
    snapshot = MapSnapshot(max_points, snap_lock, name=snap_name)
    try:
        clock = StageClock()
        worker = _BAClient(ba_jobs_q, ba_results_q, clock) if ba_jobs_q is not None else None
        schedule = MapperSchedule.live(ba_worker=worker is not None,
                                       local_ba_before_points=mapper_config.local_ba_before_points)
        mapper = Mapper(K, mapper_config, schedule=schedule, rig=rig)
        collector = IdleTimeGC().start()  # for the life of the process
        done_q.put(MapperReady())  # imports done, the mapper made: the main process starts capture now
        skipped_ba = skipped_resection = 0
        # keyframes added since the last local BA was handed to the worker: a job covers them all, so all but
        # its newest were merged into it rather than given a window of their own (deferred)
        keyframes_since_job = 0
        # of those, the ones merged into the first job (keyframes before the map had a landmark to adjust)
        skipped_before_first_job = None
        bas_announced = 0  # local BAs whose keyframe poses went to the main process (KeyframePoses)
        last_publish, map_changed = 0.0, False
        ba_wanted_since = None  # (perf_counter) when the mapper first wanted the local BA not yet submitted
        last_keyframe_at = None
        # when (seconds after the first frame) the map first had a landmark, and the first local BA left: a late
        # start merges every keyframe before it into one job
        first_frame_at = first_landmark_s = first_job_s = None

        gathering = None  # the snapshot being gathered, a piece at a time (Mapper.map_points_in_pieces)

        def publish_if_due(whole: bool = False) -> None:
            # the live surface rebuilds every couple of seconds: a snapshot twice a second is plenty, and
            # gathering the whole map takes long enough that it is done in pieces, so no frame waits for all of it
            nonlocal last_publish, map_changed, gathering
            if gathering is None:
                if not (map_changed and (whole or time.monotonic() - last_publish >= SNAPSHOT_PERIOD_S)):
                    return
                gathering, map_changed = mapper.map_points_in_pieces(None if whole else SNAPSHOT_PIECE), False
            t = time.perf_counter()
            done = next(gathering)
            while whole and done is None:
                done = next(gathering)
            if done is not None:
                points, colors = done
                if len(points):
                    snapshot.publish(points, colors)
                gathering, last_publish = None, time.monotonic()
            clock.add("gather_snapshot", time.perf_counter() - t)

        last_housekeeping = time.monotonic()
        # multiprocessing queues' read ends, to sleep on both the frames and the worker's answers
        answer_waitable = worker is not None and all(hasattr(q, "_reader") for q in (ready_q, ba_results_q))
        keyframe_captured: dict[int, int] = {}  # keyframe id -> its frame's capture time, until its points exist

        def points_done() -> None:
            # a frame's latency ends with its pose; a keyframe's new points follow in idle moments: how long after
            # its capture they exist is timed too
            now = time.monotonic_ns()
            for kf_id in mapper.structured:
                captured = keyframe_captured.pop(kf_id, None)
                if captured is not None:
                    clock.add("keyframe_points_after_capture", (now - captured) * 1e-9)
            if mapper.structured and mapper.frames:
                ids = mapper.frames[-1].track_ids
                if ids is not None:
                    known = [t for t in ids.tolist() if t in mapper.landmarks]
                    done_q.put(NewTrackPoints(np.array(known, np.int64),
                                           np.array([mapper.landmarks[t] for t in known]).reshape(-1, 3)))
            mapper.structured.clear()

        def announce_poses() -> None:
            # after a local BA, the moved keyframes' poses for the live dense surface (a window's worth, tiny)
            nonlocal bas_announced
            if keyframe_poses and len(mapper.ba_times) != bas_announced:
                bas_announced = len(mapper.ba_times)
                ids, poses, spans = mapper.newest_reference_poses(mapper_config.window_keyframes + 2)
                if len(ids):
                    done_q.put(KeyframePoses(ids, poses, spans))

        def note_first_landmark() -> None:
            nonlocal first_landmark_s
            if first_landmark_s is None and first_frame_at is not None and mapper.landmarks:
                first_landmark_s = time.perf_counter() - first_frame_at

        def note_ba_wanted() -> None:
            nonlocal ba_wanted_since
            if ba_wanted_since is None and mapper.local_ba_wanted:
                ba_wanted_since = time.perf_counter()

        def ba_round() -> None:
            # the finished job applied, and the next one sent at once: the worker idles as little as it can
            nonlocal map_changed, skipped_ba, keyframes_since_job, ba_wanted_since
            nonlocal skipped_before_first_job, first_job_s
            t = time.perf_counter()
            applied = worker.collect(mapper)
            if applied:
                announce_poses()
                clock.add("apply_local_ba", time.perf_counter() - t)
            map_changed |= applied
            if worker.in_flight is None and mapper.local_ba_wanted:
                t = time.perf_counter()
                if ba_wanted_since is not None:
                    clock.add("local_ba_wanted_to_submit", t - ba_wanted_since)
                if last_keyframe_at is not None:  # the newest keyframe the job covers: added -> its job sent
                    clock.add("keyframe_added_to_local_ba_submit", t - last_keyframe_at)
                ba_wanted_since = None
                job = mapper.local_ba_job()
                if job is not None:
                    worker.submit(job)
                    skipped_ba += max(keyframes_since_job - 1, 0)
                    keyframes_since_job = 0
                    if skipped_before_first_job is None:
                        skipped_before_first_job = skipped_ba
                        first_job_s = time.perf_counter() - first_frame_at
                    clock.add("submit_local_ba", time.perf_counter() - t)

        def housekeeping() -> None:
            nonlocal last_housekeeping
            if worker is not None:
                ba_round()
            publish_if_due()
            last_housekeeping = time.monotonic()

        while True:
            try:
                slot = ready_q.get_nowait()
            except queue.Empty:
                slot = _IDLE
            if slot is _IDLE or time.monotonic() - last_housekeeping >= HOUSEKEEPING_MAX_DELAY_S:
                housekeeping()
            if slot is _IDLE:
                # nothing waits: the moment for maintenance (garbage collection, the last keyframe's new points,
                # retiring old keyframes one at a time)
                t = time.perf_counter()
                if collector.collect_if_due():
                    clock.add("collect_garbage", time.perf_counter() - t)
                    continue
                t = time.perf_counter()
                work = mapper.maintain()
                note_first_landmark()
                note_ba_wanted()
                if work is not None:
                    announce_poses()  # (an inline local BA follows a keyframe's last piece of points)
                    clock.add(f"{work}_keyframe", time.perf_counter() - t)
                    points_done()
                    map_changed = True
                    continue
                t = time.perf_counter()
                try:
                    if worker is not None and worker.in_flight and gathering is None and answer_waitable:
                        # asleep until a frame or the worker's answer comes, whichever is first (a poll of the
                        # frames alone would leave the answer waiting, the worker idle)
                        wait_for_any([ready_q._reader, worker.results_q._reader], timeout=HOUSEKEEPING_MAX_DELAY_S)
                        continue
                    busy = (worker is not None and worker.in_flight) or gathering is not None
                    slot = ready_q.get(timeout=0.005) if busy else ready_q.get()
                except queue.Empty:
                    continue
                finally:
                    clock.add("wait_for_frames", time.perf_counter() - t)
            if isinstance(slot, EndOfFrames):
                break
            obs, prior, arrival_ns = ring.read(slot.slot)
            done_q.put(SlotFree(slot.slot))
            try:
                backlog = ready_q.qsize()
            except NotImplementedError:  # macOS has no qsize; never skip there
                backlog = 0
            run_ba = worker is not None or backlog <= backlog_skip_ba
            resect = backlog == 0  # behind: a frame between keyframes takes its corrected prior for now
            t = time.perf_counter()
            views = ring.read_views(slot.slot) if ring_cameras > 1 else ()
            is_kf = mapper.add(obs, prior, local_ba=run_ba, resect=resect, partners=views or None)
            clock.add("add_keyframe" if is_kf else "add_frame", time.perf_counter() - t)
            if first_frame_at is None:
                first_frame_at = t
            note_first_landmark()
            note_ba_wanted()
            kf_id = mapper.frames[-1].keyframe if is_kf else -1  # (the reference's: stereo partners follow it)
            if is_kf:
                keyframe_captured[kf_id] = arrival_ns
                now = time.perf_counter()
                if last_keyframe_at is not None:
                    clock.add("keyframe_gap", now - last_keyframe_at)
                last_keyframe_at = now
            points_done()
            if is_kf and worker is not None:
                keyframes_since_job += 1
                worker.keyframe_added()
            elif is_kf and not run_ba:
                skipped_ba += 1  # this keyframe's own BA is covered by the next window's
            if not is_kf and not resect:
                skipped_resection += 1
            map_changed |= bool(is_kf)
            done_q.put(FramePose(obs.frame_seq, time.monotonic_ns(), arrival_ns, mapper.frames[-1].T_refined,
                                 bool(is_kf), skipped_ba, skipped_resection, kf_id))
            if worker is not None and (worker.result_ready() or (worker.in_flight is None and mapper.local_ba_wanted)):
                # between frames, not only in idle moments: an answer waiting (or a window wanted with none out)
                # keeps the worker idle, and every keyframe added meanwhile is deferred
                ba_round()
        publish_if_due(whole=True)  # (the map as it ended, if it changed since the last snapshot)
        if worker is not None:
            worker.collect(mapper, timeout_s=600.0)  # the last window's BA, then the final pass
        t0 = time.perf_counter()
        result = mapper.finish()
        result.stats["final_ba_wall_s"] = time.perf_counter() - t0
        if worker is not None:
            for s_ in worker.solve_s:
                clock.add("local_ba_solve_in_worker", s_)
        result.stats["mapper_stages_ms"] = clock.summary()
        result.stats["garbage_collected"] = collector.collected
        result.stats["local_ba_skipped"] = skipped_ba
        result.stats["resection_skipped"] = skipped_resection
        if worker is not None:
            result.stats["local_ba_worker_runs"] = worker.runs
            result.stats["local_ba_worker_failed"] = worker.failed
            result.stats["local_ba_round_trip"] = round_trip_summary(worker.keyframes_per_flight,
                                                                     clock.samples.get("keyframe_gap", []),
                                                                     clock.samples.get("local_ba_in_flight", []))
            result.stats["local_ba_round_trip"].update(deferred_into_the_first_job=skipped_before_first_job or 0,
                                                       first_landmark_s=first_landmark_s, first_job_s=first_job_s)
        final_conn.send(FinalMap(result))
    except BaseException:  # reported to the main loop, never lost with the process
        final_conn.send(MapperFailed(traceback.format_exc()))
    finally:
        ring.close()
        snapshot.close()
        final_conn.close()


class StageClock:
    """Where the mapper process's time goes, per kind of work (ms per call): the live report's answer to "which
    part of the mapper is the bottleneck" (frames vs keyframes, BA results applied, snapshots, idle waits)."""

    def __init__(self) -> None:
        self.samples: dict[str, list[float]] = {}
        self._t0 = time.perf_counter()

    def add(self, name: str, seconds: float) -> None:
        self.samples.setdefault(name, []).append(seconds * 1e3)

    def summary(self) -> dict:
        wall = (time.perf_counter() - self._t0) * 1e3
        out = {}
        for name, v in self.samples.items():
            a = np.asarray(v)
            out[name] = {"count": len(a), "mean": float(a.mean()), "p50": float(np.percentile(a, 50)),
                         "p99": float(np.percentile(a, 99)), "max": float(a.max()),
                         "share_of_wall": float(a.sum() / max(wall, 1e-9))}
        return out


def round_trip_summary(keyframes_per_flight: list[int], keyframe_gap_ms: list[float],
                       in_flight_ms: list[float]) -> dict:
    """How the local BA's round trip meets the keyframes: per collected job, how many keyframes arrived while it
    was out (they all go into the next job: all but one of them deferred), against the gaps between keyframes."""
    k = np.asarray(keyframes_per_flight, int)
    gap, flight = np.asarray(keyframe_gap_ms, float), np.asarray(in_flight_ms, float)
    return {"jobs": int(len(k)),
            "keyframes_while_in_flight": {"mean": float(k.mean()) if len(k) else 0.0,
                                          "max": int(k.max()) if len(k) else 0,
                                          "jobs_with_two_or_more": int((k >= 2).sum())},
            "keyframe_gap_ms_mean": float(gap.mean()) if len(gap) else None,
            "in_flight_ms_mean": float(flight.mean()) if len(flight) else None,
            # > 1: jobs take longer than keyframes come, and keyframes queue up behind them
            "in_flight_over_keyframe_gap": float(flight.mean() / gap.mean()) if len(gap) and len(flight) else None}


def drain(q) -> list:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out
