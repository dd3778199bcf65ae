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
    volume's memory, over ``keyframes`` true depth maps at ``resolution``; best of ``repeats`` passes."""
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
    passes = []
    for _ in range(repeats):
        volume = TsdfVolume(config, device)
        integrate, refuse = [], []
        numbers = []
        for depth, colour in maps:
            _sync(device)
            t0 = time.perf_counter()
            numbers.append(volume.integrate(depth, colour))
            _sync(device)
            integrate.append(time.perf_counter() - t0)
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
        passes.append({"integrate_ms": 1e3 * float(np.median(integrate[1:])),  # the first pays for compilation
                       "integrate_first_ms": 1e3 * integrate[0],
                       "refuse_ms": 1e3 * float(np.median(refuse)), "mesh_ms": 1e3 * mesh_s,
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
            f"{r['integrate_first_ms']:.0f} ms), take out + put back {r['refuse_ms']:.1f} ms, mesh "
            f"{r['mesh_ms']:.0f} ms ({r['triangles']} triangles); {r['blocks']} blocks, {r['volume_mb']:.0f} MB")
