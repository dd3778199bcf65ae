"""Hand-eye and time-offset calibration as the app runs them, and the bring-up of a new rig.

A new rig has a robot model but no hand-eye. It comes up in two steps: ``lapreco record`` without
``--hand-eye`` records a *calibration session* (frames and joint readings of the scope looking at a board; the
session's robot section has no ``T_tip_camera``), then ``lapreco calibrate handeye`` turns it into
``handeye.yaml``, which ``record``, ``run`` and ``replay`` take with ``--hand-eye``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from lapreco_hil.calib.boards import parse_board
from lapreco_hil.calib.files import read_camera_yaml, read_handeye_yaml, write_handeye_yaml
from lapreco_hil.errors import CalibrationError, ConfigError
from lapreco_hil.outputs import write_json
from lapreco_hil.types import RobotDescription

log = logging.getLogger(__name__)

# the board of the bring-up recipe: the ChArUco the simulated board scene shows; a real rig names its own
EXAMPLE_BOARD = "charuco:10x7:0.004:0.003:DICT_5X5_100"


def hand_eye_missing_message(robot_url: str, grabber_url: str, robot_model: str | None = None,
                             tip_frame: str | None = None) -> str:
    """What ``run`` (or ``record`` without a robot model) says when there is no hand-eye: the two commands
    that make one."""
    model = f"--robot-model {robot_model or 'MODEL.urdf'} --tip-frame {tip_frame or 'TIP_LINK'}"
    return (f"robot '{robot_url}' has no hand-eye calibration (T_tip_camera); bring the rig up in two steps: "
            f"(1) with the scope looking at a calibration board, moved about at least two axes: "
            f"lapreco record --robot '{robot_url}' --grabber '{grabber_url}' {model} --seconds 20 "
            f"--out handeye-session ; (2) lapreco calibrate handeye handeye-session --board {EXAMPLE_BOARD} "
            f"--out handeye.yaml (your board's spec) ; then pass --hand-eye handeye.yaml")


def calibrate_next_step(session_dir: str) -> str:
    """What to run after recording a calibration session."""
    return (f"no hand-eye: {session_dir} is a calibration session; next: lapreco calibrate handeye {session_dir} "
            f"--board BOARD --out handeye.yaml (BOARD: the board in view, e.g. {EXAMPLE_BOARD}), then pass "
            f"--hand-eye handeye.yaml")


def check_model_matches_driver(robot, robot_model: str) -> None:
    """A real robot's driver converts encoder counts by the joints of its URL's model (``model=``, default ecm):
    a --robot-model whose joints differ in name, type (revolute: rad, prismatic: m) or limits would have its
    readings converted by the other model's joints and recorded without a word. One ConfigError names both."""
    joint_map = getattr(robot, "joint_map", None)
    if joint_map is None:
        return  # a simulator or a session: it reads by the model it describes
    from lapreco_hil.kinematics import load_urdf_model, prismatic_joints
    from lapreco_hil.robot_models import urdf_path

    m = load_urdf_model(urdf_path(robot_model))
    names, prismatic = tuple(m.names[1:]), prismatic_joints(m)
    same = (names == tuple(joint_map.names) and np.array_equal(prismatic, joint_map.is_prismatic)
            and np.allclose(m.lowerPositionLimit, joint_map.lower) and np.allclose(m.upperPositionLimit, joint_map.upper))
    if not same:
        def joints(ns, pr):
            return ", ".join(f"{n} ({'m' if p else 'rad'})" for n, p in zip(ns, pr))
        raise ConfigError(f"robot model '{robot_model}' (--robot-model or the hand-eye file's): its joints ({joints(names, prismatic)}, or their limits) "
                          f"differ from the model robot '{robot.url.raw}' converts its encoder counts by "
                          f"('{robot.config.model}': {joints(joint_map.names, joint_map.is_prismatic)}); give the "
                          f"same model in the URL (model={robot_model})")


