"""``lapreco bench pipeline`` (run by lapreco_hil.app.bench): the full live runtime on a simulated source in
real time, reporting sustained frame rate, drops and end-to-end latency percentiles.

Source: a session recorded first (or one given with --session) and replayed in real time from disk, paced to
its frame rate, late frames lost as from a real grabber. The simulated world rendered live (--source sim) is
the other choice, but its ray caster shares the machine with the pipeline: at 1080p60 on the H100 machine it
delivered 25 frames a second (docs/benchmarks.md)."""

from __future__ import annotations

from dataclasses import replace

from lapreco_hil.config import PipelineConfig


def bench_config(features: int, surface: str = "auto", config: PipelineConfig | None = None) -> PipelineConfig:
    """``config`` (the defaults) with ``features`` tracked and the ``[surface] mode``. The final global BA after
    capture stops is timed apart from the live figures (report.json ``live.final_ba_s``)."""
    config = config or PipelineConfig()
    return replace(config, tracker=replace(config.tracker, max_features=features),
                   surface=replace(config.surface, mode=surface))


def _seconds(s) -> str:
    return "-" if s is None else f"{s:.1f}"


def format_table(r: dict) -> str:
    f, lat = r["frames"], r["latency_ms"]
    failed = r["live"].get("local_ba_worker_failed", 0)
    warning = ([f"local BA failed in the worker in {failed} of {failed + r['live'].get('local_ba_worker_runs', 0)} "
                "windows (not applied; the mapper's log has each error)"] if failed else [])
    return "\n".join([
        f"live pipeline, {r['resolution']} at {r['fps_target']:g} fps for {r['seconds']:g} s ({r['device']}, "
        f"{r['tracker']} tracker, {r['source']} source, {r['machine']})",
        "| sustained fps | frames in | mapped | dropped (source / capture / mapper) | latency p50 / p95 / p99 ms "
        "| keyframes' BA deferred | resection deferred | map's end s (its global BA s) |",
        "|---|---|---|---|---|---|---|---|",
        f"| {r['sustained_fps']:.1f} | {f['in']} | {f['processed']} | {f['dropped']} ({f['dropped_source']} / "
        f"{f['dropped_capture']} / {f['mapper_skipped']}) | {lat.get('p50', 0):.0f} / {lat.get('p95', 0):.0f} / "
        f"{lat.get('p99', 0):.0f} | {r['live'].get('local_ba_skipped', 0)} "
        f"({r['live'].get('local_ba_deferred_share', 0):.1%}) | {r['live'].get('resection_skipped', 0)} | "
        f"{_seconds(r['live'].get('final_ba_s'))} ({_seconds(r['live'].get('final_global_ba_s'))}) |",
    ] + warning)
