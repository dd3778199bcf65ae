"""Simulated robot and grabber: the RobotDriver and Grabber interfaces over one SimWorld.

``sim://<scene>?width=640&height=480&fps=25&seed=0&device=cpu&frames=150&pace=afap|realtime&speed=0.2``
A robot and a grabber with the same scene name, opened in the same DeviceContext, share one world.
``optics=0|30`` is the scope's viewing angle (default 30: an angled scope).

``stereo=1&baseline_mm=5`` on the grabber makes it a stereo scope: camera 1 (right) sits ``baseline_mm`` to
the right of camera 0 along camera 0's x axis (an angled scope tilts both), is rendered by the same renderer,
and its image is ``Frame.views[0]``; ``right_focal_scale`` makes its focal lengths differ from the left's, as a
real pair's do. Camera 0 stays the world's true camera: the robot's pose, the hand-eye and the ground truth
refer to it. Rendering takes twice as long; the mono path is unchanged.

``link=serial|canopen`` on the robot puts the real driver in between: the simulated arm's encoder-side
joints drive a device emulator (a Dynamixel chain on a pseudo-terminal, CiA 402 nodes on a python-can
virtual bus) and the robot's samples are what the real driver reads from it. Polling needs time to pass
between frames, so a linked world's clock flows (``speed``, default 0.2 x real time).

Parameters: :class:`SimRobotConfig`, :class:`SimGrabberConfig`. In a run where every device is simulated the
devices stamp on simulated time (starting at 1 s); in a run with a real device (a sim grabber with a robot on
a serial port) they stamp on the host's monotonic clock like the real one, simulated time laid on it from
their opening, and the grabber is paced in real time (see ``lapreco_hil.registry``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.robot.base import RobotDriver
from lapreco_hil.errors import ConfigError
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.registry import HOST, DeviceContext, DeviceURL, URLConfig, parse_bool, url_param
from lapreco_hil.types import Frame, JointSample, RobotDescription

from lapreco_hil.simulators.world import SCENES, SimSettings, SimWorld
from lapreco_hil.simulators.world.world import T0_NS, stereo_rig

# URL parameter -> SimSettings field
_FIELDS = {"rate": "robot_rate_hz", "speed": "clock_speed", "optics": "optics_deg"}
LINKS = ("direct", "serial", "canopen")
PACES = ("afap", "realtime")


@dataclass(frozen=True)
class SimWorldConfig(URLConfig):
    """The simulated world's parameters (a robot and a grabber of one scene must agree on those they give)."""

    width: int = url_param(SimSettings.width, low=16, high=8192, unit="px")
    height: int = url_param(SimSettings.height, low=16, high=8192, unit="px")
    fps: float = url_param(SimSettings.fps, low=0.1, high=1000.0)
    seed: int = url_param(SimSettings.seed)
    device: str | None = url_param(None, help="Warp device for rendering (cpu, cuda:0)")
    rate: float = url_param(SimSettings.robot_rate_hz, low=0.1, high=10_000.0, unit="Hz", help="robot readings")
    speed: float | None = url_param(None, low=1e-3, high=100.0, help="simulated time flows at this x real time")
    instrument: bool = url_param(False, parse=parse_bool, help="a moving instrument in view")
    optics: float = url_param(SimSettings.optics_deg, low=0.0, high=70.0, unit="deg",
                              help="the scope's viewing angle from its shaft (0 or 30 typical)")

    def world_params(self, url: DeviceURL) -> dict:
        """The world parameters the URL gives (the others keep the world's defaults)."""
        return {k: getattr(self, k) for k in url.query if k in _WORLD_KEYS}


_WORLD_KEYS = tuple(SimWorldConfig.known_parameters())


@dataclass(frozen=True)
class SimRobotConfig(SimWorldConfig):
    link: str = url_param("direct", choices=LINKS, help="direct, or through a device emulator and the real driver")
    offset_ms: float = url_param(0.0, low=-1e6, high=1e6, unit="ms", help="kinematics clock offset")


@dataclass(frozen=True)
class SimGrabberConfig(SimWorldConfig):
    frames: int | None = url_param(None, low=0, help="end after this many frames")
    pace: str | None = url_param(None, choices=PACES, help="afap (default on the simulated clock) or realtime")
    stereo: bool = url_param(False, parse=parse_bool, help="a stereo scope: the right view in Frame.views")
    baseline_mm: float = url_param(5.0, low=0.5, high=30.0, unit="mm", help="stereo baseline (4-5.5 mm typical)")
    right_focal_scale: float = url_param(1.0, low=0.8, high=1.25, help="right camera's focal lengths / left's")


def _world_for(url: DeviceURL, params: dict, context: DeviceContext) -> SimWorld:
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


