"""``lapreco demo``: simulated robot and grabber (one simulated world) through the pipeline; writes the
outputs contract and a report with accuracy against the world's ground truth."""

from __future__ import annotations

from dataclasses import replace

from lapreco_hil.config import load_config
from lapreco_hil.frontend import resolve_tracker
from lapreco_hil.offline import reconstruct
from lapreco_hil.outputs import check_output_dir, prepare_output_dir
from lapreco_hil.pose_sources import RobotPoseSource
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.warp_device import resolve_device
from lapreco_hil.app.record import sim_url
from lapreco_hil.app.run import run_live


def run_demo(scene: str = "skull", frames: int = 150, resolution=(640, 480), fps: float = 25.0,
             out: str = "lapreco-demo", device: str = "auto", tracker: str = "auto",
             config_path: str | None = None, seed: int = 0, progress: bool = True,
             drift_check: bool | None = None, robot_link: str = "direct", sim_speed: float = 0.2,
             instrument: bool = False, runtime: str = "live", view_every: float = 0.0,
             stereo_baseline_mm: float | None = None, surface: str | None = None) -> dict:
    """``robot_link`` 'serial' or 'canopen' reads the simulated robot through the real driver and a device
    emulator; the simulated clock then flows at ``sim_speed`` x real time so the driver can poll it.
    ``stereo_baseline_mm``: a stereo scope with this baseline (None: mono). ``surface``: "dense" or "alpha"
    instead of the configuration's [surface] mode."""
    config = load_config(config_path)
    if surface is not None:
        config = replace(config, surface=replace(config.surface, mode=surface))
    if drift_check is not None:
        config = replace(config, tracker=replace(config.tracker, drift_check=drift_check))
    check_output_dir(out)
    device = resolve_device(device)
    tracker = resolve_tracker(tracker, device)
    url = sim_url(scene, resolution, fps, seed, instrument, robot_link, sim_speed)
    context = DeviceContext(device=device)
    robot = open_robot(url + f"&link={robot_link}", context)
    stereo = f"&stereo=1&baseline_mm={stereo_baseline_mm}" if stereo_baseline_mm else ""
    grabber = open_grabber(url + f"&frames={frames}" + stereo, context)
    fields = {"command": "demo", "scene": scene, "robot_link": robot_link, "instrument": instrument,
              "runtime": runtime, "stereo_baseline_mm": stereo_baseline_mm}
    if runtime == "live":
        if view_every:
            config = replace(config, runtime=replace(config.runtime, view_period_s=view_every))
        return run_live(robot, grabber, config, out, tracker=tracker, device=device, progress=progress,
                        total=frames, report_fields=fields)
    poses = RobotPoseSource(robot, robot.description, config.prior)
    with robot, grabber:
        out_dir = prepare_output_dir(out)  # once the devices are open: a failed start leaves no folder
        return reconstruct(grabber, poses, grabber.camera, config, out_dir, tracker=tracker, device=device,
                           truth=grabber.ground_truth, progress=progress, total=frames, label=f"demo {scene}",
                           report_fields=fields)
