"""The live run's figures: counters the stages bump from their threads, the latency of every mapped frame,
per-stage times, queue depths, and the report's live fields made from them at the end."""

from __future__ import annotations

import collections
import gc
import threading
import time

import numpy as np


LONG_GC_PAUSE_MS = 20.0  # a main-process collection this long is listed with its time (a frame period at 50 fps)


class GcPauses:
    """The main process's garbage collections during a live run (``gc.callbacks``): per generation how many and
    how long, and when the long ones happened. Capture and tracking run in this process; a full collection
    walks every object of it while holding the GIL, a stall of every thread (the mapper's process collects
    only when idle: ``mapper_process.IdleTimeGC``)."""

    def __init__(self, started_ns: int, clock=time.monotonic_ns) -> None:
        self.started_ns, self.clock = started_ns, clock
        self.count = [0, 0, 0]
        self.total_ns = [0, 0, 0]
        self.max_ns = [0, 0, 0]
        self.long: list[tuple[float, int, float]] = []  # (s into the run, generation, ms)
        self._began: dict[int, int] = {}

    def _callback(self, phase: str, info: dict) -> None:
        now = self.clock()
        if phase == "start":
            self._began[threading.get_ident()] = now
            return
        began = self._began.pop(threading.get_ident(), None)
        if began is None:
            return
        g, took = min(int(info.get("generation", 2)), 2), now - began
        self.count[g] += 1
        self.total_ns[g] += took
        self.max_ns[g] = max(self.max_ns[g], took)
        if took >= LONG_GC_PAUSE_MS * 1e6 and len(self.long) < 100:
            self.long.append((round((began - self.started_ns) * 1e-9, 3), g, round(took * 1e-6, 1)))

    def start(self) -> None:
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)

    def stop(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def summary(self) -> dict:
        return {"collections": list(self.count), "total_ms": [round(t * 1e-6, 1) for t in self.total_ns],
                "max_ms": [round(t * 1e-6, 2) for t in self.max_ns], "long": list(self.long),
                "long_ms": LONG_GC_PAUSE_MS}


class LiveMetrics:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: collections.Counter = collections.Counter()
        self.latency_ns: list[int] = []  # capture -> refined pose, per mapped frame (appended by one thread)
        self.stage_s: dict[str, list[float]] = collections.defaultdict(list)
        self.depth: dict[str, list[int]] = collections.defaultdict(list)
        self.first_arrival_ns = 0
        self.last_done_ns = 0
        self.started_ns = time.monotonic_ns()
        self.event_span_ns: dict[str, list[int]] = {}  # an event's first and last time (drops: when, not only how many)
        self.gc = GcPauses(self.started_ns)  # started and stopped by the run

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def set(self, key: str, value: int) -> None:
        with self._lock:
            self.counts[key] = value

    def mark(self, key: str) -> None:
        """``add(key)``, remembering when the first and the last of them happened."""
        now = time.monotonic_ns()
        with self._lock:
            self.counts[key] += 1
            self.event_span_ns.setdefault(key, [now, now])[1] = now

    def get(self, key: str) -> int:
        return self.counts.get(key, 0)

    def time_stage(self, name: str, seconds: float) -> None:
        self.stage_s[name].append(seconds)

    def sample_depth(self, queue_name: str, depth: int) -> None:
        self.depth[queue_name].append(depth)

    def frame_done(self, arrival_ns: int, done_ns: int) -> None:
        self.latency_ns.append(done_ns - arrival_ns)
        self.first_arrival_ns = min(self.first_arrival_ns or arrival_ns, arrival_ns)
        self.last_done_ns = done_ns

    def report(self, *, wall_s: float, result, poses, errors: dict, disabled: set, interrupted: bool,
               health_events: list[dict], health_event_count: int, health_counts: dict,
               time_offset: dict | None = None) -> dict:
        """report.json's live fields."""
        c = dict(self.counts)
        lat_ms = np.array(self.latency_ns, float) * 1e-6
        pct = {"p50": float(np.percentile(lat_ms, 50)), "p95": float(np.percentile(lat_ms, 95)),
               "p99": float(np.percentile(lat_ms, 99)), "max": float(lat_ms.max())} if len(lat_ms) else {}
        stage_ms = {k: {"mean": float(np.mean(v) * 1e3), "p95": float(np.percentile(v, 95) * 1e3),
                        "max": float(np.max(v) * 1e3)}
                    for k, v in self.stage_s.items() if v}
        # seconds into the run of each marked event's first and last occurrence
        spans = {k: [round((t - self.started_ns) * 1e-9, 3) for t in v] for k, v in self.event_span_ns.items()}
        processed = c.get("frames_processed", 0)
        frames_in = c.get("frames_in", 0)
        return {
            "wall_s": wall_s,
            "frames": {"in": frames_in, "processed": processed,
                       "dropped": frames_in - processed + c.get("dropped_source", 0) - c.get("bad_timestamps", 0)
                       - c.get("frames_without_pose", 0),
                       "without_pose": c.get("frames_without_pose", 0),
                       "without_pose_by_cause": poses.without_pose.as_dict(),
                       "dropped_source": c.get("dropped_source", 0), "dropped_capture": c.get("dropped_capture", 0),
                       "passed_before_start": c.get("passed_before_start", 0),
                       "mapper_skipped": c.get("mapper_skipped", 0), "tracking_errors": c.get("tracking_errors", 0),
                       "dropped_record": c.get("dropped_record", 0), "bad_timestamps": c.get("bad_timestamps", 0),
                       "dropped_capture_span_s": spans.get("dropped_capture"),
                       # frames the capture thread put in page-locked memory for the Warp front-end on CUDA, and
                       # those it could not (every buffer still held: a recorder's backlog)
                       "page_locked": c.get("frames_page_locked", 0),
                       "not_page_locked": c.get("frames_not_page_locked", 0)},
            # the pose source's samples refused (the keys keep their first name: a tracker's refusals are here too)
            "pose_source": getattr(poses, "source", "robot"),
            "robot_samples_rejected": poses.rejected,  # (a given-pose source refuses nothing)
            "robot_samples_rejected_by_cause": dict(poses.rejected_by_cause),
            # what the robot driver counted on its link (lost readings, reconnects, device faults)
            "robot_faults": dict(poses.robot.faults) if poses.robot is not None else {},
            # frames mapped per second while the source delivered (the final global BA is not in it)
            "throughput_fps": processed / max((self.last_done_ns - self.first_arrival_ns) * 1e-9, 1e-9)
            if processed > 1 else 0.0,
            "latency_ms": {**pct, "note": "capture (the grabber's host-clock stamp, else frame in hand) -> refined pose available"},
            "stage_ms": stage_ms,
            # the video-kinematics offset in use and what the run's own motion says it is (runtime/time_offset_watch)
            "time_offset": time_offset,
            "queue_depth": {k: {"mean": float(np.mean(v)), "max": int(np.max(v))} for k, v in self.depth.items() if v},
            # keyframes merged into a later keyframe's local BA instead of a window of their own (deferred)
            "live": {"local_ba_skipped": c.get("local_ba_skipped", 0),
                     "local_ba_deferred_share": c.get("local_ba_skipped", 0) / max(c.get("keyframes", 0), 1),
                     "resection_skipped": c.get("resection_skipped", 0), "surface_rebuilds": c.get("surface_rebuilds", 0),
                     "views": c.get("views", 0), "capture_timeouts": c.get("capture_timeouts", 0),
                     # the live dense stage: keyframes it fused, re-fused after BA moved them, left to the final build
                     "dense_keyframes": c.get("dense_keyframes", 0), "dense_refused": c.get("dense_refused", 0),
                     "dense_left_to_final": c.get("dense_left_to_final", 0),
                     "stage_errors": dict(errors), "disabled_stages": sorted(disabled),
                     "interrupted": interrupted,
                     # the map's end after capture stops: all of it, and its global BA alone
                     "final_ba_s": result.stats.get("final_ba_wall_s"),
                     "final_global_ba_s": result.stats.get("final_ba_s"),
                     # where that global BA's time went: the problem, the solver's stages and timing
                     "final_global_ba": result.stats.get("final_ba"),
                     # the mapper process's own time, by kind of work (the usual bottleneck)
                     "mapper_stages_ms": result.stats.get("mapper_stages_ms", {}),
                     # the worker's windows: solved, and failed (a failure is logged; its window is not applied)
                     "local_ba_worker_runs": result.stats.get("local_ba_worker_runs", 0),
                     "local_ba_worker_failed": result.stats.get("local_ba_worker_failed", 0),
                     # the worker's local BA against the keyframes: jobs, keyframes that came while one was out
                     "local_ba_round_trip": result.stats.get("local_ba_round_trip"),
                     # unreachable objects the mapper's idle-time collections found (automatic GC is off there)
                     "mapper_garbage_collected": result.stats.get("garbage_collected")},
            # the main process's garbage collections (a long one stalls capture and tracking alike)
            "gc_main_process": self.gc.summary(),
            "health": {"events": health_events[:200], "event_count": health_event_count, "counts": dict(health_counts)},
            # every change of health the run saw (device, state, detail, time), as shown on the console
            "health_events": health_events,
        }