class HostTimeline:
    """Simulated time laid on the host's clock, for simulated devices in a run with real ones: simulated time
    T0 is the host time of the first such device's opening, and flows at the world's speed (default 1)."""

    def __init__(self, host_clock, speed: float) -> None:
        self.host_clock = host_clock
        self.speed = speed
        self.epoch_ns = host_clock()

    def to_host(self, t_sim_ns: int) -> int:
        return self.epoch_ns + int(round((t_sim_ns - T0_NS) / self.speed))

    def to_sim(self, t_host_ns: int) -> int:
        return T0_NS + int(round((t_host_ns - self.epoch_ns) * self.speed))

    def sim_now(self) -> int:
        return self.to_sim(self.host_clock())

    def sleep_until(self, t_host_ns: int) -> None:
        delay = (t_host_ns - self.host_clock()) * 1e-9
        if delay > 0:
            time.sleep(delay)


def _host_timeline(world: SimWorld, url: DeviceURL, context: DeviceContext) -> HostTimeline | None:
    """The timeline when this run stamps on the host's clock (a real device in it); None on simulated time."""
    if context.clock_domain(url.raw) != HOST:
        return None
    return context.shared("sim-host-timeline", url.name,
                          lambda: HostTimeline(context.clock_ns, world.settings.clock_speed or 1.0))


def _scenes() -> Discovery:
    return Discovery("simulated (robot and grabber; link=serial|canopen on the robot goes through a device emulator)",
                     tuple(FoundDevice(name, f"sim://{name}") for name in sorted(SCENES)))


class SimRobot(RobotDriver):
    """Encoder readings of the simulated holder, at ``rate`` Hz of simulated time (``link=direct``), or
    what a real driver reads from a device emulator (``link=serial|canopen``). Stamped on simulated time, or
    on the host's clock when the run has a real device."""

    clock_domain = "simulated"

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        config = SimRobotConfig.from_url(url)
        self.url = url
        self.config = config
        self.link = config.link
        params = config.world_params(url)
        if self.link != "direct" and "speed" not in params:
            params["speed"] = 0.2
        self.world = _world_for(url, params, context)
        if self.link != "direct" and self.world.settings.clock_speed is None:
            raise ConfigError(f"device URL '{url.raw}': link={self.link} needs a flowing clock; open the grabber "
                              f"of '{url.name}' with the same speed=... (e.g. speed=0.2)")
        self.info = self.world.kinematics.info
        # a kinematics clock that is off: readings of time t are stamped t + offset (public surgical datasets
        # have offsets up to seconds; calibrate time-offset recovers it)
        self.stamp_offset_ns = int(round(config.offset_ms * 1e6))
        self._context = context
        self._next_seq = 0
        self._open = False
        self._timeline: HostTimeline | None = None
        self.emulator = None
        self.driver: RobotDriver | None = None

    @classmethod
    def discover(cls) -> Discovery:
        return _scenes()

    def _open_link(self) -> None:
        from lapreco_hil.drivers.robot.joint_map import cia402_joint_map, dynamixel_joint_map
        from lapreco_hil.registry import open_robot

        world, timeline = self.world, self._timeline
        ids = list(range(1, len(self.info.joint_names) + 1))
        # the robot's own rate in simulated time, as wall-clock polling on the flowing clock
        speed = timeline.speed if timeline else world.settings.clock_speed
        rate = world.settings.robot_rate_hz * speed
        # the emulator and the driver share the run's clock: simulated, or the host's with the world laid on it
        clock = timeline.host_clock if timeline else world.now_ns
        to_sim = timeline.to_sim if timeline else (lambda t: t)

        def joints_at(t_ns: int):
            return world.arm.motor_joints(world.seconds(to_sim(t_ns)))

        context = DeviceContext(**{**self._context.options, "clock_ns": clock})
        if self.link == "serial":
            from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

            joint_map = dynamixel_joint_map(world.robot_model)
            self.emulator = DynamixelChainEmulator(ids, joint_map, joints_at, clock)
            url = f"serial://{self.emulator.port}?baud=1000000&ids={','.join(map(str, ids))}&rate={rate}"
        else:
            from lapreco_hil.simulators.canopen_emulator import CANopenDriveChainEmulator

            joint_map = cia402_joint_map(world.robot_model)
            channel = f"lapreco-sim-{id(self)}"
            self.emulator = CANopenDriveChainEmulator(channel, ids, joint_map, joints_at, clock)
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
        if not self._open:
            self._timeline = _host_timeline(self.world, self.url, self._context)
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

    def _read(self, timeout_s: float | None) -> list[JointSample]:
        if self.driver is not None:
            return [JointSample(s.q, s.t_ns + self.stamp_offset_ns, s.seq) for s in self.driver.read(timeout_s)]
        timeline = self._timeline
        if timeline is None:
            now = self.world.now_ns()
        else:
            next_host = timeline.to_host(self.sample_time_ns(self._next_seq))
            if timeout_s and next_host > timeline.host_clock():  # nothing due yet: wait for one, up to timeout_s
                timeline.sleep_until(min(next_host, timeline.host_clock() + int(timeout_s * 1e9)))
            now = timeline.sim_now()
        to_stamp = timeline.to_host if timeline else (lambda t: t)
        out = []
        while self.sample_time_ns(self._next_seq) <= now:
            seq = self._next_seq
            t_ns = self.sample_time_ns(seq)
            q = self.world.arm.reported_joints(self.world.seconds(t_ns), seq)
            out.append(JointSample(q, to_stamp(t_ns) + self.stamp_offset_ns, seq))
            self._next_seq += 1
        return out

    @property
    def health(self) -> Health:
        if self.driver is not None:
            return self.driver.health
        t_ns = self._timeline.host_clock() if self._timeline else self.world.now_ns()
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=t_ns)

    @property
    def faults(self):
        """What the real driver counted on the link (nothing without one)."""
        return self.driver.faults if self.driver is not None else super().faults


