"""Shared memory between the tracking thread and the mapper process: a ring of observation slots (the tracks
each camera of the rig saw and the pose prior, one frame each) and a snapshot of the map (landmarks) for the live
surface. Only small control messages (slot numbers, refined poses) go through multiprocessing queues.

Segments are named ``lapreco_<owner pid>_<random>``: a run killed outright (kill -9, out of memory) cannot
unlink its own, and multiprocessing's resource tracker may have been killed with it, so the next run
unlinks every such segment whose owner process is gone (``unlink_leftovers``)."""

from __future__ import annotations

import logging
import os
import secrets
from multiprocessing import shared_memory
from pathlib import Path
from typing import Sequence

import numpy as np

from lapreco_hil.types import FUNNEL_STAGES, Observations, PosePrior

log = logging.getLogger(__name__)
PREFIX = "lapreco_"
SHM_DIR = Path("/dev/shm")  # where POSIX shared memory shows as files (Linux)


def new_segment_name(owner_pid: int | None = None) -> str:
    return f"{PREFIX}{owner_pid or os.getpid()}_{secrets.token_hex(4)}"


def owner_pid(name: str) -> int | None:
    """The owner pid in a segment name made by ``new_segment_name`` (None for any other name)."""
    parts = name.lstrip("/").split("_")
    if len(parts) != 3 or parts[0] + "_" != PREFIX or not parts[1].isdigit():
        return None
    return int(parts[1])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def unlink_leftovers(shm_dir: Path = SHM_DIR) -> list[str]:
    """Unlink the segments of runs whose owner process is gone; returns their names. Where shared memory is
    not visible as files (macOS) there is nothing to list, and nothing is done."""
    try:
        entries = list(shm_dir.iterdir())
    except OSError:
        return []
    removed = []
    for entry in entries:
        pid = owner_pid(entry.name)
        if pid is None or _alive(pid):
            continue
        try:
            entry.unlink()
        except FileNotFoundError:  # another run's start took it meanwhile
            continue
        except OSError as exc:
            log.warning("could not remove the shared memory '%s' left by process %d: %s", entry, pid, exc)
            continue
        removed.append(entry.name)
    if removed:
        log.info("removed %d shared-memory segments left by killed runs", len(removed))
    return removed


def _segment(name: str | None, size: int) -> shared_memory.SharedMemory:
    return shared_memory.SharedMemory(name=name or new_segment_name(), create=name is None, size=size)


