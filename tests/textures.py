"""Synthetic frames shared by the tests of the drift check and the stereo rescue."""

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