class SimGrabber(Grabber):
    """Renders what the true camera sees at the robot's true pose; as fast as possible or paced to fps.
    Stamped on simulated time, or on the host's clock (paced in real time) when the run has a real device."""

    clock_domain = "simulated"

    def __init__(self, url: DeviceURL, context: DeviceContext) -> None:
        config = SimGrabberConfig.from_url(url)
        self.url = url
        self.config = config
        stereo_only = [k for k in ("baseline_mm", "right_focal_scale") if k in url.query]
        if stereo_only and not config.stereo:
            raise url.error(f"{stereo_only[0]}= describes a stereo scope; add stereo=1")
        self.world = _world_for(url, config.world_params(url), context)
        self._rig = stereo_rig(self.world.camera, config.baseline_mm * 1e-3, config.right_focal_scale) \
            if config.stereo else None
        self.max_frames = config.frames
        self.realtime = config.pace == "realtime"
        self._context = context
        self._timeline: HostTimeline | None = None
        self._seq = 0
        self._open = False
        self._wall0 = 0.0

    @classmethod
    def discover(cls) -> Discovery:
        return _scenes()

    @property
    def camera(self):
        return self.world.camera

    @property
    def rig(self):
        """Camera 0 is the world's true camera (its poses are the ground truth, the hand-eye is to it); a stereo
        scope's camera 1 is rendered by the same renderer at T_cam0_cam1."""
        return self._rig if self._rig is not None else super().rig

    def _render(self, t_ns: int, seq: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        if self._rig is None:
            return self.world.render(t_ns, seq)[0], ()
        images = [image for image, _ in self.world.render_rig(t_ns, seq, self._rig)]
        return images[0], tuple(images[1:])

    @property
    def nominal_fps(self) -> float:
        return self.world.settings.fps

    def open(self) -> None:
        if not self._open:
            self._timeline = _host_timeline(self.world, self.url, self._context)
            if self._timeline is not None and self.config.pace == "afap":
                raise ConfigError(f"device URL '{self.url.raw}': pace=afap runs ahead of real time, but this run "
                                  f"has a real device and stamps on the host's clock; leave pace out (real time)")
        self._open = True
        self._wall0 = time.monotonic()

    def close(self) -> None:
        self._open = False

    def frame_time_ns(self, seq: int) -> int:
        return T0_NS + int(round(seq * 1e9 / self.world.settings.fps))

    def _read_on_host_clock(self, timeline: HostTimeline) -> Frame | None:
        # a camera does not wait for its reader: frames whose time has passed are gone
        due = int((timeline.sim_now() - T0_NS) * 1e-9 * self.world.settings.fps)
        self._seq = max(self._seq, due)
        if self.max_frames is not None and self._seq >= self.max_frames:
            return None
        seq = self._seq
        t_sim = self.frame_time_ns(seq)
        t_host = timeline.to_host(t_sim)
        timeline.sleep_until(t_host)
        image, views = self._render(t_sim, seq)
        self._seq += 1
        return Frame(image=image, t_ns=t_host, seq=seq, host_ns=t_host, views=views)

    def read(self, timeout_s: float | None = None) -> Frame | None:
        if self._timeline is not None:
            return self._read_on_host_clock(self._timeline)
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
        image, views = self._render(t_ns, seq)
        self.world.advance_to(t_ns + int(self.world.settings.delivery_latency_s * 1e9))
        self._seq += 1
        return Frame(image=image, t_ns=t_ns, seq=seq, host_ns=due_ns, views=views)

    @property
    def health(self) -> Health:
        t_ns = self._timeline.host_clock() if self._timeline else self.world.now_ns()
        return Health(HealthState.OK if self._open else HealthState.DISCONNECTED, t_ns=t_ns)

    @property
    def ground_truth(self) -> GroundTruth:
        def camera_pose(t_ns: int):
            timeline = self._timeline
            return self.world.true_camera_pose(timeline.to_sim(t_ns) if timeline else t_ns)

        return GroundTruth(self.world.surface_mesh(), camera_pose)
