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
        for it in range(self.max_iterations):
            wx = b[:, 0:1] + A[:, 0, 0:1] * off[None, :, 0] + A[:, 0, 1:2] * off[None, :, 1]
            wy = b[:, 1:2] + A[:, 1, 0:1] * off[None, :, 0] + A[:, 1, 1:2] * off[None, :, 1]
            J = sample(image, wx, wy).astype(np.float64)
            if it == 0:
                rs, js = ref64.std(1) + 1e-6, J.std(1) + 1e-6
                gain = js / rs
                bias = J.mean(1) - gain * ref64.mean(1)
            gx = sample(grad_x, wx, wy).astype(np.float64)
            gy = sample(grad_y, wx, wy).astype(np.float64)
            r = J - gain[:, None] * ref64 - bias[:, None]
            G = np.stack([gx * off[None, :, 0], gx * off[None, :, 1], gy * off[None, :, 0], gy * off[None, :, 1],
                          gx, gy, -ref64, -np.ones_like(ref64)], axis=2)  # (N, P, 8)
            H = np.einsum("npi,npj->nij", G, G) + np.eye(8) * 1e-6
            g = np.einsum("npi,np->ni", G, r)
            try:
                delta = -np.linalg.solve(H, g[..., None])[..., 0]
            except np.linalg.LinAlgError:
                delta = np.zeros((n, 8))
            A += delta[:, :4].reshape(n, 2, 2)
            b += delta[:, 4:6]
            gain += delta[:, 6]
            bias += delta[:, 7]
            if np.nanmax(np.abs(delta[:, 4:6])) < 0.01:
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
