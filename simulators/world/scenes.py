"""Ground-truth scenes at real scale, in metres.

Each scene is given in its own *scene frame*: the region of interest (ROI) at the origin, +z pointing out of
the viewed surface towards where the scope looks from, +y up in the image. The simulated world places the
scene frame in front of the scope's home pose, so one scan trajectory fits every scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

from lapreco_hil.errors import SceneError

from lapreco_hil.simulators.world.renderer import Material
from lapreco_hil.simulators.world.textures import (apple_texture, bone_texture, fat_texture, gallbladder_texture,
                                                   liver_texture, steel_texture, uterus_texture, value_noise)


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    vertices: np.ndarray  # (V, 3) float64, scene frame, metres
    faces: np.ndarray  # (F, 3) int32
    face_material: np.ndarray  # (F,) int32
    materials: tuple[Material, ...]
    working_distance_m: float  # camera-to-ROI distance at the home pose
    # a calibration board in the scene: its spec (lapreco_hil.calib.boards) and T_scene_board
    board: tuple[str, np.ndarray] | None = None


def _asset(name: str) -> str:
    return str(resources.files(__package__).joinpath("assets", name))


def _read_obj(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a Wavefront OBJ (polygons fanned): the skull loads without VTK."""
    verts, faces = [], []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(v) for v in line.split()[1:4]])
            elif line.startswith("f "):
                idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    return np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int32)


def _read_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    if name.endswith(".obj"):
        return _read_obj(_asset(name))
    import pyvista as pv

    mesh = pv.read(_asset(name)).triangulate().clean()
    faces = mesh.faces.reshape(-1, 4)[:, 1:].astype(np.int32)
    return np.asarray(mesh.points, dtype=np.float64), faces


def _surface_hit(vertices, faces, origin, direction) -> np.ndarray:
    """First intersection of a ray with a triangle mesh (Moller-Trumbore, vectorised over triangles)."""
    v0, v1, v2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    qv = np.cross(s, e1)
    v = (qv @ direction) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not hit.any():
        raise SceneError("scene construction: the ROI ray misses the mesh")
    return origin + direction * t[hit].min()


def _grid_sheet(size_m: float, n: int, height_fn) -> tuple[np.ndarray, np.ndarray]:
    """A square height-field sheet in the xy plane (z = height_fn(x, y)), triangulated."""
    xs = np.linspace(-size_m / 2, size_m / 2, n)
    X, Y = np.meshgrid(xs, xs)
    Z = height_fn(X, Y)
    verts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])]).astype(np.int32)
    return verts, faces


def _merge(parts):
    verts, faces, mats = [], [], []
    base = 0
    for v, f, m in parts:
        verts.append(v)
        faces.append(f + base)
        mats.append(np.full(len(f), m, np.int32))
        base += len(v)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32), np.concatenate(mats)


def skull_scene(rng: np.random.Generator) -> Scene:
    """A real skull scan scaled to 190 mm length, viewed at the face from 110 mm."""
    v, f = _read_mesh("skull.obj")
    v = v * (0.19 / float(np.ptp(v[:, 2])))  # mesh: +y up, +z forward (face); z extent = skull length
    roi = _surface_hit(v, f, np.array([0.0, float(v[:, 1].min() + 0.5 * np.ptp(v[:, 1])), 1.0]),
                       np.array([0.0, 0.0, -1.0]))
    v = v - roi
    bone = Material(bone_texture(rng), texel_size_m=0.00012, specular=0.12, shininess=18.0)
    return Scene("skull", "skull (real scan, 190 mm long), face and orbits", v, f, np.zeros(len(f), np.int32),
                 (bone,), working_distance_m=0.11)


def liver_scene(rng: np.random.Generator) -> Scene:
    """Liver and gallbladder (real models, mm -> m) viewed anteriorly, over a fat/omentum sheet."""
    liver_v, liver_f = _read_mesh("liver.vtk")
    gb_v, gb_f = _read_mesh("gallbladder.vtk")
    # models in mm; view from -y (anterior), +z up: scene x = x, y = z, z = -y
    to_scene = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    liver_v = liver_v @ to_scene.T * 1e-3
    gb_v = gb_v @ to_scene.T * 1e-3
    aim = 0.65 * gb_v.mean(axis=0) + 0.35 * liver_v.mean(axis=0)
    roi = _surface_hit(liver_v, liver_f, np.array([aim[0], aim[1], 1.0]), np.array([0.0, 0.0, -1.0]))
    liver_v, gb_v = liver_v - roi, gb_v - roi
    lobules = value_noise((64, 64), rng, octaves=3, base_cells=6)

    def omentum(x, y):
        i = np.clip(((x + 0.2) / 0.4 * 63).astype(int), 0, 63)
        j = np.clip(((y + 0.2) / 0.4 * 63).astype(int), 0, 63)
        return -0.05 + 0.004 * lobules[j, i] + 0.002 * np.sin(x * 180) * np.cos(y * 150)

    sheet_v, sheet_f = _grid_sheet(0.4, 160, omentum)
    v, f, m = _merge([(liver_v, liver_f, 0), (gb_v, gb_f, 1), (sheet_v, sheet_f, 2)])
    mats = (
        Material(liver_texture(rng), texel_size_m=0.00010, specular=0.45, shininess=60.0),
        Material(gallbladder_texture(rng), texel_size_m=0.00010, specular=0.5, shininess=50.0),
        Material(fat_texture(rng), texel_size_m=0.00012, specular=0.3, shininess=30.0),
    )
    return Scene("liver", "liver and gallbladder (real models) over omentum, anterior view", v, f, m, mats,
                 working_distance_m=0.10)


