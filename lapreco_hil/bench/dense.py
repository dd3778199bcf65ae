"""Depth maps by multi-view stereo (lapreco_hil.dense.depth): time per keyframe and accuracy against the renderer's
true depth, on keyframes rendered by the simulator's own renderer with a pinhole camera (the mapper hands
stereo undistorted keyframes) and the true poses.

Two kinds of simulated keyframes: a simulated world's scene along the robot's scan trajectory (``liver``: real
organ models at 70-150 mm, a wet specular surface, grazing slopes and folds), or ``sheet``: a wavy sheet with
the liver texture seen from above at 75 mm by views offset sideways (a controlled case with no occlusion).
The sweep's depth range is the true depth's 1st-99th percentile widened by 10%, as a keyframe's landmarks give.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import platform
import re
import time

import numpy as np

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.types import KeyframeView

log = logging.getLogger(__name__)

WORLD_OFFSETS_S = (0.0, 0.6, -0.6, 1.2, -1.2, 1.8, -1.8, 2.4, -2.4)  # keyframe times about the reference's
SHEET_OFFSETS_MM = ((0, 0), (6, 0), (-6, 0), (0, 6), (0, -6), (9, 9), (-9, -9), (9, -9), (-9, 9))


def _landmark_range(depth: np.ndarray) -> tuple[float, float]:
    d = depth[depth > 0]
    return float(np.percentile(d, 1)) * 0.9, float(np.percentile(d, 99)) * 1.1


def _pinhole(camera, width: int, height: int):
    from lapreco_hil.camera import CameraModel

    return CameraModel(width, height, camera.fx, camera.fy, camera.cx, camera.cy,
                       fov_radius_px=camera.fov_radius_px)


def _fov_mask(camera) -> np.ndarray:
    ys, xs = np.mgrid[0:camera.height, 0:camera.width]
    return np.hypot(xs - camera.cx, ys - camera.cy) < camera.fov_radius_px - 1.0


def _K(camera) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def world_keyframes(scene: str, resolution: tuple[int, int], n_views: int, device: str, t0_s: float = 2.0,
                    instrument: str | None = None) -> tuple[list[KeyframeView], list[np.ndarray], list | None]:
    """``n_views`` keyframes of a simulated world's scene (the reference first, then the others at
    ``WORLD_OFFSETS_S`` about it), their true depths (of the scene, without an instrument) and, with an
    ``instrument`` ("moving": where the simulator moves it at each keyframe's time; "static": held where it is at
    the reference's time), each keyframe's instrument pixels."""
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    width, height = resolution
    scene_world = SimWorld(SimSettings(scene=scene, width=width, height=height, device=device))
    world = scene_world
    if instrument is not None:
        world = SimWorld(SimSettings(scene=scene, width=width, height=height, device=device, instrument=True))
    camera = _pinhole(world.camera, width, height)
    mask = _fov_mask(camera)
    t_ref = world.now_ns() + int(t0_s * 1e9)
    views, truths, tools = [], [], []
    for i, dt in enumerate(WORLD_OFFSETS_S[:n_views]):
        t = t_ref + int(dt * 1e9)
        T = world.true_camera_pose(t)
        if instrument is not None:
            world._move_instrument(t if instrument == "moving" else t_ref)
        image, depth = world.renderer.render(T, seed=i, camera=camera)
        truth = depth
        if instrument is not None:
            _, truth = scene_world.renderer.render(T, seed=i, camera=camera)
            tools.append(mask & (np.abs(depth - truth) > 1e-4))
        views.append(KeyframeView(i, image[:, :, ::-1].copy(), _K(camera), T, mask, _landmark_range(truth)))
        truths.append(truth)
    return views, truths, (tools if instrument is not None else None)


def sheet_keyframes(resolution: tuple[int, int], n_views: int, device: str, distance_m: float = 0.075,
                    specular: float = 0.0) -> tuple[list[KeyframeView], list[np.ndarray]]:
    """``n_views`` keyframes of a wavy textured sheet (6 mm waves) seen from ``distance_m``, the reference over
    its centre, the others ``SHEET_OFFSETS_MM`` aside, all looking at the centre; and their true depths."""
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.geometry import make_T
    from lapreco_hil.simulators.world.renderer import Lighting, Material, Renderer
    from lapreco_hil.simulators.world.scenes import _grid_sheet
    from lapreco_hil.simulators.world.textures import liver_texture

    width, height = resolution
    fx = (width / 2) / np.tan(np.deg2rad(70.0) / 2)
    camera = CameraModel(width, height, fx, fx, (width - 1) / 2, (height - 1) / 2,
                         fov_radius_px=0.68 * np.hypot(width, height) / 2)
    vertices, faces = _grid_sheet(0.2, 120, lambda x, y: 0.006 * np.sin(x * 60) * np.cos(y * 45))
    material = Material(liver_texture(np.random.default_rng(0)), texel_size_m=0.0003, specular=specular,
                        shininess=60.0)
    renderer = Renderer(vertices, faces, np.zeros(len(faces), np.int32), [material], camera,
                        Lighting(light_w=0.004), device=device)
    mask = _fov_mask(camera)
    views, truths = [], []
    for i, (dx, dy) in enumerate(SHEET_OFFSETS_MM[:n_views]):
        eye = np.array([dx * 1e-3, dy * 1e-3, distance_m])
        z = -eye / np.linalg.norm(eye)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        T = make_T(np.column_stack([x, np.cross(z, x), z]), eye)
        image, depth = renderer.render(T, seed=i, camera=camera)
        views.append(KeyframeView(i, image[:, :, ::-1].copy(), _K(camera), T, mask, _landmark_range(depth)))
        truths.append(depth)
    return views, truths


def plane_keyframes(resolution: tuple[int, int], n_views: int, tilt_deg: float, distance_m: float = 0.08,
                    baseline_m: float = 0.006, seed: int = 0) -> tuple[list[KeyframeView], list[np.ndarray]]:
    """``n_views`` keyframes of a flat textured plane whose normal is ``tilt_deg`` from the reference's optical
    axis (about its y axis), crossing the axis at ``distance_m``: the reference at the origin looking along z,
    the others ``baseline_m`` aside (right, left, up, down, then diagonals) looking at the same point. Rendered
    exactly (each pixel's ray meets the plane; a band-limited random texture, bilinear, on 0.1 mm texels), with
    the true depths; a keyframe's mask is where the plane lies at 30-250 mm."""
    import cv2

    from lapreco_hil.geometry import make_T

    width, height = resolution
    f = (width / 2) / np.tan(np.deg2rad(60.0) / 2)
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(seed)
    texels = 1024
    noise = rng.random((texels // 8, texels // 8))
    texture = cv2.GaussianBlur(cv2.resize(noise, (texels, texels), interpolation=cv2.INTER_CUBIC), (0, 0), 2.0)
    texture = (texture - texture.min()) / (np.ptp(texture) + 1e-12)
    tilt = np.deg2rad(tilt_deg)
    normal = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])  # towards the reference camera
    point = np.array([0.0, 0.0, distance_m])
    e1 = np.array([np.cos(tilt), 0.0, np.sin(tilt)])  # the plane's texture axes
    e2 = np.array([0.0, 1.0, 0.0])
    texel_m = 1e-4
    offsets = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)]
    ys, xs = np.mgrid[0:height, 0:width]
    rays = np.linalg.inv(K) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    views, truths = [], []
    for i in range(n_views):
        eye = np.zeros(3) if i == 0 else np.array([*offsets[(i - 1) % 8], 0.0]) * baseline_m
        z = point - eye
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        T = make_T(np.column_stack([x, np.cross(z, x), z]), eye)
        d_world = T[:3, :3] @ rays
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (normal @ (point - eye)) / (normal @ d_world)  # along each ray (camera z = s: rays have z = 1)
        hit = eye[:, None] + d_world * s
        a = ((hit - point[:, None]).T @ e1) / texel_m + texels / 2
        b = ((hit - point[:, None]).T @ e2) / texel_m + texels / 2
        depth = np.where(np.isfinite(s) & (s > 0.03) & (s < 0.25), s, 0.0).reshape(height, width)
        inside = (a >= 0) & (a < texels - 1) & (b >= 0) & (b < texels - 1)
        map_a = np.clip(a, 0, texels - 1).reshape(height, width).astype(np.float32)
        map_b = np.clip(b, 0, texels - 1).reshape(height, width).astype(np.float32)
        grey = cv2.remap(texture.astype(np.float32), map_a, map_b, cv2.INTER_LINEAR)
        depth[~inside.reshape(height, width)] = 0.0
        image = np.repeat((40 + 180 * grey)[:, :, None], 3, axis=2).astype(np.uint8)
        mask = depth > 0
        views.append(KeyframeView(i, image, K, T, mask, _landmark_range(depth)))
        truths.append(depth.astype(np.float32))
    return views, truths


