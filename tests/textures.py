"""Synthetic frames shared by the tests of the drift check, the stereo rescue and the dense maps."""

import cv2
import numpy as np


def low_contrast_frame(shift, noise_seed, width: int, height: int, margin: int, contrast=6.0, noise=3.0):
    """Smooth random texture of ``contrast`` grey levels (std) moved by ``shift`` px, with its own sensor noise
    (seeded by ``noise_seed``): a BGR frame of ``width`` x ``height``, cut ``margin`` px inside the moved texture."""
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.normal(0, 1, (height + 2 * margin, width + 2 * margin)).astype(np.float32),
                               (0, 0), 2.0)
    texture /= texture.std()
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(texture, M, (width + 2 * margin, height + 2 * margin), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)[margin:-margin, margin:-margin]
    grey = 120 + contrast * moved + np.random.default_rng(noise_seed).normal(0, noise, (height, width))
    return cv2.cvtColor(np.clip(grey, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def plane_grey_views(camera, plane_z_m: float, texel_m: float, camera_x_m: dict) -> dict:
    """A smooth random texture on a fronto-parallel plane ``plane_z_m`` ahead, seen by pinhole ``camera``s moved
    sideways by ``camera_x_m[i]`` (metres): {i: float32 grey image}, without noise."""
    rng = np.random.default_rng(0)
    n = 2048
    texture = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 1.5)
    texture = (128 + 40 * texture / texture.std()).astype(np.float32)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float32)
    views = {}
    for i, x0 in camera_x_m.items():
        x = x0 + (u - camera.cx) / camera.fx * plane_z_m
        y = (v - camera.cy) / camera.fy * plane_z_m
        views[i] = cv2.remap(texture, (x / texel_m + n / 2).astype(np.float32),
                             (y / texel_m + n / 2).astype(np.float32), cv2.INTER_LINEAR)
    return views