def _lat_long(nt: int, nphi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta, phi) grids of a closed lat-long surface and its triangles (vertex index = i_theta * nphi + i_phi)."""
    theta = np.linspace(0.0, np.pi, nt)
    phi = np.linspace(0.0, 2 * np.pi, nphi, endpoint=False)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    idx = np.arange(nt * nphi).reshape(nt, nphi)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
    faces = np.concatenate([np.column_stack([a, c, d]), np.column_stack([a, d, b])]).astype(np.int32)
    return T, P, faces


def _on_table(obj_v: np.ndarray, obj_f: np.ndarray, table_m: float, elevation_deg: float):
    """An object standing on a flat table (z = 0), turned into the scene frame of a scope looking down at
    ``elevation_deg``, with the ROI where the optical axis meets the object; (vertices, faces, materials)."""
    table_v, table_f = _grid_sheet(table_m, 60, lambda x, y: np.zeros_like(x))
    v, f, m = _merge([(obj_v, obj_f, 0), (table_v, table_f, 1)])
    elev = np.deg2rad(elevation_deg)
    z_s = np.array([0.0, -np.cos(elev), np.sin(elev)])
    y_s = np.array([0.0, 0.0, 1.0]) - z_s * z_s[2]
    y_s /= np.linalg.norm(y_s)
    R = np.vstack([np.cross(y_s, z_s), y_s, z_s])
    v = v @ R.T
    roi = _surface_hit(v, f, np.array([0.0, (obj_v.mean(axis=0) @ R.T)[1], 1.0]), np.array([0.0, 0.0, -1.0]))
    return v - roi, f, m


def _drape(rng: np.random.Generator, colour) -> Material:
    tex = np.ones((256, 256, 3), np.float32) * np.array(colour, np.float32)
    tex *= (0.7 + 0.6 * value_noise((256, 256), rng, octaves=6, base_cells=16))[..., None]
    return Material(tex, texel_size_m=0.00025, specular=0.05, shininess=10.0)


def apple_scene(rng: np.random.Generator) -> Scene:
    """A 76 mm apple on a drape, seen from 40 degrees above the table (the seed's first experiment)."""
    radius = 0.038
    T, P, apple_f = _lat_long(96, 192)
    # dimples at stem (theta=0) and calyx, slightly wider shoulders
    r = radius * (1.0 - 0.22 * np.exp(-(T**2) / 0.05) - 0.12 * np.exp(-((np.pi - T) ** 2) / 0.06)
                  + 0.04 * np.sin(T) * np.cos(T) + 0.01 * np.cos(5 * P) * np.sin(T))
    pts = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r * np.cos(T)], -1).reshape(-1, 3)
    apple_v = pts + np.array([0.0, 0.0, 0.95 * radius])  # resting on the table (z = 0)
    v, f, m = _on_table(apple_v, apple_f, 0.4, 40.0)
    drape = _drape(rng, (0.18, 0.40, 0.42))
    mats = (Material(apple_texture(rng), texel_size_m=0.00010, specular=0.6, shininess=80.0), drape)
    return Scene("apple", "apple (76 mm) on a drape, 40 degrees from above", v, f, m, mats,
                 working_distance_m=0.09)


def uterus_scene(rng: np.random.Generator) -> Scene:
    """An ex-vivo uterus (about 80 x 55 x 40 mm, pear-shaped, wet and shiny) on a drape, as in the seed's second
    experiment, viewed from above at 45 degrees."""
    T_, P, organ_f = _lat_long(80, 160)
    # long axis x: wider fundus (x > 0), narrowing to the cervix, flattened front to back
    along = np.cos(T_)
    radius = 0.026 * (1.0 + 0.25 * along) * (1.0 + 0.03 * np.sin(3 * P) * np.sin(T_))
    x = 0.04 * along
    y = radius * np.sin(T_) * np.cos(P)
    z = 0.72 * radius * np.sin(T_) * np.sin(P)
    pts = np.stack([x, y, z], -1).reshape(-1, 3) + np.array([0.0, 0.0, 0.016])
    v, f, m = _on_table(pts, organ_f, 0.3, 45.0)
    drape = _drape(rng, (0.20, 0.35, 0.45))
    mats = (Material(uterus_texture(rng), texel_size_m=0.00010, specular=0.7, shininess=90.0), drape)
    return Scene("uterus", "ex-vivo uterus (80 mm, wet serosa) on a drape, 45 degrees from above", v, f, m, mats,
                 working_distance_m=0.09)