def describe_rig(robot, grabber, camera_file: str | None = None, hand_eye_file: str | None = None,
                 robot_model: str | None = None, tip_frame: str | None = None):
    """(camera, description or None): the lens and the robot's description from files where given, else from
    what the devices know. The description may lack a hand-eye (T_tip_camera None)."""
    camera = read_camera_yaml(camera_file) if camera_file else grabber.camera
    if camera is None:
        raise ConfigError(f"grabber '{grabber.url.raw}' does not know its lens; pass --camera camera.yaml "
                          f"(from 'lapreco calibrate lens')")
    description = robot.description
    if hand_eye_file or robot_model or tip_frame:
        he = read_handeye_yaml(hand_eye_file) if hand_eye_file else {}
        base = description or RobotDescription("", "", None)
        description = replace(base, urdf=robot_model or he.get("robot_model") or base.urdf,
                              tip_frame=tip_frame or he.get("tip_frame") or base.tip_frame,
                              T_tip_camera=he["T_tip_camera"] if he else base.T_tip_camera)
    if description is not None and description.urdf:
        check_model_matches_driver(robot, description.urdf)
    return camera, description


def recording_rig(robot, grabber, camera_file: str | None = None, hand_eye_file: str | None = None,
                  robot_model: str | None = None, tip_frame: str | None = None):
    """(camera, description, calibration_only) for ``lapreco record``. Without a hand-eye (no --hand-eye and
    none known to the robot) but with a robot model and tip link, the description has T_tip_camera None
    and the session recorded is a calibration session for ``lapreco calibrate handeye``."""
    camera, description = describe_rig(robot, grabber, camera_file, hand_eye_file, robot_model, tip_frame)
    if description is None or not description.urdf or not description.tip_frame:
        raise ConfigError(f"robot '{robot.url.raw}' has no robot model; pass --robot-model (a packaged name such "
                          f"as 'ecm' or a URDF) and --tip-frame (the link that holds the scope)")
    calibration_only = description.T_tip_camera is None
    if calibration_only:
        log.warning("no hand-eye for robot '%s': recording a calibration session (frames and joints; no "
                    "T_tip_camera): 'lapreco calibrate handeye' turns it into handeye.yaml", robot.url.raw)
    return camera, description, calibration_only


def require_hand_eye(robot, grabber, description: RobotDescription | None) -> RobotDescription:
    """The description, when it can make camera poses; else the bring-up recipe as a ConfigError."""
    if description is None or not description.urdf or not description.tip_frame or description.T_tip_camera is None:
        raise ConfigError(hand_eye_missing_message(robot.url.raw, grabber.url.raw,
                                                   description.urdf if description else None,
                                                   description.tip_frame if description else None))
    return description


def hand_eye_stations(session, board, camera, stride: int):
    """Stations (tip pose from the joint readings at each used frame, board pose by PnP) of a session."""
    from lapreco_hil.calib.handeye import board_station
    from lapreco_hil.config import PriorConfig
    from lapreco_hil.kinematics import CameraKinematics, PoseAtTime
    from lapreco_hil.robot_models import urdf_path

    robot = session.robot
    kin = CameraKinematics(str(urdf_path(robot.urdf)), robot.tip_frame, np.eye(4), robot.T_world_base)
    prior = PriorConfig()
    joints = PoseAtTime(kin, prior.joint_sigma, prior.floor_rot_sigma_rad, prior.floor_trans_sigma_m,
                        capacity=max(4096, len(session.joint_samples)))
    joints.extend(session.joint_samples)
    from lapreco_hil.calib.time_offset import JointTrack

    track = JointTrack(np.array([j.t_ns for j in session.joint_samples], np.int64),
                       np.array([j.q for j in session.joint_samples]))
    stations = []
    for i in range(0, len(session), stride):
        frame = session.frame(i)
        t = frame.t_ns + session.meta.time_offset_ns
        q = joints.q_at(t)
        st = board_station(f"frame {frame.seq}", frame.image, board, camera, kin.tip_pose(q), q=q)
        if st is not None:
            st.side = track.at(np.array([t]))[1][0]  # the side of each joint's backlash
            st.t_s = (t - session.joint_samples[0].t_ns) * 1e-9
            stations.append(st)
    return stations, kin