class ObservationRing:
    """Slots of one frame each: its pose prior and what the front-end saw in each camera of the rig (camera 0's
    observations, then a stereo partner's, found in ``Frame.views``), sized at start for the rig's ``cameras``.
    A slot keeps, per camera, the tracks (the strongest ``max_tracks``), the new-track count and the funnel."""

    HEADER = 4  # seq, t_ns, cameras written, arrival (monotonic ns)
    PRIOR = 16 + 36  # T_world_camera, covariance
    VIEW_HEADER = 3 + len(FUNNEL_STAGES)  # camera index, n tracks, n new, the funnel's counts

    def __init__(self, slots: int, max_tracks: int, name: str | None = None, cameras: int = 1) -> None:
        if cameras < 1:
            raise ValueError("an observation ring needs at least one camera")
        self.slots, self.max_tracks, self.cameras = slots, max_tracks, cameras
        self._view_bytes = 8 * self.VIEW_HEADER + 8 * max_tracks + 16 * max_tracks + 3 * max_tracks
        self._view_bytes = (self._view_bytes + 7) // 8 * 8
        self._slot_bytes = 8 * self.HEADER + 8 * self.PRIOR + cameras * self._view_bytes
        self._slot_bytes = (self._slot_bytes + 63) // 64 * 64
        size = self._slot_bytes * slots
        self.shm = _segment(name, size)
        self.owner = name is None

    @property
    def name(self) -> str:
        return self.shm.name

    def _header(self, slot: int):
        off = slot * self._slot_bytes
        buf = self.shm.buf
        header = np.ndarray((self.HEADER,), np.int64, buf, off)
        prior = np.ndarray((self.PRIOR,), np.float64, buf, off + 8 * self.HEADER)
        return header, prior

    def _view(self, slot: int, camera: int):
        off = slot * self._slot_bytes + 8 * self.HEADER + 8 * self.PRIOR + camera * self._view_bytes
        buf, m = self.shm.buf, self.max_tracks
        head = np.ndarray((self.VIEW_HEADER,), np.int64, buf, off)
        off += 8 * self.VIEW_HEADER
        ids = np.ndarray((m,), np.int64, buf, off)
        off += 8 * m
        uv = np.ndarray((m, 2), np.float64, buf, off)
        off += 16 * m
        colors = np.ndarray((m, 3), np.uint8, buf, off)
        return head, ids, uv, colors

    def _write_view(self, slot: int, k: int, obs: Observations) -> int:
        head, ids, uv, colors = self._view(slot, k)
        n = min(len(obs), self.max_tracks)
        head[:3] = (obs.camera, n, obs.n_new)
        head[3:] = [obs.funnel.get(stage, 0) for stage in FUNNEL_STAGES]
        ids[:n], uv[:n], colors[:n] = obs.track_ids[:n], obs.uv[:n], obs.colors[:n]
        return n

    def _read_view(self, slot: int, k: int, seq: int, t_ns: int) -> Observations:
        head, ids, uv, colors = self._view(slot, k)
        camera, n, n_new = (int(v) for v in head[:3])
        funnel = {stage: int(v) for stage, v in zip(FUNNEL_STAGES, head[3:]) if v}
        return Observations(seq, t_ns, ids[:n].copy(), uv[:n].copy(), colors[:n].copy(), n_new=n_new,
                            camera=camera, funnel=funnel)

    def write(self, slot: int, obs: Observations, prior: PosePrior, arrival_ns: int,
              views: Sequence[Observations] = ()) -> int:
        """Copies camera 0's observations (the strongest ``max_tracks`` if there are more) and those of the
        rig's other cameras in the same frame (``views``) into the slot; returns camera 0's count."""
        if 1 + len(views) > self.cameras:
            raise ValueError(f"a frame with {1 + len(views)} cameras' observations; the ring was sized for "
                             f"{self.cameras}")
        header, pr = self._header(slot)
        header[:] = (obs.frame_seq, obs.t_ns, 1 + len(views), arrival_ns)
        pr[:16] = prior.T_world_camera.ravel()
        pr[16:] = prior.cov.ravel()
        n = self._write_view(slot, 0, obs)
        for k, view in enumerate(views, start=1):
            self._write_view(slot, k, view)
        return n

    def read(self, slot: int) -> tuple[Observations, PosePrior, int]:
        """Camera 0's observations, the pose prior, the frame's arrival time."""
        header, pr = self._header(slot)
        seq, t_ns, _, arrival = (int(v) for v in header)
        prior = PosePrior(pr[:16].reshape(4, 4).copy(), pr[16:].reshape(6, 6).copy(), t_ns)
        return self._read_view(slot, 0, seq, t_ns), prior, arrival

    def read_views(self, slot: int) -> tuple[Observations, ...]:
        """The observations of the rig's other cameras written with the slot's frame (none for a mono one)."""
        header, _ = self._header(slot)
        seq, t_ns, written = int(header[0]), int(header[1]), int(header[2])
        return tuple(self._read_view(slot, k, seq, t_ns) for k in range(1, written))

    def close(self) -> None:
        self.shm.close()
        if self.owner:
            self.shm.unlink()


class MapSnapshot:
    """The mapper's landmarks as of its last keyframe, for the live surface; a version counter says when it
    changed. Written by the mapper process only, under the lock given to both sides."""

    def __init__(self, max_points: int, lock, name: str | None = None) -> None:
        self.max_points = max_points
        self.lock = lock
        size = 16 + 24 * max_points + 3 * max_points
        self.shm = _segment(name, size)
        self.owner = name is None
        self._header = np.ndarray((2,), np.int64, self.shm.buf, 0)
        self._points = np.ndarray((max_points, 3), np.float64, self.shm.buf, 16)
        self._colors = np.ndarray((max_points, 3), np.uint8, self.shm.buf, 16 + 24 * max_points)
        if self.owner:
            self._header[:] = 0

    @property
    def name(self) -> str:
        return self.shm.name

    def publish(self, points: np.ndarray, colors: np.ndarray) -> None:
        n = min(len(points), self.max_points)
        with self.lock:  # over capacity, the newest points (the active map comes last) are kept
            self._points[:n] = points[len(points) - n:]
            self._colors[:n] = colors[len(colors) - n:]
            self._header[1] = n
            self._header[0] += 1

    def size(self) -> int:
        """Points in the snapshot now (0 once closed)."""
        header = self._header
        return int(header[1]) if header is not None else 0

    def read(self) -> tuple[int, np.ndarray, np.ndarray]:
        with self.lock:
            version, n = int(self._header[0]), int(self._header[1])
            return version, self._points[:n].copy(), self._colors[:n].copy()

    def close(self) -> None:
        # views into the buffer must go before the mapping can be closed
        self._header = self._points = self._colors = None
        self.shm.close()
        if self.owner:
            self.shm.unlink()
