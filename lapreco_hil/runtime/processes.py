"""The mapper process and its optional local-BA worker, seen from the main process: shared memory made,
processes spawned, start-up awaited, liveness watched, the final map asked for, everything stopped and
unlinked. Spawned (not forked: the main process has CUDA and GUI threads), and told to die with the main
process (mapper_process.die_with_parent), so a kill -9 of the run leaves no mapper behind; the shared memory of
an earlier run that was killed outright is unlinked at start (shm.unlink_leftovers)."""

from __future__ import annotations

import collections
import logging
import multiprocessing as mp
import os
import queue
import threading
import time

from lapreco_hil.mapping.mapper import local_schedule
from lapreco_hil.runtime.mapper_process import ba_worker_main, drain, mapper_main
from lapreco_hil.runtime.messages import (BAWorkerReady, EndOfFrames, EndOfJobs, EndOfResults, FinalMap,
                                          MapperFailed, MapperReady, SlotReady)
from lapreco_hil.runtime.shm import MapSnapshot, ObservationRing, unlink_leftovers

log = logging.getLogger(__name__)


class MapperProcesses:
    def __init__(self, K, config, *, use_ba_worker: bool, cameras: int = 1, rig=None,
                 keyframe_poses: bool = False) -> None:
        self.K, self.config, self.rt = K, config, config.runtime
        self.use_ba_worker = use_ba_worker
        self.cameras = cameras  # the rig's cameras: each frame's slot holds the observations of each
        self.rig = rig  # a stereo scope's rig: the mapper ties each keyframe's partner views to it
        self.keyframe_poses = keyframe_poses  # the mapper sends keyframe poses after each local BA (dense surface)
        self.ring: ObservationRing | None = None
        self.snapshot: MapSnapshot | None = None
        self.mapper: mp.Process | None = None
        self.ba_worker: mp.Process | None = None
        self.ready_q = self.done_q = self.ba_jobs = self.ba_results = None
        self._final_recv = None
        # slots of the ring the mapper has handed back; taken by tracking, returned through SlotFree
        self.free_slots: collections.deque = collections.deque(range(self.rt.mapper_slots))
        self._submit_lock = threading.Lock()  # tracking and the shutdown both write to the mapper's queue

    @property
    def mapper_pid(self) -> int | None:
        return self.mapper.pid if self.mapper is not None else None

    @property
    def slots_in_use(self) -> int:
        return self.rt.mapper_slots - len(self.free_slots)

    def start(self) -> None:
        unlink_leftovers()
        ctx = mp.get_context("spawn")
        rt = self.rt
        self.ring = ObservationRing(rt.mapper_slots, rt.max_tracks, cameras=self.cameras)
        snap_lock = ctx.Lock()
        self.snapshot = MapSnapshot(rt.max_landmarks, snap_lock)
        self._final_recv, send = ctx.Pipe(duplex=False)
        parent = os.getpid()
        self.ready_q, self.done_q = ctx.Queue(), ctx.Queue()
        if self.use_ba_worker:
            self.ba_jobs, self.ba_results = ctx.Queue(), ctx.Queue()
            self.ba_worker = ctx.Process(target=ba_worker_main, name="lapreco local BA", daemon=True,
                                         args=(local_schedule(self.config.mapper), self.ba_jobs, self.ba_results,
                                               parent, self.config.mapper),
                                         kwargs={"ready_q": self.done_q})
            self.ba_worker.start()
        self.mapper = ctx.Process(
            target=mapper_main, name="lapreco mapper", daemon=True,
            args=(self.ring.name, rt.mapper_slots, rt.max_tracks, self.snapshot.name, rt.max_landmarks, snap_lock,
                  self.K, self.config.mapper, rt.mapper_backlog_skip_ba, self.ready_q, self.done_q, send, parent,
                  self.ba_jobs, self.ba_results), kwargs={"ring_cameras": self.cameras, "rig": self.rig,
                                                        "keyframe_poses": self.keyframe_poses})
        self.mapper.start()
        send.close()  # the mapper holds the sending end; a dead mapper then reads as EOF here

    def wait_ready(self, timeout_s: float) -> bool:
        """Until the mapper, and the BA worker if there is one, say they are up: the worker's first window would
        otherwise wait for its kernels' compile (seconds on a cold cache) while keyframes pile up and their BA is
        deferred. False when one died or the time passed (the watch then reports a death). A KeyboardInterrupt
        goes to the caller."""
        waiting = {MapperReady} | ({BAWorkerReady} if self.ba_worker is not None else set())
        deadline = time.monotonic() + timeout_s
        while waiting and time.monotonic() < deadline and self.dead() is None:
            try:
                waiting.discard(type(self.done_q.get(timeout=0.5)))
            except queue.Empty:
                continue
        if waiting:
            log.warning("capture starts before the %s said it was ready",
                        " and ".join(sorted("mapper" if w is MapperReady else "local BA worker" for w in waiting)))
        return not waiting

    def submit(self, obs, prior, arrival_ns: int, views=()) -> bool:
        """Hand one frame's observations to the mapper (camera 0's, and ``views``: those of the rig's other
        cameras); False when no slot is free (the mapper is a whole ring behind)."""
        try:
            slot = self.free_slots.popleft()
        except IndexError:
            return False
        self.ring.write(slot, obs, prior, arrival_ns, views)
        with self._submit_lock:
            self.ready_q.put(SlotReady(slot))
        return True

    def slot_freed(self, slot: int) -> None:
        self.free_slots.append(slot)

    def dead(self) -> str | None:
        """Which process has died, with its exit code, or None while both live."""
        if not self.mapper.is_alive():
            return f"the mapper process exited (code {self.mapper.exitcode})"
        if self.ba_worker is not None and not self.ba_worker.is_alive():
            return f"the local BA worker process exited (code {self.ba_worker.exitcode})"
        return None

    def last_word(self, timeout_s: float = 1.0) -> FinalMap | MapperFailed | None:
        """What a mapper that ended sent on its pipe (its error), if anything."""
        try:
            return self._final_recv.recv() if self._final_recv.poll(timeout_s) else None
        except EOFError:
            return None

    def finish(self, timeout_s: float = 3600.0) -> tuple[FinalMap | MapperFailed | None, str | None]:
        """Ask the mapper for its final map; (its answer, or None with the reason). A mapper or BA worker killed
        meanwhile (out of memory) is reported at once, not after the timeout."""
        with self._submit_lock:
            self.ready_q.put(EndOfFrames())
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._final_recv.poll(0.5):
                word = self.last_word(0)
                if word is not None:
                    return word, None
                self.mapper.join(timeout=5.0)  # the pipe's end: the mapper is gone without a word
                return None, self._death_note()
            if not self.mapper.is_alive() or (self.ba_worker is not None and not self.ba_worker.is_alive()):
                word = self.last_word(0.5)
                return (word, None) if word is not None else (None, self._death_note())
        return None, f"no final map from the mapper after {timeout_s:.0f} s"

    def _death_note(self) -> str:
        dead, code = ("mapper", self.mapper.exitcode) if not self.mapper.is_alive() else \
            ("local BA worker", self.ba_worker.exitcode)
        hint = " (killed: out of memory?)" if code == -9 else ""
        return f"the {dead} process died while the final map was made (exit code {code}){hint}"

    def stop(self) -> None:
        """Both processes ended (asked, then terminated); called after ``finish`` or on a dead mapper."""
        if self.mapper is not None and self.mapper.pid is not None:  # (started)
            self.mapper.join(timeout=10.0)
            if self.mapper.is_alive():
                self.mapper.terminate()
        if self.ba_worker is not None and self.ba_worker.pid is not None:
            self.ba_jobs.put(EndOfJobs())
            self.ba_worker.join(timeout=10.0)
            if self.ba_worker.is_alive():
                self.ba_worker.terminate()

    def end_results(self) -> None:
        """Ends the results reader (after the mapper's last message)."""
        self.done_q.put(EndOfResults())

    def close(self) -> None:
        """Shared memory unmapped and unlinked."""
        if self.ready_q is not None:
            drain(self.ready_q)
        if self.ring is not None:
            self.ring.close()
        if self.snapshot is not None:
            self.snapshot.close()