def calibrate_hand_eye_session(session_dir: str, board_spec: str, out: str, camera_file: str | None = None,
                               stride: int = 5, json_file: str | None = None, refinement: str = "poses",
                               joint_wander_s: float = 0.0, backlash=None) -> dict:
    """``lapreco calibrate handeye``: stations from the session, every closed-form method, the refinement
    (``refinement`` "poses", the default, or "joints" with the arm's joint-error time constant
    ``joint_wander_s`` and per-joint ``backlash``: ``calib.handeye.refine_in_joint_space``), the report;
    writes ``out`` (handeye.yaml) and, if asked, the report as JSON."""
    from lapreco_hil.calib.handeye import calibrate_hand_eye
    from lapreco_hil.sessions import Session

    if refinement != "joints" and (joint_wander_s or backlash is not None):
        raise CalibrationError("--joint-wander-s and --backlash describe the arm for the joint-space refinement; "
                               "add --refine joints")
    session = Session(session_dir)
    if session.meta.pose_source == "marker_poses":
        raise CalibrationError(f"session '{session_dir}' follows a tracked scope (marker poses), not a robot; its "
                               f"hand-eye comes from 'lapreco calibrate handeye-tracked --session {session_dir} "
                               f"--board-tool NAME' (the board's tracked tool; or from per-view pose files)")
    if session.meta.pose_source != "joints":
        raise CalibrationError(f"session '{session_dir}' has camera poses, not joint readings; hand-eye "
                               f"calibration needs the robot's kinematics")
    board = parse_board(board_spec)
    camera = read_camera_yaml(camera_file) if camera_file else session.meta.camera
    stations, kin = hand_eye_stations(session, board, camera, stride)
    if len(stations) < 3:
        raise CalibrationError(f"session '{session_dir}': the board ({board_spec}) was found in {len(stations)} "
                               f"stations; at least 3 are needed")
    from lapreco_hil.config import PriorConfig

    options = {}
    if refinement == "joints":
        if backlash is not None and len(backlash) not in (1, kin.n_joints):
            raise CalibrationError(f"--backlash gives {len(backlash)} values; the robot has {kin.n_joints} joints "
                                   f"(give one value for all, or one per joint)")
        # the joint errors have the pipeline's joint prior (the robot's 1-sigma joint error)
        options = {"tip_pose": kin.tip_pose, "joint_sigma": PriorConfig().joint_sigma,
                   "wander_time_s": joint_wander_s, "backlash": backlash}
    result = calibrate_hand_eye(stations, camera, refinement=refinement, **options)
    robot = session.robot
    write_handeye_yaml(out, result["T_tip_camera"], robot_model=session.meta.robot.urdf
                       if not Path(session.meta.robot.urdf).suffix else None, tip_frame=robot.tip_frame,
                       extra={"stations": len(stations),
                              "reprojection_rms_px": result["refined"]["reprojection_rms_px"],
                              "method_spread_rotation_deg": result["agreement"]["rotation_deg"],
                              "method_spread_translation_mm": result["agreement"]["translation_mm"]})
    if json_file:
        write_json(json_file, result)
    return result


def estimate_session_time_offset(session_dir: str, search_ms: float = 1000.0, apply: bool = False,
                                 hand_eye_file: str | None = None, json_file: str | None = None,
                                 joint_wander_s: float = 0.0) -> dict:
    """``lapreco calibrate time-offset``: the estimate's summary; with ``apply`` it is written into the
    session's time_offset_ns (and the estimate under source.time_offset_estimate). ``joint_wander_s``: the
    arm's joint-error time constant, if known (it widens the uncertainty; ``estimate_from_tracks``)."""
    from lapreco_hil.calib.time_offset import estimate_time_offset
    from lapreco_hil.sessions import Session
    from lapreco_hil.sessions.format import META_FILE

    if not (isinstance(search_ms, (int, float)) and math.isfinite(search_ms) and search_ms > 0):
        raise CalibrationError(f"--search-ms must be a positive, finite number of milliseconds, got {search_ms}")
    session = Session(session_dir)
    hand_eye = read_handeye_yaml(hand_eye_file)["T_tip_camera"] if hand_eye_file else None
    est = estimate_time_offset(session, search_s=search_ms / 1e3, T_tip_camera=hand_eye, wander_time_s=joint_wander_s)
    summary = {**est.summary(), "joint_wander_s": joint_wander_s}
    if apply:
        path = session.folder / META_FILE
        doc = json.loads(path.read_text())
        doc["time_offset_ns"] = est.offset_ns
        doc.setdefault("source", {})["time_offset_estimate"] = summary
        write_json(path, doc)
        summary["applied_to"] = str(path)
    if json_file:
        write_json(json_file, summary)
    return summary
