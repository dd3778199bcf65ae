"""The live run's start: capture waits for the mapper and the local-BA worker to say they are ready, and a worker
that cannot start is reported at once instead of after the start's timeout."""

import queue

import numpy as np

from lapreco_hil.config import MapperConfig, PipelineConfig, RuntimeConfig
from lapreco_hil.runtime.processes import MapperProcesses

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
SMALL = RuntimeConfig(mapper_slots=4, max_tracks=64, max_landmarks=256)


def _processes(ba_device: str) -> MapperProcesses:
    config = PipelineConfig(mapper=MapperConfig(ba_solver="schur", ba_device=ba_device), runtime=SMALL)
    return MapperProcesses(K, config, use_ba_worker=True)


def _end(procs: MapperProcesses) -> None:
    if procs.dead() is None:
        procs.finish(timeout_s=60)
    procs.stop()
    procs.close()


def test_the_start_waits_for_the_ba_worker_as_for_the_mapper():
    procs = _processes("cpu")
    procs.start()
    try:
        assert procs.wait_ready(300.0) is True
        # both ready messages were taken by the start: none is left for the results reader
        assert procs.dead() is None
        try:
            stray = procs.done_q.get(timeout=1.0)
        except queue.Empty:
            stray = None
        assert stray is None, f"left on the results queue after the start: {stray!r}"
    finally:
        _end(procs)


def test_a_ba_worker_that_cannot_start_ends_the_wait_and_is_named():
    procs = _processes("cuda:99")  # no machine here has a hundredth GPU: the worker's kernel load fails
    procs.start()
    try:
        assert procs.wait_ready(300.0) is False
        assert "local BA worker" in (procs.dead() or "")
    finally:
        _end(procs)
