"""``lapreco record`` (devices by URL into a session) and ``lapreco sim-record`` (the simulated world, with
ground truth)."""

from __future__ import annotations

from dataclasses import dataclass

from lapreco_hil.app.handeye import recording_rig
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot, open_tracker
from lapreco_hil.sessions.recorder import RecordStats, record, record_tracked, scope_tool
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


def tracker_setup(tool: str, hand_eye_file: str | None = None, max_rms_mm: float | None = None):
    """The tracked scope's TrackerSetup: its tool, and the hand-eye T_marker_camera from a hand-eye file (the
    'T_tip_camera' that 'lapreco calibrate handeye-tracked' writes for the scope's marker), or none."""
    from lapreco_hil.calib.files import read_handeye_yaml
    from lapreco_hil.sessions.format import DEFAULT_MAX_RMS_MM, TrackerSetup

    T_marker_camera = read_handeye_yaml(hand_eye_file)["T_tip_camera"] if hand_eye_file else None
    return TrackerSetup(tool, T_marker_camera, max_rms_mm=max_rms_mm or DEFAULT_MAX_RMS_MM)


def record_tracked_session(marker_url: str, grabber_url: str, out: str, *, tool: str | None = None,
                           seconds: float | None = None, frames: int | None = None, camera_file: str | None = None,
                           hand_eye_file: str | None = None, device: str = "auto",
                           progress: bool = True) -> Recording:
    """``lapreco record --marker``: frames and the tracker's marker poses (every tool's; ``tool``: the
    scope's, default the tracker's only one). Without ``hand_eye_file`` a calibration session."""
    from lapreco_hil.calib.files import read_camera_yaml

    context = DeviceContext(device=resolve_device(device))
    tracker, grabber = open_tracker(marker_url, context), open_grabber(grabber_url, context)
    camera = read_camera_yaml(camera_file) if camera_file else None
    # the tracker first: its bring-up takes a while, and a grabber does not hold the frames that pass meanwhile
    with tracker, grabber:
        setup = tracker_setup(scope_tool(tracker, tool), hand_eye_file)
        stats = record_tracked(grabber, tracker, out, setup, seconds=seconds, max_frames=frames, camera=camera,
                               source={"tracker": marker_url, "grabber": grabber_url}, progress=progress)
    return Recording(stats, setup.T_marker_camera is None)


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
