"""Simulated robot and grabber: the RobotDriver and Grabber interfaces over one SimWorld.

``sim://<scene>?width=640&height=480&fps=25&seed=0&device=cpu&frames=150&pace=afap|realtime&speed=0.2``
A robot and a grabber with the same scene name, opened in the same DeviceContext, share one world.

``link=serial|canopen`` on the robot puts the real driver in between: the simulated arm's encoder-side
joints drive a device emulator (a Dynamixel chain on a pseudo-terminal, CiA 402 nodes on a python-can
virtual bus) and the robot's samples are what the real driver reads from it. Polling needs time to pass
between frames, so a linked world's clock flows (``speed``, default 0.2 x real time).
"""

from __future__ import annotations

import time
from dataclasses import replace


from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.errors import ConfigError
from lapreco_hil.registry import DeviceContext, DeviceURL
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.types import Frame, JointSample, RobotDescription

from .world import SimSettings, SimWorld
from .world.world import T0_NS

_WORLD_KEYS = {"width": int, "height": int, "fps": float, "seed": int, "device": str, "rate": float,
               "speed": float, "instrument": lambda v: v.lower() in ("1", "true", "yes")}
_FIELDS = {"rate": "robot_rate_hz", "speed": "clock_speed"}
LINKS = ("direct", "serial", "canopen")


def _world_for(url: DeviceURL, context: DeviceContext) -> SimWorld:
    params = {k: url.get(k, cast=c) for k, c in _WORLD_KEYS.items() if k in url.query}

    def make() -> SimWorld:
        settings = SimSettings(scene=url.name)
        settings = replace(settings, **{_FIELDS.get(k, k): v for k, v in params.items()})
        if settings.device is None and context.options.get("device"):
            settings = replace(settings, device=context.options["device"])
        return SimWorld(settings)

    world = context.shared("sim", url.name, make)
    for k, v in params.items():
        have = getattr(world.settings, _FIELDS.get(k, k))
        if have != v:
            raise ConfigError(f"device URL '{url.raw}': {k}={v} conflicts with the simulated world "
                              f"'{url.name}' already opened with {k}={have}; give both devices the same parameters")
    return world


class SimRobot(RobotDriver):
    """Encoder readings of the simulated holder, at ``rate`` Hz of simulated time (``link=direct``), or
    what a real driver reads from a device emulator (``link=serial|canopen``)."""

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        self.url = url
        self.link = url.get("link", "direct")
        if self.link not in LINKS:
            raise ConfigError(f"device URL '{url.raw}': link must be one of {', '.join(LINKS)}, got '{self.link}'")
        if self.link != "direct" and "speed" not in url.query:
            url = replace(url, query={**url.query, "speed": "0.2"})
        self.world = _world_for(url, context)
        if self.link != "direct" and self.world.settings.clock_speed is None:
            raise ConfigError(f"device URL '{url.raw}': link={self.link} needs a flowing clock; open the grabber "
                              f"of '{url.name}' with the same speed=... (e.g. speed=0.2)")
        self.info = self.world.kinematics.info
        # a kinematics clock that is off: readings of time t are stamped t + offset (public surgical datasets
        # have offsets up to seconds; calibrate time-offset recovers it)
        self.stamp_offset_ns = int(round(url.get("offset_ms", 0.0, float) * 1e6))
        self._context = context
        self._next_seq = 0
        self._open = False
        self.emulator = None
        self.driver: RobotDriver | None = None

    def _open_link(self) -> None:
        from lapreco_hil.drivers.robot.joint_map import JointMap
        from lapreco_hil.registry import open_robot

        world = self.world
        ids = list(range(1, len(self.info.joint_names) + 1))
        # the robot's own rate in simulated time, as wall-clock polling on the flowing clock
        rate = world.settings.robot_rate_hz * world.settings.clock_speed

        def joints_at(t_ns: int):
            return world.arm.motor_joints(world.seconds(t_ns))

        context = DeviceContext(**{**self._context.options, "clock_ns": world.now_ns})
        if self.link == "serial":
            from .dynamixel_emulator import DynamixelChainEmulator

            joint_map = JointMap.for_model(world.robot_model)
            self.emulator = DynamixelChainEmulator(ids, joint_map, joints_at, world.now_ns)
            url = f"serial://{self.emulator.port}?baud=1000000&ids={','.join(map(str, ids))}&rate={rate}"
        else:
            from .canopen_emulator import CANopenDriveChainEmulator

            joint_map = JointMap.for_model(world.robot_model, counts_per_rev=4 * 4096)
            channel = f"lapreco-sim-{id(self)}"
            self.emulator = CANopenDriveChainEmulator(channel, ids, joint_map, joints_at, world.now_ns)
            url = f"canopen://virtual/{channel}?nodes=1-{len(ids)}&rate={rate}"
        self.driver = open_robot(url + f"&model={world.robot_model}", context)
        try:
            self.driver.open()
        except BaseException:
            self.emulator.close()
            raise

    @property
    def description(self) -> RobotDescription:
        """What a real robot's configuration file would say."""
        return RobotDescription(self.world.robot_model, self.world.tip_frame, self.world.T_tip_camera)

    def open(self) -> None:
        if self.link != "direct" and self.driver is None:
            self._open_link()
        self._open = True

    def close(self) -> None:
        self._open = False
        if self.driver is not None:
            self.driver.close()
            self.emulator.close()
            self.driver = self.emulator = None

    def sample_time_ns(self, seq: int) -> int:
        return T0_NS + int(round(seq * 1e9 / self.world.settings.robot_rate_hz))

    def read(self, timeout_s: float | None = None) -> list[JointSample]:
        if self.driver is not None:
            return [JointSample(s.q, s.t_ns + self.stamp_offset_ns, s.seq) for s in self.driver.read(timeout_s)]
        now = self.world.now_ns()
        out = []
        while self.sample_time_ns(self._next_seq) <= now:
            seq = self._next_seq
            t_ns = self.sample_time_ns(seq)
            q = self.world.arm.reported_joints(self.world.seconds(t_ns), seq)
            out.append(JointSample(q, t_ns + self.stamp_offset_ns, seq))
            self._next_seq += 1
        return out

    @property
    def health(self) -> Health:
        if self.driver is not None:
            return self.driver.health
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=self.world.now_ns())

    @property
    def faults(self) -> dict[str, int]:
        """What the real driver counted on the link (nothing without one)."""
        return dict(self.driver.faults) if self.driver is not None else {}


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
        if self.realtime:
            # a camera does not wait for its reader: frames whose time has passed are gone (the sequence
            # numbers show the gap, as a real grabber's do)
            due = int((time.monotonic() - self._wall0) * self.world.settings.fps)
            if due > self._seq:
                self._seq = due
                if self.max_frames is not None and self._seq >= self.max_frames:
                    return None
        seq = self._seq
        t_ns = self.frame_time_ns(seq)
        due_ns = None  # when the frame is captured on this host's monotonic clock (real time only)
        if self.realtime:
            due_ns = int(self._wall0 * 1e9) + t_ns - T0_NS
            delay = due_ns * 1e-9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        image, _ = self.world.render(t_ns, seq)
        self.world.advance_to(t_ns + int(self.world.settings.delivery_latency_s * 1e9))
        self._seq += 1
        return Frame(image=image, t_ns=t_ns, seq=seq, host_ns=due_ns)

    @property
    def health(self) -> Health:
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=self.world.now_ns())

    @property
    def ground_truth(self) -> GroundTruth:
        return GroundTruth(self.world.surface_mesh(), self.world.true_camera_pose)
