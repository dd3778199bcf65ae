"""The reconstruction pipeline, one frame at a time: capture -> pose at time -> front-end -> mapper, then the
surface and the outputs at the end of the run.

This sequential runner is the simplest honest form of the data flow in DESIGN.md; stage times are measured
per frame so the live, pipelined runtime can be compared against it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import ReconstructionError
from lapreco_hil.frontend import make_frontend, partner_views
from lapreco_hil.mapping.mapper import Mapper, MapperSchedule, MapResult
from lapreco_hil.mapping.prediction import MotionPredictor

log = logging.getLogger(__name__)

# what to check when no frame has a pose, by the pose source's kind (its ``source``)
NO_POSE_HINTS = {
    "robot": "is the robot connected (a replay: joints.csv), and does its stream cover the video?",
    "camera poses": "do the camera poses' times (camera_poses.csv's t_ns, with time_offset_ns) cover the "
                    "frames' times?",
    "tracker": "is the scope's tool tracked, and do its marker poses' times (marker_poses.csv's t_ns, with "
               "time_offset_ns) cover the frames' times?",
}


@dataclass
class RunResult:
    map: MapResult
    frames_in: int
    frames_processed: int
    wall_s: float
    stage_s: dict[str, list[float]]
    latency_s: list[float]
    frames_without_pose: int = 0  # frames no pose brackets (pose_sources): skipped, not mapped
    without_pose_by_cause: dict | None = None  # geometry.NO_POSE_CAUSES -> frames
    dense: object | None = None  # the dense surface ([surface] mode = "dense"): a dense.surface.DenseResult
    surface_note: str | None = None  # why a dense run made the alpha shape instead


def run_sequence(grabber, poses, camera: CameraModel, config: PipelineConfig, tracker: str = "opencv",
                 progress=None, device: str | None = None, rig: Rig | None = None,
                 predict: bool = True, offset_watch=None) -> RunResult:
    """Every frame of ``grabber`` through the pipeline; ``poses`` is a pose source (lapreco_hil.pose_sources).
    ``rig``: the scope's cameras when it has more than one (``camera`` is its camera 0); ``predict``: start
    each track where the pose source's motion says it lands (pose-predicted tracking); ``offset_watch``: the
    time-offset watch (runtime/time_offset_watch.py), given each frame's tracks and that motion as the live
    tracking stage gives them (with prediction only: the motion is the prediction's)."""
    frontend = make_frontend(tracker, camera, config.tracker, device)
    mapper = Mapper(camera.K, config.mapper, schedule=MapperSchedule.offline(), rig=rig)
    predictor = MotionPredictor(mapper, config.mapper.scene_depth_m) if predict and config.tracker.predict else None
    # the dense surface keeps each keyframe's image as it comes, and is built once at the end with the final poses
    # (imported here: VTK and its kin load only for a run that makes a surface)
    from lapreco_hil.dense.surface import dense_surface_for

    dense, surface_note = dense_surface_for(camera, config, device or "cpu", rig)
    stages: dict[str, list[float]] = {k: [] for k in ("capture", "pose", "frontend", "mapper")}
    latency: list[float] = []
    frames_in = frames_without_pose = 0
    prev_obs = None  # the last mapped frame's tracks (the offset watch's)
    t_start = time.perf_counter()
    while True:
        t0 = time.perf_counter()
        frame = grabber.read()
        if frame is None:
            break
        t1 = time.perf_counter()
        frames_in += 1
        poses.poll()
        if not poses.has_pose(frame.t_ns):
            frames_without_pose += 1
            continue
        prior = poses.prior_at(frame.t_ns)
        t2 = time.perf_counter()
        motion = predictor.motion(prior.T_world_camera) if predictor is not None else None
        obs = frontend.process(frame, motion)
        t3 = time.perf_counter()
        n_keyframes = len(mapper.keyframes)
        if mapper.add(obs, prior, partners=partner_views(frontend, frame, mapper.rig)) and dense is not None:
            for kf in mapper.keyframes[n_keyframes:]:  # the new keyframe and its stereo partners
                dense.add_view(kf.id, frame.image_of(kf.camera), kf.T_world_camera, kf.camera, kf.reference)
        t4 = time.perf_counter()
        for name, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            stages[name].append(dt)
        latency.append(t4 - t1)  # frame in hand -> pose/points available
        if offset_watch is not None and motion is not None and prev_obs is not None:
            offset_watch.observe(prev_obs, obs, motion)  # (outside the stage times: no stage of the pipeline)
        prev_obs = obs
        if progress is not None:
            progress.update(1)
            progress.set_postfix(tracks=len(obs), keyframes=len(mapper.keyframes), points=len(mapper.landmarks),
                                 refresh=False)
    if frames_in == 0:
        raise ReconstructionError("the grabber delivered no frames; check the grabber URL")
    by_cause = getattr(poses, "without_pose", None)
    by_cause = by_cause.as_dict() if by_cause is not None else None
    if frames_without_pose:
        poses.warn_without_pose()
    if frames_without_pose == frames_in:
        hint = NO_POSE_HINTS.get(getattr(poses, "source", "robot"), NO_POSE_HINTS["robot"])
        raise ReconstructionError(f"none of the {frames_in} frames has a pose ({by_cause}): {hint}")
    t5 = time.perf_counter()
    result = mapper.finish()
    stages["final_ba"] = [time.perf_counter() - t5]
    dense_result = None
    if dense is not None:
        t6 = time.perf_counter()
        dense_result = dense.build(result)
        stages["dense"] = [time.perf_counter() - t6]
    processed = frames_in - frames_without_pose
    return RunResult(result, frames_in, processed, time.perf_counter() - t_start, stages, latency,
                     frames_without_pose, by_cause, dense_result, surface_note)
