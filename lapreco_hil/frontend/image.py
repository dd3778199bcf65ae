"""The image both trackers run on, one definition for the OpenCV baseline and the Warp kernels.

Image = albedo x shading (the scope-tip light moves with the camera, vignetting, the camera's gain), so in the
log domain shading and gain are additive and a high-pass (log minus its Gaussian blur) keeps the texture. The
blur's sigma must be wide against what LK sees on its coarsest pyramid level: a narrow high-pass leaves the
coarse levels with next to no signal, so LK's capture range shrinks to a few pixels and real frames, whose
texture is coarser than the simulator's, are lost beyond ~20 px of motion. ``TrackerConfig.shading_sigma_px``
is therefore the sigma in pixels of the coarsest level; at full resolution it is that times 2^levels. That wide
blur is taken at a reduced resolution (block means, the blur, bilinear upsampling), as the Warp kernels do.

The number of pyramid levels (``TrackerConfig.pyramid_levels``, ``"auto"``: ``pyramid_levels``) follows the
image motion LK must reach without a pose prediction and the image's size: LK converges on its coarsest level
when the motion there is within about LK_COARSE_REACH_PX, and a coarsest level smaller than
``pyramid_min_coarsest_px`` has too few pixels to track on.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from lapreco_hil.config import TrackerConfig
from lapreco_hil.errors import ConfigError

# the log is taken of (grey + LOG_OFFSET): log(1 + grey) stretches the sensor noise of dark regions (the cavity
# beyond the light, the scope's vignetted rim) into full-range texture, which LK's coarse levels then follow
LOG_OFFSET = 16.0
# 8-bit levels per unit of the log high-pass when the baseline tracks it as an 8-bit image
HIGHPASS_GAIN = 96.0
# what the 8-bit image keeps of the log high-pass (a specular highlight beyond it is clamped, so its edge
# does not outweigh the texture in LK's sums or the corner threshold)
HIGHPASS_RANGE = 128.0 / HIGHPASS_GAIN
# the motion (px on the coarsest level) LK alone still converges from on real frames (docs/benchmarks.md,
# "LK's reach without the motion")
LK_COARSE_REACH_PX = 2.5
# how far the global motion prior (frontend.global_motion) can put a track from where it is: LK from the prior
# climbs only the levels this needs. All of them let a periodic texture (a chessboard zoomed at 80 px per frame)
# pull most tracks one period off on the coarse levels, and the consensus then agreed on the wrong homography
# (docs/benchmarks.md, session 22)
PRIOR_ERROR_PX = 20.0
# the baseline's shading estimate: at a resolution reduced by a power of two up to this, keeping its sigma at
# least SHADING_MIN_SIGMA_PX pixels there; the 3-level sigma (24 px) stays at full resolution, exactly the blur
# the simulated and real-frame figures were measured with (a coarser one moved them: docs/benchmarks.md, session 11)
SHADING_MAX_FACTOR = 32
SHADING_MIN_SIGMA_PX = 16.0


def pyramid_levels(config: TrackerConfig, width: int, height: int) -> int:
    """The pyramid levels above full resolution for a ``width`` x ``height`` image: the configured number, or
    with ``"auto"`` the fewest that bring ``expected_motion_px`` within LK_COARSE_REACH_PX on the coarsest
    level, as long as that level keeps ``pyramid_min_coarsest_px`` pixels on its shorter side."""
    if config.pyramid_levels != "auto":
        if isinstance(config.pyramid_levels, bool) or not isinstance(config.pyramid_levels, int) \
                or config.pyramid_levels < 0:
            raise ConfigError(f'[tracker] pyramid_levels = {config.pyramid_levels!r}: must be a whole number >= 0 '
                              f'or "auto"')
        return config.pyramid_levels
    return levels_for_reach(config.expected_motion_px, config, width, height)


def prior_levels(config: TrackerConfig, width: int, height: int) -> int:
    """LK's pyramid levels above full resolution for tracks started from the global motion prior: those that
    reach PRIOR_ERROR_PX, never more than ``pyramid_levels`` gives."""
    return min(pyramid_levels(config, width, height), levels_for_reach(PRIOR_ERROR_PX, config, width, height))


def levels_for_reach(reach_px: float, config: TrackerConfig, width: int, height: int) -> int:
    """The fewest pyramid levels that bring a motion of ``reach_px`` within LK_COARSE_REACH_PX on the coarsest
    level, as long as that level keeps ``pyramid_min_coarsest_px`` pixels on its shorter side."""
    for_motion = math.ceil(math.log2(max(reach_px / LK_COARSE_REACH_PX, 1.0)))
    for_size = int(math.floor(math.log2(max(min(width, height) / config.pyramid_min_coarsest_px, 1.0))))
    return max(0, min(for_motion, for_size))


def predicted_levels(config: TrackerConfig, levels: int, width: int, height: int, uncertainty_px: float) -> int:
    """LK's pyramid levels for tracks started where a pose prediction puts them: the coarse-window levels
    (``coarse_from_level`` and up) only where the prediction's ``uncertainty_px`` needs them, never more than
    ``levels`` (the front-end's pyramid). Those levels are there to reach the whole motion without a prediction;
    with one they only cost: their wide window averages the motion of texture hundreds of pixels around a weak
    corner, and the finer levels cannot bring it back (docs/frontend-real-frames.md). The levels below them
    stay, as every predicted figure was measured with them. ``[tracker] reduced_predicted_levels`` off: all of
    ``levels``."""
    if not config.reduced_predicted_levels:
        return levels
    return min(levels, max(levels_for_reach(uncertainty_px, config, width, height), config.coarse_from_level - 1))


def shading_sigma_px(config: TrackerConfig, levels: int) -> float:
    """The high-pass's Gaussian sigma at full resolution for a pyramid of ``levels`` (0: no shading removal)."""
    return float(config.shading_sigma_px) * 2.0 ** levels


def shading_factor(sigma_px: float, max_factor: int = SHADING_MAX_FACTOR,
                   min_sigma_px: float = SHADING_MIN_SIGMA_PX) -> int:
    """The resolution reduction (a power of two, at most ``max_factor``) at which a full-resolution ``sigma_px``
    blur is taken, keeping at least ``min_sigma_px`` of sigma there."""
    factor = 1
    while factor < max_factor and sigma_px / (2 * factor) >= min_sigma_px:
        factor *= 2
    return factor


def shading_level(log: np.ndarray, sigma_px: float) -> np.ndarray:
    """The Gaussian blur of ``log`` (float32) with a full-resolution ``sigma_px``, taken at reduced resolution:
    factor x factor block means (blocks past the border: replicated pixels), the blur there (OpenCV's default
    border, reflected, as the full-resolution blur had), bilinear upsampling with pixel centres aligned."""
    factor = shading_factor(sigma_px)
    h, w = log.shape
    hp, wp_ = -(-h // factor) * factor, -(-w // factor) * factor
    padded = cv2.copyMakeBorder(log, 0, hp - h, 0, wp_ - w, cv2.BORDER_REPLICATE) if (hp, wp_) != (h, w) else log
    low = cv2.resize(padded, (wp_ // factor, hp // factor), interpolation=cv2.INTER_AREA) if factor > 1 else log
    low = cv2.GaussianBlur(low, (0, 0), sigma_px / factor)
    if factor == 1:
        return low
    return cv2.resize(low, (wp_, hp), interpolation=cv2.INTER_LINEAR)[:h, :w]


def remove_shading(gray: np.ndarray, sigma_px: float) -> np.ndarray:
    """Log-domain high-pass (float32) with a full-resolution sigma."""
    log = np.log(gray.astype(np.float32) + LOG_OFFSET)
    return log - shading_level(log, sigma_px)


def to_u8(high: np.ndarray) -> np.ndarray:
    return np.clip(high * HIGHPASS_GAIN + 128.0, 0, 255).astype(np.uint8)


def tracker_image(gray: np.ndarray, config: TrackerConfig, levels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(the 8-bit image LK and the corner detector run on, its float version for the drift check): the log
    high-pass clamped to HIGHPASS_RANGE, or plain intensity in [0, 1] with ``shading_sigma_px`` 0. ``levels``:
    the pyramid LK runs on (None: ``pyramid_levels`` for this image's size)."""
    if levels is None:
        levels = pyramid_levels(config, gray.shape[1], gray.shape[0])
    sigma = shading_sigma_px(config, levels)
    if sigma > 0:
        high = np.clip(remove_shading(gray, sigma), -HIGHPASS_RANGE, HIGHPASS_RANGE)
        return to_u8(high), high
    return gray, gray.astype(np.float32) / 255.0
