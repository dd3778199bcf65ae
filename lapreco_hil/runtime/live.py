"""The live runtime: capture, tracking (pose prior + front-end), mapping (its own process), surface/view and
recording run concurrently, joined by bounded queues, each with an explicit, counted policy when it falls
behind (DESIGN.md, the seed's Fig 1):

- capture never blocks: it keeps the newest ``capture_queue`` frames; older ones are dropped and counted;
- tracking takes every frame capture kept (LK needs consecutive frames) and writes its observations into a
  shared-memory slot for the mapper; with no free slot the frame is not mapped (counted);
- the mapper process maps every frame it gets while a BA worker process solves the newest window of
  keyframes, back to back (BA runs on the newest keyframes only; keyframes it skipped are counted); frames
  come first there: a keyframe's new points, BA jobs and results, the map snapshot and garbage collection
  wait for moments when no frame waits, in short pieces (runtime/mapper_process.py);
- the surface is rebuilt every ``surface_period_s`` from the mapper's latest landmarks, the live textured view
  rendered every ``view_period_s``; recording has its own queue (drops counted) so disk never stalls capture.

Latency runs from a frame's capture (the grabber's host-clock stamp where it has one) to its refined pose.

An exception in any stage is stored and raised on the main loop (or, for the optional stages under
``on_stage_error = "degrade"``, the stage is switched off and the run goes on); a mapper process that dies is
always fatal. Nothing dies silently.
"""

from __future__ import annotations

import collections
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import CameraModel
from ..config import PipelineConfig
from ..errors import ConfigError, DeviceTimeoutError, LaprecoError, ReconstructionError
from ..frontend import make_frontend
from .coverage import ViewCoverage
from ..mapping.mapper import local_schedule
from .mapper_process import ba_worker_main, drain, mapper_main
from .shm import MapSnapshot, ObservationRing

log = logging.getLogger(__name__)
ESSENTIAL = ("capture", "tracking", "mapper")
MAPPER_START_TIMEOUT_S = 120.0  # for the mapper process to be up before capture starts


class StageError(LaprecoError):
    """A stage of the live runtime failed; the run was stopped cleanly."""


@dataclass
class _Counters:
    lock: threading.Lock = field(default_factory=threading.Lock)
    values: collections.Counter = field(default_factory=collections.Counter)

    def add(self, key: str, n: int = 1) -> None:
        with self.lock:
            self.values[key] += n


