"""``lapreco bench ...``: each benchmark with its device-dependent defaults; the live ones (pipeline, soak) run
the live runtime through :func:`lapreco_hil.app.run.run_live`. The measurement helpers and tables live in
lapreco_hil.bench."""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

from lapreco_hil.config import load_config
from lapreco_hil.frontend import resolve_tracker
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot
from lapreco_hil.warp_device import resolve_device
from lapreco_hil.app.record import sim_record
from lapreco_hil.app.run import run_live


def bench_pipeline(device: str = "auto", resolution: tuple[int, int] | None = None, fps: float | None = None,
                   seconds: float = 20.0, features: int | None = None, source: str = "auto",
                   tracker: str = "auto", scene: str = "skull", session: str | None = None,
                   surface: str = "auto", config: str | None = None) -> dict:
    """The live runtime in real time (``surface``: ``[surface] mode``; ``config``: a TOML file the bench's
    features and surface mode are set on). Defaults: 1920x1080 at 60 fps with 2000 features on a GPU, 384x288 at
    25 fps with 800 on a CPU. Source 'replay' (and 'auto'): a session recorded first (or ``session``), replayed
    in real time; 'sim': the simulated world rendered live."""
    from lapreco_hil.bench.pipeline import bench_config

    device = resolve_device(device)
    gpu = device.startswith("cuda")
    w, h = resolution or ((1920, 1080) if gpu else (384, 288))
    fps = fps or (60.0 if gpu else 25.0)
    features = features or (2000 if gpu else 800)
    tracker = resolve_tracker(tracker, device)
    if source == "auto" or session is not None:
        source = "replay"
    config = bench_config(features, surface, load_config(config))
    frames = int(round(fps * seconds))
    with tempfile.TemporaryDirectory() as tmp:
        ctx = DeviceContext(device=device)
        if source == "replay":
            if session is None:
                session = str(Path(tmp) / "session")
                sim_record(scene, session, frames=frames, resolution=(w, h), fps=fps, device=device, progress=False)
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
            "live": report.get("live", {}), "inliers": report["inliers"], "surface": report.get("surface"),
            "dense": report.get("dense"), "keyframes": report.get("keyframes"), "landmarks": report.get("landmarks"),
            "funnel": report.get("funnel"), "time_offset": report.get("time_offset"),
            "gc_main_process": report.get("gc_main_process")}


def bench_soak(device: str = "auto", resolution: tuple[int, int] = (320, 240), fps: float = 10.0,
               minutes: float = 30.0, features: int = 400, scene: str = "skull", tracker: str = "auto",
               sample_s: float = 10.0, stream: str | None = None, surface: str = "auto") -> dict:
    """The live runtime on the endless simulated world for ``minutes``, sampled every ``sample_s``; each sample
    is also appended to ``stream`` (JSON lines) as it is taken. ``surface``: ``[surface] mode`` (dense: the
    live dense stage's volume and kept keyframes are in the main process's memory)."""
    from lapreco_hil.bench.pipeline import bench_config
    from lapreco_hil.bench.soak import Sampler, summarize

    device = resolve_device(device)
    w, h = resolution
    tracker = resolve_tracker(tracker, device)
    config = bench_config(features, surface)
    ctx = DeviceContext(device=device)
    # an endless simulated world (its scan is periodic), rendered as the camera would deliver it
    url = f"sim://{scene}?width={w}&height={h}&fps={fps}&speed=1.0"
    robot, grabber = open_robot(url, ctx), open_grabber(url + "&pace=realtime", ctx)
    sampler = Sampler(sample_s, stream)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            report = run_live(robot, grabber, config, str(Path(tmp) / "out"), tracker=tracker, device=device,
                              seconds=minutes * 60.0, progress=False, report_fields={"command": "bench soak"},
                              write=False, on_live=sampler.attach)
        finally:
            sampler.stop()
    wall = time.perf_counter() - t0
    samples = sampler.samples
    f = report["frames"]
    return {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "device": device,
            "tracker": tracker, "scene": scene, "resolution": f"{w}x{h}", "fps_target": fps, "minutes": minutes,
            "features": features, "wall_s": wall, "frames": f, "latency_ms": report["latency_ms"],
            "keyframes": report["keyframes"], "landmarks": report["landmarks"], "inliers": report["inliers"],
            "final_ba_s": report["live"].get("final_ba_s"), "health_counts": report["health"]["counts"],
            "surface": report.get("surface"), "dense": report.get("dense"),
            "live": {k: v for k, v in report["live"].items() if k.startswith("dense")},
            "summary": summarize(samples, warmup_s=min(120.0, minutes * 60 / 4), stretch_s=min(300.0, minutes * 60 / 4)),
            "samples": samples}


