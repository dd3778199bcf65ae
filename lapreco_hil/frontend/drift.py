"""Drift check after Zinsser et al., as the seed paper uses it: every track keeps its first patch I; in each
frame an affine warp with gain and bias,  alpha I(x) + beta ~ J(A x + b),  is fitted to the current image J by
Gauss-Newton, starting from the tracker's position. The fitted b replaces the tracker's position (frame-to-frame
tracking drifts; registration against the first patch does not), and tracks whose normalised residual or
deformation is too large are dropped.

This is the vectorised CPU version (numpy + cv2.remap), used by the OpenCV baseline and as the reference
the Warp kernels are tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DriftCheckResult:
    positions: np.ndarray  # (N, 2) registered positions
    keep: np.ndarray  # (N,) bool
    residual: np.ndarray  # (N,) rms residual / patch contrast
    A: np.ndarray  # (N, 2, 2)


def patch_offsets(patch_px: int) -> np.ndarray:
    r = (patch_px - 1) / 2
    g = np.arange(patch_px, dtype=np.float32) - r
    X, Y = np.meshgrid(g, g)
    return np.column_stack([X.ravel(), Y.ravel()])  # (P, 2)


def sample(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 image at (N, P) coordinates (border replicated)."""
    return cv2.remap(image, xs.astype(np.float32), ys.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def drift_smoothing_weights(sigma_px: float) -> np.ndarray:
    """A separable Gaussian of ``sigma_px`` as float32 taps (radius 3 sigma); one tap of 1 for none. Why smooth
    at all: Shi-Tomasi picks a low-contrast corner partly where the sensor noise made one, that noise does not come
    back in the next frame, and the residual test, relative to the patch's contrast, refuses the track though it
    is right (``TrackerConfig.drift_smoothing_px``; docs/results.md, session 15)."""
    if sigma_px <= 0:
        return np.ones(1, np.float32)
    radius = int(np.ceil(3.0 * sigma_px))
    g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_px) ** 2)
    return (g / g.sum()).astype(np.float32)


def drift_image(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """The image the drift check registers on and takes its first patches from: the tracker image (float32)
    smoothed with ``drift_smoothing_weights(sigma_px)``, border replicated (as the Warp kernels blur); the image
    itself for 0."""
    taps = drift_smoothing_weights(sigma_px)
    if len(taps) == 1:
        return image
    return cv2.sepFilter2D(image, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REPLICATE)


def gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) gradients of a float32 image as ``AffineDriftCheck.register`` takes them: 3x3 Sobel / 8."""
    return (cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
            cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8))


class AffineDriftCheck:
    def __init__(self, patch_px: int = 13, max_iterations: int = 6, max_residual: float = 0.45,
                 max_stretch: float = 1.6, max_correction_px: float = 3.0) -> None:
        self.offsets = patch_offsets(patch_px)
        self.max_iterations = max_iterations
        self.max_residual = max_residual
        self.max_stretch = max_stretch
        self.max_correction_px = max_correction_px

    def reference_patches(self, image: np.ndarray, positions: np.ndarray) -> np.ndarray:
        xs = positions[:, 0:1] + self.offsets[None, :, 0]
        ys = positions[:, 1:2] + self.offsets[None, :, 1]
        return sample(image, xs, ys)

    def register(self, image: np.ndarray, grad_x: np.ndarray, grad_y: np.ndarray, ref: np.ndarray,
                 A0: np.ndarray, positions: np.ndarray) -> DriftCheckResult:
        """Fit alpha ref + beta ~ image(A x + b) for each of N tracks, from (A0, b = positions)."""
        n = len(positions)
        if n == 0:
            return DriftCheckResult(positions.copy(), np.zeros(0, bool), np.zeros(0), A0.copy())
        off = self.offsets
        A = A0.astype(np.float64).copy()
        b = positions.astype(np.float64).copy()
        gain = np.ones(n)
        bias = np.zeros(n)
        # gain and bias start from the patch statistics
        ref64 = ref.astype(np.float64)
        ref32 = ref.astype(np.float32)
        ox, oy = off[None, :, 0].astype(np.float32), off[None, :, 1].astype(np.float32)
        active = np.arange(n)  # tracks still moving; converged ones leave the loop (most converge in a few steps)
        # the Jacobian and residual in float32 (169 terms per sum: ample precision), solved in float64
        G = np.empty((n, off.shape[0], 8), np.float32)
        for it in range(self.max_iterations):
            a = active
            Aa, ba, refa = A[a], b[a], ref32[a]
            wx = ba[:, 0:1] + Aa[:, 0, 0:1] * ox + Aa[:, 0, 1:2] * oy
            wy = ba[:, 1:2] + Aa[:, 1, 0:1] * ox + Aa[:, 1, 1:2] * oy
            J = sample(image, wx, wy)
            if it == 0:
                rs, js = ref64.std(1) + 1e-6, J.std(1).astype(np.float64) + 1e-6
                gain = js / rs
                bias = J.mean(1).astype(np.float64) - gain * ref64.mean(1)
            gx = sample(grad_x, wx, wy)
            gy = sample(grad_y, wx, wy)
            r = J - gain[a, None].astype(np.float32) * refa - bias[a, None].astype(np.float32)
            Ga = G[: len(a)]
            Ga[..., 0], Ga[..., 1], Ga[..., 2], Ga[..., 3] = gx * ox, gx * oy, gy * ox, gy * oy
            Ga[..., 4], Ga[..., 5], Ga[..., 6], Ga[..., 7] = gx, gy, -refa, -1.0
            Gt = Ga.transpose(0, 2, 1)
            H = (Gt @ Ga).astype(np.float64) + np.eye(8) * 1e-6  # batched BLAS: every track's normal equations
            g = (Gt @ r[..., None])[..., 0].astype(np.float64)
            try:
                delta = -np.linalg.solve(H, g[..., None])[..., 0]
            except np.linalg.LinAlgError:
                delta = np.zeros((len(a), 8))
            A[a] += delta[:, :4].reshape(-1, 2, 2)
            b[a] += delta[:, 4:6]
            gain[a] += delta[:, 6]
            bias[a] += delta[:, 7]
            step = np.abs(delta[:, 4:6]).max(axis=1)
            active = a[~(step < 0.01)]  # NaN steps stay active (and fail the checks below)
            if len(active) == 0:
                break
        wx = b[:, 0:1] + A[:, 0, 0:1] * off[None, :, 0] + A[:, 0, 1:2] * off[None, :, 1]
        wy = b[:, 1:2] + A[:, 1, 0:1] * off[None, :, 0] + A[:, 1, 1:2] * off[None, :, 1]
        r = sample(image, wx, wy) - gain[:, None] * ref64 - bias[:, None]
        residual = np.sqrt(np.mean(r**2, axis=1)) / (np.abs(gain) * ref64.std(1) + 1e-6)
        sv = np.linalg.svd(np.nan_to_num(A, nan=1e6), compute_uv=False)
        stretch_ok = (sv[:, 0] <= self.max_stretch) & (sv[:, 1] >= 1.0 / self.max_stretch) & (np.linalg.det(A) > 0)
        moved = np.linalg.norm(b - positions, axis=1)
        keep = (np.isfinite(residual) & (residual <= self.max_residual) & stretch_ok
                & (moved <= self.max_correction_px) & (gain > 0.2) & (gain < 5.0))
        return DriftCheckResult(b, keep, residual, A)
