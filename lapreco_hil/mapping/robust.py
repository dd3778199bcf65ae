"""The seed's robust cost: minimise sum rho(||x - Pi(X)||^2), first with Cauchy's loss to get near the optimum,
then with Tukey's biweight (redescending: gross outliers get no weight); the scale, i.e. the outlier
threshold, comes from the median absolute deviation of the residuals and is re-estimated before each stage.

GTSAM's m-estimators take a fixed k in whitened units, so the schedule whitens the reprojection errors with
the MAD scale and uses the textbook tuning constants (95% efficiency at the Gaussian).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD_TO_SIGMA = 1.4826  # sigma of a Gaussian = 1.4826 x its median absolute deviation
CAUCHY_K = 2.3849
TUKEY_C = 4.6851


def _median_in_place(e: np.ndarray) -> float:
    """The median of finite values ``e`` (1-D, reordered), exactly as ``np.median`` gives it (the middle value or
    the mean of the two) by one selection: a partition at the upper middle rank leaves the lower middle value as
    the largest of the values before it (``np.median`` selects both ranks at once, several times slower)."""
    n = e.size
    e.partition(n // 2)
    if n % 2:
        return float(e[n // 2])
    return float((e[:n // 2].max() + e[n // 2]) / 2.0)


def mad_sigma(residuals_xy: np.ndarray, floor: float = 0.0) -> float:
    """Robust sigma of residual components (any shape; NaN/inf ignored): 1.4826 x MAD about the median."""
    e = np.asarray(residuals_xy, dtype=float).ravel()
    finite = np.isfinite(e)
    return sigma_of_mad(mad_in_place(e[finite] if not finite.all() else e.copy()), floor)


def mad_in_place(values: np.ndarray) -> float | None:
    """The median absolute deviation about the median of the finite ``values`` (any shape, contiguous): where all
    are finite, the array itself is reordered and overwritten (no copy; a solver's own read-back); None where
    none is finite."""
    e = values.reshape(-1)
    finite = np.isfinite(e)
    if not finite.all():
        e = e[finite]
    if not e.size:
        return None
    np.subtract(e, _median_in_place(e), out=e)
    return _median_in_place(np.abs(e, out=e))


def sigma_of_mad(mad: float | None, floor: float = 0.0) -> float:
    """``mad_sigma`` of a median absolute deviation found elsewhere (a GPU's sort); None: no finite component."""
    if mad is None:
        return max(floor, 1.0)
    return max(float(MAD_TO_SIGMA * mad), floor)


@dataclass(frozen=True)
class RobustStage:
    loss: str  # "cauchy" | "tukey" | "huber" | "none"
    k: float  # tuning constant in units of the MAD sigma
    iterations: int


@dataclass(frozen=True)
class RobustSchedule:
    """Stages run in order; the scale is re-estimated from the current residuals before each one."""

    stages: tuple[RobustStage, ...] = (RobustStage("cauchy", CAUCHY_K, 10), RobustStage("tukey", TUKEY_C, 10))
    sigma_floor_px: float = 0.2  # never trust the image more than this (MAD of a perfect fit goes to 0)
    sigma_ceiling_px: float = 8.0

    @staticmethod
    def least_squares(iterations: int = 20, sigma_px: float | None = None) -> "RobustSchedule":
        return RobustSchedule((RobustStage("none", 0.0, iterations),))

    def inlier_threshold_px(self, sigma: float) -> float:
        """Observations beyond the last stage's k x sigma are outliers (Tukey gives them zero weight)."""
        last = self.stages[-1]
        return (last.k if last.loss != "none" else 3.0) * sigma


def irls_weight(loss: str, e: np.ndarray, k_sigma: float) -> np.ndarray:
    """IRLS weight rho'(e)/e of residual norms ``e`` for a loss with threshold k_sigma (pixels)."""
    if loss == "cauchy":
        return 1.0 / (1.0 + (e / k_sigma) ** 2)
    if loss == "tukey":
        return np.where(e < k_sigma, (1.0 - (e / k_sigma) ** 2) ** 2, 0.0)
    if loss == "huber":
        return np.where(e <= k_sigma, 1.0, k_sigma / np.maximum(e, 1e-12))
    return np.ones_like(e)