def depth_errors(depth_m: np.ndarray, truth_m: np.ndarray) -> dict:
    """Accuracy of the kept depths against the truth (mm), over the pixels where both exist."""
    kept = (depth_m > 0) & (truth_m > 0)
    err = np.abs(depth_m[kept] - truth_m[kept]) * 1e3
    if not err.size:
        return {"kept": 0}
    return {"kept": int(kept.sum()), "median_mm": float(np.median(err)), "p95_mm": float(np.percentile(err, 95)),
            "over_1mm": float(np.mean(err > 1.0)), "over_5mm": float(np.mean(err > 5.0))}


def _device_activities(wp, device: str, run) -> dict:
    """GPU time (ms) per kernel and memory operation of one ``run()``, summed by name (Warp's CUDA activity
    timing; a kernel's module hash is left off its name), largest first."""
    try:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        try:
            run()
        finally:
            results = wp.timing_end()
    except RuntimeError as exc:  # the figures without the breakdown rather than none
        log.warning("no GPU activity timing on %s: %s", device, exc)
        return {}
    totals: dict[str, float] = {}
    for result in results:
        name = re.sub(r"_[0-9a-f]{8}$", "", result.name.removeprefix("forward kernel "))
        totals[name] = totals.get(name, 0.0) + float(result.elapsed)
    return dict(sorted(((k, round(v, 4)) for k, v in totals.items()), key=lambda item: -item[1]))


