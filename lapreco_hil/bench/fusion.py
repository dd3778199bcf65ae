"""TSDF fusion timed on this machine: the simulated skull's true depth maps (rendered with the undistorted camera
along the scan) integrated one keyframe at a time, a keyframe taken out and put back (a pose update), the mesh
extracted; with the volume's memory. Depth maps are the renderer's, so stereo's cost is not in these figures
(``bench_depth`` measures it)."""

from __future__ import annotations

import platform
import time
from dataclasses import replace

import numpy as np

from lapreco_hil.config import FusionConfig
from lapreco_hil.dense.fusion import TsdfVolume
from lapreco_hil.dense.types import DepthMap


def _sync(device: str) -> None:
    import warp as wp

    wp.synchronize_device(device)


def bench_fusion(device: str, resolution: tuple[int, int] = (1920, 1080), repeats: int = 3, keyframes: int = 24,
                 config: FusionConfig | None = None, scene: str = "skull") -> dict:
    """Median milliseconds per keyframe to integrate (and to take out and put back), per mesh extraction, and the
    volume's memory, over ``keyframes`` true depth maps at ``resolution``; best of ``repeats`` passes. Also: the
    integration from inputs already on the device, the host's time to queue one (before the device is waited
    for), and the kernel launches, copies and waits for the device per integration (steady state)."""
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.simulators.world import SimSettings, SimWorld
    from lapreco_hil.warp_device import init_warp, resolve_device

    init_warp()
    device = resolve_device(device)
    config = config or FusionConfig()
    width, height = resolution
    world = SimWorld(SimSettings(scene=scene, width=width, height=height, device=device))
    cam = world.camera
    pinhole = CameraModel(width, height, cam.fx, cam.fy, cam.cx, cam.cy)
    maps = []
    for s in np.linspace(0.0, 10.0, keyframes):
        T = world.true_camera_pose(1_000_000_000 + int(s * 1e9))
        image, depth = world.renderer.render(T, camera=pinhole)
        valid = depth > 0
        maps.append((DepthMap(len(maps), depth, valid.astype(np.float32), pinhole.K, T), image[..., ::-1].copy()))
    import warp as wp

    # the same maps already on the device (a depth map made there, as the live path can hand them over)
    on_device = [(DepthMap(d.kf_id, wp.array(d.depth_m, dtype=wp.float32, device=device),
                           wp.array(d.confidence, dtype=wp.float32, device=device), d.K, d.T_world_camera),
                  wp.array(np.ascontiguousarray(c), dtype=wp.uint8, device=device)) for d, c in maps]
    passes = []
    for _ in range(repeats):
        volume = TsdfVolume(config, device)
        integrate, refuse, resident = [], [], []
        numbers = []
        work = []
        for depth, colour in maps:
            _sync(device)
            before = (volume.stats.launches, volume.stats.copies, volume.stats.waits)
            t0 = time.perf_counter()
            numbers.append(volume.integrate(depth, colour))
            queued = time.perf_counter() - t0
            _sync(device)
            integrate.append(time.perf_counter() - t0)
            work.append((queued, volume.stats.launches - before[0], volume.stats.copies - before[1],
                         volume.stats.waits - before[2]))
        # put back the last maps from device arrays: no host copies
        for (depth, colour), n in list(zip(on_device, numbers))[-4:]:
            _sync(device)
            t0 = time.perf_counter()
            volume.deintegrate(depth, colour, integration=n)
            _sync(device)
            t1 = time.perf_counter()
            volume.integrate(depth, colour)
            _sync(device)
            resident.append(time.perf_counter() - t1)
        for (depth, colour), n in list(zip(maps, numbers))[-4:]:
            moved = replace(depth, T_world_camera=depth.T_world_camera.copy())
            moved.T_world_camera[:3, 3] += 0.0002
            _sync(device)
            t0 = time.perf_counter()
            volume.deintegrate(depth, colour, integration=n)
            volume.integrate(moved, colour)
            _sync(device)
            refuse.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        mesh = volume.extract_mesh()
        mesh_s = time.perf_counter() - t0
        # a keyframe re-fused, then meshed again: only the chunks it touched are contoured
        depth, colour = maps[len(maps) // 2]
        volume.deintegrate(depth, colour, integration=numbers[len(maps) // 2])
        volume.integrate(depth, colour)
        t0 = time.perf_counter()
        volume.extract_mesh()
        mesh_again_s = time.perf_counter() - t0
        chunks_again = volume.stats.meshed_chunks
        steady = work[2:] or work  # the first two settle the pool's size
        passes.append({"integrate_ms": 1e3 * float(np.median(integrate[1:])),  # the first pays for compilation
                       "integrate_first_ms": 1e3 * integrate[0],
                       "integrate_device_inputs_ms": 1e3 * float(np.median(resident)),
                       "integrate_host_ms": 1e3 * float(np.median([w[0] for w in steady])),
                       "launches_per_integrate": float(np.median([w[1] for w in steady])),
                       "copies_per_integrate": float(np.median([w[2] for w in steady])),
                       "waits_per_integrate": float(np.median([w[3] for w in steady])),
                       "refuse_ms": 1e3 * float(np.median(refuse)), "mesh_ms": 1e3 * mesh_s,
                       "mesh_after_one_refused_ms": 1e3 * mesh_again_s, "chunks_after_one_refused": chunks_again,
                       "triangles": int(mesh.n_cells), "points": int(mesh.n_points),
                       "blocks": volume.blocks_in_use, "volume_mb": volume.memory_bytes / 2**20,
                       "evicted_blocks": volume.stats.evicted_blocks})
    best = min(passes, key=lambda p: p["integrate_ms"])
    return {"device": device, "host": platform.node(), "resolution": [width, height], "keyframes": keyframes,
            "scene": scene, "voxel_mm": config.voxel_m * 1e3, "truncation_voxels": config.truncation_voxels,
            "max_blocks": config.max_blocks, **best, "passes": passes}


def format_table(result: dict) -> str:
    r = result
    return (f"fusion on {r['device']} ({r['resolution'][0]}x{r['resolution'][1]}, {r['keyframes']} keyframes, "
            f"{r['voxel_mm']:g} mm voxels): integrate {r['integrate_ms']:.1f} ms per keyframe (first "
            f"{r['integrate_first_ms']:.0f} ms; {r['integrate_device_inputs_ms']:.1f} ms from inputs on the device; "
            f"{r['integrate_host_ms']:.1f} ms to queue, {r['launches_per_integrate']:g} launches, "
            f"{r['copies_per_integrate']:g} copies, {r['waits_per_integrate']:g} waits), take out + put back "
            f"{r['refuse_ms']:.1f} ms, mesh {r['mesh_ms']:.0f} ms ({r['triangles']} triangles; again after one "
            f"keyframe re-fused {r['mesh_after_one_refused_ms']:.0f} ms, {r['chunks_after_one_refused']} chunks); "
            f"{r['blocks']} blocks, {r['volume_mb']:.0f} MB")


def _rss_mb() -> float | None:
    """This process's resident memory now (Linux), MB; None elsewhere."""
    try:
        with open("/proc/self/statm") as f:
            import os

            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def soak_fusion(device: str = "cpu", resolution: tuple[int, int] = (320, 240), keyframes: int = 300,
                max_blocks: int = 4096, keep_keyframes: int = 16, every: int = 10, step_m: float = 0.01) -> dict:
    """Memory over a long run of the dense surface: ``keyframes`` views of a textured plane 5 cm away, each
    ``step_m`` along it (new ground all the time), through ``DenseSurface`` (JPEG-kept images, PNG-kept maps,
    the volume with its block cap), every third keyframe re-fused after a pose update of the newest three. Every
    ``every`` keyframes: blocks in use, the volume's device memory, the kept images' memory and the process's
    resident memory. Depth maps are the plane's true depth: what is measured is fusion's and the surface's
    memory, not stereo's."""
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.config import PipelineConfig
    from lapreco_hil.dense.surface import DenseSurface, nearest_views
    from lapreco_hil.geometry import make_T
    from lapreco_hil.warp_device import init_warp, resolve_device

    init_warp()
    device = resolve_device(device)
    width, height = resolution
    f = 0.9 * width
    camera = CameraModel(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    config = PipelineConfig()
    config = replace(config, fusion=replace(config.fusion, max_blocks=max_blocks, keep_keyframes=keep_keyframes))

    def plane_depth(ref, sources, depth_config, dev):
        depth = np.full((height, width), 0.05, np.float32)
        return DepthMap(ref.kf_id, depth, np.ones_like(depth), ref.K, ref.T_world_camera)

    dense = DenseSurface(camera, config, device, depth_fn=plane_depth, sources_fn=nearest_views)
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 255, (height, width, 3), np.uint8)
    samples = []
    t0 = time.perf_counter()
    for i in range(keyframes):
        dense.add_view(i, np.roll(texture, 7 * i, axis=1), make_T(np.eye(3), [step_m * i, 0.0, 0.0]))
        dense.fuse_pending()
        if i % 3 == 2:  # bundle adjustment moved the newest keyframes a little
            nudge = make_T(np.eye(3), [0.0, 0.0002 * (1 if i % 2 else -1), 0.0])
            dense.update_poses({k: nudge @ dense.views[k].T_world_camera for k in list(dense.views)[-3:]})
        if (i + 1) % every == 0:
            memory = dense.report()["memory"]
            samples.append({"keyframe": i + 1, "blocks": memory["blocks"], "volume_mb": memory["volume_mb"],
                            "kept_images_mb": memory["kept_images_mb"], "rss_mb": _rss_mb(),
                            "evicted_blocks": memory["evicted_blocks"], "seconds": time.perf_counter() - t0})
    return {"device": device, "resolution": [width, height], "keyframes": keyframes, "max_blocks": max_blocks,
            "keep_keyframes": keep_keyframes, "step_m": step_m, "refused": dense.refused,
            "released": dense.released, "unallocated_blocks": dense.volume.stats.unallocated_blocks,
            "integration_ms_per_keyframe": 1e3 * dense.timings["integration_s"] / max(dense.fused + dense.refused, 1),
            "samples": samples}


def format_soak(result: dict) -> str:
    s = result["samples"]
    half = s[len(s) // 2:]

    def span(key):
        values = [x[key] for x in half if x[key] is not None]
        return f"{min(values):.1f}-{max(values):.1f}" if values else "n/a"

    return (f"fusion soak on {result['device']} ({result['resolution'][0]}x{result['resolution'][1]}, "
            f"{result['keyframes']} keyframes, cap {result['max_blocks']} blocks, {result['keep_keyframes']} kept): "
            f"second half: blocks {min(x['blocks'] for x in half)}-{max(x['blocks'] for x in half)}, volume "
            f"{span('volume_mb')} MB, kept images {span('kept_images_mb')} MB, process {span('rss_mb')} MB; "
            f"{s[-1]['evicted_blocks']} blocks evicted, {result['refused']} re-fused, {result['released']} released; "
            f"{result['integration_ms_per_keyframe']:.1f} ms per fusion (the surface's host work and the volume's)")
