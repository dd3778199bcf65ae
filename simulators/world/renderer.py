"""Ray-casting renderer of the simulated world in Warp: the same kernel runs on the CPU and on CUDA.

What it models (what a laparoscope sees): a pinhole camera with OpenCV's/the seed's lens distortion (each
distorted pixel is undistorted by fixed-point iteration, as cv2.undistortPoints does, and its ray cast), a
light at the scope tip (Lambert with inverse-square falloff and a cos^2 spot profile, plus Blinn-Phong
highlights that move with the camera), the scope's circular field of view, and sensor noise
(read + shot). Textures are sampled triplanar in the scene frame with a mip level from the pixel's
footprint, so texture does not shimmer as the camera moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from lapreco_hil.camera import CameraModel

MAX_LEVELS = 12


@wp.func
def _mirror(i: int, n: int) -> int:
    p = 2 * n
    m = i % p
    if m < 0:
        m += p
    if m >= n:
        m = p - 1 - m
    return m


@wp.func
def _texel(tex: wp.array(dtype=wp.vec3), off: int, w: int, h: int, x: int, y: int) -> wp.vec3:
    return tex[off + _mirror(y, h) * w + _mirror(x, w)]


@wp.func
def _bilinear(tex: wp.array(dtype=wp.vec3), off: int, w: int, h: int, u: float, v: float) -> wp.vec3:
    x = u - 0.5
    y = v - 0.5
    x0 = int(wp.floor(x))
    y0 = int(wp.floor(y))
    fx = x - float(x0)
    fy = y - float(y0)
    a = _texel(tex, off, w, h, x0, y0)
    b = _texel(tex, off, w, h, x0 + 1, y0)
    c = _texel(tex, off, w, h, x0, y0 + 1)
    d = _texel(tex, off, w, h, x0 + 1, y0 + 1)
    return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy


@wp.func
def _sample_level(tex: wp.array(dtype=wp.vec3), lv_off: wp.array(dtype=int), lv_w: wp.array(dtype=int),
                  lv_h: wp.array(dtype=int), mat: int, level: int, s: float, t: float) -> wp.vec3:
    k = mat * MAX_LEVELS + level
    w = lv_w[k]
    h = lv_h[k]
    # s, t in level-0 texels; this level has w/w0 as many
    scale = float(w) / float(lv_w[mat * MAX_LEVELS])
    return _bilinear(tex, lv_off[k], w, h, s * scale, t * scale)


@wp.func
def _sample_trilinear(tex: wp.array(dtype=wp.vec3), lv_off: wp.array(dtype=int), lv_w: wp.array(dtype=int),
                      lv_h: wp.array(dtype=int), n_levels: int, mat: int, lod: float, s: float,
                      t: float) -> wp.vec3:
    l = wp.clamp(lod, 0.0, float(n_levels - 1))
    l0 = int(wp.floor(l))
    l1 = wp.min(l0 + 1, n_levels - 1)
    f = l - float(l0)
    a = _sample_level(tex, lv_off, lv_w, lv_h, mat, l0, s, t)
    b = _sample_level(tex, lv_off, lv_w, lv_h, mat, l1, s, t)
    return a * (1.0 - f) + b * f


@wp.kernel
def _render_kernel(
    mesh: wp.uint64,
    normals: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=int),
    tri_material: wp.array(dtype=int),
    tex: wp.array(dtype=wp.vec3),
    lv_off: wp.array(dtype=int),
    lv_w: wp.array(dtype=int),
    lv_h: wp.array(dtype=int),
    mat_levels: wp.array(dtype=int),
    mat_texel_m: wp.array(dtype=float),
    mat_ks: wp.array(dtype=float),
    mat_shininess: wp.array(dtype=float),
    mat_planar: wp.array(dtype=int),  # 1: texture mapped on a plane (origin, u, v axes in the world)
    mat_origin: wp.array(dtype=wp.vec3),
    mat_u: wp.array(dtype=wp.vec3),
    mat_v: wp.array(dtype=wp.vec3),
    intrinsics: wp.vec4,  # fx, fy, cx, cy
    dist: wp.array(dtype=float),  # OpenCV's 12 coefficients
    R_wc: wp.mat33,
    t_wc: wp.vec3,
    fov_radius: float,
    light_w: float,  # irradiance at 1 m on axis
    ambient: float,
    noise_read: float,
    noise_shot: float,
    seed: int,
    image: wp.array3d(dtype=wp.uint8),
    depth: wp.array2d(dtype=float),
):
    row, col = wp.tid()
    fx = intrinsics[0]
    fy = intrinsics[1]
    cx = intrinsics[2]
    cy = intrinsics[3]
    u = float(col)
    v = float(row)
    depth[row, col] = 0.0
    # circular field of view with a 1.5 px soft edge
    fov = float(1.0)
    if fov_radius > 0.0:
        rr = wp.sqrt((u - cx) * (u - cx) + (v - cy) * (v - cy))
        fov = wp.clamp((fov_radius - rr) / 1.5, 0.0, 1.0)
    color = wp.vec3(0.0, 0.0, 0.0)
    if fov > 0.0:
        # undistort the pixel (fixed point, as cv2.undistortPoints)
        x0 = (u - cx) / fx
        y0 = (v - cy) / fy
        x = x0
        y = y0
        k1 = dist[0]
        k2 = dist[1]
        p1 = dist[2]
        p2 = dist[3]
        k3 = dist[4]
        k4 = dist[5]
        k5 = dist[6]
        k6 = dist[7]
        s1 = dist[8]
        s2 = dist[9]
        s3 = dist[10]
        s4 = dist[11]
        for _it in range(30):
            r2 = x * x + y * y
            icdist = (1.0 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1.0 + ((k3 * r2 + k2) * r2 + k1) * r2)
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r2 * r2
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r2 * r2
            x = (x0 - dx) * icdist
            y = (y0 - dy) * icdist
        d_cam = wp.normalize(wp.vec3(x, y, 1.0))
        d = R_wc * d_cam
        q = wp.mesh_query_ray(mesh, t_wc, d, 10.0)
        if q.result:
            p = t_wc + d * q.t
            i0 = indices[q.face * 3 + 0]
            i1 = indices[q.face * 3 + 1]
            i2 = indices[q.face * 3 + 2]
            n = wp.normalize(normals[i0] * q.u + normals[i1] * q.v + normals[i2] * (1.0 - q.u - q.v))
            if wp.dot(n, d) > 0.0:
                n = -n
            cos_i = wp.max(-wp.dot(n, d), 0.0)
            mat = tri_material[q.face]
            # footprint of the pixel on the surface, in level-0 texels -> mip level
            texel = mat_texel_m[mat]
            footprint = q.t / (fx * d_cam[2]) / wp.max(cos_i, 0.25)
            lod = wp.log2(wp.max(footprint / texel, 1.0e-6))
            aw = n[0] * n[0] * n[0] * n[0]
            bw = n[1] * n[1] * n[1] * n[1]
            cw = n[2] * n[2] * n[2] * n[2]
            ws = aw + bw + cw
            nl = mat_levels[mat]
            albedo = wp.vec3(0.0, 0.0, 0.0)
            if mat_planar[mat] == 1:
                rel = p - mat_origin[mat]
                albedo = _sample_trilinear(tex, lv_off, lv_w, lv_h, nl, mat, lod, wp.dot(rel, mat_u[mat]) / texel,
                                           wp.dot(rel, mat_v[mat]) / texel)
            else:
                ca = _sample_trilinear(tex, lv_off, lv_w, lv_h, nl, mat, lod, p[1] / texel, p[2] / texel)
                cb = _sample_trilinear(tex, lv_off, lv_w, lv_h, nl, mat, lod, p[0] / texel, p[2] / texel)
                cc = _sample_trilinear(tex, lv_off, lv_w, lv_h, nl, mat, lod, p[0] / texel, p[1] / texel)
                albedo = (ca * aw + cb * bw + cc * cw) / ws
            spot = d_cam[2] * d_cam[2]
            irradiance = light_w * spot / (q.t * q.t)
            spec = mat_ks[mat] * wp.pow(cos_i, mat_shininess[mat]) * irradiance
            color = albedo * (cos_i * irradiance + ambient) + wp.vec3(spec, spec, spec)
            depth[row, col] = q.t * d_cam[2]
    rng = wp.rand_init(seed, row * image.shape[1] + col)
    for ch in range(3):
        c = color[ch] * fov
        c = c + wp.randn(rng) * (noise_read + noise_shot * wp.sqrt(wp.max(c, 0.0)))
        # BGR, as OpenCV and frame grabbers deliver it
        image[row, col, 2 - ch] = wp.uint8(int(wp.clamp(c * 255.0 + 0.5, 0.0, 255.0)))


@dataclass(frozen=True)
class Material:
    texture: np.ndarray  # (h, w, 3) float32 RGB in [0, 1]
    texel_size_m: float  # metres per texel at level 0
    specular: float = 0.3
    shininess: float = 40.0
    # texture on a plane instead of triplanar: (origin, u axis, v axis) in the scene frame; texel (s, t) lies
    # at origin + s * texel_size * u + t * texel_size * v (a calibration board must be exact, not blended)
    planar: tuple | None = None


@dataclass(frozen=True)
class Lighting:
    light_w: float = 0.012  # irradiance 1.2 at 0.1 m on axis
    ambient: float = 0.04
    noise_read: float = 0.006
    noise_shot: float = 0.012


class Renderer:
    """Owns the scene's device buffers (mesh, BVH, textures) and an output image; ``render`` casts one frame."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
                 materials: list[Material], camera: CameraModel, lighting: Lighting = Lighting(),
                 device: str | None = None, T_world_scene: np.ndarray | None = None) -> None:
        from lapreco_hil.simulators.world.textures import mip_chain

        self.device = wp.get_device(device)
        self.camera = camera
        self.lighting = lighting
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.int32)
        normals = vertex_normals(v, f)
        with wp.ScopedDevice(self.device):
            self._points = wp.array(v, dtype=wp.vec3)
            self._indices = wp.array(f.ravel(), dtype=int)
            self._normals = wp.array(normals, dtype=wp.vec3)
            self._mesh = wp.Mesh(points=self._points, indices=self._indices)
            self._tri_material = wp.array(np.ascontiguousarray(face_material, np.int32), dtype=int)
            data, off, ws, hs, nlev = [], [], [], [], []
            total = 0
            for m in materials:
                chain = mip_chain(m.texture, MAX_LEVELS)
                nlev.append(len(chain))
                for lvl in range(MAX_LEVELS):
                    img = chain[min(lvl, len(chain) - 1)]
                    off.append(total if lvl < len(chain) else off[-1])
                    hs.append(img.shape[0])
                    ws.append(img.shape[1])
                    if lvl < len(chain):
                        data.append(img.reshape(-1, 3))
                        total += img.shape[0] * img.shape[1]
            self._tex = wp.array(np.concatenate(data).astype(np.float32), dtype=wp.vec3)
            self._lv_off = wp.array(np.array(off, np.int32), dtype=int)
            self._lv_w = wp.array(np.array(ws, np.int32), dtype=int)
            self._lv_h = wp.array(np.array(hs, np.int32), dtype=int)
            self._mat_levels = wp.array(np.array(nlev, np.int32), dtype=int)
            self._mat_texel = wp.array(np.array([m.texel_size_m for m in materials], np.float32), dtype=float)
            self._mat_ks = wp.array(np.array([m.specular for m in materials], np.float32), dtype=float)
            self._mat_sh = wp.array(np.array([m.shininess for m in materials], np.float32), dtype=float)
            T = np.eye(4) if T_world_scene is None else np.asarray(T_world_scene, float)
            planar = [m.planar or ((0, 0, 0), (1, 0, 0), (0, 1, 0)) for m in materials]
            self._mat_planar = wp.array(np.array([m.planar is not None for m in materials], np.int32), dtype=int)
            self._mat_origin = wp.array(np.array([T[:3, :3] @ o + T[:3, 3] for o, _, _ in planar], np.float32),
                                        dtype=wp.vec3)
            self._mat_u = wp.array(np.array([T[:3, :3] @ u for _, u, _ in planar], np.float32), dtype=wp.vec3)
            self._mat_v = wp.array(np.array([T[:3, :3] @ v for _, _, v in planar], np.float32), dtype=wp.vec3)
        # per camera (a stereo scope's second camera renders the same scene): its coefficients and output buffers
        self._targets: dict[CameraModel, tuple] = {}
        self._own_target = self._target(camera)

    def _target(self, camera: CameraModel) -> tuple:
        """(distortion coefficients, image, depth) device buffers of a camera, made on its first use."""
        target = self._targets.get(camera)
        if target is None:
            with wp.ScopedDevice(self.device):
                target = (wp.array(np.asarray(camera.dist, np.float32), dtype=float),
                          wp.zeros((camera.height, camera.width, 3), dtype=wp.uint8),
                          wp.zeros((camera.height, camera.width), dtype=float))
            self._targets[camera] = target
        return target

    def move_vertices(self, start: int, vertices: np.ndarray, normals: np.ndarray) -> None:
        """Replace vertices ``start:`` (a rigid part that moves, e.g. an instrument) and refit the BVH."""
        from lapreco_hil.warp_device import device_lock

        with device_lock(self.device):
            self._move_vertices(start, vertices, normals)

    def _move_vertices(self, start: int, vertices: np.ndarray, normals: np.ndarray) -> None:
        # only the moving part goes to the device; the rest of the mesh stays where it is
        self._points[start:].assign(np.ascontiguousarray(vertices, np.float32))
        self._normals[start:].assign(np.ascontiguousarray(normals, np.float32))
        self._mesh.refit()

    def render(self, T_world_camera: np.ndarray, seed: int = 0,
               camera: CameraModel | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(BGR uint8 image, depth along the optical axis in metres, 0 where nothing was hit) seen by ``camera``
        (default: the renderer's) at ``T_world_camera``."""
        from lapreco_hil.warp_device import device_lock

        with device_lock(self.device):
            return self._render(T_world_camera, seed, camera or self.camera)

    def _render(self, T_world_camera: np.ndarray, seed: int, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        light = self.lighting
        dist, image, depth = self._own_target if cam is self.camera else self._target(cam)
        R = T_world_camera[:3, :3].astype(np.float32)
        t = T_world_camera[:3, 3].astype(np.float32)
        wp.launch(
            _render_kernel,
            dim=(cam.height, cam.width),
            inputs=[
                self._mesh.id, self._normals, self._indices, self._tri_material, self._tex, self._lv_off,
                self._lv_w, self._lv_h, self._mat_levels, self._mat_texel, self._mat_ks, self._mat_sh,
                self._mat_planar, self._mat_origin, self._mat_u, self._mat_v,
                wp.vec4(cam.fx, cam.fy, cam.cx, cam.cy), dist, wp.mat33(*R.ravel()), wp.vec3(*t),
                float(cam.fov_radius_px), light.light_w, light.ambient, light.noise_read, light.noise_shot,
                int(seed), image, depth,
            ],
            device=self.device,
        )
        # on the CPU device .numpy() is a view of the buffer the next render overwrites: hand out copies
        return image.numpy().copy(), depth.numpy().copy()


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)
