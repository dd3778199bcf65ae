"""A global image-motion prior for frames without a pose prediction: the frame-to-frame homography from a dense,
coarse-to-fine alignment of the whole image at low resolution, so that every track starts LK where that motion puts
it instead of where it was.

Why: without a prediction LK starts each track at its old position and its coarse pyramid levels must carry the
whole motion; on a periodic pattern (a dot grid, a chessboard) the coarse levels blur the pattern away and a track
takes a neighbouring copy, and beyond the pyramid's reach (a small frame moving fast) tracks are lost. A dense
alignment uses the whole image (the board's border, the context around it), so a periodic pattern does not fool
it the way a track's window is fooled. The tracks' consensus (``frontend.consensus``) then mends what is left.

The alignment (OpenCV's ECC, a homography) runs on a log high-pass of the frame reduced to at most
``ALIGN_MAX_SIDE`` pixels, from several seeds: the identity (coarse to fine over ``ALIGN_LEVELS`` levels), the
previous frame's image motion (constant velocity; on the finest alignment level only, as it is already close), a
translation from phase correlation (coarse to fine) and a similarity from the Fourier-Mellin method (the turn and
zoom from phase correlation of the log-polar magnitude spectra, then the shift; ECC from level
``FOURIER_MELLIN_FIRST_LEVEL``): a turn or zoom of a periodic pattern that ECC cannot reach from a shift. The seeds
are tried cheapest first, and the first alignment that correlates at least ``GOOD_CORRELATION`` is taken (a smooth
scope motion costs one alignment on the finest level); otherwise the seed whose alignment correlates best wins;
below ``MIN_CORRELATION``, or with a degenerate homography, there is no prior and LK starts where the tracks were.

Host code (numpy + OpenCV) shared by both front-ends: the Warp front-end runs it on the host's grey frame before
its graph and sends the homography up (``warp/frontend.py``). docs/frontend-real-frames.md, "A global motion
prior", has the figures."""

from __future__ import annotations

import cv2
import numpy as np

from lapreco_hil.frontend.image import HIGHPASS_RANGE, LOG_OFFSET

# the alignment image's longer side at most this (a power-of-two reduction of the frame)
ALIGN_MAX_SIDE = 256
# pyramid levels of the alignment image, finest included; the coarsest must keep some texture
ALIGN_LEVELS = 3
ALIGN_MIN_SIDE = 24
# the alignment image's high-pass (px of the alignment image): shading and gain out, the texture's context kept
ALIGN_HIGHPASS_SIGMA_PX = 6.0
# ECC's iterations per level and its convergence threshold (change of the correlation)
ECC_ITERATIONS = 40
ECC_EPS = 1e-4
# no prior from an alignment that correlates less than this (ECC's correlation coefficient, 1: perfect)
MIN_CORRELATION = 0.6
# an alignment that correlates at least this well is taken without trying the seeds after it: a wrong basin (a
# periodic pattern's neighbouring copy) leaves the border and the context misaligned, far below it
GOOD_CORRELATION = 0.95
# seeds closer than this (alignment pixels, at the image's corners) are aligned once
SAME_SEED_PX = 1.0
# a homography of one frame's scope motion changes the scale by less than this factor
MAX_SCALE_CHANGE = 2.0
# the Fourier-Mellin seed: the log-polar magnitude spectrum's samples along the radius and over 360 degrees (the
# first half is used: a real image's magnitude spectrum repeats every 180 degrees)
LOGPOLAR_RADII = 128
LOGPOLAR_ANGLES = 360
# ECC from the Fourier-Mellin seed starts on this pyramid level (0: the finest): the seed is within a few alignment
# pixels already, and the coarsest level blurs a fine periodic pattern away (a chessboard zooming out: ECC gives up
# there even from the true motion)
FOURIER_MELLIN_FIRST_LEVEL = 1


def reduction(width: int, height: int) -> int:
    """The power of two that brings the frame's longer side to at most ALIGN_MAX_SIDE."""
    factor = 1
    while max(width, height) / factor > ALIGN_MAX_SIDE:
        factor *= 2
    return factor


