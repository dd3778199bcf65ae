"""Tissue textures for the simulated world, as float32 RGB images in [0, 1].

Liver and fat come from crops of a real laparoscope frame (assets/liver_frame_1920x1080.png) with
procedural vessels drawn over them; bone and apple are procedural. Every texture is seeded, so a scene
looks the same in every run.
"""

from __future__ import annotations

from importlib import resources

import cv2
import numpy as np

# crops of the real frame (x0, y0, x1, y1) inside its circular field of view, away from highlights
_LIVER_CROP = (240, 380, 560, 640)
_FAT_CROP = (950, 690, 1400, 980)


def _asset(name: str) -> str:
    return str(resources.files(__package__).joinpath("assets", name))


def _real_frame() -> np.ndarray:
    image = cv2.imread(_asset("liver_frame_1920x1080.png"), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(_asset("liver_frame_1920x1080.png"))
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def value_noise(shape: tuple[int, int], rng: np.random.Generator, octaves: int = 5,
                base_cells: int = 4) -> np.ndarray:
    """Smooth multi-octave noise in [0, 1] (bicubic-upsampled random grids)."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = base_cells * 2**o
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.55
    out /= total
    return (out - out.min()) / max(float(out.max() - out.min()), 1e-6)


def draw_vessels(image: np.ndarray, rng: np.random.Generator, n_trees: int, color, max_width: int,
                 segment_px: float) -> None:
    """Branching vessel trees (random walks that fork and thin), anti-aliased, in place."""
    h, w = image.shape[:2]
    color = tuple(float(c) for c in color)
    stack = []
    for _ in range(n_trees):
        stack.append((rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * np.pi), max_width, 40))
    while stack:
        x, y, ang, width, steps = stack.pop()
        for _ in range(steps):
            ang += rng.normal(0, 0.25)
            nx, ny = x + segment_px * np.cos(ang), y + segment_px * np.sin(ang)
            cv2.line(image, (int(x * 16), int(y * 16)), (int(nx * 16), int(ny * 16)), color,
                     max(1, int(width)), cv2.LINE_AA, shift=4)
            x, y = nx, ny
            if not (0 <= x < w and 0 <= y < h):
                break
            if width > 1 and rng.random() < 0.08:
                stack.append((x, y, ang + rng.choice([-1, 1]) * rng.uniform(0.4, 1.0), width - 1, steps // 2))


def liver_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    crop = _real_frame()[_LIVER_CROP[1]:_LIVER_CROP[3], _LIVER_CROP[0]:_LIVER_CROP[2]]
    tex = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)
    # flatten the crop's shading so the renderer's lighting is the only shading
    tex /= np.maximum(cv2.GaussianBlur(tex, (0, 0), size / 6), 1e-3)
    tex *= np.array([0.55, 0.20, 0.17], np.float32)
    # the capsule's fine mottling and lobule pattern
    tex *= (0.8 + 0.4 * value_noise((size, size), rng, octaves=6, base_cells=8))[..., None]
    draw_vessels(tex, rng, n_trees=6, color=(0.30, 0.05, 0.06), max_width=3, segment_px=6)
    return np.clip(tex, 0, 1)


def fat_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    crop = _real_frame()[_FAT_CROP[1]:_FAT_CROP[3], _FAT_CROP[0]:_FAT_CROP[2]]
    tex = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)
    draw_vessels(tex, rng, n_trees=8, color=(0.65, 0.08, 0.05), max_width=2, segment_px=5)
    return np.clip(tex, 0, 1)


def gallbladder_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    base = np.ones((size, size, 3), np.float32) * np.array([0.75, 0.72, 0.62], np.float32)
    base *= (0.85 + 0.3 * value_noise((size, size), rng))[..., None]
    draw_vessels(base, rng, n_trees=10, color=(0.7, 0.15, 0.12), max_width=2, segment_px=4)
    return np.clip(base, 0, 1)


def bone_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    n = value_noise((size, size), rng, octaves=6, base_cells=6)
    fine = value_noise((size, size), rng, octaves=3, base_cells=64)
    base = np.array([0.86, 0.80, 0.66], np.float32)
    tex = base * (0.70 + 0.30 * n[..., None]) * (0.85 + 0.15 * fine[..., None])
    # pores and stains
    for _ in range(900):
        x, y = rng.integers(0, size, 2)
        r = int(rng.integers(1, 3))
        cv2.circle(tex, (int(x), int(y)), r, tuple(float(c) for c in base * rng.uniform(0.35, 0.6)), -1,
                   cv2.LINE_AA)
    draw_vessels(tex, rng, n_trees=5, color=tuple(base * 0.45), max_width=1, segment_px=4)
    return np.clip(tex, 0, 1)


def uterus_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Serosa of an ex-vivo uterus: pale pink, mottled, with fine subserosal vessels."""
    base = np.array([0.80, 0.52, 0.50], np.float32)
    tex = base * (0.75 + 0.25 * value_noise((size, size), rng, octaves=5, base_cells=8)[..., None])
    tex *= (0.9 + 0.1 * value_noise((size, size), rng, octaves=3, base_cells=48))[..., None]
    draw_vessels(tex, rng, n_trees=14, color=(0.55, 0.18, 0.22), max_width=2, segment_px=5)
    return np.clip(tex, 0, 1)


def steel_texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    """Brushed steel of an instrument shaft."""
    streaks = value_noise((size, size), rng, octaves=2, base_cells=4)
    return np.clip(np.ones((size, size, 3), np.float32) * (0.35 + 0.15 * streaks[..., None]), 0, 1)


def apple_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    streak = value_noise((size, size // 8), rng, octaves=4, base_cells=4)
    streak = cv2.resize(streak, (size, size), interpolation=cv2.INTER_CUBIC)
    blotch = value_noise((size, size), rng, octaves=5, base_cells=3)
    red = np.array([0.62, 0.06, 0.05], np.float32)
    yellow = np.array([0.85, 0.65, 0.18], np.float32)
    mix = np.clip(0.3 + 0.9 * streak * blotch, 0, 1)[..., None]
    tex = red * mix + yellow * (1 - mix)
    for _ in range(1500):  # lenticels
        x, y = rng.integers(0, size, 2)
        cv2.circle(tex, (int(x), int(y)), 1, (0.9, 0.85, 0.55), -1, cv2.LINE_AA)
    return np.clip(tex, 0, 1)


def mip_chain(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """Level 0 is the texture; each next level halves it (area filter), for footprint-aware sampling."""
    chain = [texture.astype(np.float32)]
    for _ in range(levels - 1):
        h, w = chain[-1].shape[:2]
        if min(h, w) < 4:
            break
        chain.append(cv2.resize(chain[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return chain
