"""Writing a session while capturing, crash-safe.

Each frame is encoded to a temporary file and renamed into place before its row is appended to
frames.csv (a rig's frame: all its cameras' images first, then all their rows at once), and every table is flushed to the OS after each frame: a process killed at any moment (kill -9)
leaves a session whose complete rows all point at complete files. (Flushing to the OS survives a killed
process; ``fsync_every`` also survives a power cut, at a cost in throughput.)

PNG encoding is the cost of recording (tens of ms per HD frame on one core), so frames are encoded by a
pool of threads (OpenCV releases the GIL) and their rows appended in capture order as they finish; at most
``2 x workers`` frames wait, after which ``add_frame`` waits for the oldest (the grabber's own queue then
drops and counts frames, rather than memory growing without bound).
"""

from __future__ import annotations

import collections
import csv
from array import array
import json
import os
import shutil
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from lapreco_hil.camera import FieldOfView, Rig
from lapreco_hil.errors import CalibrationError, OutputError, SessionError
from lapreco_hil.geometry import tum_values
from lapreco_hil.types import Frame, JointSample
from lapreco_hil.sessions import format as fmt


def _write_json_atomic(path: Path, doc: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2), encoding="utf-8")
    os.replace(tmp, path)


class SessionWriter:
    """Opens a new session folder and appends to it. Use as a context manager; ``close`` marks it complete.

    A rig of more than one camera (``meta.rig``), or a field of view that version 1 cannot hold, is written
    as version 2: each frame's ``views`` beside its image, each camera's images at their own size in
    ``frames/<camera name>/``; a one-camera session is written as version 1."""

    def __init__(self, folder: str | Path, meta: fmt.SessionMeta, urdf_file: str | Path | None = None,
                 png_compression: int = 1, fsync_every: int = 0, workers: int | None = None) -> None:
        self.folder = Path(folder)
        if self.folder.exists() and (not self.folder.is_dir() or any(self.folder.iterdir())):
            raise OutputError(f"session folder '{self.folder}' already exists and is not empty; choose a new "
                              f"--out (sessions are never overwritten)")
        try:
            (self.folder / fmt.FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create session folder '{self.folder}' ({exc.strerror})") from None
        if meta.pose_source == "joints":
            if meta.robot is None or urdf_file is None:
                raise SessionError("a session with pose_source 'joints' needs a robot description and its URDF")
            shutil.copyfile(urdf_file, self.folder / "robot.urdf")
            meta = replace(meta, robot=replace(meta.robot, urdf="robot.urdf"))
        self.version = meta.version
        if self.version == 2:
            meta = self._copy_masks(meta)
            for name in meta.camera_names:
                (self.folder / fmt.FRAMES_DIR / name).mkdir(exist_ok=True)
        self.meta = meta
        # Huffman-only deflate: faster than level 1 and smaller on noisy video
        self._png = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression),
                     cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
        self.workers = workers or max(1, min(8, os.cpu_count() or 1))
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="session-png")
        self._pending: collections.deque[tuple[list[Future], str]] = collections.deque()
        self._fsync_every = fsync_every
        self.n_frames = self.n_queued = self.n_joints = self.n_poses = self.n_truth = self.n_events = 0
        self.n_markers = 0
        self._last_marker_t: dict[str, int] = {}  # tool -> its last recorded time
        self.last_skipped_joints = ""  # why the last joint sample was not recorded (names the joint and value)
        # capture times of the recorded samples that place the camera (joint readings, or the scope tool's marker
        # poses a replay accepts: in the volume, RMS within max_rms_mm): what a replay's poses come from, for the
        # recording's pose coverage (sessions/recorder.py)
        self.pose_times = array("q")
        self._last_frame_t = self._last_joint_t = self._last_pose_t = self._last_truth_t = None
        _write_json_atomic(self.folder / fmt.META_FILE, meta.to_json(self.folder))
        self._tables = {"frames": self._open_table(fmt.FRAMES_FILE, fmt.FRAME_COLUMNS[self.version])}
        if meta.pose_source == "joints":
            self._tables["joints"] = self._open_table(fmt.JOINTS_FILE, ("seq", "t_ns", *meta.joint_names))
        elif meta.pose_source == "marker_poses":
            if meta.tracker is None:
                raise SessionError("a session with pose_source 'marker_poses' needs a tracker setup (its tool)")
            self._tables["markers"] = self._open_table(fmt.MARKER_POSES_FILE, fmt.MARKER_COLUMNS)
        else:
            self._tables["poses"] = self._open_table(fmt.CAMERA_POSES_FILE, fmt.POSE_COLUMNS)
        self.closed = False

    def _copy_masks(self, meta: fmt.SessionMeta) -> fmt.SessionMeta:
        """The cameras' mask files copied into masks/ (a session holds everything it names)."""
        cameras = []
        for name, cam in zip(meta.camera_names, meta.rig.cameras):
            if cam.fov is not None and cam.fov.kind == "mask":
                try:
                    inside = cam.fov.inside()
                except CalibrationError as exc:
                    raise SessionError(f"camera '{name}': {exc}") from None
                if inside.shape != (cam.height, cam.width):
                    raise SessionError(f"camera '{name}': field-of-view mask '{cam.fov.mask_file}' is "
                                       f"{inside.shape[1]}x{inside.shape[0]}, the camera is {cam.width}x"
                                       f"{cam.height}; a mask must have its camera's size")
                target = self.folder / fmt.MASKS_DIR / f"{name}.png"
                target.parent.mkdir(exist_ok=True)
                cv2.imwrite(str(target), inside.astype(np.uint8) * 255)
                cam = replace(cam, fov=FieldOfView.mask(target, inside))
            cameras.append(cam)
        rig = Rig(tuple(cameras), meta.rig.T_cam0_cam, meta.rig.sigma_rotation_rad, meta.rig.sigma_translation_m)
        return replace(meta, camera=cameras[0], rig=rig)

    def _open_table(self, name: str, header) -> object:
        path = self.folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(path, "w", encoding="utf-8", newline="\n")
        fh.write(",".join(header) + "\n")
        fh.flush()
        return fh

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- appending ------------------------------------------------------------------------------------------
    def add_frame(self, frame: Frame) -> None:
        if self._last_frame_t is not None and frame.t_ns <= self._last_frame_t:
            raise SessionError(f"frame seq {frame.seq}: capture time {frame.t_ns} ns is not after the previous "
                               f"frame's {self._last_frame_t} ns; not recorded")
        rig = self.meta.rig
        if frame.n_cameras != len(rig):
            raise SessionError(f"frame seq {frame.seq} carries {frame.n_cameras} image(s) (Frame.views), the "
                               f"session's rig has {len(rig)} camera(s); record with the grabber's rig")
        for k, cam in enumerate(rig.cameras):
            image = frame.image_of(k)
            if image.shape[:2] != (cam.height, cam.width):
                which = "" if len(rig) == 1 else f"camera {k} ({self.meta.camera_names[k]}) of "
                raise SessionError(f"{which}frame seq {frame.seq} is {image.shape[1]}x{image.shape[0]}, the "
                                   f"session's camera is {cam.width}x{cam.height}")
        if self.version == 1:
            names = [f"{fmt.FRAMES_DIR}/{self.n_queued:06d}.png"]
            rows = f"{frame.seq},{frame.t_ns},{names[0]}\n"
        else:
            names = [f"{fmt.FRAMES_DIR}/{c}/{self.n_queued:06d}.png" for c in self.meta.camera_names]
            rows = "".join(f"{frame.seq},{frame.t_ns},{k},{name}\n" for k, name in enumerate(names))
        self.n_queued += 1
        self._last_frame_t = frame.t_ns
        while len(self._pending) >= 2 * self.workers:
            self._drain(block_on_oldest=True)
        futures = [self._pool.submit(self._encode, frame.image_of(k), frame.seq, self.folder / name)
                   for k, name in enumerate(names)]
        self._pending.append((futures, rows))
        self._drain()

    def _encode(self, image: np.ndarray, seq: int, final: Path) -> None:
        ok, buf = cv2.imencode(".png", image, self._png)
        if not ok:
            raise OutputError(f"cannot encode frame seq {seq} as PNG")
        tmp = final.with_name(final.name + ".tmp")
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())
        os.replace(tmp, final)

    def _drain(self, block_on_oldest: bool = False, all_: bool = False) -> None:
        """Append the rows of finished frames (every camera's image in place), oldest first, stopping at the
        first unfinished one."""
        wrote = False
        while self._pending and (all(f.done() for f in self._pending[0][0]) or block_on_oldest or all_):
            futures, rows = self._pending.popleft()
            for future in futures:
                future.result()  # re-raises an encoding or disk error here, in the recording thread
            self._tables["frames"].write(rows)  # one write: a frame's rows are appended together
            self.n_frames += 1
            wrote = True
            block_on_oldest = False
        if wrote:
            self._flush()

    def _add_joint_samples(self, samples: list[JointSample]) -> int:
        """Append the samples that are valid and newer than the last one; returns how many were skipped."""
        fh = self._tables["joints"]
        scale = self.meta.joint_scale
        skipped = 0
        for s in samples:
            q = np.asarray(s.q, float)
            why = self._joint_sample_fault(s.t_ns, q, scale.shape)
            if why:
                skipped += 1
                self.last_skipped_joints = why
                continue
            fh.write(f"{s.seq},{s.t_ns}," + ",".join(f"{v:.9g}" for v in q / scale) + "\n")
            self._last_joint_t = s.t_ns
            self.pose_times.append(int(s.t_ns))
            self.n_joints += 1
        return skipped

    def _joint_sample_fault(self, t_ns: int, q: np.ndarray, shape) -> str:
        if q.shape != shape:
            return f"{q.size} joint values, the session has {shape[0]} joints"
        bad = np.flatnonzero(~np.isfinite(q))
        if len(bad):
            return f"joint '{self.meta.joint_names[int(bad[0])]}' = {q[int(bad[0])]}"
        if self._last_joint_t is not None and t_ns <= self._last_joint_t:
            return f"time {t_ns} ns is not after the last recorded sample's {self._last_joint_t} ns"
        return ""

    def add_marker_samples(self, samples) -> int:
        """Append MarkerSamples (every tool's, with their quality fields: refusing is the pose source's job);
        a non-finite pose or a time not after the tool's last one is skipped. Returns how many were skipped."""
        fh = self._tables["markers"]
        scale = fmt.LENGTH_UNITS[self.meta.length_unit]
        skipped = 0
        for s in samples:
            T = np.asarray(s.T_tracker_marker, float)
            last = self._last_marker_t.get(s.tool)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not fmt.TOOL_NAME.fullmatch(s.tool):
                skipped += 1
                self.last_skipped_joints = f"tool '{s.tool}': not a finite 4x4 pose"
                continue
            if last is not None and s.t_ns <= last:
                skipped += 1
                self.last_skipped_joints = f"tool '{s.tool}': time {s.t_ns} ns is not after its last {last} ns"
                continue
            v = tum_values(T)
            v[:3] = [x / scale for x in v[:3]]
            fh.write(f"{s.t_ns},{s.tool}," + ",".join(f"{x:.9g}" for x in v)
                     + f",{float(s.rms_mm):.6g},{int(bool(s.in_volume))}\n")
            self._last_marker_t[s.tool] = s.t_ns
            self.n_markers += 1
            tracker = self.meta.tracker
            if s.tool == tracker.tool and s.in_volume and float(s.rms_mm) <= tracker.max_rms_mm:
                self.pose_times.append(int(s.t_ns))  # (one a replay refuses covers no frame)
        return skipped

    def add_joints(self, samples: list) -> int:
        """Append pose samples: joint readings, or in a marker_poses session the tracker's MarkerSamples (the
        live runtime's Record stage hands whatever its pose source polled here); returns how many were skipped."""
        if "markers" in self._tables:
            return self.add_marker_samples(samples)
        return self._add_joint_samples(samples)

    def add_event(self, t_ns: int, device: str, event: str, detail: str = "") -> None:
        """One row of events.csv: a device fault or health change noticed at session time ``t_ns``."""
        if "events" not in self._tables:
            self._tables["events"] = self._open_table(fmt.EVENTS_FILE, fmt.EVENT_COLUMNS)
        # the csv module quotes a detail that holds commas or quotes (RFC 4180)
        csv.writer(self._tables["events"], lineterminator="\n").writerow(
            [int(t_ns), device, event, " ".join(str(detail).split())])
        self.n_events += 1

    def set_health(self, health: dict) -> None:
        """The devices' fault counts for session.json's ``health`` (written when the session is closed)."""
        self.meta = replace(self.meta, health=dict(health))

    def add_camera_pose(self, t_ns: int, T_world_camera: np.ndarray) -> None:
        if self._last_pose_t is not None and t_ns <= self._last_pose_t:
            return
        self._tables["poses"].write(self._pose_row(t_ns, T_world_camera))
        self._last_pose_t = t_ns
        self.n_poses += 1
        self.pose_times.append(int(t_ns))

    def add_true_pose(self, t_ns: int, T_world_camera: np.ndarray) -> None:
        if "truth" not in self._tables:
            self._tables["truth"] = self._open_table(fmt.TRUTH_POSES_FILE, fmt.POSE_COLUMNS)
        if self._last_truth_t is not None and t_ns <= self._last_truth_t:
            return
        self._tables["truth"].write(self._pose_row(t_ns, T_world_camera))
        self._last_truth_t = t_ns
        self.n_truth += 1

    def _pose_row(self, t_ns: int, T: np.ndarray) -> str:
        v = tum_values(T)
        scale = fmt.LENGTH_UNITS[self.meta.length_unit]
        v[:3] = [x / scale for x in v[:3]]
        return f"{t_ns}," + ",".join(f"{x:.9g}" for x in v) + "\n"

    def set_truth_surface(self, mesh) -> None:
        path = self.folder / fmt.TRUTH_SURFACE_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name("surface.tmp.ply")
        mesh.scale(1.0 / fmt.LENGTH_UNITS[self.meta.length_unit]).save(str(tmp), binary=True)
        os.replace(tmp, path)

    def _flush(self) -> None:
        for fh in self._tables.values():
            fh.flush()
        if self._fsync_every and self.n_frames % self._fsync_every == 0:
            for fh in self._tables.values():
                os.fsync(fh.fileno())

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._drain(all_=True)
        finally:
            self._pool.shutdown(wait=True)
        for fh in self._tables.values():
            fh.flush()
            os.fsync(fh.fileno())
            fh.close()
        counts = {"frames": self.n_frames, "joint_samples": self.n_joints, "camera_poses": self.n_poses,
                  **({"marker_poses": self.n_markers} if "markers" in self._tables else {}),
                  "true_camera_poses": self.n_truth, "events": self.n_events}
        self.meta = replace(self.meta, complete=True, counts=counts)
        _write_json_atomic(self.folder / fmt.META_FILE, self.meta.to_json(self.folder))