def reduced(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` reduced by ``factor`` (block means)."""
    h, w = image.shape[:2]
    return image if factor == 1 else cv2.resize(image, (-(-w // factor), -(-h // factor)),
                                                interpolation=cv2.INTER_AREA)


def reduced_maps(map_x: np.ndarray, map_y: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Undistortion maps (full resolution) for a frame reduced by ``factor``: each reduced pixel's source, in
    reduced pixels; None where they are the identity (no distortion)."""
    h, w = map_x.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    if np.abs(map_x - xs).max() < 0.01 and np.abs(map_y - ys).max() < 0.01:
        return None
    centre = 0.5 * (factor - 1)
    mx = (reduced(map_x, factor) - centre) / factor
    my = (reduced(map_y, factor) - centre) / factor
    return mx.astype(np.float32), my.astype(np.float32)


def reduced_grey(bgr: np.ndarray, factor: int, maps: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """The distorted BGR frame as the reduced, undistorted grey image ``GlobalMotion.estimate_reduced`` takes:
    reduced first (cheap), then undistorted at the reduced size (``reduced_maps``; the lens's distortion is smooth
    over a block)."""
    grey = cv2.cvtColor(reduced(bgr, factor), cv2.COLOR_BGR2GRAY)
    return grey if maps is None else cv2.remap(grey, maps[0], maps[1], cv2.INTER_LINEAR,
                                               borderMode=cv2.BORDER_REPLICATE)


def alignment_image(small: np.ndarray) -> np.ndarray:
    """The reduced grey frame (uint8, undistorted) as a clamped log high-pass (float32): the gain, the vignetting
    and the light's slow falloff out, a saturated highlight clamped as on the tracker image."""
    log = np.log(small.astype(np.float32) + LOG_OFFSET)
    high = log - cv2.GaussianBlur(log, (0, 0), ALIGN_HIGHPASS_SIGMA_PX)
    return np.clip(high, -HIGHPASS_RANGE, HIGHPASS_RANGE)


def _scaled(H: np.ndarray, scale: float, offset: float = 0.0) -> np.ndarray:
    """H in the pixels x' = scale * (x - offset) (cv2.pyrDown: scale 1/2, offset 0; a reduction by block means of
    f pixels: scale 1/f, offset (f - 1) / 2, the block's centre)."""
    A = np.array([[scale, 0.0, -scale * offset], [0.0, scale, -scale * offset], [0.0, 0.0, 1.0]])
    return A @ H @ np.linalg.inv(A)


def plausible(H: np.ndarray | None) -> bool:
    """A finite homography that keeps orientation and changes the scale by less than MAX_SCALE_CHANGE."""
    if H is None or not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
        return False
    A = H[:2, :2] / H[2, 2]
    det = float(np.linalg.det(A))
    return 1.0 / MAX_SCALE_CHANGE**2 < det < MAX_SCALE_CHANGE**2


def logpolar_spectrum(image: np.ndarray) -> np.ndarray:
    """The log magnitude spectrum of the alignment image (Hann-windowed, zero-padded to a square so that the
    spectrum's axes have one scale), resampled log-polar about its centre: LOGPOLAR_ANGLES / 2 rows (0-180 degrees)
    by LOGPOLAR_RADII columns (log radius, 1 to half the square's side). The magnitude spectrum ignores a shift; a
    turn of the image turns it, a zoom by s scales it by 1/s: in log-polar both are shifts."""
    h, w = image.shape
    n = cv2.getOptimalDFTSize(max(h, w))
    square = np.zeros((n, n), np.float32)
    square[:h, :w] = image * cv2.createHanningWindow((w, h), cv2.CV_32F)
    F = cv2.dft(square, flags=cv2.DFT_COMPLEX_OUTPUT)
    magnitude = np.fft.fftshift(np.log1p(cv2.magnitude(F[..., 0], F[..., 1])))
    c = 0.5 * n
    polar = cv2.warpPolar(magnitude, (LOGPOLAR_RADII, LOGPOLAR_ANGLES), (c, c), c,
                          cv2.INTER_LINEAR | cv2.WARP_POLAR_LOG)
    return polar[:LOGPOLAR_ANGLES // 2].astype(np.float64)


def fourier_mellin(prev: np.ndarray, cur: np.ndarray, prev_polar: np.ndarray,
                   cur_polar: np.ndarray) -> np.ndarray:
    """The similarity (alignment pixels, previous -> current) between two alignment images by the Fourier-Mellin
    method: phase correlation of their ``logpolar_spectrum`` gives the turn and the zoom (about the image's centre),
    then phase correlation of the previous image with the current one turned and zoomed back gives the shift."""
    h, w = prev.shape
    radial = np.tile(np.hanning(LOGPOLAR_RADII)[None, :], (prev_polar.shape[0], 1))
    (d_radius, d_angle), _ = cv2.phaseCorrelate(prev_polar, cur_polar, radial)
    angle = -360.0 * d_angle / LOGPOLAR_ANGLES  # degrees, counter-clockwise as cv2.getRotationMatrix2D's
    n = cv2.getOptimalDFTSize(max(h, w))
    scale = float(np.exp(-d_radius * np.log(0.5 * n) / LOGPOLAR_RADII))
    S = np.vstack([cv2.getRotationMatrix2D((0.5 * (w - 1), 0.5 * (h - 1)), angle, scale), [0.0, 0.0, 1.0]])
    back = cv2.warpPerspective(cur, S, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)  # back(x) = cur(S x)
    (dx, dy), _ = cv2.phaseCorrelate(prev.astype(np.float64), back.astype(np.float64))
    return S @ np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


class DistinctStarts:
    """Starting homographies of one alignment, each aligned once: a start within SAME_SEED_PX of an earlier one at
    every corner of the alignment image (``shape``: its rows, columns) would end where that one did."""

    def __init__(self, shape: tuple[int, int]) -> None:
        h, w = shape
        self._corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]).reshape(-1, 1, 2)
        self._seen: list[np.ndarray] = []

    def new(self, H0: np.ndarray) -> bool:
        """Whether ``H0`` is a new start (it is remembered)."""
        moved = cv2.perspectiveTransform(self._corners, np.asarray(H0, np.float64)).reshape(-1, 2)
        if any(np.abs(moved - m).max() < SAME_SEED_PX for m in self._seen):
            return False
        self._seen.append(moved)
        return True


class GlobalMotion:
    """The image motion between consecutive frames of one camera (``estimate``); it keeps the previous frame's
    alignment image and motion."""

    def __init__(self, width: int, height: int) -> None:
        self.factor = reduction(width, height)
        w, h = -(-width // self.factor), -(-height // self.factor)
        self.levels = 1
        while self.levels < ALIGN_LEVELS and min(w, h) >> self.levels >= ALIGN_MIN_SIDE:
            self.levels += 1
        self._prev: list[np.ndarray] | None = None
        # the previous alignment image's logpolar_spectrum, where its frame needed the Fourier-Mellin seed
        self._prev_polar: np.ndarray | None = None
        self.fourier_mellin = True  # the rotation-and-zoom seed (off: the seeds before it, for comparisons)
        self.last: np.ndarray | None = None  # the last frame's motion (full-resolution pixels), when known

    def _pyramid(self, image: np.ndarray) -> list[np.ndarray]:
        levels = [image]
        for _ in range(self.levels - 1):
            levels.append(cv2.pyrDown(levels[-1]))
        return levels

    @staticmethod
    def _align(prev: list[np.ndarray], cur: list[np.ndarray], H0: np.ndarray,
               first: int) -> tuple[float, np.ndarray | None]:
        """ECC of ``cur`` to ``prev`` (pyramids) from ``H0`` (alignment pixels of the finest level) on the levels
        ``first`` .. 0; (correlation, homography) or (-1, None) where ECC gave up."""
        H = _scaled(H0, 0.5**first)
        rho = -1.0
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, ECC_ITERATIONS, ECC_EPS)
        for level in range(first, -1, -1):
            try:
                rho, W = cv2.findTransformECC(prev[level], cur[level], H.astype(np.float32),
                                              cv2.MOTION_HOMOGRAPHY, criteria, None, 5)
            except cv2.error:  # "iterations do not converge": the correlation fell (no overlap, wrong basin)
                return -1.0, None
            H = W.astype(np.float64)
            if level:
                H = _scaled(H, 2.0)
        return float(rho), H

    def forget(self) -> None:
        """A frame that is not aligned (it came with a pose prediction): the next has no previous image (so a
        frame with a prediction costs nothing here; a run without poses has none on any frame)."""
        self._prev = None
        self._prev_polar = None
        self.last = None

    def to_alignment(self, H: np.ndarray) -> np.ndarray:
        """A homography of full-resolution pixels in the finest alignment level's pixels."""
        return _scaled(H, 1.0 / self.factor, 0.5 * (self.factor - 1.0))

    def to_full(self, H: np.ndarray) -> np.ndarray:
        """A homography of the finest alignment level's pixels in full-resolution pixels."""
        f = float(self.factor)
        return _scaled(H, f, -0.5 * (f - 1.0) / f)

    def took(self, H: np.ndarray) -> None:
        """The frame's motion ``H`` (full-resolution pixels) was found elsewhere (the device's alignment from
        the first seed): it seeds the next frame; the host keeps no alignment image of it."""
        self._prev = None
        self._prev_polar = None
        self.last = H

    def estimate_images(self, prev: np.ndarray, cur: np.ndarray, seeds: tuple[np.ndarray, ...] = (),
                        aligned: tuple = ()) -> np.ndarray | None:
        """``estimate_reduced`` of two frames' alignment images (``alignment_image``, made elsewhere: the
        device's), the earlier one as the previous frame's. ``aligned``: alignments already made of these images
        on the finest level, (start, correlation, homography or None) in alignment pixels: their starts are not
        tried again, and each competes as the best."""
        self._prev, self._prev_polar = self._pyramid(prev.astype(np.float32)), None
        return self._estimate(self._pyramid(cur.astype(np.float32)), seeds, aligned)

    def estimate(self, gray: np.ndarray, seeds: tuple[np.ndarray, ...] = ()) -> np.ndarray | None:
        """``estimate_reduced`` of the undistorted full-resolution grey frame ``gray`` (uint8)."""
        return self.estimate_reduced(reduced(gray, self.factor), seeds)

    def estimate_reduced(self, small: np.ndarray, seeds: tuple[np.ndarray, ...] = ()) -> np.ndarray | None:
        """The homography (full-resolution pixels, previous frame -> this one) of the undistorted grey frame
        reduced by ``factor`` (uint8), or None (the first frame, or no alignment correlated well enough).
        ``seeds``: more starting motions (full-resolution pixels), e.g. the tracks' consensus of the previous
        frame."""
        return self._estimate(self._pyramid(alignment_image(small)), seeds)

    def _estimate(self, cur: list[np.ndarray], seeds: tuple[np.ndarray, ...], aligned: tuple = ()) -> np.ndarray | None:
        prev, prev_polar = self._prev, self._prev_polar
        self._prev, self._prev_polar = cur, None
        if prev is None or prev[0].shape != cur[0].shape:
            self.last = None
            return None
        best_rho, best = -1.0, None
        starts = DistinctStarts(cur[0].shape)
        for H0, rho, H in aligned:
            starts.new(H0)
            if H is not None and rho > best_rho and plausible(H):
                best_rho, best = rho, H
        for H0, first in ([] if best_rho >= GOOD_CORRELATION else self._seeds(prev, cur, prev_polar, seeds)):
            if not starts.new(H0):
                continue
            rho, H = self._align(prev, cur, H0, first)
            if H is not None and rho > best_rho and plausible(H):
                best_rho, best = rho, H
                if rho >= GOOD_CORRELATION:
                    break
        if best is None or best_rho < MIN_CORRELATION:
            self.last = None
            return None
        self.last = self.to_full(best)
        return self.last

    def _seeds(self, prev: list[np.ndarray], cur: list[np.ndarray], prev_polar: np.ndarray | None,
               seeds: tuple[np.ndarray, ...]):
        """The starting motions (alignment pixels) and the level ECC starts each from, cheapest and likeliest
        first; each computed only when the ones before it did not align well enough (``GOOD_CORRELATION``)."""
        for H in (self.last, *seeds):
            if plausible(H):
                yield self.to_alignment(H), 0
        coarsest = self.levels - 1
        yield np.eye(3), coarsest
        (dx, dy), _ = cv2.phaseCorrelate(prev[0].astype(np.float64), cur[0].astype(np.float64))
        yield np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]), coarsest
        if self.fourier_mellin:
            if prev_polar is None:
                prev_polar = logpolar_spectrum(prev[0])
            self._prev_polar = logpolar_spectrum(cur[0])
            similarity = fourier_mellin(prev[0], cur[0], prev_polar, self._prev_polar)
            if plausible(similarity):
                yield similarity, min(FOURIER_MELLIN_FIRST_LEVEL, coarsest)
