"""``lapreco calibrate handeye-tracked``: the hand-eye of an optically tracked scope (a marker on the scope, a
marker on the board, both in the tracker's frame) from tracked board views: the files in, the calibration
(``calib.handeye.calibrate_tracked_hand_eye``), the leave-one-view-out triangulation figure for a stereo scope
(``calib.handeye.leave_one_view_out``), handeye.yaml and the report out."""

from __future__ import annotations

import glob
import logging
import re
from pathlib import Path

import numpy as np

from lapreco_hil.calib.boards import parse_board
from lapreco_hil.calib.files import read_camera_yaml, write_handeye_yaml
from lapreco_hil.errors import CalibrationError
from lapreco_hil.outputs import write_json

log = logging.getLogger(__name__)


def _natural_key(path: str) -> list:
    """File names ordered with their numbers as numbers (view 10 after view 9)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", Path(path).name)]


def expand_paths(items: list[str], what: str) -> list[str]:
    """Paths from the command line, a quoted glob pattern expanded here, in natural order; a one-line error
    naming the option when nothing matches."""
    out = []
    for item in items:
        if any(c in item for c in "*?["):
            matched = glob.glob(item)
            if not matched:
                raise CalibrationError(f"{what} '{item}' matches no file")
            out += matched
        else:
            out.append(item)
    if not out:
        raise CalibrationError(f"{what}: no files given")
    return sorted(dict.fromkeys(out), key=_natural_key)


def read_tracker_matrix(path: str | Path) -> np.ndarray:
    """One tracker pose: a 4x4 rigid transform as text (rotation, translation in mm, last row 0 0 0 1)."""
    try:
        M = np.loadtxt(path, dtype=np.float64)
    except OSError:
        raise CalibrationError(f"{path}: cannot read the tracker pose (missing file?)") from None
    except ValueError as exc:
        raise CalibrationError(f"{path}: not a 4x4 matrix of numbers ({exc})") from None
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise CalibrationError(f"{path}: a tracker pose must be 4 rows of 4 finite numbers, got shape {M.shape}")
    R = M[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0 or not np.allclose(M[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)")
    return M


def tracked_views(scope_poses: list[str], board_poses: list[str], detections: dict[str, list]) -> list:
    """TrackedViews from the pose files and each camera's detections, all in view order (the i-th of each)."""
    from lapreco_hil.calib.handeye import TrackedView, tracker_pose

    both = sorted(set(scope_poses) & set(board_poses))
    if both:
        raise CalibrationError(f"{both[0]} is given both as a scope pose and as a board pose: narrow the patterns "
                               f"(e.g. 'calib.tracking.[0-9]*.txt' for the scope)")
    counts = {"--scope-poses": len(scope_poses), "--board-poses": len(board_poses),
              **{f"--{side} images": len(d) for side, d in detections.items()}}
    if len(set(counts.values())) != 1:
        raise CalibrationError("one file of each per tracked view: got " +
                               ", ".join(f"{n} {k}" for k, n in counts.items()))
    views = []
    for i, (scope, brd) in enumerate(zip(scope_poses, board_poses)):
        T_bm_sm = tracker_pose(read_tracker_matrix(brd), read_tracker_matrix(scope))
        found = {side: d[i] for side, d in detections.items() if d[i] is not None}
        views.append(TrackedView(Path(scope).name, T_bm_sm, found))
    return views


def detect_images(paths: list[str], board) -> list:
    """Per image, the board's (pixels, ids) or None where it was not found."""
    from lapreco_hil.calib.lens import load_images

    images = load_images(paths)
    out = []
    for p in paths:
        found = board.detect(images[p])
        if found is None:
            log.warning("%s: the board was not found; the view is left out for this camera", p)
        out.append(found)
    return out


def calibrate_tracked(scope_poses: list[str], board_poses: list[str], left: list[str], board_spec: str,
                      camera_file: str, out: str, right: list[str] | None = None,
                      camera_right_file: str | None = None, json_file: str | None = None,
                      leave_one_out: bool = True) -> dict:
    """The whole command: reads, detects, calibrates (one camera, or a stereo pair: one hand-eye for the left
    camera plus the rig), for a pair the leave-one-view-out figure, writes ``out`` and the JSON report."""
    if bool(right) != bool(camera_right_file):
        raise CalibrationError("a stereo scope needs both --right (its images) and --camera-right (its lens)")
    board = parse_board(board_spec)
    scope = expand_paths(scope_poses, "--scope-poses")
    boards = expand_paths(board_poses, "--board-poses")
    cameras = {"left": read_camera_yaml(camera_file)}
    images = {"left": expand_paths(left, "--left")}
    if right:
        cameras["right"] = read_camera_yaml(camera_right_file)
        images["right"] = expand_paths(right, "--right")
    counts = {side: len(p) for side, p in images.items()}
    if len({len(scope), len(boards), *counts.values()}) != 1:
        raise CalibrationError(f"one file of each per tracked view: got {len(scope)} --scope-poses, {len(boards)} "
                               f"--board-poses, " + ", ".join(f"{n} --{s} images" for s, n in counts.items()))
    detections = {side: detect_images(paths, board) for side, paths in images.items()}
    return calibrate_tracked_views(tracked_views(scope, boards, detections), board_spec, cameras, out, json_file,
                                   leave_one_out)


