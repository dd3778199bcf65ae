"""The simulated world: a scene, a camera on the simulated holder, a light at the scope tip, and a clock.

A simulated robot and a simulated grabber opened with the same name share one SimWorld (see
``lapreco_hil.registry.DeviceContext``), the way python-can's virtual buses with the same channel do.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.geometry import make_T, rot_x, transform_points
from lapreco_hil.kinematics import CameraKinematics
from lapreco_hil.robot_models import urdf_path

from lapreco_hil.simulators.robot import ComplianceModel, ScanTrajectory, SimulatedArm
from lapreco_hil.simulators.world.renderer import Lighting, Renderer, vertex_normals
from lapreco_hil.simulators.world.scenes import build_scene, instrument_material, instrument_mesh, instrument_pose

T0_NS = 1_000_000_000  # simulated time starts at 1 s: timestamps are never 0


def default_camera(width: int, height: int, hfov_deg: float = 70.0) -> CameraModel:
    """A laparoscope-like camera: strong barrel distortion in the seed's model, circular field of view."""
    fx = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    return CameraModel.from_paper_model(
        width, height, fx, fx, (width - 1) / 2 + 0.004 * width, (height - 1) / 2 - 0.003 * height,
        k=(-0.28, 0.09, -0.012), t=(0.0006, -0.0004), p=(0.0008, -0.0006),
        fov_radius_px=0.68 * np.hypot(width, height) / 2,
    )


def thirty_degree_optics(angle_deg: float = 30.0) -> np.ndarray:
    """Hand-eye T_tip_camera of an angled scope: optical axis tilted from the shaft (tip z), lens 1.5 mm
    off the shaft axis."""
    return make_T(rot_x(np.deg2rad(angle_deg)), [0.0, -0.0015, 0.0])


def stereo_rig(camera: CameraModel, baseline_m: float, right_focal_scale: float = 1.0) -> Rig:
    """A stereo scope's two cameras: camera 1 sits ``baseline_m`` to the right of camera 0 (x in camera 0's
    frame), looking the same way (an angled scope tilts both along one axis), with camera 0's lens except for
    its focal lengths scaled by ``right_focal_scale`` (real pairs differ by a fraction of a percent)."""
    right = CameraModel(camera.width, camera.height, camera.fx * right_focal_scale, camera.fy * right_focal_scale,
                        camera.cx, camera.cy, camera.dist, camera.fov_radius_px)
    T_cam0_cam1 = make_T(np.eye(3), [baseline_m, 0.0, 0.0])
    return Rig((camera, right), (np.eye(4), T_cam0_cam1))


@dataclass(frozen=True)
class SimSettings:
    scene: str = "skull"
    width: int = 640
    height: int = 480
    fps: float = 25.0
    robot_rate_hz: float = 200.0
    hfov_deg: float = 70.0
    optics_deg: float = 30.0  # the scope's viewing angle from its shaft (0: forward-viewing, 30: angled)
    seed: int = 0
    device: str | None = None
    delivery_latency_s: float = 0.02  # frame transfer: robot samples up to capture + this are available
    # None: simulated time advances only as frames are delivered (as fast as possible, deterministic);
    # a number: it flows with the wall clock at this rate, so threads that poll devices (real drivers on
    # emulators) see time pass between frames
    clock_speed: float | None = None
    instrument: bool = False  # a moving instrument shaft in view (not part of the true surface)
    trajectory: ScanTrajectory = field(default_factory=ScanTrajectory)
    compliance: ComplianceModel = field(default_factory=ComplianceModel)
    lighting: Lighting = field(default_factory=Lighting)