def bench_fusion_routes(estimator, ref: KeyframeView, sources: list[KeyframeView], device: str,
                        repeats: int) -> dict:
    """A new depth map fused as the live dense surface fuses it (``TsdfVolume.integrate`` quantised as kept, then
    the kept copy read back, ``quantised_map``), by two routes, median ms over ``repeats`` after two warm-ups:
    from host inputs (the map downloaded by the estimator, then uploaded again with the host's colour) and from
    device inputs (the map left on the device, ``compute(on_device=True)``, with the reference's colour from the
    estimator's view cache). ``download_ms``: the estimator's last step (the map and its funnel, or the funnel
    only; timed with the estimator's ``profile``, so that it is the step and not the wait for the sweep);
    ``integrate_ms``: the integration until the device has finished it; ``keep_ms``: reading the
    quantised map back; ``total_ms``: the three, what the route adds to a keyframe after its sweep."""
    from lapreco_hil.config import FusionConfig
    from lapreco_hil.dense.fusion import TsdfVolume
    from lapreco_hil.dense.surface import KEPT_STEPS
    from lapreco_hil.warp_device import init_warp

    wp = init_warp()
    out = {}
    profile, estimator.profile = estimator.profile, True
    for route, on_device in (("host_inputs", False), ("device_inputs", True)):
        volume = TsdfVolume(FusionConfig(), device)
        times: dict[str, list[float]] = {"download_ms": [], "integrate_ms": [], "keep_ms": []}
        for i in range(max(1, repeats) + 2):
            depth_map = estimator.compute(ref, sources, on_device=on_device)
            colour = estimator.view_colour(ref.kf_id) if on_device else ref.colour
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            volume.integrate(depth_map, colour, quantise=KEPT_STEPS)
            wp.synchronize_device(device)
            t1 = time.perf_counter()
            volume.quantised_map()
            t2 = time.perf_counter()
            if i >= 2:  # the first two compile the kernels and size the volume's pool
                times["download_ms"].append(depth_map.stats["times_ms"]["download_ms"])
                times["integrate_ms"].append((t1 - t0) * 1e3)
                times["keep_ms"].append((t2 - t1) * 1e3)
            del depth_map  # (the estimator's host buffer is free again)
        medians = {k: float(np.median(v)) for k, v in times.items()}
        out[route] = {**medians, "total_ms": sum(medians.values())}
    estimator.profile = profile
    return out


