"""The image both trackers run on, one definition for the OpenCV baseline and the Warp kernels.

Image = albedo x shading (the scope-tip light moves with the camera, vignetting, the camera's gain), so in the
log domain shading and gain are additive and a high-pass (log minus its Gaussian blur) keeps the texture. The
blur's sigma must be wide against what LK sees on its coarsest pyramid level: a narrow high-pass leaves the
coarse levels with next to no signal, so LK's capture range shrinks to a few pixels and real frames, whose
texture is coarser than the simulator's, are lost beyond ~20 px of motion. ``TrackerConfig.shading_sigma_px``
is therefore the sigma in pixels of the coarsest level; at full resolution it is that times 2^levels.
"""

from __future__ import annotations

import cv2
import numpy as np

from lapreco_hil.config import TrackerConfig

# the log is taken of (grey + LOG_OFFSET): log(1 + grey) stretches the sensor noise of dark regions (the cavity
# beyond the light, the scope's vignetted rim) into full-range texture, which LK's coarse levels then follow
LOG_OFFSET = 16.0
# 8-bit levels per unit of the log high-pass when the baseline tracks it as an 8-bit image
HIGHPASS_GAIN = 96.0
# what the 8-bit image keeps of the log high-pass (a specular highlight beyond it is clamped, so its edge
# does not outweigh the texture in LK's sums or the corner threshold)
HIGHPASS_RANGE = 128.0 / HIGHPASS_GAIN


def shading_sigma_px(config: TrackerConfig) -> float:
    """The high-pass's Gaussian sigma at full resolution (0: no shading removal)."""
    return float(config.shading_sigma_px) * 2.0 ** config.pyramid_levels


def remove_shading(gray: np.ndarray, sigma_px: float) -> np.ndarray:
    """Log-domain high-pass (float32) with a full-resolution sigma."""
    log = np.log(gray.astype(np.float32) + LOG_OFFSET)
    return log - cv2.GaussianBlur(log, (0, 0), sigma_px)


def to_u8(high: np.ndarray) -> np.ndarray:
    return np.clip(high * HIGHPASS_GAIN + 128.0, 0, 255).astype(np.uint8)


def tracker_image(gray: np.ndarray, config: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """(the 8-bit image LK and the corner detector run on, its float version for the drift check): the log
    high-pass clamped to HIGHPASS_RANGE, or plain intensity in [0, 1] with ``shading_sigma_px`` 0."""
    sigma = shading_sigma_px(config)
    if sigma > 0:
        high = np.clip(remove_shading(gray, sigma), -HIGHPASS_RANGE, HIGHPASS_RANGE)
        return to_u8(high), high
    return gray, gray.astype(np.float32) / 255.0