class SimWorld:
    def __init__(self, settings: SimSettings) -> None:
        self.settings = settings
        self.scene = build_scene(settings.scene, seed=settings.seed)
        self.camera = default_camera(settings.width, settings.height, settings.hfov_deg)
        self.T_tip_camera = thirty_degree_optics(settings.optics_deg)
        self.robot_model = "ecm"
        self.tip_frame = "ecm_tip"
        self.kinematics = CameraKinematics(str(urdf_path(self.robot_model)), self.tip_frame, self.T_tip_camera)
        self.arm = SimulatedArm(settings.trajectory, settings.compliance, settings.seed)
        # place the scene's ROI on the optical axis of the home pose, facing the camera
        T_world_home = self.kinematics.camera_pose(np.asarray(settings.trajectory.home))
        T_home_scene = make_T(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, self.scene.working_distance_m])
        self.T_world_scene = T_world_home @ T_home_scene
        self.vertices_world = transform_points(self.T_world_scene, self.scene.vertices)
        vertices, faces, face_material = self.vertices_world, self.scene.faces, self.scene.face_material
        materials = list(self.scene.materials)
        self._instrument = None
        if settings.instrument:
            iv, iff = instrument_mesh()
            self._instrument = (len(vertices), iv, vertex_normals(iv.astype(np.float32), iff))
            vertices = np.concatenate([vertices, iv])
            faces = np.concatenate([faces, iff + len(self.vertices_world)]).astype(np.int32)
            face_material = np.concatenate([face_material, np.full(len(iff), len(materials), np.int32)])
            materials.append(instrument_material())
        self.renderer = Renderer(vertices, faces, face_material, materials, self.camera, settings.lighting,
                                 settings.device, T_world_scene=self.T_world_scene)
        self._lock = threading.Lock()
        self._now_ns = T0_NS
        self._wall0_ns = time.monotonic_ns()

    # --- time -------------------------------------------------------------------------------------------
    def now_ns(self) -> int:
        speed = self.settings.clock_speed
        with self._lock:
            if speed is not None:
                self._now_ns = max(self._now_ns, T0_NS + int((time.monotonic_ns() - self._wall0_ns) * speed))
            return self._now_ns

    def advance_to(self, t_ns: int) -> None:
        """Stepped clock: time moves to t. Flowing clock: wait (sleep) until it has got there."""
        speed = self.settings.clock_speed
        if speed is not None:
            behind = t_ns - self.now_ns()
            if behind > 0:
                time.sleep(behind * 1e-9 / speed)
            return
        with self._lock:
            self._now_ns = max(self._now_ns, int(t_ns))

    @staticmethod
    def seconds(t_ns: int) -> float:
        return (t_ns - T0_NS) * 1e-9

    # --- truth --------------------------------------------------------------------------------------------
    def true_camera_pose(self, t_ns: int) -> np.ndarray:
        return self.kinematics.camera_pose(self.arm.true_joints(self.seconds(t_ns)))

    def _move_instrument(self, t_ns: int) -> None:
        if self._instrument is not None:
            start, iv, inormals = self._instrument
            T = self.T_world_scene @ instrument_pose(self.seconds(t_ns))
            self.renderer.move_vertices(start, transform_points(T, iv), inormals @ T[:3, :3].T)

    def _noise_seed(self, seq: int, camera: int = 0) -> int:
        return self.settings.seed * 1_000_003 + seq + camera * 500_009

    def render(self, t_ns: int, seq: int) -> tuple[np.ndarray, np.ndarray]:
        self._move_instrument(t_ns)
        return self.renderer.render(self.true_camera_pose(t_ns), seed=self._noise_seed(seq))

    def render_rig(self, t_ns: int, seq: int, rig: Rig) -> list[tuple[np.ndarray, np.ndarray]]:
        """(image, depth) of every camera of a rig whose camera 0 is the true camera, at one instant; camera 0's
        is what ``render`` gives, each other camera's sensor noise is its own."""
        self._move_instrument(t_ns)
        T_world_cam0 = self.true_camera_pose(t_ns)
        return [self.renderer.render(T_world_cam0 @ T_cam0_cam, seed=self._noise_seed(seq, k), camera=camera)
                for k, (camera, T_cam0_cam) in enumerate(zip(rig.cameras, rig.T_cam0_cam))]

    def surface_mesh(self):
        """The ground-truth surface in the world frame, as a pyvista PolyData (metres)."""
        import pyvista as pv

        faces = np.hstack([np.full((len(self.scene.faces), 1), 3), self.scene.faces]).ravel()
        return pv.PolyData(self.vertices_world, faces)
