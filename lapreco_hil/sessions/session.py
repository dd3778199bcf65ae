"""Reading a session folder: metadata, the frame index, joint samples or camera poses, ground truth."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.errors import SessionError
from lapreco_hil.geometry import SampledPoses
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.types import Frame, JointSample, RobotDescription
from lapreco_hil.sessions import format as fmt

log = logging.getLogger(__name__)


class Session:
    """A session opened for reading. Everything but the images is read and checked on open, so a bad
    session fails at once with the file and line, not halfway through a replay."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.meta = fmt.read_meta(self.folder)
        self.truncated: list[str] = []
        # tables with fewer rows than session.json's counts say were recorded: {table: {recorded, found}}
        self.shortfall: dict[str, dict[str, int]] = {}
        self._read_frames()
        self.joint_samples: list[JointSample] = []
        self.pose_t_ns = np.zeros(0, np.int64)
        self.poses = np.zeros((0, 4, 4))
        if self.meta.pose_source == "joints":
            self._read_joints()
        else:
            self.pose_t_ns, self.poses = fmt.read_pose_table(self.folder / fmt.CAMERA_POSES_FILE,
                                                             fmt.LENGTH_UNITS[self.meta.length_unit])
            if len(self.pose_t_ns) == 0:
                raise SessionError(f"{self.folder / fmt.CAMERA_POSES_FILE}: no poses")
        if not self.meta.complete:
            log.warning("session '%s' was not closed cleanly (recording cut short?); reading its %d complete "
                        "frames", self.folder, len(self.frame_t_ns))
        self._check_counts()

    def _check_counts(self) -> None:
        """Compare the rows found with the counts session.json recorded: a table cut short after the recording
        was closed (a copy that stopped halfway, a hand edit) is flagged, never replayed as if it were whole."""
        found = {"frames": (fmt.FRAMES_FILE, len(self.frame_t_ns))}
        if self.meta.pose_source == "joints":
            found["joint_samples"] = (fmt.JOINTS_FILE, len(self.joint_samples))
        else:
            found["camera_poses"] = (fmt.CAMERA_POSES_FILE, len(self.pose_t_ns))
        for key, (name, n) in found.items():
            recorded = self.meta.counts.get(key)
            if isinstance(recorded, int) and not isinstance(recorded, bool) and n < recorded:
                self.shortfall[key] = {"recorded": recorded, "found": n}
                log.warning("session '%s' is shorter than its %s says: %s has %d %s, %d were recorded; the "
                            "rest is missing (an incomplete copy?)", self.folder, fmt.META_FILE, name, n,
                            key.replace("_", " "), recorded)

    # --- frames ---------------------------------------------------------------------------------------------
    def _read_frames(self) -> None:
        path = self.folder / fmt.FRAMES_FILE
        rows, truncated = fmt.read_rows(path, ("seq", "t_ns", "file"))
        if truncated:
            self.truncated.append(fmt.FRAMES_FILE)
        self.frame_seq = np.array([fmt.parse_int(path, i + 2, "seq", r[0]) for i, r in enumerate(rows)], np.int64)
        self.frame_t_ns = np.array([fmt.parse_int(path, i + 2, "t_ns", r[1]) for i, r in enumerate(rows)],
                                   np.int64)
        if not rows:
            raise SessionError(f"{path}: no frames")
        fmt.check_increasing(path, self.frame_t_ns)
        fmt.check_increasing(path, self.frame_seq, "seq")
        self.frame_files = [self._frame_file(path, i + 2, r[2]) for i, r in enumerate(rows)]

    def _frame_file(self, table: Path, lineno: int, name: str) -> Path:
        """The frame file a row names, checked: relative, inside the session folder (after following
        symbolic links), and there."""
        where = f"{table}: line {lineno}: frame file '{name}'"
        if not name or Path(name).is_absolute() or name.startswith(("/", "\\")) or name[1:2] == ":":
            raise SessionError(f"{where} is not a relative path; frame paths must be relative to the session "
                               f"folder (e.g. frames/000000.png)")
        file = self.folder / name
        root = self.folder.resolve()
        try:
            resolved = file.resolve()
        except (OSError, RuntimeError) as exc:  # a symbolic-link loop
            raise SessionError(f"{where} cannot be resolved ({exc})") from None
        if not resolved.is_relative_to(root):
            raise SessionError(f"{where} leads outside the session folder (to '{resolved}'); frame paths must "
                               f"stay inside it")
        if not resolved.is_file():
            raise SessionError(f"{where} is missing")
        return file

    def __len__(self) -> int:
        return len(self.frame_t_ns)

    def frame(self, i: int) -> Frame:
        path = self.frame_files[i]
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SessionError(f"{path}: cannot decode the image (corrupt or not an image file)")
        if image.dtype != np.uint8:
            raise SessionError(f"{path}: {image.dtype} pixels; frames must be 8-bit")
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        elif image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        cam = self.meta.camera
        if image.shape[:2] != (cam.height, cam.width):
            raise SessionError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, the session's camera is "
                               f"{cam.width}x{cam.height}")
        return Frame(image=image, t_ns=int(self.frame_t_ns[i]), seq=int(self.frame_seq[i]))

    @property
    def frame_period_ns(self) -> int:
        if self.meta.nominal_fps:
            return int(round(1e9 / self.meta.nominal_fps))
        if len(self.frame_t_ns) > 1:
            return int(np.median(np.diff(self.frame_t_ns)))
        return 40_000_000

    # --- poses ----------------------------------------------------------------------------------------------
    def _read_joints(self) -> None:
        path = self.folder / fmt.JOINTS_FILE
        names = self.meta.joint_names
        rows, truncated = fmt.read_rows(path, ("seq", "t_ns", *names))
        if truncated:
            self.truncated.append(fmt.JOINTS_FILE)
        scale = self.meta.joint_scale
        t = np.empty(len(rows), np.int64)
        for i, r in enumerate(rows):
            t[i] = fmt.parse_int(path, i + 2, "t_ns", r[1])
            q = np.array([fmt.parse_float(path, i + 2, n, v) for n, v in zip(names, r[2:])]) * scale
            self.joint_samples.append(JointSample(q, int(t[i]), fmt.parse_int(path, i + 2, "seq", r[0])))
        if not rows:
            raise SessionError(f"{path}: no joint samples")
        fmt.check_increasing(path, t)

    @property
    def robot(self) -> RobotDescription:
        """The robot description with the URDF resolved against the session folder."""
        r = self.meta.robot
        if r is None:
            raise SessionError(f"{self.folder / fmt.META_FILE}: no 'robot' section")
        urdf = self.folder / r.urdf
        return RobotDescription(str(urdf) if urdf.is_file() else r.urdf, r.tip_frame, r.T_tip_camera,
                                r.T_world_base)

    # --- ground truth ---------------------------------------------------------------------------------------
    def ground_truth(self) -> GroundTruth | None:
        surface_path = self.folder / fmt.TRUTH_SURFACE_FILE
        poses_path = self.folder / fmt.TRUTH_POSES_FILE
        surface = poses = None
        if surface_path.is_file():
            import pyvista as pv

            try:
                surface = pv.read(str(surface_path))
            except Exception as exc:  # VTK raises several kinds for a bad file
                raise SessionError(f"{surface_path}: cannot read the ground-truth mesh ({exc})") from None
            if surface.n_points == 0:
                raise SessionError(f"{surface_path}: the ground-truth mesh is empty")
            surface = surface.scale(fmt.LENGTH_UNITS[self.meta.length_unit])
        if poses_path.is_file():
            t, T = fmt.read_pose_table(poses_path, fmt.LENGTH_UNITS[self.meta.length_unit])
            if len(t):
                poses = SampledPoses(t, T)
        if surface is None and poses is None:
            return None
        return GroundTruth(surface, poses)
