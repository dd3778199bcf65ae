"""Off-screen rendering of a reconstruction: mesh or points, with camera pyramids (green = refined pose, as in
the seed's Fig 2). Works headless through VTK's EGL or OSMesa render window."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from pathlib import Path

import numpy as np
import pyvista as pv

from lapreco_hil.geometry import transform_points


# how to get a renderer on a headless machine (README, "Headless rendering")
ENABLE_RENDERING = ("install Mesa's EGL libraries (Debian/Ubuntu: apt-get install libegl1 libgl1) or a VTK built "
                    "with OSMesa (pip install vtk-osmesa in place of vtk)")
_EGL_PLATFORM_DEVICE_EXT = 0x313F


def offscreen_unavailable() -> str | None:
    """Why VTK cannot open an off-screen window on this machine, or None when it can. Asked before rendering
    because VTK, finding neither a usable EGL device nor OSMesa, crashes the process (SIGSEGV) instead of
    raising."""
    if os.environ.get("DISPLAY"):
        return None
    if _osmesa_present():
        return None
    if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW") == "vtkOSOpenGLRenderWindow":
        return "VTK_DEFAULT_OPENGL_WINDOW asks for OSMesa, and no OSMesa library is installed"
    if _egl_devices_that_initialise() > 0:
        return None
    return "no display, no EGL device that initialises, and no OSMesa library"


def _osmesa_present() -> bool:
    import vtkmodules

    bundled = Path(vtkmodules.__file__).parent.parent / "vtk.libs"  # vtk-osmesa wheels carry their own
    return bool(ctypes.util.find_library("OSMesa")) or any(bundled.glob("libOSMesa*"))


def _egl_devices_that_initialise() -> int:
    """EGL devices (EGL_EXT_device_enumeration, as VTK's EGL window uses them) whose display initialises."""
    try:
        egl = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
    except OSError:
        return 0
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    query_addr = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
    display_addr = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
    if not query_addr or not display_addr:
        return 0
    query = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p),
                             ctypes.POINTER(ctypes.c_int))(query_addr)
    get_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(display_addr)
    egl.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int)]
    egl.eglTerminate.argtypes = [ctypes.c_void_p]
    n = ctypes.c_int(0)
    if not query(0, None, ctypes.byref(n)) or n.value <= 0:
        return 0
    devices = (ctypes.c_void_p * n.value)()
    query(n.value, devices, ctypes.byref(n))
    working = 0
    for device in devices[:n.value]:
        display = get_display(_EGL_PLATFORM_DEVICE_EXT, device, None)
        major, minor = ctypes.c_int(), ctypes.c_int()
        if display and egl.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)):
            egl.eglTerminate(display)
            working += 1
    return working


def camera_pyramid(T_world_camera: np.ndarray, width: int, height: int, fx: float, depth: float) -> pv.PolyData:
    w, h = width / (2 * fx) * depth, height / (2 * fx) * depth
    local = np.array([[0, 0, 0], [-w, -h, depth], [w, -h, depth], [w, h, depth], [-w, h, depth]])
    pts = transform_points(T_world_camera, local)
    lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 2, 1, 2, 2, 2, 3, 2, 3, 4, 2, 4, 1]
    return pv.PolyData(pts, lines=np.array(lines))


def render_reconstruction(path: str, mesh: pv.PolyData | None, points: np.ndarray, colors: np.ndarray,
                          cameras: list[tuple[np.ndarray, bool]], image_size: tuple[int, int],
                          window_size: tuple[int, int] = (1024, 768), fx: float = 500.0) -> None:
    if not os.environ.get("DISPLAY"):
        # headless: go straight to EGL (Mesa or NVIDIA) instead of trying X first
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    plotter.set_background("#10141a")
    extent = float(np.ptp(points, axis=0).max()) if len(points) else 0.05
    if mesh is not None and mesh.n_cells > 0:
        if "RGB" in mesh.point_data:
            plotter.add_mesh(mesh, scalars="RGB", rgb=True, smooth_shading=True)
        else:
            plotter.add_mesh(mesh, color="#d9b38c", smooth_shading=True)
    elif len(points):
        cloud = pv.PolyData(points)
        cloud.point_data["RGB"] = colors
        plotter.add_mesh(cloud, scalars="RGB", rgb=True, point_size=4, render_points_as_spheres=True)
    for T, refined in cameras:
        plotter.add_mesh(camera_pyramid(T, image_size[0], image_size[1], fx, 0.05 * extent + 1e-3),
                         color="#33dd55" if refined else "#dd7733", line_width=2)
    if cameras:
        centres = np.array([T[:3, 3] for T, _ in cameras])
        look = points.mean(axis=0) if len(points) else centres.mean(axis=0) + cameras[0][0][:3, 2] * 0.1
        mean_T = cameras[len(cameras) // 2][0]
        # view from behind, above and beside the cameras so both the surface and the pyramids show
        eye = (centres.mean(axis=0) - mean_T[:3, 2] * 1.2 * extent - mean_T[:3, 1] * 0.7 * extent
               + mean_T[:3, 0] * 0.5 * extent)
        plotter.camera_position = [tuple(eye), tuple(look), tuple(-mean_T[:3, 1])]
    plotter.screenshot(path)
    plotter.close()
