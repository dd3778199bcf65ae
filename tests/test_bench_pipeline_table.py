"""The live pipeline bench's table: a local BA that failed in the worker is said, not hidden in the JSON."""

from lapreco_hil.bench.pipeline import format_table


def _result(failed: int) -> dict:
    return {"resolution": "1920x1080", "fps_target": 60.0, "seconds": 120.0, "device": "cuda:0", "tracker": "warp",
            "source": "replay", "machine": "x", "sustained_fps": 60.0,
            "frames": {"in": 7200, "processed": 7200, "dropped": 0, "dropped_source": 0, "dropped_capture": 0,
                       "mapper_skipped": 0},
            "latency_ms": {"p50": 11.0, "p95": 31.0, "p99": 50.0},
            "live": {"local_ba_skipped": 30, "local_ba_deferred_share": 0.04, "resection_skipped": 90,
                     "final_ba_s": 8.4, "final_global_ba_s": 4.2, "local_ba_worker_runs": 700,
                     "local_ba_worker_failed": failed}}


def test_the_table_names_failed_worker_windows():
    assert "failed in the worker in 12 of 712 windows" in format_table(_result(12))


def test_no_failure_line_without_failures():
    table = format_table(_result(0))
    assert "failed" not in table
    assert "| 60.0 | 7200 | 7200 | 0 (0 / 0 / 0) | 11 / 31 / 50 | 30 (4.0%) | 90 | 8.4 (4.2) |" in table
