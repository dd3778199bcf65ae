"""Shared memory between the tracking thread and the mapper process: a ring of observation slots (tracks and
pose prior of one frame each) and a snapshot of the map (landmarks) for the live surface. Only small control
messages (slot numbers, refined poses) go through multiprocessing queues."""

from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np

from ..types import Observations, PosePrior


class ObservationRing:
    HEADER = 4  # seq, t_ns, n tracks, arrival (monotonic ns)
    PRIOR = 16 + 36  # T_world_camera, covariance

    def __init__(self, slots: int, max_tracks: int, name: str | None = None) -> None:
        self.slots, self.max_tracks = slots, max_tracks
        self._slot_bytes = 8 * self.HEADER + 8 * self.PRIOR + 8 * max_tracks + 16 * max_tracks + 3 * max_tracks
        self._slot_bytes = (self._slot_bytes + 63) // 64 * 64
        size = self._slot_bytes * slots
        self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=size)
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
        self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=size)
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
        header = getattr(self, "_header", None)
        return int(header[1]) if header is not None else 0

    def read(self) -> tuple[int, np.ndarray, np.ndarray]:
        with self.lock:
            version, n = int(self._header[0]), int(self._header[1])
            return version, self._points[:n].copy(), self._colors[:n].copy()

    def close(self) -> None:
        # views into the buffer must go before the mapping can be closed
        del self._header, self._points, self._colors
        self.shm.close()
        if self.owner:
            self.shm.unlink()