def bench_depth(device: str, resolution: tuple[int, int], views: int, repeats: int, scene: str = "liver",
                config: DepthConfig | None = None, sweep: str | None = None, method: str | None = None,
                fusion: bool = True) -> dict:
    """Time ``DepthEstimator.compute`` of one keyframe against ``views`` source views (after a warm-up that compiles
    the kernels and allocates the buffers), median over ``repeats``; and its accuracy, before and after the
    geometric check against the sources' own depth maps.

    ``total_ms`` is the steady state of a mapper that keeps one estimator: the reference is new (prepared) and
    its sources are in the estimator's prepared-view cache (each was a reference before), the map's steps queued
    on the device and waited for once, as a mapper runs it; ``host_steps_ms``: its steps' host times then (each
    the host's time to queue the step; the last, ``download_ms``, includes the wait for the device).
    ``steps_ms`` is the stepped profile (the estimator's ``profile``: the device synchronised at each step's end,
    ``profiled_total_ms`` their sum). ``cold_ms`` prepares every view (a fresh estimator's first map, less
    compiling and allocating), ``cold_steps_ms`` its profile. ``device_ops``: what the device was asked for one
    steady-state map. ``sweep``: the estimator's window sums (None: the device's default); ``method``:
    ``[depth] method`` (None: the config's). ``fusion``: also fuse the map from host inputs and from device
    inputs (``bench_fusion_routes``)."""
    from lapreco_hil.dense.depth import DepthEstimator
    from lapreco_hil.warp_device import init_warp

    wp = init_warp()
    cfg = config or DepthConfig()
    if method is not None:
        cfg = dataclasses.replace(cfg, method=method)
    if scene == "sheet":
        keyframes, truths = sheet_keyframes(resolution, views + 1, device)
    else:
        keyframes, truths, _ = world_keyframes(scene, resolution, views + 1, device)
    ref, sources = keyframes[0], keyframes[1:]
    estimator = DepthEstimator(cfg, device, sweep=sweep)
    estimator.compute(ref, sources)

    def timed(forget: int | None) -> tuple[float, float, dict]:
        if forget is None:
            estimator.forget()
        else:
            estimator.forget(forget)
        wp.synchronize_device(device)
        t0, c0 = time.perf_counter(), time.process_time()
        depth_map = estimator.compute(ref, sources)
        wp.synchronize_device(device)
        return (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3, depth_map

    def median_steps(maps: list) -> dict:
        names = maps[0].stats["times_ms"]
        return {k: float(np.median([m.stats["times_ms"][k] for m in maps])) for k in names if k != "total_ms"}

    totals, cpu, cold, steady_maps = [], [], [], []
    for _ in range(max(1, repeats)):  # as a mapper runs it: one wait per map
        wall, _, depth_map = timed(None)
        cold.append(wall)
        wall, cpu_ms, depth_map = timed(ref.kf_id)
        totals.append(wall)
        cpu.append(cpu_ms)
        steady_maps.append(depth_map.stats)
    device_ops = depth_map.stats["device_ops"]
    estimator.profile = True  # the stepped profile: a wait at each step's end
    profiled, cold_profiled, profiled_totals = [], [], []
    for _ in range(max(1, repeats)):
        cold_profiled.append(timed(None)[2])
        wall, _, depth_map = timed(ref.kf_id)
        profiled.append(depth_map)
        profiled_totals.append(wall)
    estimator.profile = False
    activities = _device_activities(wp, device, lambda: timed(ref.kf_id)) if wp.get_device(device).is_cuda else {}
    routes = bench_fusion_routes(estimator, ref, sources, device, repeats) if fusion else None
    # the sources' own maps (each against the others) for the forward-backward check
    source_maps = [estimator.compute(s, [v for v in keyframes if v is not s]) for s in sources]
    checked = estimator.check_geometry(depth_map, source_maps)
    in_view = (ref.mask if ref.mask is not None else np.ones(truths[0].shape, bool)) & (truths[0] > 0)
    return {
        "device": device, "resolution": f"{resolution[0]}x{resolution[1]}", "scene": scene, "views": views,
        "repeats": repeats, "planes": depth_map.stats["planes"], "sweep": estimator.sweep, "method": cfg.method,
        "total_ms": float(np.median(totals)), "cold_ms": float(np.median(cold)),
        # this process's CPU time: on a shared machine the wall time also counts other processes' turns (Warp's
        # CPU kernels run on one thread, so on the CPU device this is the time on an idle core; on CUDA a wait
        # for the device spins, and counts)
        "process_cpu_ms": float(np.median(cpu)), "load_average": os.getloadavg()[0],
        "host_steps_ms": {k: float(np.median([s["times_ms"][k] for s in steady_maps]))
                          for k in steady_maps[0]["times_ms"] if k != "total_ms"},
        "steps_ms": median_steps(profiled), "profiled_total_ms": float(np.median(profiled_totals)),
        "cold_steps_ms": median_steps(cold_profiled),
        "device_ops": device_ops,
        # GPU time per kernel and copy of one steady-state map (CUDA only): where the device's time goes
        "device_ms": activities,
        # the map fused as the live surface fuses it, from host inputs and from device inputs
        "fusion_routes": routes,
        "funnel": checked.stats["funnel"],
        "accuracy": depth_errors(depth_map.depth_m, truths[0]),
        "accuracy_checked": depth_errors(checked.depth_m, truths[0]),
        "coverage": float(np.count_nonzero(depth_map.valid & in_view) / max(1, np.count_nonzero(in_view))),
        "coverage_checked": float(np.count_nonzero(checked.valid & in_view) / max(1, np.count_nonzero(in_view))),
        "cpu_threads": os.cpu_count(), "machine": platform.node(), "processor": platform.processor(),
    }


def format_table(result: dict) -> str:
    def acc(a: dict) -> str:
        if not a.get("kept"):
            return "no depth kept"
        return (f"median {a['median_mm']:.3f} mm, p95 {a['p95_mm']:.2f} mm, >1 mm {100 * a['over_1mm']:.2f}%, "
                f">5 mm {100 * a['over_5mm']:.2f}% of {a['kept']} px")

    def joined(steps: dict) -> str:
        return ", ".join(f"{k.removesuffix('_ms')} {v:.1f}" for k, v in steps.items())

    lines = [
        f"depth map, {result['scene']} {result['resolution']}, {result['views']} source views, {result['planes']} "
        f"coarse planes, {result.get('sweep', 'sliding')} sweep, method {result.get('method', 'sweep')}, on "
        f"{result['device']} ({result['machine']}; median of {result['repeats']})",
        f"time per keyframe: {result['total_ms']:.1f} ms wall, one wait (the host's steps: "
        f"{joined(result.get('host_steps_ms', {}))} ms), {result['process_cpu_ms']:.1f} ms of this process's CPU "
        f"time (load average {result['load_average']:.1f} on {result['cpu_threads']} threads); the sources "
        "prepared before",
        f"stepped profile (a wait at each step's end): {result.get('profiled_total_ms', float('nan')):.1f} ms "
        f"({joined(result['steps_ms'])} ms)",
        f"every view prepared: {result.get('cold_ms', float('nan')):.1f} ms wall (stepped: "
        f"{joined(result.get('cold_steps_ms', {}))} ms)",
        f"sweep only:        {acc(result['accuracy'])}; {100 * result['coverage']:.1f}% of the in-view pixels",
        f"geometric check:   {acc(result['accuracy_checked'])}; {100 * result['coverage_checked']:.1f}% of the "
        "in-view pixels",
        "funnel: " + ", ".join(f"{k} {v}" for k, v in result["funnel"].items()),
    ]
    if result.get("device_ops"):
        ops = result["device_ops"]
        lines.append(f"asked of the device per map: {ops['launches']} launches, {ops['uploads']} uploads "
                     f"({ops['uploaded_bytes'] / 1e6:.2f} MB), {ops['downloads']} downloads "
                     f"({ops['downloaded_bytes'] / 1e6:.2f} MB), {ops['synchronisations']} waits, "
                     f"{ops['allocations']} allocations")
    if result.get("fusion_routes"):
        lines.append(_format_routes(result["fusion_routes"]))
    if result.get("device_ms"):
        lines.append(f"GPU time of one map: {sum(result['device_ms'].values()):.2f} ms: " + ", ".join(
            f"{k} {v:.2f}" for k, v in list(result["device_ms"].items())[:10]))
    return "\n".join(lines)


def _format_routes(routes: dict) -> str:
    def one(r: dict) -> str:
        return (f"{r['total_ms']:.2f} ms (download {r['download_ms']:.2f}, integrate {r['integrate_ms']:.2f}, kept "
                f"copy back {r['keep_ms']:.2f})")

    return (f"fusing the map as kept: from host inputs {one(routes['host_inputs'])}; from device inputs "
            f"{one(routes['device_inputs'])}")
