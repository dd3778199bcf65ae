"""What the live runtime's processes say to each other: one small frozen (picklable) dataclass per kind of
message, so each side matches on a type and reads named fields instead of positions in a tuple.

main process -> mapper: ``SlotReady`` (a frame's observations wait in that shared-memory slot), ``EndOfFrames``
BA worker -> main process: ``BAWorkerReady``
mapper -> main process: ``MapperReady``, ``SlotFree``, ``FramePose``, ``NewTrackPoints``, ``KeyframePoses``; on its pipe
``FinalMap`` or
``MapperFailed``
mapper -> BA worker: ``BAJob``, ``EndOfJobs``; BA worker -> mapper: ``BAResult``"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SlotReady:
    slot: int


@dataclass(frozen=True)
class EndOfFrames:
    """No more frames: finish the map and send it."""


@dataclass(frozen=True)
class MapperReady:
    """The mapper's imports are done and its Mapper made: capture may start."""


@dataclass(frozen=True)
class BAWorkerReady:
    """The local-BA worker's kernels are loaded: its first window will not wait for a compile."""


@dataclass(frozen=True)
class SlotFree:
    slot: int


@dataclass(frozen=True)
class FramePose:
    """One frame mapped: its refined pose, when it was ready, and the mapper's skip counters so far."""

    seq: int
    done_ns: int
    arrival_ns: int
    T_world_camera: np.ndarray
    is_keyframe: bool
    local_ba_skipped: int
    resection_skipped: int
    keyframe_id: int = -1  # the frame's keyframe (its rig's reference camera's), -1: none


@dataclass(frozen=True)
class NewTrackPoints:
    """The world points of the newest frame's tracks that have one, sent when new points were made: the
    tracking stage predicts where each track lands in the next frame from them."""

    track_ids: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class KeyframePoses:
    """The newest reference keyframes' poses after a local BA moved them, with the depths each one's landmarks
    span (near, far in metres; NaN: too few): the live dense surface takes out and puts back the depth maps of
    those that moved, and bounds new ones' stereo search."""

    keyframe_ids: np.ndarray
    poses: np.ndarray
    depth_ranges: np.ndarray


@dataclass(frozen=True)
class FinalMap:
    result: object  # mapping.Reconstruction


@dataclass(frozen=True)
class MapperFailed:
    traceback: str

    @property
    def last_line(self) -> str:
        lines = self.traceback.strip().splitlines()
        return lines[-1] if lines else "unknown error"


@dataclass(frozen=True)
class BAJob:
    job_id: int
    problem: object  # mapping.bundle_adjustment.BAProblem


@dataclass(frozen=True)
class EndOfJobs:
    """The BA worker's stop word."""


@dataclass(frozen=True)
class BAResult:
    job_id: int
    solved: object  # the solution, or None when the solve raised
    error: str  # the traceback when it raised, else ""
    solve_s: float
    # when the worker took the job and when its answer was ready (time.monotonic_ns, one clock for every process
    # of the machine): the round trip's legs, measured by the mapper (0: not stamped)
    started_ns: int = 0
    done_ns: int = 0


@dataclass(frozen=True)
class EndOfResults:
    """The main process's word to its own results reader (after the mapper's last FramePose)."""
