"""Reading a session folder: metadata, the frame index, joint samples or camera poses, ground truth."""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.errors import SessionError
from lapreco_hil.geometry import SampledPoses
from lapreco_hil.ground_truth import GroundTruth
from lapreco_hil.types import Frame, JointSample, RobotDescription
from lapreco_hil.sessions import format as fmt

log = logging.getLogger(__name__)

# two frames read as a stereo pair must stand at least this far apart (below it there is no epipolar line to
# search along: the pair is tracked as two frames)
MIN_PAIR_BASELINE_M = 1e-4


class Session:
    """A session opened for reading. Everything but the images is read and checked on open, so a bad
    session fails at once with the file and line, not halfway through a replay."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.meta = fmt.read_meta(self.folder)
        self.truncated: list[str] = []
        # tables with fewer rows than session.json's counts say were recorded: {table: {recorded, found}}
        self.shortfall: dict[str, dict[str, int]] = {}
        self._jpeg_warned = False  # frames are lossless by the spec: one warning per session for a JPEG frame
        self._jpeg_lock = threading.Lock()  # (replay:// decodes frames in several threads)
        self._read_frames()
        self.joint_samples: list[JointSample] = []
        self.pose_t_ns = np.zeros(0, np.int64)
        self.poses = np.zeros((0, 4, 4))
        self.markers: fmt.MarkerTable | None = None  # pose_source "marker_poses": every tool's rows
        if self.meta.pose_source == "joints":
            self._read_joints()
        elif self.meta.pose_source == "marker_poses":
            self._read_markers()
        else:
            self.pose_t_ns, self.poses = fmt.read_pose_table(self.folder / fmt.CAMERA_POSES_FILE,
                                                             fmt.LENGTH_UNITS[self.meta.length_unit],
                                                             self.meta.complete)
            if len(self.pose_t_ns) == 0:
                raise SessionError(f"{self.folder / fmt.CAMERA_POSES_FILE}: no poses")
        if not self.meta.complete:
            log.warning("session '%s' was not closed cleanly (recording cut short?); reading its %d complete "
                        "frames", self.folder, len(self.frame_t_ns))
        self._check_counts()
        self.pair_as_rig = False  # a version-1 pair of frames read as one frame of a rig of two (pair_frames_as_rig)

    def pair_frames_as_rig(self, camera: CameraModel | None = None, offset_ns: int | None = None) -> bool:
        """Read a version-1 session of exactly two frames with their camera poses, two views of known relative
        pose as a calibrated stereo pair is written in version 1, as one frame of a rig of two: the second view
        camera 1 at the poses' relative transform (held by bundle adjustment within both poses' sigmas), both
        views ``camera`` (default: the session's). Only where each frame has a pose at its own time (plus
        ``offset_ns``, default the session's) and the two are apart (a baseline of at least MIN_PAIR_BASELINE_M).
        Why: a rig's views are matched along their epipolar lines with an affine refinement, while the temporal
        tracker's first step with a motion slides along the line on weak texture; an outside review's rendered
        skull pair made its sparse points at 0.56 mm RMS as two frames and 0.31 mm as a rig (docs/session-format.md,
        "Two frames"). The replay asks for it; other readers (an export, a live run's replay:// grabber) see the
        two frames. Returns whether it did."""
        if (self.pair_as_rig or self.meta.file_version != 1 or self.meta.pose_source != "camera_poses"
                or len(self.frame_t_ns) != 2 or len(self.meta.rig) != 1):
            return False
        at = self.frame_t_ns + (self.meta.time_offset_ns if offset_ns is None else offset_ns)
        idx = np.minimum(np.searchsorted(self.pose_t_ns, at), len(self.pose_t_ns) - 1)
        if np.any(self.pose_t_ns[idx] != at):
            return False
        T0, T1 = self.poses[idx[0]], self.poses[idx[1]]
        T01 = np.linalg.inv(T0) @ T1
        if np.linalg.norm(T01[:3, 3]) < MIN_PAIR_BASELINE_M:
            return False
        camera = self.meta.camera if camera is None else camera
        sigma = self.meta.pose_sigma
        rig = Rig((camera, camera), (np.eye(4), T01), sigma_rotation_rad=float(np.sqrt(2.0) * sigma.rotation_rad),
                  sigma_translation_m=float(np.sqrt(2.0) * sigma.translation_m))
        self.meta = replace(self.meta, camera=camera, rig=rig, camera_names=("first", "second"))
        self._files = [(self._files[0][0], self._files[1][0])]
        self.frame_files = self.frame_files[:1]
        self.second_frame = (int(self.frame_seq[1]), int(self.frame_t_ns[1]))  # (seq, t_ns), for the outputs
        self.frame_seq, self.frame_t_ns = self.frame_seq[:1], self.frame_t_ns[:1]
        self.pair_as_rig = True
        log.info("session '%s': its two frames read as a stereo pair (camera 1 at the poses' relative transform, "
                 "baseline %.2f mm)", self.folder, 1e3 * float(np.linalg.norm(rig.T_cam0_cam[1][:3, 3])))
        return True

    def _check_counts(self) -> None:
        """Compare the rows found with the counts session.json recorded: a table cut short after the recording
        was closed (a copy that stopped halfway, a hand edit) is flagged, never replayed as if it were whole."""
        found = {"frames": (fmt.FRAMES_FILE, len(self.frame_t_ns))}
        if self.meta.pose_source == "joints":
            found["joint_samples"] = (fmt.JOINTS_FILE, len(self.joint_samples))
        elif self.meta.pose_source == "marker_poses":
            found["marker_poses"] = (fmt.MARKER_POSES_FILE, len(self.markers))
        else:
            found["camera_poses"] = (fmt.CAMERA_POSES_FILE, len(self.pose_t_ns))
        for key, (name, n) in found.items():
            recorded = self.meta.counts.get(key)
            if isinstance(recorded, int) and not isinstance(recorded, bool) and n < recorded:
                self.shortfall[key] = {"recorded": recorded, "found": n}
                log.warning("session '%s' is shorter than its %s says: %s has %d %s, %d were recorded; the "
                            "rest is missing (an incomplete copy?)", self.folder, fmt.META_FILE, name, n,
                            key.replace("_", " "), recorded)

    # --- the cameras ----------------------------------------------------------------------------------------
    @property
    def rig(self) -> Rig:
        """Every camera of the session with its extrinsics (a version-1 session: a rig of one)."""
        return self.meta.rig

    @property
    def camera(self) -> CameraModel:
        """Camera 0, the rig's reference (the session's one camera in version 1)."""
        return self.meta.camera

    # --- frames ---------------------------------------------------------------------------------------------
    def _read_frames(self) -> None:
        path = self.folder / fmt.FRAMES_FILE
        version = self.meta.file_version or self.meta.version
        rows, truncated = fmt.read_rows(path, fmt.FRAME_COLUMNS[version], complete=self.meta.complete)
        if truncated:
            self.truncated.append(fmt.FRAMES_FILE)
        if version == 1:
            groups = [[(i + 2, r[0], r[1], "0", r[2])] for i, r in enumerate(rows)]
        else:
            groups = self._rig_frames(path, rows, truncated)
        if not groups:
            raise SessionError(f"{path}: no frames")
        first = [g[0] for g in groups]
        self.frame_seq = np.array([fmt.parse_int(path, ln, "seq", seq) for ln, seq, *_ in first], np.int64)
        self.frame_t_ns = np.array([fmt.parse_int(path, ln, "t_ns", t) for ln, _, t, *_ in first], np.int64)
        self._check_increasing(path, [g[0][0] for g in groups])
        # per frame, each camera's image file (camera k: files[i][k])
        self._files = [tuple(self._frame_file(path, ln, name) for ln, *_, name in
                             sorted(g, key=lambda row: int(row[3]))) for g in groups]
        self.frame_files = [f[0] for f in self._files]

    def _check_increasing(self, path: Path, lines: list[int]) -> None:
        for what, values in (("t_ns", self.frame_t_ns), ("seq", self.frame_seq)):
            bad = np.flatnonzero(np.diff(values) <= 0)
            if bad.size:
                i = int(bad[0]) + 1
                raise SessionError(f"{path}: line {lines[i]}: {what} {values[i]} does not increase (previous "
                                   f"frame {values[i - 1]}); {what} must be strictly increasing")

    def _rig_frames(self, path: Path, rows: list[list[str]], truncated: bool) -> list[list[tuple]]:
        """Version 2: the rows of one frame (consecutive, the same seq and t_ns, one per camera), grouped as
        [(line, seq, t_ns, camera, file), ...]."""
        n, names = len(self.meta.rig), self.meta.camera_names
        groups: list[list[tuple]] = []
        for i, (seq, t_ns, camera, name) in enumerate(rows):
            lineno = i + 2
            k = fmt.parse_int(path, lineno, "camera", camera)
            if not 0 <= k < n:
                raise SessionError(f"{path}: line {lineno}: column 'camera' = {k} is out of range; the rig has "
                                   f"{n} camera{'s' if n > 1 else ''} (0..{n - 1}, session.json's rig.cameras)")
            group = groups[-1] if groups else None
            if group is not None and group[0][1] == seq:
                if group[0][2] != t_ns:
                    raise SessionError(f"{path}: line {lineno}: t_ns {t_ns} differs from line {group[0][0]}'s "
                                       f"{group[0][2]} for the same seq {seq}; the cameras of a frame share its "
                                       f"capture time")
                twice = [ln for ln, *_, c, _ in group if int(c) == k]
                if twice:
                    raise SessionError(f"{path}: line {lineno}: camera {k} ({names[k]}) appears twice for seq "
                                       f"{seq} (lines {twice[0]} and {lineno}); give one row per camera")
                group.append((lineno, seq, t_ns, str(k), name))
            else:
                if group is not None:
                    self._check_complete(path, group)
                groups.append([(lineno, seq, t_ns, str(k), name)])
        if groups and len(groups[-1]) < n:
            if truncated or not self.meta.complete:
                # the writer appends a frame's rows together: a frame cut short by a crash is unfinished
                log.warning("%s: the last frame (seq %s) lacks %d of its %d images (a recording cut short); it "
                            "is left out", path, groups[-1][0][1], n - len(groups[-1]), n)
                groups.pop()
            else:
                self._check_complete(path, groups[-1])
        return groups

    def _check_complete(self, path: Path, group: list[tuple]) -> None:
        n, names = len(self.meta.rig), self.meta.camera_names
        if len(group) < n:
            have = {int(row[3]) for row in group}
            missing = [k for k in range(n) if k not in have]
            lines = f"line {group[0][0]}" if len(group) == 1 else f"lines {group[0][0]}-{group[-1][0]}"
            raise SessionError(f"{path}: {lines}: seq {group[0][1]} has no image for camera "
                               f"{', '.join(f'{k} ({names[k]})' for k in missing)}; every frame needs one row "
                               f"per camera of the rig, with the same seq and t_ns, on consecutive lines")

    def _frame_file(self, table: Path, lineno: int, name: str) -> Path:
        """The frame file a row names, checked: relative, inside the session folder (after following
        symbolic links), and there."""
        return fmt.inside_session(self.folder, name, f"{table}: line {lineno}: frame file '{name}'",
                                  "an image file")

    def __len__(self) -> int:
        return len(self.frame_t_ns)

    def frame(self, i: int) -> Frame:
        """Frame i: camera 0's image, and the other cameras' in ``views`` (each at its own size)."""
        names = self.meta.camera_names if len(self.meta.rig) > 1 else ("",)
        if not self._jpeg_warned:
            for path in self._files[i]:
                self._warn_if_jpeg(path)
        images = tuple(self._image(path, cam, name) for path, cam, name in
                       zip(self._files[i], self.meta.rig.cameras, names))
        return Frame(image=images[0], t_ns=int(self.frame_t_ns[i]), seq=int(self.frame_seq[i]), views=images[1:])

    def _warn_if_jpeg(self, path: Path) -> None:
        """Warn (once per session) about a JPEG frame: the format asks for lossless frames, and JPEG's 8x8 block
        artefacts sit on the image grid, not on the scene, and pull corners with them. Read, not refused."""
        try:
            with open(path, "rb") as fh:
                head = fh.read(3)
        except OSError:
            return  # decoding it reports the problem
        if head != b"\xff\xd8\xff":  # JPEG's start-of-image marker, whatever the file's name
            return
        with self._jpeg_lock:
            if self._jpeg_warned:
                return
            self._jpeg_warned = True
        log.warning("%s: a JPEG frame; frames should be lossless (PNG): JPEG artefacts bias tracking (warned once "
                    "for this session)", path)

    @staticmethod
    def _image(path: Path, cam: CameraModel, name: str) -> np.ndarray:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SessionError(f"{path}: cannot decode the image (corrupt or not an image file)")
        if image.dtype != np.uint8:
            raise SessionError(f"{path}: {image.dtype} pixels; frames must be 8-bit")
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        elif image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if image.shape[:2] != (cam.height, cam.width):
            which = f"camera '{name}'" if name else "camera"
            raise SessionError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, the session's {which} is "
                               f"{cam.width}x{cam.height}; each image must have its camera's size")
        return image

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
        rows, truncated = fmt.read_rows(path, ("seq", "t_ns", *names), complete=self.meta.complete)
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

    def _read_markers(self) -> None:
        path = self.folder / fmt.MARKER_POSES_FILE
        self.markers, truncated = fmt.read_marker_table(path, fmt.LENGTH_UNITS[self.meta.length_unit],
                                                        self.meta.complete)
        if truncated:
            self.truncated.append(fmt.MARKER_POSES_FILE)
        tool = self.meta.tracker.tool
        if tool not in self.markers.tools:
            found = sorted(set(self.markers.tools))
            raise SessionError(f"{path}: no row of the scope's tool '{tool}' (session.json's tracker.tool); the "
                               f"table has {', '.join(repr(t) for t in found) if found else 'no rows'}")

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
            t, T = fmt.read_pose_table(poses_path, fmt.LENGTH_UNITS[self.meta.length_unit], self.meta.complete)
            if len(t):
                poses = SampledPoses(t, T)
        if surface is None and poses is None:
            return None
        return GroundTruth(surface, poses)