def tracked_views_from_session(session_dir: str, board, board_tool: str, stride: int = 5) -> tuple[list, dict]:
    """(TrackedViews, cameras) from a tracked-scope session (pose_source "marker_poses", e.g. a calibration
    session from ``lapreco record --marker``): every ``stride``-th frame whose time both the scope's tool and
    ``board_tool`` bracket with accepted samples (in the volume, within the RMS limit; interpolated on SE(3) with
    the gap rule), with the board detected in each camera's image (a stereo rig's first two: left, right)."""
    from lapreco_hil.calib.handeye import TrackedView
    from lapreco_hil.pose_sources import PoseTrack
    from lapreco_hil.sessions import Session

    session = Session(session_dir)
    meta = session.meta
    if meta.pose_source != "marker_poses":
        raise CalibrationError(f"session '{session_dir}' has {meta.pose_source.replace('_', ' ')}, not a tracker's "
                               f"marker poses; record one with 'lapreco record --marker ...'")
    table, tracker = session.markers, meta.tracker
    if board_tool == tracker.tool:
        raise CalibrationError(f"--board-tool '{board_tool}' is the scope's tool (session.json's tracker.tool); "
                               f"give the board's")
    tracks = {}
    for tool in (tracker.tool, board_tool):
        track = PoseTrack()
        for t, name, T, rms, inside in zip(table.t_ns, table.tools, table.poses, table.rms_mm, table.in_volume):
            if name == tool and inside and rms <= tracker.max_rms_mm:
                track.add(int(t), T)
        if len(track) < 2:
            raise CalibrationError(f"session '{session_dir}': {len(track)} usable poses of tool '{tool}' (in the "
                                   f"volume, RMS within {tracker.max_rms_mm} mm); tools in marker_poses.csv: "
                                   f"{', '.join(sorted(set(table.tools)))}")
        tracks[tool] = track
    cameras = dict(zip(("left", "right"), meta.rig.cameras[:2]))
    views = []
    left_out: dict[str, int] = {}  # frames without poses of both tools around them, by cause
    for i in range(0, len(session), stride):
        t = int(session.frame_t_ns[i]) + meta.time_offset_ns
        causes = [f"tool '{tool}': {cause}" for tool, track in tracks.items()
                  if (cause := track.no_pose_cause(t)) is not None]
        if causes:
            left_out[causes[0]] = left_out.get(causes[0], 0) + 1
            continue
        T_bm_sm = np.linalg.inv(tracks[board_tool](t)) @ tracks[tracker.tool](t)
        frame = session.frame(i)
        found = {side: board.detect(frame.image_of(k)) for k, side in enumerate(cameras)}
        views.append(TrackedView(f"frame {frame.seq}", T_bm_sm, {s: d for s, d in found.items() if d is not None}))
    if not views:
        raise CalibrationError(f"session '{session_dir}': no frame has poses of both the scope's tool "
                               f"'{tracker.tool}' and the board's '{board_tool}' around it")
    if left_out:
        log.warning("session '%s': %d of %d frames used left out for want of tracker poses around them (%s); "
                    "a frame before the first pose or after the last can mean a time offset not declared in "
                    "session.json's time_offset_ns", session_dir, sum(left_out.values()),
                    len(range(0, len(session), stride)), "; ".join(f"{n} x {c}" for c, n in left_out.items()))
    return views, cameras


def calibrate_tracked_session(session_dir: str, board_spec: str, board_tool: str, out: str, stride: int = 5,
                              json_file: str | None = None, leave_one_out: bool = True) -> dict:
    """``lapreco calibrate handeye-tracked --session S --board-tool NAME``: the tracked hand-eye from a session's
    frames and marker poses (the lenses: the session's cameras)."""
    views, cameras = tracked_views_from_session(session_dir, parse_board(board_spec), board_tool, stride)
    try:
        return calibrate_tracked_views(views, board_spec, cameras, out, json_file, leave_one_out)
    except CalibrationError as exc:
        if stride > 1 and "at least 3 are needed" in str(exc):
            raise CalibrationError(f"{exc}; --stride {stride} took every {stride}th frame of the session: try "
                                   f"--stride 1") from None
        raise


def calibrate_tracked_views(views: list, board_spec: str, cameras: dict, out: str, json_file: str | None = None,
                            leave_one_out: bool = True) -> dict:
    """Calibrate from TrackedViews (detections already made), write ``out`` (and the JSON report); the report."""
    from lapreco_hil.calib.handeye import calibrate_tracked_hand_eye, leave_one_view_out

    board = parse_board(board_spec)
    result = calibrate_tracked_hand_eye(views, board, cameras)
    if leave_one_out and len(cameras) == 2:
        result["leave_one_view_out"] = leave_one_view_out(views, board, cameras)
    extra = {"T_boardmarker_pattern": result["T_boardmarker_pattern"], "views": len(views),
             "sigma_px": result["sigma_px"]}
    for side, rms in result["reprojection_rms_px"].items():
        extra[f"reprojection_rms_px_{side}"] = rms
    if result["T_left_right"] is not None:
        extra["T_left_right"] = result["T_left_right"]
    if "leave_one_view_out" in result:
        extra["leave_one_view_out_mean_mm"] = result["leave_one_view_out"]["mean_mm"]
    # T_tip_camera: the scope marker is the "tip" the rest of the app reads a hand-eye for
    write_handeye_yaml(out, result["T_scopemarker_camera"], tip_frame="scope_marker", extra=extra)
    if json_file:
        write_json(json_file, result)
    return result
