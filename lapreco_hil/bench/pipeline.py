"""``lapreco bench pipeline``: the full live runtime on a simulated source in real time, reporting sustained
frame rate, drops and end-to-end latency percentiles.

Source: a session recorded first (or one given with --session) and replayed in real time from disk, paced to
its frame rate, late frames lost as from a real grabber. The simulated world rendered live (--source sim) is
the other choice, but its ray caster shares the machine with the pipeline: at 1080p60 on the H100 machine it
delivered 25 frames a second (docs/benchmarks.md)."""

from __future__ import annotations

import platform
import tempfile
from dataclasses import replace
from pathlib import Path


def run(device: str, resolution: tuple[int, int], fps: float, seconds: float, features: int, source: str = "auto",
        tracker: str = "auto", scene: str = "skull", session: str | None = None) -> dict:
    from ..cli.main import main as cli_main
    from ..cli.run import run_live
    from ..config import PipelineConfig
    from ..errors import ReconstructionError
    from ..frontend import resolve_tracker
    from ..registry import DeviceContext, open_grabber, open_robot

    w, h = resolution
    tracker = resolve_tracker(tracker, device)
    if source == "auto" or session is not None:
        source = "replay"
    config = PipelineConfig()
    # the final global BA after capture stops is not part of the live figures (and at 2000 tracks over
    # hundreds of keyframes it takes minutes): inliers are labelled from the residuals instead
    config = replace(config, tracker=replace(config.tracker, max_features=features),
                     mapper=replace(config.mapper, final_global_ba=False))
    frames = int(round(fps * seconds))
    with tempfile.TemporaryDirectory() as tmp:
        ctx = DeviceContext(device=device)
        if source == "replay":
            if session is None:
                session = Path(tmp) / "session"
                status = cli_main(["sim-record", "--scene", scene, "--resolution", f"{w}x{h}", "--fps", str(fps),
                                   "--frames", str(frames), "--device", device, "--no-progress", "--out", str(session)])
                if status != 0:
                    raise ReconstructionError(f"bench pipeline: recording the {scene} session failed "
                                              f"(status {status})")
            url = f"replay://{session}?pace=realtime"
            robot, grabber = open_robot(url, ctx), open_grabber(url, ctx)
            # (a given session sets the figures' resolution, rate and length)
            w, h = grabber.camera.width, grabber.camera.height
            fps = 1e9 / grabber.session.frame_period_ns
            seconds = len(grabber) / fps
        else:
            url = f"sim://{scene}?width={w}&height={h}&fps={fps}&speed=1.0"
            robot, grabber = open_robot(url, ctx), open_grabber(url + f"&pace=realtime&frames={frames}", ctx)
        report = run_live(robot, grabber, config, str(Path(tmp) / "out"), tracker=tracker, device=device,
                          progress=False, report_fields={"command": "bench pipeline"}, write=False)
    f = report["frames"]
    return {"machine": platform.processor() or platform.machine(), "device": device, "tracker": tracker,
            "source": source, "resolution": f"{w}x{h}", "fps_target": fps, "seconds": seconds,
            "features": features, "tracks": report["tracks"], "frames": f,
            "sustained_fps": report["throughput_fps"], "latency_ms": report["latency_ms"],
            "stage_ms": report["stage_ms"], "wall_s": report.get("wall_s"), "queue_depth": report.get("queue_depth", {}),
            "live": report.get("live", {}), "inliers": report["inliers"]}


def format_table(r: dict) -> str:
    f, lat = r["frames"], r["latency_ms"]
    return "\n".join([
        f"live pipeline, {r['resolution']} at {r['fps_target']:g} fps for {r['seconds']:g} s ({r['device']}, "
        f"{r['tracker']} tracker, {r['source']} source, {r['machine']})",
        "| sustained fps | frames in | mapped | dropped (source / capture / mapper) | latency p50 / p95 / p99 ms "
        "| BA deferred | resection deferred |",
        "|---|---|---|---|---|---|---|",
        f"| {r['sustained_fps']:.1f} | {f['in']} | {f['processed']} | {f['dropped']} ({f['dropped_source']} / "
        f"{f['dropped_capture']} / {f['mapper_skipped']}) | {lat.get('p50', 0):.0f} / {lat.get('p95', 0):.0f} / "
        f"{lat.get('p99', 0):.0f} | {r['live'].get('local_ba_skipped', 0)} | {r['live'].get('resection_skipped', 0)} |",
    ])