def instrument_mesh(length_m: float = 0.12, radius_m: float = 0.0025, n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A 5 mm instrument shaft along +z from its tip at the origin, with a closed tip."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    zs = np.linspace(0.0, length_m, 25)
    ring = np.column_stack([radius_m * np.cos(ang), radius_m * np.sin(ang)])
    verts = np.concatenate([np.column_stack([ring, np.full(n, z)]) for z in zs] + [np.array([[0.0, 0.0, -0.002]])])
    faces = []
    for k in range(len(zs) - 1):
        for i in range(n):
            a, b = k * n + i, k * n + (i + 1) % n
            faces += [[a, b + n, b], [a, a + n, b + n]]
    tip = len(verts) - 1
    faces += [[tip, (i + 1) % n, i] for i in range(n)]
    return verts, np.array(faces, np.int32)


def instrument_material() -> Material:
    return Material(steel_texture(np.random.default_rng(0)), texel_size_m=0.0002, specular=0.9, shininess=120.0)


def instrument_pose(t_s: float) -> np.ndarray:
    """T_scene_instrument at t: the shaft pivots about a trocar up and to the side while its tip sweeps over
    the region of interest, 6-14 mm above it, covering part of the view."""
    trocar = np.array([0.07, 0.06, 0.08])
    tip = np.array([0.014 * np.sin(2 * np.pi * t_s / 5.0), 0.010 * np.sin(2 * np.pi * t_s / 3.3 + 1.0),
                    0.010 + 0.004 * np.sin(2 * np.pi * t_s / 4.1)])
    z = trocar - tip
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = tip
    return T


BOARD_SPEC = "charuco:10x7:0.004:0.003:DICT_5X5_100"


def board_scene(rng: np.random.Generator) -> Scene:
    """A ChArUco calibration board (10 x 7 squares of 4 mm, 3 mm markers: 9 x 6 = 54 inner corners) on a
    flat plate, viewed from 70 mm, as used to calibrate a laparoscope's lens and hand-eye."""
    import cv2

    square, px = 0.004, 64  # texels per square: the texture is exact at the board's corners
    cols, rows, margin = 10, 7, 2 * px
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100)
    board = cv2.aruco.CharucoBoard((cols, rows), square, 0.003, dictionary)
    gray = board.generateImage((cols * px, rows * px), marginSize=0).astype(np.float32) / 255.0
    tex = np.ones((rows * px + 2 * margin, cols * px + 2 * margin), np.float32)
    tex[margin:margin + rows * px, margin:margin + cols * px] = gray
    tex = np.repeat((0.02 + 0.33 * tex)[..., None], 3, axis=2)  # matte plate: white not saturated at 70 mm
    texel = square / px
    w, h = tex.shape[1] * texel, tex.shape[0] * texel
    verts = np.array([[-w / 2, h / 2, 0.0], [w / 2, h / 2, 0.0], [w / 2, -h / 2, 0.0], [-w / 2, -h / 2, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    origin, u, v = verts[0], np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])  # texture rows run down
    T_scene_board = np.eye(4)
    T_scene_board[:3, :3] = np.column_stack([u, v, np.cross(u, v)])  # OpenCV board frame: z into the board
    T_scene_board[:3, 3] = origin + margin * texel * (u + v)
    # the board's centre at the scene origin (the ROI on the optical axis)
    centre = T_scene_board[:3, :3] @ np.array([cols * square / 2, rows * square / 2, 0.0]) + T_scene_board[:3, 3]
    verts = verts - centre
    origin = origin - centre
    T_scene_board[:3, 3] -= centre
    plate = Material(tex, texel_size_m=texel, specular=0.15, shininess=30.0, planar=(origin, u, v))
    return Scene("board", "ChArUco calibration board, 10 x 7 squares of 4 mm", verts, faces,
                 np.zeros(2, np.int32), (plate,), working_distance_m=0.07, board=(BOARD_SPEC, T_scene_board))


SCENES = {"skull": skull_scene, "liver": liver_scene, "apple": apple_scene, "uterus": uterus_scene,
          "board": board_scene}


def build_scene(name: str, seed: int = 0) -> Scene:
    try:
        builder = SCENES[name]
    except KeyError:
        raise SceneError(f"unknown scene '{name}' (known: {', '.join(sorted(SCENES))})") from None
    return builder(np.random.default_rng(seed))
