"""The mapper in its own process. GTSAM's optimiser holds the GIL for the whole solve (measured: a Python
thread runs at a few per cent of its speed during one; docs/benchmarks.md), so a local BA in a thread would
stall capture and tracking for its duration. Observations arrive through shared memory (ObservationRing),
slot numbers and refined poses through queues; the final map goes back through a pipe."""

from __future__ import annotations

import logging
import queue
import time
import traceback

import numpy as np

log = logging.getLogger(__name__)


def mapper_main(ring_name: str, ring_slots: int, max_tracks: int, snap_name: str, max_points: int, snap_lock,
                K: np.ndarray, mapper_config, backlog_skip_ba: int, ready_q, done_q, final_conn) -> None:
    """Process body: take slots until a None arrives, then finish the map and send it (or the error)."""
    import signal

    from ..mapping.mapper import Mapper
    from .shm import MapSnapshot, ObservationRing

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle: it ends the run cleanly
    ring = ObservationRing(ring_slots, max_tracks, name=ring_name)
    snapshot = MapSnapshot(max_points, snap_lock, name=snap_name)
    try:
        mapper = Mapper(K, mapper_config)
        skipped_ba = skipped_resection = 0
        while True:
            slot = ready_q.get()
            if slot is None:
                break
            obs, prior, arrival_ns = ring.read(slot)
            done_q.put(("free", slot))
            try:
                backlog = ready_q.qsize()
            except NotImplementedError:  # macOS has no qsize; never skip there
                backlog = 0
            run_ba = backlog <= backlog_skip_ba
            resect = backlog == 0  # behind: a frame between keyframes takes its corrected prior for now
            is_kf = mapper.add(obs, prior, local_ba=run_ba, resect=resect)
            if is_kf and not run_ba:
                skipped_ba += 1
            if not is_kf and not resect:
                skipped_resection += 1
            if is_kf:
                points, colors = mapper.map_points()
                if len(points):
                    snapshot.publish(points, colors)
            done_q.put(("pose", obs.frame_seq, time.monotonic_ns(), arrival_ns,
                        mapper.frames[-1].T_refined, bool(is_kf), skipped_ba, skipped_resection))
        t0 = time.perf_counter()
        result = mapper.finish()
        result.stats["final_ba_wall_s"] = time.perf_counter() - t0
        result.stats["local_ba_skipped"] = skipped_ba
        result.stats["resection_skipped"] = skipped_resection
        final_conn.send(("ok", result))
    except BaseException:  # reported to the main loop, never lost with the process
        final_conn.send(("error", traceback.format_exc()))
    finally:
        ring.close()
        snapshot.close()
        final_conn.close()


def drain(q) -> list:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out
