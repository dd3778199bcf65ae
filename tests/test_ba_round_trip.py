"""The live local BA's round trip as the mapper sees it: each job timed from its submission to its collection,
leg by leg (to the worker, solved, its answer waiting), and the keyframes that came while it was out."""

from __future__ import annotations

import queue
import time

import pytest

from lapreco_hil.runtime.mapper_process import StageClock, _BAClient, round_trip_summary
from lapreco_hil.runtime.messages import BAJob, BAResult


class AppliedLog:
    """The mapper's side of ``collect``: what was applied, in order."""

    def __init__(self) -> None:
        self.applied = []

    def apply_local_ba(self, problem, solved, ticket) -> None:
        self.applied.append((problem, solved, ticket))


def _answer(client: _BAClient, results: queue.Queue, to_worker_ms: float, solve_ms: float, error: str = "") -> None:
    """The worker's answer to the job in flight, stamped as if it took it ``to_worker_ms`` after submission."""
    job_id, _, _, submitted_ns = client.in_flight
    started = submitted_ns + int(to_worker_ms * 1e6)
    done = started + int(solve_ms * 1e6)
    while time.monotonic_ns() < done:  # (the answer cannot be collected before it exists)
        time.sleep(0.001)
    results.put(BAResult(job_id, None if error else "solved", error, solve_ms * 1e-3, started, done))


def test_a_job_is_timed_from_submission_to_collection_and_counts_the_keyframes_meanwhile():
    jobs, results = queue.Queue(), queue.Queue()
    clock = StageClock()
    client, mapper = _BAClient(jobs, results, clock), AppliedLog()
    client.keyframe_added()  # nothing out yet: not a keyframe that waited for a job
    assert not client.result_ready() and not client.collect(mapper)
    client.submit(("problem 0", {"last_kf": 3}))
    assert isinstance(jobs.get_nowait(), BAJob)
    for _ in range(3):
        client.keyframe_added()
    assert not client.result_ready() and not client.collect(mapper)  # still out
    _answer(client, results, to_worker_ms=2.0, solve_ms=10.0)
    time.sleep(0.005)  # the answer waits for the mapper
    assert client.result_ready()
    assert client.collect(mapper)
    assert mapper.applied == [("problem 0", "solved", {"last_kf": 3})]
    assert client.in_flight is None and client.runs == 1 and client.keyframes_per_flight == [3]
    s = {k: v[0] for k, v in clock.samples.items()}
    assert s["local_ba_to_worker"] == pytest.approx(2.0)
    assert s["local_ba_result_waited"] >= 5.0
    # the legs make up the whole flight (one clock for both processes)
    assert s["local_ba_in_flight"] == pytest.approx(s["local_ba_to_worker"] + 10.0 + s["local_ba_result_waited"],
                                                    abs=1e-6)
    # the next job counts its own keyframes; a failed one is timed and counted, and applies nothing
    client.submit(("problem 1", {"last_kf": 7}))
    _answer(client, results, to_worker_ms=1.0, solve_ms=3.0, error="Traceback: singular")
    assert client.collect(mapper)
    assert client.failed == 1 and len(mapper.applied) == 1 and client.keyframes_per_flight == [3, 0]
    assert len(clock.samples["local_ba_in_flight"]) == 2


def test_the_round_trip_summary_sets_flights_against_keyframe_gaps():
    summary = round_trip_summary([0, 1, 3, 2], [100.0, 120.0, 140.0], [60.0, 90.0, 300.0, 150.0])
    assert summary["jobs"] == 4
    assert summary["keyframes_while_in_flight"] == {"mean": 1.5, "max": 3, "jobs_with_two_or_more": 2}
    assert summary["keyframe_gap_ms_mean"] == pytest.approx(120.0)
    assert summary["in_flight_ms_mean"] == pytest.approx(150.0)
    assert summary["in_flight_over_keyframe_gap"] == pytest.approx(1.25)
    empty = round_trip_summary([], [], [])
    assert empty["jobs"] == 0 and empty["in_flight_over_keyframe_gap"] is None
