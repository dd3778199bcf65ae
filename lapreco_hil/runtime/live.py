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
  rendered every ``view_period_s``; recording has its own queue (drops counted) so disk never stalls capture;
- the dense surface, when on, is made in a process of its own from the keyframes' images (runtime/dense_process.py),
  so its work takes neither tracking's Python lock nor its Warp stream and device lock.

Latency runs from a frame's capture (the grabber's host-clock stamp where it has one) to its refined pose.

The parts: the stages (runtime/stages.py), the supervisor that runs them and the mapper processes and owns the
shutdown (runtime/supervisor.py, runtime/processes.py), device and tracking health (runtime/health.py: each
change is a console line and a report event) and the figures (runtime/metrics.py). ``LiveRun`` puts them
together and turns the outcome into a result or a clear error."""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import ConfigError, LaprecoError, ReconstructionError
from lapreco_hil.frontend import make_frontend
from lapreco_hil.mapping.mapper import ba_solver
from lapreco_hil.mapping.prediction import TrackPoints
from lapreco_hil.runtime.coverage import ViewCoverage
from lapreco_hil.runtime.health import HealthMonitor
from lapreco_hil.runtime.messages import MapperFailed
from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.dense_process import DenseProcess, DenseProcessError, DenseSpec
from lapreco_hil.runtime.processes import MapperProcesses
from lapreco_hil.runtime.time_offset_watch import TimeOffsetWatch
from lapreco_hil.runtime.stages import (Capture, LatestView, RecentFrames, Record, Results, RigCheck,
                                        StageLinks, Surface, Tracking)
from lapreco_hil.runtime.supervisor import Supervisor

log = logging.getLogger(__name__)
FEW_FRAMES = 3  # a run that maps fewer frames than this says why
# frames the tracking stage keeps for the dense surface until the mapper names its keyframes (it answers within a
# few frames; at 1080p this is about 200 MB)
RECENT_FRAMES = 32
# page-locked frame buffers beyond those the capture queue and the recent frames can hold at once (the frame
# being tracked, one being staged)
PAGE_LOCKED_SPARE = 4


class StageError(LaprecoError):
    """A stage of the live runtime failed; the run was stopped cleanly."""


class LiveRun:
    def __init__(self, grabber, poses, camera: CameraModel, config: PipelineConfig, *, tracker: str, device: str,
                 out_dir: Path | None = None, recorder=None, on_stage_error: str = "stop", frontend=None,
                 progress=None, health_log_interval_s: float = 1.0) -> None:
        if on_stage_error not in ("stop", "degrade"):
            raise ValueError("on_stage_error must be 'stop' or 'degrade'")
        rt = config.runtime
        if rt.ba_worker not in ("auto", "on", "off"):
            raise ConfigError(f"[runtime] ba_worker = '{rt.ba_worker}': use auto, on or off")
        ba_solver(config.mapper)  # a bad [mapper] ba_solver is a ConfigError here, not in the mapper process
        self.grabber, self.poses, self.camera, self.config = grabber, poses, camera, config
        self.out_dir, self.recorder, self.on_stage_error, self.progress = out_dir, recorder, on_stage_error, progress
        self.device = device
        # a Warp front-end is built before capture starts, and used only by the tracking thread
        self._make_frontend = lambda: make_frontend(tracker, camera, config.tracker, device)
        self.metrics = LiveMetrics()
        self.links = StageLinks()
        self.stop = self.links.stop  # set by the caller (Ctrl-C) or on a fatal error
        self.latest = LatestView()
        use_worker = rt.ba_worker == "on" or (rt.ba_worker == "auto" and (os.cpu_count() or 1) >= 4)
        rig = getattr(grabber, "rig", None)  # the ring's slots hold each of the rig's cameras' observations of a frame
        stereo = rig if rig is not None and rig.is_stereo else None
        self._stereo = stereo is not None  # (the front-end's warm-up then captures a rig's frames too)
        # the dense surface ([surface] mode = "dense"): keyframe images kept until the mapper names them, fused in
        # a process of its own; None with the alpha shape (or, with a note, where multi-view stereo cannot run)
        self.dense, self.recent, self.dense_result, self.surface_note = None, None, None, None
        if camera is not None:
            from lapreco_hil.dense.surface import dense_functions_for

            functions, self.surface_note = dense_functions_for(config, live=True, device=device)
            if functions is not None:
                view = rt.view_period_s > 0 and out_dir is not None  # the live view is the mesh's one reader
                # the live stage's depth maps by [depth] live_method (the final build of an offline run: method)
                live_depth = dataclasses.replace(config.depth, method=config.depth.live_method)
                spec = DenseSpec(camera, dataclasses.replace(config, depth=live_depth), device, stereo, *functions,
                                 period_s=rt.surface_period_s if view else None, busy_share=rt.dense_busy_share)
                self.dense = DenseProcess(spec, self.links, self.metrics)
                self.recent = RecentFrames(RECENT_FRAMES)
        self.processes = MapperProcesses(camera.K if camera is not None else None, config, use_ba_worker=use_worker,
                                         cameras=len(rig) if rig is not None else 1, rig=stereo,
                                         keyframe_poses=self.dense is not None)
        self.supervisor = Supervisor(self.processes, self.links, self.metrics, on_stage_error=on_stage_error)
        recording = recorder is not None
        page_locked = None
        if tracker == "warp" and str(device).startswith("cuda") and camera is not None:
            from lapreco_hil.frontend.warp.page_locked import PageLockedFrames

            held = rt.capture_queue + (RECENT_FRAMES if self.recent is not None else 0) + PAGE_LOCKED_SPARE
            page_locked = PageLockedFrames((camera.height, camera.width, 3), held, device)
        self.capture = Capture(grabber, self.links, self.metrics, capture_queue=rt.capture_queue,
                               record_queue=rt.record_queue, recording=recording, page_locked=page_locked)
        coverage = ViewCoverage(camera, partial_below=rt.partial_view_below) if camera is not None else None
        self.offset_watch = (TimeOffsetWatch(camera.K, poses.time_offset_ns)
                             if camera is not None and hasattr(poses, "time_offset_ns") else None)
        self.track_points = TrackPoints()  # the mapper's newest track points, for pose-predicted tracking
        self.tracking = Tracking(poses, self.links, self.metrics, self.latest, coverage, self.processes.submit,
                                 device=device, degrade=on_stage_error == "degrade", recording=recording,
                                 track_points=self.track_points if config.tracker.predict else None,
                                 scene_depth_m=config.mapper.scene_depth_m,
                                 offset_watch=self.offset_watch, rig=stereo, recent=self.recent)
        self.tracking.frontend = frontend
        source = getattr(getattr(grabber, "url", None), "raw", None) or "grabber"
        self.rig_check = RigCheck(stereo, self.latest, self.links, source) if stereo is not None else None
        self.health = HealthMonitor(log_interval_s=health_log_interval_s)
        self.health.add("grabber", lambda: grabber.health)
        robot = poses.robot  # (a pose source given camera poses has no robot)
        if robot is not None:
            self.health.add("robot", lambda: robot.health)
        if hasattr(poses, "health"):
            # what the pose source refuses ("robot readings", "tracker readings")
            self.health.add(f"{getattr(poses, 'source', 'robot')} readings", lambda: poses.health)
        self.health.add("front-end", self.tracking.front_end_health)
        self.health.add("frame times", self.capture.frame_times_health)
        if self.offset_watch is not None:
            self.health.add("time offset", self.offset_watch.health)

    # --- read while the run goes (any thread) ------------------------------------------------------------------
    @property
    def mapper_pid(self) -> int | None:
        return self.processes.mapper_pid

    @property
    def degraded(self) -> bool:
        """Any device not OK, tracks lost or partial, or frame times refused, as last polled."""
        return self.health.degraded

    @property
    def interrupted(self) -> bool:
        return self.supervisor.interrupted

    @property
    def errors(self) -> dict[str, str]:
        return self.supervisor.errors

    def status(self) -> dict:
        """A consistent-enough view of the run while it goes (for samplers; cheap, any thread)."""
        snapshot = self.processes.snapshot
        return {"frames_in": self.metrics.get("frames_in"), "frames_processed": self.metrics.get("frames_processed"),
                "keyframes": self.metrics.get("keyframes"), "latency_ns": self.metrics.latency_ns,
                "mapper_pid": self.mapper_pid, "degraded": self.degraded,
                "finishing": self.stop.is_set(),  # capture has stopped; the final map is being made
                "map_points": snapshot.size() if snapshot is not None else 0}

    # --- the run -----------------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None) -> tuple[object, dict]:
        if self.tracking.frontend is None:
            # made (and, for the Warp one, compiled and captured) before capture starts, so the first
            # seconds of a live source are not lost to it
            self.tracking.frontend = self._make_frontend()
            if hasattr(self.tracking.frontend, "warm_up"):
                self.tracking.frontend.warm_up(rig=self._stereo)
        self.metrics.gc.start()
        try:
            return self._run(seconds)
        finally:
            self.metrics.gc.stop()
            if self.dense is not None:
                self.dense.close()

    def _run(self, seconds: float | None) -> tuple[object, dict]:
        if self.dense is not None:
            self.dense.start()  # (its imports and kernels load while the mapper starts)
        sup = self.supervisor
        sup.start_processes()
        if self.dense is not None and not self.interrupted:
            try:
                self.dense.wait_ready()  # (one that died is reported by its stage's thread, as any stage error)
            except KeyboardInterrupt:  # Ctrl-C meanwhile: end as from the main loop, cleanly
                sup.interrupted = True
                self.links.stop.set()
        stages = {"capture": self.capture.run, "tracking": self.tracking.run,
                  "results": Results(self.processes.done_q, self.processes.slot_freed, self.metrics, self.latest,
                                     self.progress, track_points=self.track_points, dense=self.dense,
                                     recent=self.recent).run,
                  "surface": Surface(self.processes.snapshot, self.camera, self.config, self.out_dir, self.links,
                                     self.metrics, self.latest, dense=self.dense).run,
                  "health": lambda: self.health.run_until(self.links.finished)}
        if self.recorder is not None:
            stages["record"] = Record(self.recorder, self.links).run
        if self.dense is not None:
            stages["dense"] = self.dense.run
        if self.rig_check is not None:
            stages["rig check"] = self.rig_check.run
        sup.run(stages, seconds)
        fatal = sup.fatal_errors()
        mapper_raised = set(fatal) == {"mapper"} and isinstance(sup.final, MapperFailed)
        if (not fatal or mapper_raised) and self.metrics.get("frames_processed") == 0 \
                and self.metrics.get("frames_without_pose") > 0:
            # the cause of a mapper that failed on nothing to map is upstream: say that one
            raise ReconstructionError(f"the live run mapped no frames: {self.why_few_frames()}")
        if isinstance(sup.final, MapperFailed):
            fatal["mapper"] = sup.final.last_line
        if fatal:
            stage, msg = next(iter(fatal.items()))
            raise StageError(f"live run stopped: stage '{stage}' failed: {msg}")
        if sup.final is None:
            raise StageError("live run stopped: the mapper process did not return its map")
        result = sup.final.result
        if self.metrics.get("frames_without_pose"):
            self.poses.warn_without_pose()
        if not result.frames:
            raise ReconstructionError(f"the live run mapped no frames: {self.why_few_frames()}")
        if self.dense is not None and "dense" not in self.links.disabled:
            try:
                self.dense_result = self.dense.finish(result)  # every kept keyframe at its final pose
            except DenseProcessError as exc:
                sup.errors["dense"] = str(exc)
                if self.on_stage_error == "stop":
                    raise StageError(f"live run stopped: stage 'dense' failed: {exc}") from None
                log.error("%s; the alpha shape instead", exc)
                self.links.disabled.add("dense")
                self.metrics.add("dense_disabled")
        metrics = self.report(result)
        if self.rig_check is not None:
            metrics["rig_check"] = self.rig_check.fits or []
        if len(result.frames) < FEW_FRAMES:
            log.warning("the live run mapped only %d frames: %s", len(result.frames), self.why_few_frames())
            metrics["live"]["few_frames_why"] = self.why_few_frames()
        return result, metrics

    def why_few_frames(self) -> str:
        """Where the frames went: none in, without a pose (and why the robot's readings were refused), dropped,
        or tracked but not mapped; with the next step."""
        m, poses = self.metrics, self.poses
        frames_in, without_pose = m.get("frames_in"), m.get("frames_without_pose")
        rejected = poses.rejected
        source = getattr(poses, "source", "robot")
        if frames_in == 0:
            return (f"no frame came from the grabber ({m.get('capture_timeouts')} read timeouts); check the grabber "
                    "URL and cable, or run 'lapreco devices --probe URL'")
        parts = [f"{frames_in} frames in, {without_pose} without a pose"]
        if without_pose and rejected:
            causes = ", ".join(f"{n} {cause}" for cause, n in sorted(poses.rejected_by_cause.items(),
                                                                     key=lambda kv: -kv[1]))
            last = poses.last_refusal
            parts.append(f"the {source} delivered {rejected} readings that were refused ({causes})"
                         + (f"; last refused: {last}" if last else ""))
            parts.append("check the robot model and its joint limits against the robot: "
                         "'lapreco devices --probe URL' shows what it reads" if source == "robot" else
                         f"check the {source}: 'lapreco devices --probe URL' shows what it reads")
        elif without_pose and (refused_by_driver := self._refused_by_driver()):
            n, last = refused_by_driver
            faults = getattr(getattr(self.poses, "robot", None), "faults", {}) or {}
            if int(faults.get("refused_encoder_error", 0)):  # the device flags its encoder: a hardware fault
                parts.append(f"the robot's driver refused {n} readings ({int(faults['refused_encoder_error'])} "
                             f"because a servo flags an encoder error: its positions are not trustworthy)"
                             + (f"; last refused: {last}" if last else ""))
                parts.append("a hardware fault, not the joint map: check the servo named (its Hardware Error "
                             "Status, address 70; its encoder, cable and power), then power-cycle or reboot it; "
                             "'lapreco devices --probe URL' shows why each reading was refused")
            else:
                parts.append(f"the robot's driver refused {n} readings (out of the model's joint limits, or "
                             f"flagged by the device)" + (f"; last refused: {last}" if last else ""))
                parts.append("check the robot model, its joint map and units against the robot: "
                             "'lapreco devices --probe URL' shows what it reads")
        elif without_pose:
            parts.append(f"the {source} delivered no reading; check its URL and link, or run "
                         "'lapreco devices --probe URL'")
        else:
            if m.get("passed_before_start"):
                parts.append(f"{m.get('passed_before_start')} frames passed before capture started (the source "
                             "made them while the run was starting)")
            parts.append(f"{m.get('dropped_capture')} dropped at capture, {m.get('bad_timestamps')} with bad time "
                         f"stamps, {m.get('tracking_errors')} tracking errors, {m.get('mapper_skipped')} not handed "
                         "to the mapper")
        return "; ".join(parts)

    def _refused_by_driver(self) -> tuple[int, str] | None:
        """(readings the robot's driver received and refused, its last fault), when it refused any: they never
        reach the pose source, whose own count of refusals is then 0."""
        from lapreco_hil.sessions.recorder import REFUSED_READING_FAULTS

        robot = getattr(self.poses, "robot", None)
        faults = dict(getattr(robot, "faults", {}) or {})
        n = sum(int(faults.get(k, 0)) for k in REFUSED_READING_FAULTS)
        return (n, getattr(robot, "last_fault", "") or "") if n else None

    def report(self, result) -> dict:
        sup = self.supervisor
        events = self.health.event_dicts()
        return self.metrics.report(wall_s=sup.wall_s, result=result, poses=self.poses, errors=sup.errors,
                                   disabled=self.links.disabled, interrupted=sup.interrupted, health_events=events,
                                   health_event_count=self.health.event_count, health_counts=self.health.counts,
                                   time_offset=self.offset_watch.summary() if self.offset_watch is not None else None)
