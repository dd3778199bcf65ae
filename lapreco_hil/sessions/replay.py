"""Sessions as devices: ``replay://<session folder>?pace=afap|realtime[&queue=N]`` for a grabber and a robot.

The grabber reports the session's rig and delivers every camera's image of a frame (``Frame.views``).

A real-time replay plays the frames at their recorded rate and, like a frame grabber, holds at most ``queue``
of them (default 4, as the V4L2 driver's): a reader more than that many frames behind loses the oldest,
and the sequence numbers show the gap. ``pace=afap`` hands every frame on as fast as it is read.

A grabber and a robot opened on the same session in one DeviceContext share one reader and one replay
clock: each frame handed on releases the joint samples captured up to one frame period after it (what a
live run would have had in hand), so replays are deterministic.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.errors import ConfigError, SessionError
from lapreco_hil.kinematics import CameraKinematics
from lapreco_hil.registry import RECORDED, DeviceContext, DeviceURL, URLConfig, url_param
from lapreco_hil.robot_models import urdf_path
from lapreco_hil.types import Frame, JointLimits, JointSample, RobotInfo
from lapreco_hil.sessions.session import Session


@dataclass(frozen=True)
class ReplayGrabberConfig(URLConfig):
    pace: str = url_param("afap", choices=("afap", "realtime"), help="as fast as possible, or the recorded rate")
    queue: int = url_param(4, low=1, unit="frame", help="frames held for a slow reader (realtime)")


@dataclass(frozen=True)
class ReplayRobotConfig(URLConfig):
    # the robot follows the grabber's pace; it takes the grabber's parameters so one URL opens both
    pace: str = url_param("afap", choices=("afap", "realtime"))
    queue: int = url_param(4, low=1, unit="frame")


class _ReplayClock:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.now_ns = -(2**62)

    def advance_to(self, t_ns: int) -> None:
        with self._lock:
            self.now_ns = max(self.now_ns, t_ns)


def _shared(url: DeviceURL, context: DeviceContext) -> tuple[Session, _ReplayClock]:
    if not url.name:
        raise ConfigError(f"device URL '{url.raw}': give the session folder, e.g. replay://recordings/run1")
    session = context.shared("replay", url.name, lambda: Session(url.name))
    clock = context.shared("replay-clock", url.name, _ReplayClock)
    return session, clock


# frames decoded ahead of the reader, in parallel (OpenCV's decoders release the GIL): decoding one 1080p PNG
# takes longer than a 60 fps frame period (docs/benchmarks.md), so a real-time replay needs several at once
READ_AHEAD = 8


class ReplayGrabber(Grabber):
    clock_domain = RECORDED

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        config = ReplayGrabberConfig.from_url(url)
        self.url = url
        self.session, self.clock = _shared(url, context)
        self.realtime = config.pace == "realtime"
        self.queue_len = config.queue
        self._i = 0
        self._open = False
        self._wall0: float | None = None
        self._ahead: dict[int, Future] = {}  # frame index -> its decoding
        self._pool: ThreadPoolExecutor | None = None

    @property
    def camera(self):
        return self.session.meta.camera

    @property
    def rig(self):
        """The session's cameras: a version-2 session's frames carry the other cameras' images in ``views``."""
        return self.session.meta.rig

    @property
    def ground_truth(self):
        return self.session.ground_truth()

    def __len__(self) -> int:
        return len(self.session)

    def open(self) -> None:
        self._open = True
        workers = max(1, min(READ_AHEAD, (os.cpu_count() or 2) // 2))
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="replay-decode")
        self._wall0 = None  # a real-time replay starts playing at the first read, not at open

    def close(self) -> None:
        self._open = False
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._ahead.clear()

    def _frame(self, i: int) -> Frame:
        """Frame i, decoded ahead together with the next few (in order: a skipped frame's decoding is dropped)."""
        if self._pool is None:
            return self.session.frame(i)
        for j in [j for j in self._ahead if j < i]:
            self._ahead.pop(j).cancel()
        for j in range(i, min(i + READ_AHEAD, len(self.session))):
            if j not in self._ahead:
                self._ahead[j] = self._pool.submit(self.session.frame, j)
        return self._ahead.pop(i).result()

    def read(self, timeout_s: float | None = None) -> Frame | None:
        if self._wall0 is None:
            self._wall0 = time.monotonic()
        if self.realtime:
            # like a grabber, a real-time replay does not wait for its reader: it holds the last ``queue``
            # frames; older ones are gone (skipped), and the sequence numbers show the gap
            t0 = int(self.session.frame_t_ns[0])
            late_ns = int((time.monotonic() - self._wall0) * 1e9) - self.queue_len * self.session.frame_period_ns
            while self._i < len(self.session) and self.session.frame_t_ns[self._i] - t0 < late_ns:
                self._i += 1
        if self._i >= len(self.session):
            return None
        frame = self._frame(self._i)
        if self.realtime:
            due_ns = int(self._wall0 * 1e9) + frame.t_ns - int(self.session.frame_t_ns[0])
            delay = due_ns * 1e-9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            frame = dataclasses.replace(frame, host_ns=due_ns)  # captured then, on this host's clock
        self.clock.advance_to(frame.t_ns + self.session.meta.time_offset_ns + self.session.frame_period_ns)
        self._i += 1
        return frame

    @property
    def health(self) -> Health:
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED)


class ReplayRobot(RobotDriver):
    clock_domain = RECORDED

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        ReplayRobotConfig.from_url(url)
        self.url = url
        self.session, self.clock = _shared(url, context)
        if self.session.meta.pose_source != "joints":
            raise SessionError(f"session '{url.name}' carries {self.session.meta.pose_source.replace('_', ' ')}, not "
                               f"joint readings; replay it with 'lapreco replay {url.name}'")
        self.description = self.session.robot
        meta = self.session.meta
        # (only joint count and limits are read here; a calibration session has no hand-eye)
        kin = CameraKinematics(str(urdf_path(self.description.urdf)), self.description.tip_frame,
                               np.eye(4) if self.description.T_tip_camera is None else self.description.T_tip_camera)
        if kin.n_joints != len(meta.joint_names):
            raise SessionError(f"session '{url.name}': joints.csv has {len(meta.joint_names)} joints, the robot "
                               f"model {kin.n_joints}")
        self.info = RobotInfo(kin.info.name, meta.joint_names, JointLimits(kin.info.limits.lower,
                                                                           kin.info.limits.upper))
        self._i = 0
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def _read(self, timeout_s: float | None) -> list[JointSample]:
        samples = self.session.joint_samples
        now = self.clock.now_ns
        start = self._i
        while self._i < len(samples) and samples[self._i].t_ns <= now:
            self._i += 1
        return samples[start:self._i]

    @property
    def health(self) -> Health:
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED)
