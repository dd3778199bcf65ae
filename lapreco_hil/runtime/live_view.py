"""The live view: the current frame projected onto the current mesh (projective texturing, the seed's "video
beamer"), rendered off-screen from the current camera pose, to PNG files and an MP4.

One PyVista plotter lives in the thread that calls ``render`` (VTK objects are not shared between threads)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pyvista as pv

from lapreco_hil.camera import CameraModel
from lapreco_hil.geometry import inv_T


def projective_tcoords(mesh: pv.PolyData, camera: CameraModel, T_world_camera: np.ndarray) -> tuple[np.ndarray,
                                                                                                      np.ndarray]:
    """Texture coordinates (u, v in [0, 1], v up as VTK wants) of each mesh vertex in the frame, and which
    vertices the frame actually sees (in front of the camera and inside the image)."""
    T_cw = inv_T(T_world_camera)
    pc = np.asarray(mesh.points) @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = pc[:, 2] > 1e-4
    uv = np.full((len(pc), 2), -1.0)
    if front.any():
        uv[front] = camera.project(pc[front])
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    tc = np.column_stack([(uv[:, 0] + 0.5) / camera.width, 1.0 - (uv[:, 1] + 0.5) / camera.height])
    return np.clip(tc, 0.0, 1.0), inside


class LiveView:
    def __init__(self, camera: CameraModel, out_dir: Path, period_s: float, window=(640, 480), mp4: bool = True):
        if not os.environ.get("DISPLAY"):
            os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        self.camera = camera
        self.dir = Path(out_dir) / "live"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.window = window
        self.plotter = pv.Plotter(off_screen=True, window_size=list(window))
        self.plotter.set_background("#10141a")
        self.count = 0
        self.writer = None
        if mp4:
            fps = max(1.0, 1.0 / period_s) if period_s > 0 else 5.0
            self.writer = cv2.VideoWriter(str(Path(out_dir) / "live.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                          tuple(window))

    def render(self, mesh: pv.PolyData, frame, T_world_camera: np.ndarray) -> np.ndarray:
        if mesh is None or mesh.n_cells == 0:
            return None
        textured = mesh.copy()
        tc, seen = projective_tcoords(textured, self.camera, T_world_camera)
        textured.active_texture_coordinates = tc
        rgb = cv2.cvtColor(frame.image, cv2.COLOR_BGR2RGB)
        self.plotter.clear_actors()
        self.plotter.add_mesh(textured, texture=pv.Texture(rgb), smooth_shading=True)
        unseen = textured.extract_points(~seen, adjacent_cells=False) if (~seen).any() else None
        if unseen is not None and unseen.n_points:
            self.plotter.add_mesh(unseen, color="#808890", point_size=2)
        # the virtual camera at the real one (OpenCV: x right, y down, z forward)
        cam = self.plotter.camera
        cam.position = T_world_camera[:3, 3]
        cam.focal_point = T_world_camera[:3, 3] + T_world_camera[:3, 2] * 0.05
        cam.up = -T_world_camera[:3, 1]
        cam.view_angle = float(np.degrees(2 * np.arctan(self.camera.height / (2 * self.camera.fy))))
        cam.clipping_range = (0.001, 1.0)
        image = self.plotter.screenshot(return_img=True)
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(self.dir / f"view_{self.count:05d}.png"), bgr)
        if self.writer is not None:
            self.writer.write(cv2.resize(bgr, tuple(self.window)))
        self.count += 1
        return bgr

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()
        self.plotter.close()
