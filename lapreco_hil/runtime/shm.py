"""Shared memory between the tracking thread and the mapper process: a ring of observation slots (tracks and
pose prior of one frame each) and a snapshot of the map (landmarks) for the live surface. Only small control
messages (slot numbers, refined poses) go through multiprocessing queues.

Segments are named ``lapreco_<owner pid>_<random>``: a run killed outright (kill -9, out of memory) cannot
unlink its own, and multiprocessing's resource tracker may have been killed with it, so the next run
unlinks every such segment whose owner process is gone (``unlink_leftovers``)."""

from __future__ import annotations

import logging
import os
import secrets
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np

from lapreco_hil.types import Observations, PosePrior

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
    HEADER = 4  # seq, t_ns, n tracks, arrival (monotonic ns)
    PRIOR = 16 + 36  # T_world_camera, covariance

    def __init__(self, slots: int, max_tracks: int, name: str | None = None) -> None:
        self.slots, self.max_tracks = slots, max_tracks
        self._slot_bytes = 8 * self.HEADER + 8 * self.PRIOR + 8 * max_tracks + 16 * max_tracks + 3 * max_tracks
        self._slot_bytes = (self._slot_bytes + 63) // 64 * 64
        size = self._slot_bytes * slots
        self.shm = _segment(name, size)
        self.owner = name is None

    @property
    def name(self) -> str:
        return self.shm.name

    def _views(self, slot: int):
        off = slot * self._slot_bytes
        buf, m = self.shm.buf, self.max_tracks
        header = np.ndarray((self.HEADER,), np.int64, buf, off)
        off += 8 * self.HEADER
        prior = np.ndarray((self.PRIOR,), np.float64, buf, off)
        off += 8 * self.PRIOR
        ids = np.ndarray((m,), np.int64, buf, off)
        off += 8 * m
        uv = np.ndarray((m, 2), np.float64, buf, off)
        off += 16 * m
        colors = np.ndarray((m, 3), np.uint8, buf, off)
        return header, prior, ids, uv, colors

    def write(self, slot: int, obs: Observations, prior: PosePrior, arrival_ns: int) -> int:
        """Copies the observation into the slot (the strongest ``max_tracks`` if there are more)."""
        header, pr, ids, uv, colors = self._views(slot)
        n = min(len(obs), self.max_tracks)
        header[:] = (obs.frame_seq, obs.t_ns, n, arrival_ns)
        pr[:16] = prior.T_world_camera.ravel()
        pr[16:] = prior.cov.ravel()
        ids[:n], uv[:n], colors[:n] = obs.track_ids[:n], obs.uv[:n], obs.colors[:n]
        return n

    def read(self, slot: int) -> tuple[Observations, PosePrior, int]:
        header, pr, ids, uv, colors = self._views(slot)
        seq, t_ns, n, arrival = (int(v) for v in header)
        obs = Observations(seq, t_ns, ids[:n].copy(), uv[:n].copy(), colors[:n].copy())
        prior = PosePrior(pr[:16].reshape(4, 4).copy(), pr[16:].reshape(6, 6).copy(), t_ns)
        return obs, prior, arrival

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
