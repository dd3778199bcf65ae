"""``lapreco record`` (devices by URL into a session) and ``lapreco sim-record`` (the simulated world, with
ground truth)."""

from __future__ import annotations

from dataclasses import dataclass

from lapreco_hil.app.handeye import recording_rig
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.sessions.recorder import RecordStats, record
from lapreco_hil.warp_device import resolve_device


@dataclass(frozen=True)
class Recording:
    stats: RecordStats
    # no hand-eye was known: the session is a calibration session, for 'lapreco calibrate handeye'
    calibration_only: bool


def record_session(robot_url: str, grabber_url: str, out: str, *, seconds: float | None = None,
                   frames: int | None = None, camera_file: str | None = None, robot_model: str | None = None,
                   tip_frame: str | None = None, hand_eye_file: str | None = None, device: str = "auto",
                   progress: bool = True) -> Recording:
    """Record until the source ends, ``seconds`` of capture or ``frames`` frames. A robot with a model but no
    hand-eye records a calibration session (frames and joints, no T_tip_camera: the first step of a new
    rig's bring-up, ``lapreco_hil.app.handeye``)."""
    context = DeviceContext(device=resolve_device(device))
    robot, grabber = open_robot(robot_url, context), open_grabber(grabber_url, context)
    camera, description, calibration_only = recording_rig(robot, grabber, camera_file, hand_eye_file,
                                                          robot_model, tip_frame)
    with robot, grabber:
        stats = record(grabber, robot, out, seconds=seconds, max_frames=frames, camera=camera,
                       description=description, source={"robot": robot_url, "grabber": grabber_url},
                       progress=progress)
    return Recording(stats, calibration_only)


def sim_url(scene: str, resolution: tuple[int, int], fps: float, seed: int, instrument: bool = False,
            robot_link: str = "direct", sim_speed: float = 0.2) -> str:
    """The simulated world's device URL (without the robot's link and the grabber's frame count)."""
    url = f"sim://{scene}?width={resolution[0]}&height={resolution[1]}&fps={fps}&seed={seed}"
    if instrument:
        url += "&instrument=1"
    if robot_link != "direct":
        url += f"&speed={sim_speed}"
    return url


def sim_record(scene: str, out: str, *, frames: int = 150, resolution: tuple[int, int] = (640, 480),
               fps: float = 25.0, seed: int = 0, device: str = "auto", robot_link: str = "direct",
               sim_speed: float = 0.2, instrument: bool = False, kinematics_offset_ms: float = 0.0,
               progress: bool = True) -> RecordStats:
    """A simulated session with ground truth; ``robot_link`` 'serial'/'canopen' records the robot through the
    real driver and a device emulator."""
    url = sim_url(scene, resolution, fps, seed, instrument, robot_link, sim_speed)
    context = DeviceContext(device=resolve_device(device))
    robot = open_robot(url + f"&link={robot_link}&offset_ms={kinematics_offset_ms}", context)
    grabber = open_grabber(url + f"&frames={frames}", context)
    with robot, grabber:
        return record(grabber, robot, out, max_frames=frames, progress=progress,
                      source={"simulator": url, "scene": scene, "seed": seed, "robot_link": robot_link})
