"""Simulated robot and grabber: the RobotDriver and Grabber interfaces over one SimWorld.

``sim://<scene>?width=640&height=480&fps=25&seed=0&device=cpu&frames=150&pace=afap|realtime``
A robot and a grabber with the same scene name, opened in the same DeviceContext, share one world.
"""

from __future__ import annotations

import time
from dataclasses import replace


from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.errors import ConfigError
from lapreco_hil.registry import DeviceContext, DeviceURL
from lapreco_hil.evaluation.truth import GroundTruth
from lapreco_hil.types import Frame, JointSample, RobotDescription

from .world import SimSettings, SimWorld
from .world.world import T0_NS

_WORLD_KEYS = {"width": int, "height": int, "fps": float, "seed": int, "device": str, "rate": float}


def _world_for(url: DeviceURL, context: DeviceContext) -> SimWorld:
    params = {k: url.get(k, cast=c) for k, c in _WORLD_KEYS.items() if k in url.query}

    def make() -> SimWorld:
        settings = SimSettings(scene=url.name)
        fields = {"rate": "robot_rate_hz"}
        settings = replace(settings, **{fields.get(k, k): v for k, v in params.items()})
        if settings.device is None and context.options.get("device"):
            settings = replace(settings, device=context.options["device"])
        return SimWorld(settings)

    world = context.shared("sim", url.name, make)
    for k, v in params.items():
        have = getattr(world.settings, {"rate": "robot_rate_hz"}.get(k, k))
        if have != v:
            raise ConfigError(f"device URL '{url.raw}': {k}={v} conflicts with the simulated world "
                              f"'{url.name}' already opened with {k}={have}; give both devices the same parameters")
    return world


class SimRobot(RobotDriver):
    """Encoder readings of the simulated holder, at ``rate`` Hz of simulated time."""

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        self.url = url
        self.world = _world_for(url, context)
        self.info = self.world.kinematics.info
        self._next_seq = 0
        self._open = False

    @property
    def description(self) -> RobotDescription:
        """What a real robot's configuration file would say."""
        return RobotDescription(self.world.robot_model, self.world.tip_frame, self.world.T_tip_camera)

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def sample_time_ns(self, seq: int) -> int:
        return T0_NS + int(round(seq * 1e9 / self.world.settings.robot_rate_hz))

    def read(self, timeout_s: float | None = None) -> list[JointSample]:
        now = self.world.now_ns()
        out = []
        while self.sample_time_ns(self._next_seq) <= now:
            seq = self._next_seq
            t_ns = self.sample_time_ns(seq)
            out.append(JointSample(self.world.arm.reported_joints(self.world.seconds(t_ns), seq), t_ns, seq))
            self._next_seq += 1
        return out

    @property
    def health(self) -> Health:
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=self.world.now_ns())


class SimGrabber(Grabber):
    """Renders what the true camera sees at the robot's true pose; as fast as possible or paced to fps."""

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        self.url = url
        self.world = _world_for(url, context)
        self.max_frames = url.get("frames", None, int)
        pace = url.get("pace", "afap")
        if pace not in ("afap", "realtime"):
            raise ConfigError(f"device URL '{url.raw}': pace must be 'afap' or 'realtime', got '{pace}'")
        self.realtime = pace == "realtime"
        self._seq = 0
        self._open = False
        self._wall0 = 0.0

    @property
    def camera(self):
        return self.world.camera

    @property
    def nominal_fps(self) -> float:
        return self.world.settings.fps

    def open(self) -> None:
        self._open = True
        self._wall0 = time.monotonic()

    def close(self) -> None:
        self._open = False

    def frame_time_ns(self, seq: int) -> int:
        return T0_NS + int(round(seq * 1e9 / self.world.settings.fps))

    def read(self, timeout_s: float | None = None) -> Frame | None:
        if self.max_frames is not None and self._seq >= self.max_frames:
            return None
        seq = self._seq
        t_ns = self.frame_time_ns(seq)
        if self.realtime:
            delay = self._wall0 + (t_ns - T0_NS) * 1e-9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        image, _ = self.world.render(t_ns, seq)
        self.world.advance_to(t_ns + int(self.world.settings.delivery_latency_s * 1e9))
        self._seq += 1
        return Frame(image=image, t_ns=t_ns, seq=seq)

    @property
    def health(self) -> Health:
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=self.world.now_ns())

    @property
    def ground_truth(self) -> GroundTruth:
        return GroundTruth(self.world.surface_mesh(), self.world.true_camera_pose)