class LiveRun:
    def __init__(self, grabber, poses, camera: CameraModel, config: PipelineConfig, *, tracker: str, device: str,
                 out_dir: Path | None = None, recorder=None, on_stage_error: str = "stop", frontend=None,
                 progress=None) -> None:
        if on_stage_error not in ("stop", "degrade"):
            raise ValueError("on_stage_error must be 'stop' or 'degrade'")
        if config.runtime.ba_worker not in ("auto", "on", "off"):
            raise ConfigError(f"[runtime] ba_worker = '{config.runtime.ba_worker}': use auto, on or off")
        self.grabber, self.poses, self.camera, self.config = grabber, poses, camera, config
        self.rt = config.runtime
        self.out_dir = out_dir
        self.recorder = recorder
        self.on_stage_error = on_stage_error
        # a Warp front-end is built in the tracking thread, which owns its CUDA stream and graphs (a graph
        # captured on one thread's stream cannot be launched from another's)
        self.frontend = frontend
        self._make_frontend = lambda: make_frontend(tracker, camera, config.tracker, device)
        self.device = device
        self.progress = progress
        self.counters = _Counters()
        self.errors: dict[str, str] = {}
        self.disabled: set[str] = set()
        self.stop = threading.Event()  # set by the caller (Ctrl-C) or on a fatal error
        self._capture_done = threading.Event()
        self._cond = threading.Condition()
        self._capture_q: collections.deque = collections.deque()
        self._record_q: collections.deque = collections.deque()
        self._latency_ns: list[int] = []
        self._stage_s: dict[str, list[float]] = collections.defaultdict(list)
        self._depth_samples: dict[str, list[int]] = collections.defaultdict(list)
        self._latest = None  # (frame, refined pose) for the live view
        self._latest_lock = threading.Lock()
        self._first_arrival_ns = 0
        self._health_events: list[dict] = []
        self._tracks_lost = False
        self._bad_time_wall = 0.0  # when capture last refused a frame for its time stamp
        self._coverage = ViewCoverage(camera, partial_below=config.runtime.partial_view_below)
        self.degraded = False
        self._last_done_ns = 0
        self._mesh = None

    # --- stage bodies --------------------------------------------------------------------------------------------
    def _guard(self, name: str, body) -> None:
        try:
            body()
        except BaseException as exc:  # stored, reported by the main loop
            log.error("live stage '%s' failed: %s", name, exc, exc_info=True)
            self.errors[name] = f"{type(exc).__name__}: {exc}"
            if name in ESSENTIAL or self.on_stage_error == "stop":
                self.stop.set()
            else:
                self.disabled.add(name)
                self.counters.add(f"{name}_disabled")
        finally:
            if name == "capture":
                self._capture_done.set()
                with self._cond:
                    self._cond.notify_all()

    def _capture(self) -> None:
        last_seq = last_t = None
        while not self.stop.is_set():
            try:
                frame = self.grabber.read(timeout_s=0.5)
            except DeviceTimeoutError:
                self.counters.add("capture_timeouts")
                continue
            if frame is None:
                return
            # the latency starts at capture: the grabber's host-clock stamp where it has one (time spent
            # queued in the grabber counts), else now
            arrival = frame.host_ns if frame.host_ns is not None else time.monotonic_ns()
            self.counters.add("frames_in")
            if last_t is not None and frame.t_ns <= last_t:
                # a duplicated or backwards capture time would break pose interpolation and the map's order
                self.counters.add("bad_timestamps")
                self._bad_time_wall = time.monotonic()
                continue
            last_t = frame.t_ns
            if last_seq is not None and frame.seq > last_seq + 1:
                self.counters.add("dropped_source", frame.seq - last_seq - 1)  # gone before we could read them
            last_seq = frame.seq
            with self._cond:
                if len(self._capture_q) >= self.rt.capture_queue:
                    self._capture_q.popleft()
                    self.counters.add("dropped_capture")
                self._capture_q.append((frame, arrival))
                self._depth_samples["capture"].append(len(self._capture_q))
                if self.recorder is not None and "record" not in self.disabled:
                    if len(self._record_q) >= self.rt.record_queue:
                        self._record_q.popleft()
                        self.counters.add("dropped_record")
                    self._record_q.append(("frame", frame))
                self._cond.notify_all()

    def _tracking(self) -> None:
        if self.device and str(self.device).startswith("cuda"):
            import warp as wp

            with wp.ScopedDevice(self.device):
                self._tracking_loop()
        else:
            self._tracking_loop()

    def _tracking_loop(self) -> None:
        while True:  # (run() made the front-end before starting this thread)
            with self._cond:
                while not self._capture_q and not (self._capture_done.is_set() or self.stop.is_set()):
                    self._cond.wait(0.1)
                if not self._capture_q:
                    return
                frame, arrival = self._capture_q.popleft()
            t0 = time.perf_counter()
            samples = self.poses.poll()
            if self.recorder is not None and samples and "record" not in self.disabled:
                with self._cond:
                    self._record_q.append(("joints", samples))
                    self._cond.notify_all()
            if not self.poses.has_pose(frame.t_ns):
                self.counters.add("frames_without_pose")  # no pose brackets it (counted by cause there): not mapped
                continue
            prior = self.poses.prior_at(frame.t_ns)
            t1 = time.perf_counter()
            try:
                obs = self.frontend.process(frame)
            except Exception as exc:
                if self.on_stage_error == "degrade":
                    self.counters.add("tracking_errors")
                    log.warning("tracking failed on frame %d (%s); frame skipped", frame.seq, exc)
                    continue
                raise
            t2 = time.perf_counter()
            self._tracks_lost = len(obs) == 0
            self._coverage.update(obs.uv)
            self._stage_s["pose"].append(t1 - t0)
            self._stage_s["frontend"].append(t2 - t1)
            with self._latest_lock:
                self._latest = (frame, prior.T_world_camera)
            slot = self._free.popleft() if self._free else None
            if slot is None:
                self.counters.add("mapper_skipped")  # the mapper is a whole ring behind: this frame is not mapped
                continue
            self._ring.write(slot, obs, prior, arrival)
            self._ready_q.put(slot)
            self.counters.add("frames_tracked")

    def _results(self) -> None:
        while True:
            msg = self._done_q.get()
            if msg is None:
                return
            if msg[0] == "free":
                self._free.append(msg[1])
                continue
            if msg[0] == "ready":  # (the mapper's start-up word, when run() stopped waiting for it)
                continue
            _, seq, done_ns, arrival_ns, T_refined, is_kf, skipped_ba, skipped_resection = msg
            self._latency_ns.append(done_ns - arrival_ns)
            self._first_arrival_ns = min(self._first_arrival_ns or arrival_ns, arrival_ns)
            self._last_done_ns = done_ns
            self.counters.add("frames_processed")
            if is_kf:
                self.counters.add("keyframes")
            with self.counters.lock:
                self.counters.values["local_ba_skipped"] = skipped_ba
                self.counters.values["resection_skipped"] = skipped_resection
            with self._latest_lock:
                if self._latest is not None and self._latest[0].seq == seq:
                    self._latest = (self._latest[0], T_refined)
            if self.progress is not None:
                self.progress.update(1)

    def _surface(self) -> None:
        from ..surface.mesh import alpha_shape, thin_points
        from .live_view import LiveView

        view = LiveView(self.camera, self.out_dir, self.rt.view_period_s) if self.rt.view_period_s > 0 and \
            self.out_dir is not None else None
        version = -1
        next_mesh = next_view = time.monotonic()
        try:
            while not self.stop.wait(0.02) and not self._finished.is_set():
                now = time.monotonic()
                if now >= next_mesh:
                    next_mesh = now + self.rt.surface_period_s
                    v, pts, cols = self._snapshot.read()
                    if v != version and len(pts) >= 4:
                        t0 = time.perf_counter()
                        pts, cols = thin_points(pts, cols, self.rt.surface_max_points)
                        self._mesh = alpha_shape(pts, cols, self.config.surface.alpha_factor)
                        self._stage_s["surface"].append(time.perf_counter() - t0)
                        self.counters.add("surface_rebuilds")
                        version = v
                if view is not None and now >= next_view and self._mesh is not None:
                    next_view = now + self.rt.view_period_s
                    with self._latest_lock:
                        latest = self._latest
                    if latest is not None:
                        t0 = time.perf_counter()
                        view.render(self._mesh, latest[0], latest[1])
                        self._stage_s["view"].append(time.perf_counter() - t0)
                        self.counters.add("views")
        finally:
            if view is not None:
                view.close()

    def _health(self) -> None:
        """Every device's health, polled every 20 ms: each change of state is an event (time, device, state,
        detail) in the report, and the run's own state is degraded while any device is not OK or the
        front-end has lost every track (smoke, blood, a lens against tissue)."""
        from ..drivers.health import HealthState

        devices = {"grabber": self.grabber}
        robot = getattr(self.poses, "robot", None)
        if robot is not None:
            devices["robot"] = robot
        if hasattr(self.poses, "health"):
            devices["robot readings"] = self.poses  # what the pose source refuses (NaN, beyond limits, time)
        last: dict[str, HealthState] = {}
        t0 = time.monotonic()
        while not self._finished.wait(0.02):
            now = time.monotonic() - t0
            states = {}
            for name, dev in devices.items():
                h = dev.health
                states[name] = h
                if last.get(name) is not h.state:
                    self._health_events.append({"t_s": round(now, 3), "t_monotonic": time.monotonic(),
                                                "device": name, "state": h.state.value, "detail": h.detail})
                    if h.state is not HealthState.OK:
                        self.counters.add(f"health_{name.replace(' ', '_')}_{h.state.value}")
                    last[name] = h.state
            lost, partial = self._tracks_lost, self._coverage.partial
            tracking = "no tracks" if lost else "partial view" if partial else "tracking"
            if tracking != last.get("tracks"):
                detail = f"tracks cover {self._coverage.share:.0%} of the view" if partial else ""
                self._health_events.append({"t_s": round(now, 3), "t_monotonic": time.monotonic(), "device": "front-end",
                                            "state": tracking, "detail": detail})
                if lost:
                    self.counters.add("health_tracks_lost")
                elif partial:
                    self.counters.add("health_partial_view")
                last["tracks"] = tracking
            bad_times = time.monotonic() - self._bad_time_wall < 0.25
            if bad_times != last.get("frame times", False):
                n_bad = self.counters.values.get("bad_timestamps", 0)
                self._health_events.append({"t_s": round(now, 3), "t_monotonic": time.monotonic(), "device": "frame times",
                                            "state": "refused" if bad_times else "ok",
                                            "detail": f"{n_bad} frames refused: duplicated or backwards time stamp"
                                            if bad_times else ""})
                if bad_times:
                    self.counters.add("health_frame_times_refused")
                last["frame times"] = bad_times
            self.degraded = tracking != "tracking" or bad_times or \
                any(h.state is not HealthState.OK for h in states.values())

    def _record(self) -> None:
        while True:
            with self._cond:
                while not self._record_q and not self._finished.is_set():
                    self._cond.wait(0.1)
                if not self._record_q:
                    return
                kind, item = self._record_q.popleft()
            if kind == "frame":
                self.recorder.add_frame(item)
            else:
                self.recorder.add_joints(item)

    def _await_final_map(self, proc, ba_proc, recv, timeout_s: float = 3600.0):
        """The mapper's final map (or its error), watching that it and its BA worker stay alive: a mapper
        killed meanwhile (out of memory) is reported at once, not after the timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if recv.poll(0.5):
                return recv.recv()
            if not proc.is_alive() or (ba_proc is not None and not ba_proc.is_alive()):
                if recv.poll(0.5):
                    return recv.recv()
                dead, code = ("mapper", proc.exitcode) if not proc.is_alive() else ("local BA worker", ba_proc.exitcode)
                hint = " (killed: out of memory?)" if code == -9 else ""
                self.errors["mapper"] = f"the {dead} process died while the final map was made (exit code {code}){hint}"
                return None
        self.errors["mapper"] = f"no final map from the mapper after {timeout_s:.0f} s"
        return None

    def status(self) -> dict:
        """A consistent-enough view of the run while it goes (for samplers; cheap, any thread)."""
        c = self.counters.values
        snapshot = getattr(self, "_snapshot", None)
        return {"frames_in": c.get("frames_in", 0), "frames_processed": c.get("frames_processed", 0),
                "keyframes": c.get("keyframes", 0), "latency_ns": self._latency_ns,
                "mapper_pid": getattr(self, "mapper_pid", None), "degraded": self.degraded,
                "finishing": self.stop.is_set(),  # capture has stopped; the final map is being made
                "map_points": snapshot.size() if snapshot is not None else 0}

    # --- the main loop -----------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None) -> tuple[object, dict]:
        if self.frontend is None:
            # made (and, for the Warp one, compiled and captured) before capture starts, so the first
            # seconds of a live source are not lost to it
            self.frontend = self._make_frontend()
            if hasattr(self.frontend, "warm_up"):
                self.frontend.warm_up()
        ctx = mp.get_context("spawn")
        rt = self.rt
        self._ring = ObservationRing(rt.mapper_slots, rt.max_tracks)
        snap_lock = ctx.Lock()
        self._snapshot = MapSnapshot(rt.max_landmarks, snap_lock)
        self._free = collections.deque(range(rt.mapper_slots))
        self._ready_q, self._done_q = ctx.Queue(), ctx.Queue()
        recv, send = ctx.Pipe(duplex=False)
        self._finished = threading.Event()
        ba_proc = ba_jobs = None
        if rt.ba_worker == "on" or (rt.ba_worker == "auto" and (os.cpu_count() or 1) >= 4):
            ba_jobs, ba_results = ctx.Queue(), ctx.Queue()
            ba_proc = ctx.Process(target=ba_worker_main, name="lapreco local BA", daemon=True,
                                  args=(local_schedule(self.config.mapper), ba_jobs, ba_results))
            ba_proc.start()
        proc = ctx.Process(target=mapper_main, name="lapreco mapper", daemon=True,
                           args=(self._ring.name, rt.mapper_slots, rt.max_tracks, self._snapshot.name, rt.max_landmarks,
                                 snap_lock, self.camera.K, self.config.mapper, rt.mapper_backlog_skip_ba,
                                 self._ready_q, self._done_q, send, ba_jobs, ba_results if ba_jobs else None))
        proc.start()
        # Capture starts once the mapper process is up (spawned, its imports done): frames taken while it
        # started would wait in the ring for a second or two and set the latency tail of the whole run.
        self.interrupted = False
        deadline = time.monotonic() + MAPPER_START_TIMEOUT_S
        try:
            while time.monotonic() < deadline and proc.is_alive():
                try:
                    if self._done_q.get(timeout=0.5)[0] == "ready":
                        break
                except queue.Empty:
                    continue
        except KeyboardInterrupt:  # Ctrl-C while the mapper starts: end as from the main loop, cleanly
            self.interrupted = True
            self.stop.set()
        self.mapper_pid = proc.pid
        self.ba_worker_pid = ba_proc.pid if ba_proc is not None else None
        threads = {name: threading.Thread(target=self._guard, args=(name, body), name=f"live {name}", daemon=True)
                   for name, body in (("capture", self._capture), ("tracking", self._tracking),
                                      ("results", self._results), ("surface", self._surface),
                                      ("health", self._health))}
        if self.recorder is not None:
            threads["record"] = threading.Thread(target=self._guard, args=("record", self._record), daemon=True)
        t_start = time.perf_counter()
        for th in threads.values():
            th.start()
        final = None
        try:
            while True:
                time.sleep(0.05)
                with self._cond:
                    self._depth_samples["mapper"].append(rt.mapper_slots - len(self._free))
                if self.stop.is_set():
                    break
                if not proc.is_alive():
                    self.errors["mapper"] = f"the mapper process exited (code {proc.exitcode})"
                    if recv.poll(1.0):
                        final = recv.recv()  # its last word: the error that ended it (reported below)
                    break
                if ba_proc is not None and not ba_proc.is_alive():
                    self.errors["mapper"] = f"the local BA worker process exited (code {ba_proc.exitcode})"
                    break
                if seconds is not None and time.perf_counter() - t_start >= seconds:
                    break
                if not threads["tracking"].is_alive():
                    break  # the source ended and every kept frame was tracked
        except KeyboardInterrupt:
            self.interrupted = True  # Ctrl-C: stop capturing, map what was tracked, write everything
            log.warning("interrupted: finishing the map and writing the outputs")
        finally:
            self.stop.set()
            threads["capture"].join(timeout=5.0)
            threads["tracking"].join(timeout=30.0)
            if proc.is_alive():
                self._ready_q.put(None)
                final = self._await_final_map(proc, ba_proc, recv)
                proc.join(timeout=10.0)
            if proc.is_alive():
                proc.terminate()
            if ba_proc is not None:
                ba_jobs.put(None)
                ba_proc.join(timeout=10.0)
                if ba_proc.is_alive():
                    ba_proc.terminate()
            self._done_q.put(None)
            threads["results"].join(timeout=10.0)
            self._finished.set()
            with self._cond:
                self._cond.notify_all()
            for name in ("surface", "record", "health"):
                if name in threads:
                    threads[name].join(timeout=60.0)
            wall = time.perf_counter() - t_start
            drain(self._ready_q)
            self._ring.close()
            self._snapshot.close()
        fatal = {k: v for k, v in self.errors.items() if k in ESSENTIAL or self.on_stage_error == "stop"}
        if final is not None and final[0] == "error":
            fatal["mapper"] = final[1].strip().splitlines()[-1]
        if fatal:
            stage, msg = next(iter(fatal.items()))
            raise StageError(f"live run stopped: stage '{stage}' failed: {msg}")
        if final is None:
            raise StageError("live run stopped: the mapper process did not return its map")
        result = final[1]
        if self.counters.values.get("frames_without_pose") and hasattr(self.poses, "warn_without_pose"):
            self.poses.warn_without_pose()
        if not result.frames:
            raise ReconstructionError("the live run mapped no frames; check the grabber and the robot")
        return result, self._metrics(wall, result)

    def _metrics(self, wall: float, result) -> dict:
        c = dict(self.counters.values)
        lat_ms = np.array(self._latency_ns, float) * 1e-6
        pct = (lambda a: {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
                          "p99": float(np.percentile(a, 99)), "max": float(a.max())}) if len(lat_ms) else (lambda a: {})
        stage_ms = {k: {"mean": float(np.mean(v) * 1e3), "p95": float(np.percentile(v, 95) * 1e3)}
                    for k, v in self._stage_s.items() if v}
        processed = c.get("frames_processed", 0)
        frames_in = c.get("frames_in", 0)
        return {
            "wall_s": wall,
            "frames": {"in": frames_in, "processed": processed,
                       "dropped": frames_in - processed + c.get("dropped_source", 0) - c.get("bad_timestamps", 0)
                       - c.get("frames_without_pose", 0),
                       "without_pose": c.get("frames_without_pose", 0),
                       "without_pose_by_cause": (self.poses.without_pose.as_dict()
                                                 if hasattr(self.poses, "without_pose") else None),
                       "dropped_source": c.get("dropped_source", 0), "dropped_capture": c.get("dropped_capture", 0), "mapper_skipped": c.get("mapper_skipped", 0),
                       "tracking_errors": c.get("tracking_errors", 0), "dropped_record": c.get("dropped_record", 0),
                       "bad_timestamps": c.get("bad_timestamps", 0)},
            "robot_samples_rejected": getattr(self.poses, "rejected", 0),
            "robot_samples_rejected_by_cause": dict(getattr(self.poses, "rejected_by_cause", {})),
            # what the robot driver counted on its link (lost readings, reconnects, device faults)
            "robot_faults": dict(getattr(getattr(self.poses, "robot", None), "faults", {}) or {}),
            # frames mapped per second while the source delivered (the final global BA is not in it)
            "throughput_fps": processed / max((self._last_done_ns - self._first_arrival_ns) * 1e-9, 1e-9)
            if processed > 1 else 0.0,
            "latency_ms": {**pct(lat_ms), "note": "capture (the grabber's host-clock stamp, else frame in hand) -> refined pose available"},
            "stage_ms": stage_ms,
            "queue_depth": {k: {"mean": float(np.mean(v)), "max": int(np.max(v))}
                            for k, v in self._depth_samples.items() if v},
            "live": {"local_ba_skipped": c.get("local_ba_skipped", 0),
                     "resection_skipped": c.get("resection_skipped", 0), "surface_rebuilds": c.get("surface_rebuilds", 0),
                     "views": c.get("views", 0), "capture_timeouts": c.get("capture_timeouts", 0),
                     "stage_errors": dict(self.errors), "disabled_stages": sorted(self.disabled),
                     "interrupted": getattr(self, "interrupted", False),
                     "final_ba_s": result.stats.get("final_ba_wall_s"),
                     # the mapper process's own time, by kind of work (the usual bottleneck)
                     "mapper_stages_ms": result.stats.get("mapper_stages_ms", {}),
                     # unreachable objects the mapper's idle-time collections found (automatic GC is off there)
                     "mapper_garbage_collected": result.stats.get("garbage_collected")},
            "health": {"events": self._health_events[:200], "event_count": len(self._health_events),
                       "counts": {k[len("health_"):]: v for k, v in c.items() if k.startswith("health_")}},
        }
