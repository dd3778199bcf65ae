"""Recording: frames and joint readings from live (or simulated) devices into a session, as they arrive."""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass

from ..camera import CameraModel
from ..errors import ConfigError
from ..robot_models import urdf_path
from ..types import RobotDescription
from .format import SessionMeta
from .writer import SessionWriter

log = logging.getLogger(__name__)


@dataclass
class RecordStats:
    frames: int
    joint_samples: int
    skipped_joint_samples: int
    capture_span_s: float
    wall_s: float
    stopped_by: str

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0

    def as_dict(self) -> dict:
        return {**self.__dict__, "frames_per_s": self.frames_per_s}


def record(grabber, robot, out: str, *, seconds: float | None = None, max_frames: int | None = None,
           camera: CameraModel | None = None, description: RobotDescription | None = None,
           source: dict | None = None, progress: bool = True, with_truth: bool = True) -> RecordStats:
    """Record until the grabber ends, ``seconds`` of capture time have passed, ``max_frames`` were written,
    or Ctrl-C; the session is closed (complete) in every case. ``camera``/``description`` override what the
    devices know (a real grabber does not know its lens: pass the calibration)."""
    from tqdm import tqdm

    camera = camera or grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    description = description or robot.description
    if description is None:
        raise ConfigError(f"robot '{robot.url.raw}' has no robot model/hand-eye; pass --robot-model and "
                          f"--hand-eye handeye.yaml")
    truth = grabber.ground_truth if with_truth else None
    meta = session_meta_for(grabber, robot, camera, description, source)
    stats = RecordStats(0, 0, 0, 0.0, 0.0, "end of source")
    bar = tqdm(total=max_frames, desc=f"record {out}", unit="frame", file=sys.stderr, disable=not progress)
    wall0 = time.perf_counter()
    with SessionWriter(out, meta, urdf_path(description.urdf)) as writer, bar:
        if truth is not None and truth.surface is not None:
            writer.set_truth_surface(truth.surface)
        first_t = None
        try:
            while True:
                frame = grabber.read(timeout_s=1.0)
                if frame is None:
                    break
                stats.skipped_joint_samples += writer.add_joints(robot.read(timeout_s=0.0))
                writer.add_frame(frame)
                if truth is not None and truth.camera_pose is not None:
                    writer.add_true_pose(frame.t_ns, truth.camera_pose(frame.t_ns))
                first_t = frame.t_ns if first_t is None else first_t
                stats.capture_span_s = (frame.t_ns - first_t) * 1e-9
                bar.update(1)
                if max_frames is not None and writer.n_queued >= max_frames:
                    stats.stopped_by = "frame count"
                    break
                if seconds is not None and stats.capture_span_s >= seconds:
                    stats.stopped_by = "duration"
                    break
        except KeyboardInterrupt:
            stats.stopped_by = "interrupted"
    stats.frames, stats.joint_samples = writer.n_frames, writer.n_joints  # after close: every frame on disk
    stats.wall_s = time.perf_counter() - wall0
    if stats.skipped_joint_samples:
        log.warning("%d joint samples were not recorded (non-finite, wrong size or not newer than the last)",
                    stats.skipped_joint_samples)
    return stats


def session_meta_for(grabber, robot, camera: CameraModel, description: RobotDescription,
                     source: dict | None = None) -> SessionMeta:
    return SessionMeta(camera=camera, pose_source="joints", robot=description,
                       joint_names=tuple(robot.info.joint_names),
                       joint_units=_joint_units(description, len(robot.info.joint_names)),
                       nominal_fps=getattr(grabber, "nominal_fps", None), source=source or {})


def _joint_units(description: RobotDescription, n: int) -> tuple[str, ...]:
    """'length' for prismatic joints, 'angle' for the others, read from the URDF."""
    import pinocchio as pin

    from ..kinematics import prismatic_joints

    model = pin.buildModelFromUrdf(str(urdf_path(description.urdf)))
    units = tuple("length" if p else "angle" for p in prismatic_joints(model))
    if len(units) != n:
        raise ConfigError(f"robot model '{description.urdf}' has {len(units)} joints, the robot reports {n}")
    return units