def bench_frontend(device: str = "auto", resolutions=((1920, 1080),), features=(2000,), frames: int = 40,
                   baseline: bool = True) -> dict:
    """The Warp front-end against the OpenCV baseline (``baseline``), per stage."""
    from lapreco_hil.bench.frontend import run

    return run(resolve_device(device), list(resolutions), list(features), frames=frames, baseline=baseline)


def bench_ba(repeats: int = 3, device: str = "cpu") -> dict:
    """One local BA window: 10 keyframes x 2000 points, 5% outliers; ``device``: the Schur solver's Warp device."""
    from lapreco_hil.bench.ba import run
    from lapreco_hil.warp_device import resolve_device

    return run(repeats=repeats, device=resolve_device(device))


def bench_dense(device: str = "auto", resolutions=None, views: int = 4, repeats: int = 5,
                methods=("sweep", "patchmatch")) -> dict:
    """The dense surface's steps per keyframe: a depth map (multi-view stereo, simulated liver keyframes, accuracy
    against the renderer's depth) and its integration, take-out and put-back in the TSDF volume and the meshing
    (the simulated skull's true depth maps), at each resolution (default: 1920x1080 and 384x288); the depth map
    by each ``[depth] method`` (``depth``: the first's, ``depth_by_method``: each's)."""
    from lapreco_hil.bench.dense import bench_depth
    from lapreco_hil.bench.fusion import bench_fusion
    from lapreco_hil.warp_device import resolve_device

    device = resolve_device(device)
    rows = []
    for resolution in resolutions or [(1920, 1080), (384, 288)]:
        depth = {m: bench_depth(device, tuple(resolution), views, repeats, method=m) for m in methods}
        rows.append({"resolution": list(resolution), "depth": depth[methods[0]], "depth_by_method": depth,
                     "fusion": bench_fusion(device, tuple(resolution), repeats=max(1, min(repeats, 3)))})
    return {"benchmark": "dense", "device": device, "views": views, "repeats": repeats, "rows": rows,
            "machine": platform.node(), "processor": platform.processor(), "cpu_threads": os.cpu_count()}


def bench_robot(links=("serial", "canopen"), rates=(100.0, 500.0), seconds: float = 5.0) -> dict:
    """The robot drivers on their emulators: sample rate, jitter, latency."""
    from lapreco_hil.bench.robot import run

    return run(list(links), list(rates), seconds)


def bench_session(resolutions=((640, 480), (1920, 1080)), frames: int = 60) -> dict:
    """Session write (crash-safe) and read throughput."""
    from lapreco_hil.bench.session import run

    return run(list(resolutions), frames=frames)


def bench_tracking(trackers=("warp", "opencv"), device: str = "all", speeds=(0.0, 10.0, 20.0, 40.0, 60.0, 80.0),
                   frames: int = 32, predict: str = "off") -> dict:
    """The front-ends on real laparoscopic frames moved by known plane homographies: error against the truth,
    share within 1 px, survival, tracks per frame. ``device``: cpu, cuda, or all (the CPU and, when Warp sees
    one, CUDA). ``predict``: off, on (a perfect pose source: with each track's depth, and with only a depth
    range), or both."""
    from lapreco_hil.bench.tracking import run
    from lapreco_hil.errors import ConfigError
    from lapreco_hil.warp_device import init_warp

    if device == "all":
        devices = ["cpu"] + (["cuda:0"] if init_warp().is_cuda_available() else [])
    elif device in ("cpu", "cuda"):
        devices = [resolve_device(device)]
    else:
        raise ConfigError(f"--device {device}: expected cpu, cuda or all")
    modes = {"off": ["off"], "on": ["depth", "epipolar"], "both": ["off", "depth", "epipolar"]}
    if predict not in modes:
        raise ConfigError(f"--predict {predict}: expected on, off or both")
    return run(list(trackers), devices, [float(s) for s in speeds], modes[predict], frames=frames)
