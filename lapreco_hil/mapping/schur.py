"""Bundle adjustment by Levenberg-Marquardt on the reduced camera system (the Schur complement): the same
problem, robust schedule and answers as the GTSAM solver in ``bundle_adjustment``, several times faster on a
local window because nothing is built per factor. The per-observation work runs as Warp kernels
(``schur_kernels``; Warp's CPU device by default, CUDA if asked) or in numpy (``device="numpy"``); the LM logic
and the small dense camera system stay on the host.

What is kept identical to GTSAM, so that the optimum and the path to it are the same:

- the variables and their retraction: a pose is T_world_camera moved by ``T Exp(xi)``, xi = (rotation,
  translation) in the body frame (GTSAM's Pose3 with full Expmap); a point moves in world coordinates;
- the factors: the pinhole reprojection error ``project(X) - uv`` (a point at or behind the camera gives the
  constant error 2 fx and no gradient, as GenericProjectionFactor does), pose priors ``Log(prior^-1 T)`` and
  rig ties ``Log(T_ij^-1 T_i^-1 T_j)`` whitened by the Cholesky factor of their information;
- the m-estimators (GTSAM's Cauchy and Tukey: weight and loss in whitened units) applied by reweighting the
  whitened system, the nonlinear error that LM compares (sum of losses), and LM's own schedule: lambda from
  1e-5 times/divided by 10, damping lambda*I on every variable, the model-fidelity test, the relative and
  absolute error tolerances, lambda's upper bound.

Fixed poses are left out of the unknowns (GTSAM holds them with a 1e-7 prior: the same to that precision).
The camera system is dense (6 free poses x 6 free poses): a local window's is a few hundred wide, a final
pass over a few hundred keyframes a few thousand. It is assembled point-chunk by point-chunk, each chunk's
landmark blocks eliminated into the rows of the poses that see it by one BLAS rank-k update in place, so memory
stays bounded however many landmarks there are; a long map's chunks follow its landmarks' spans of poses, so
that the work stays near the sum of (track length)^2 (``_chunks``). On a GPU the landmarks are eliminated there
instead, by atomics (``device_schur``). The system is solved by a dense Cholesky factorisation: the host's LAPACK,
or, for a final pass's wide dense system on a GPU, a blocked one on the device where the system was made
(``dense_cholesky``; ``camera_solver``), so that only the step comes back; a long map's narrow band by LAPACK's
banded one.

On a Warp device the solver's state stays there from the solve's start to its end (``_DeviceState``): the host
keeps the LM logic, the poses (a few), the pose factors and the camera system, and per LM iteration reads back
the pose system (with the camera system, where the landmarks are eliminated there and it is not solved there too)
and a trial's few scalars.
Each read-back waits for the device: the host launches, does its pose-factor work, then reads. On a GPU the
kernels reduce a GPU's way and the robust scales' medians are found there (``ObservationKernels``).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import logging
import os
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.linalg.blas
import scipy.linalg.lapack
import scipy.linalg.cython_blas
from scipy.spatial.transform import Rotation

from lapreco_hil.mapping.bundle_adjustment import BAProblem, BAResult, redundancy
from lapreco_hil.mapping.robust import RobustSchedule, mad_in_place, sigma_of_mad


log = logging.getLogger(__name__)

# GTSAM's LevenbergMarquardtParams defaults (the GTSAM solver sets relativeErrorTol 1e-5 too)
LAMBDA_INITIAL = 1e-5
LAMBDA_FACTOR = 10.0
LAMBDA_UPPER = 1e5
RELATIVE_ERROR_TOL = 1e-5
ABSOLUTE_ERROR_TOL = 1e-5
MIN_MODEL_FIDELITY = 1e-3
# landmarks are eliminated a chunk at a time through a dense (3 x chunk) x (6 x the chunk's poses) block of at
# most CHUNK_POINTS landmarks and CHUNK_ENTRIES entries: a long map's chunks each touch a few of its poses, so
# the work grows with the track lengths, not with the map's size, and the memory stays bounded
CHUNK_POINTS = 256
CHUNK_ENTRIES = 4_000_000
# landmarks whose first free poses fall in one bin of this many are ordered by their last one
CHUNK_FIRST_BIN = 16
# a problem of at most this many free poses (a local window) is cut into chunks of CHUNK_POINTS as they come
CHUNK_DENSE_POSES = 32
# a chunk grows while its dense update costs at most this many times its landmarks' own blocks
CHUNK_WASTE = 1.5
# the kernels make the blocks of consecutive chunks in one launch, up to this many entries (64 MB) at once
BATCH_ENTRIES = 8_000_000
# the camera system of a problem of more than this many free poses (a final pass, never a local window) is
# solved as a band matrix (LAPACK's banded Cholesky) where its bandwidth, in keyframe order or after a reverse
# Cuthill-McKee order, is at most 1 / BAND_MAX_SHARE of its width: keyframes co-observe only their neighbours in
# time, and the band's n b^2 work is then a small share of the dense factorisation's n^3 / 3
BAND_MIN_FREE_POSES = 64
BAND_MAX_SHARE = 3
# a dense camera system of more than this many free poses (a final pass, never a local window) is factorised and
# solved on a CUDA device where its landmarks are eliminated there (``dense_cholesky``: a blocked Cholesky of tile
# kernels, tiles of DEVICE_TILE), instead of read back (46 MB at 2400 wide) and factorised by the host's LAPACK;
# camera_solver "dense-device" asks for it on any Warp device (Warp's CPU device: the tests)
DEVICE_DENSE_MIN_FREE_POSES = 64
DEVICE_TILE = 32
# terms of the series of SE(3)'s right Jacobian (exact to 1e-13 for rotations up to 1 rad)
_JR_TERMS = 16


# --- BLAS threads ------------------------------------------------------------------------------------------------
@functools.cache
def _openblas_libraries() -> tuple:
    """The OpenBLAS copies loaded in this process (numpy's and scipy's wheels bundle one each) that can set a
    thread count for the calling thread alone (OpenBLAS >= 0.3.27); empty where there are none or no /proc."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line and ".so" in line}
    except OSError:
        return ()
    libs = []
    for path in sorted(paths):
        try:
            setter = ctypes.CDLL(path).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        setter.restype, setter.argtypes = ctypes.c_int, [ctypes.c_int]
        libs.append(setter)
    return tuple(libs)


@contextlib.contextmanager
def _blas_threads(n: int = 1):
    """BLAS on ``n`` threads for this thread, while inside. One by default: the solver's products and
    factorisations of a local window are a few hundred wide, OpenBLAS's worker threads gain little there and,
    on cores shared with the tracker and the other processes (the live runtime, a loaded machine), their
    spinning made solves 10-30x slower (docs/benchmarks.md). A final pass over a long map (a camera system
    thousands wide, nothing else running) takes the machine's cores."""
    setters = _openblas_libraries()
    previous = [set_threads(max(1, int(n))) for set_threads in setters]
    try:
        yield
    finally:
        for set_threads, m in zip(setters, previous):
            set_threads(m)


def all_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


# a machine with fewer cores is taken to be shared (a developer's, CI's): one BLAS thread there
MIN_CORES_FOR_THREADS = 8


def final_pass_threads() -> int:
    """BLAS threads for a final pass when none are configured: every core of a machine of MIN_CORES_FOR_THREADS
    or more (nothing else runs at the map's end), one on a smaller one."""
    cores = all_cores()
    return cores if cores >= MIN_CORES_FOR_THREADS else 1


@functools.cache
def _dsyrk():
    """BLAS's dsyrk (Fortran interface, LP64) from scipy's public Cython BLAS: it updates a block of a larger
    matrix in place (its leading dimension), which the Python wrapper cannot (it copies a strided block)."""
    capsule = scipy.linalg.cython_blas.__pyx_capi__["dsyrk"]
    api = ctypes.pythonapi
    api.PyCapsule_GetName.restype, api.PyCapsule_GetName.argtypes = ctypes.c_char_p, [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    pointer = api.PyCapsule_GetPointer(capsule, api.PyCapsule_GetName(capsule))
    i, d = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double)
    return ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, i, i, d, ctypes.c_void_p, i, d,
                            ctypes.c_void_p, i)(pointer)


def _subtract_gram(S: np.ndarray, block: slice, Z: np.ndarray) -> None:
    """S[block, block] -= Z^T Z in S's lower triangle, in place (S: C-ordered square float64; Z: C-ordered
    (rows, block's width))."""
    n, (rows, width) = S.shape[0], Z.shape
    assert S.flags.c_contiguous and Z.flags.c_contiguous and S.dtype == Z.dtype == np.float64
    assert block.stop - block.start == width and block.stop <= n
    if not rows or not width:
        return
    c = ctypes.c_int
    # Fortran sees S's transpose: its upper triangle is S's lower one; it sees Z^T, (width x rows)
    _dsyrk()(b"U", b"N", ctypes.byref(c(width)), ctypes.byref(c(rows)), ctypes.byref(ctypes.c_double(-1.0)),
             Z.ctypes.data, ctypes.byref(c(width)), ctypes.byref(ctypes.c_double(1.0)),
             S.ctypes.data + 8 * (block.start * n + block.start), ctypes.byref(c(n)))


# --- SE(3) in GTSAM's convention: xi = (omega, v), T Exp(xi) ------------------------------------------------
# a cross-product matrix's entries as (component, sign) of its vector, component 3 a zero appended; likewise
# se(3)'s adjoint ad(xi) = [[hat(w), 0], [hat(v), hat(w)]] of xi = (w, v), component 6 the zero: one gather and
# one product each, where their entries' assignments took a dozen small numpy calls (the pose factors' host time)
_HAT_INDEX = np.array([[3, 2, 1], [2, 3, 0], [1, 0, 3]])
_HAT_SIGN = np.array([[1.0, -1.0, 1.0], [1.0, 1.0, -1.0], [-1.0, 1.0, 1.0]])
_AD_INDEX = np.array([[6, 2, 1, 6, 6, 6], [2, 6, 0, 6, 6, 6], [1, 0, 6, 6, 6, 6],
                      [6, 5, 4, 6, 2, 1], [5, 6, 3, 2, 6, 0], [4, 3, 6, 1, 0, 6]])
_AD_SIGN = np.block([[_HAT_SIGN, np.ones((3, 3))], [_HAT_SIGN, _HAT_SIGN]])


def _with_zero(x: np.ndarray) -> np.ndarray:
    """(n, k) -> (n, k + 1): a zero column appended (the gathers' zero entries: +0 as assigned before)."""
    out = np.zeros((len(x), x.shape[1] + 1))
    out[:, :-1] = x
    return out


def hat(w: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, 3, 3) cross-product matrices."""
    return _with_zero(w)[:, _HAT_INDEX] * _HAT_SIGN


def _v_coefficients(theta: np.ndarray):
    """(1 - cos t) / t^2 and (t - sin t) / t^3, by their series near 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return a, b


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(n, 6) -> (n, 4, 4): GTSAM's Pose3::Expmap."""
    w, v = xi[:, :3], xi[:, 3:]
    W = hat(w)
    theta = np.linalg.norm(w, axis=1)
    a, b = _v_coefficients(theta)
    W2 = W @ W
    V = np.eye(3) + a[:, None, None] * W + b[:, None, None] * W2
    # Rodrigues: R = I + sin t / t W + (1 - cos t) / t^2 W^2
    sinc = np.where(theta < 1e-4, 1.0 - theta**2 / 6.0, np.sin(theta) / np.where(theta < 1e-4, 1.0, theta))
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = np.eye(3) + sinc[:, None, None] * W + a[:, None, None] * W2
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, v)
    T[:, 3, 3] = 1.0
    return T


def so3_log(R: np.ndarray) -> np.ndarray:
    """(n, 3, 3) -> (n, 3) rotation vectors: the angle from atan2(sin, cos) (accurate at every angle), the axis
    from R - R^T; beyond 3 rad, where that axis fades (its error grows as 1 / sin), scipy's (quaternion) way."""
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)  # 2 sin t u
    sin2 = np.linalg.norm(v, axis=1)
    theta = np.arctan2(0.5 * sin2, 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0))
    small = theta < 1e-4
    w = np.where(small, 0.5 + theta**2 / 12.0, theta / np.where(small, 1.0, sin2))[:, None] * v
    near_pi = theta > 3.0
    if near_pi.any():
        w[near_pi] = Rotation.from_matrix(R[near_pi]).as_rotvec()
    return w


def se3_log(T: np.ndarray) -> np.ndarray:
    """(n, 4, 4) -> (n, 6): GTSAM's Pose3::Logmap."""
    w = so3_log(T[:, :3, :3])
    theta = np.linalg.norm(w, axis=1)
    W = hat(w)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    # V^-1 = I - W/2 + c W^2, c = (1 - t sin t / (2 (1 - cos t))) / t^2
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / t**2)
    Vinv = np.eye(3) - 0.5 * W + c[:, None, None] * (W @ W)
    return np.concatenate([w, np.einsum("nij,nj->ni", Vinv, T[:, :3, 3])], axis=1)


def adjoint(T: np.ndarray) -> np.ndarray:
    """(n, 4, 4) -> (n, 6, 6) adjoint in (rotation, translation) order."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    A = np.zeros((len(T), 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    A[:, 3:, :3] = hat(t) @ R
    return A


def right_jacobian_inverse(xi: np.ndarray) -> np.ndarray:
    """(n, 6) -> (n, 6, 6): d Log(E Exp(d)) / d d at E = Exp(xi) (GTSAM's Pose3::LogmapDerivative)."""
    ad = _with_zero(xi)[:, _AD_INDEX] * _AD_SIGN
    term = np.broadcast_to(np.eye(6), ad.shape)
    Jr = term.copy()
    for k in range(1, _JR_TERMS):  # Jr = sum (-ad)^k / (k + 1)!
        term = np.matmul(term, ad)
        term /= -(k + 1)  # (-x / n and x / -n: the same value)
        Jr += term
        if np.abs(term).max() < 1e-18:  # (small tangents, a prior's error: a few terms reach double precision)
            break
    return np.linalg.inv(Jr)


def whitening(covs: np.ndarray) -> np.ndarray:
    """(n, 6, 6) covariances -> (n, 6, 6) matrices R with R^T R = cov^-1 (whitened error = R e)."""
    if not len(covs):
        return np.zeros((0, 6, 6))
    return np.transpose(np.linalg.cholesky(np.linalg.inv(covs)), (0, 2, 1))


# --- m-estimators as GTSAM defines them (whitened units) ----------------------------------------------------
def robust_weight(loss: str, e: np.ndarray, k: float) -> np.ndarray:
    if loss == "cauchy":
        return k * k / (k * k + e * e)
    if loss == "tukey":
        return np.where(np.abs(e) <= k, (1.0 - (e / k) ** 2) ** 2, 0.0)
    if loss == "huber":
        return np.where(np.abs(e) <= k, 1.0, k / np.maximum(np.abs(e), 1e-300))
    return np.ones_like(e)


def robust_loss(loss: str, e: np.ndarray, k: float) -> np.ndarray:
    if loss == "cauchy":
        return 0.5 * k * k * np.log1p((e / k) ** 2)
    if loss == "tukey":
        return np.where(np.abs(e) <= k, k * k / 6.0 * (1.0 - (1.0 - (e / k) ** 2) ** 3), k * k / 6.0)
    if loss == "huber":
        a = np.abs(e)
        return np.where(a <= k, 0.5 * e * e, k * a - 0.5 * k * k)
    return 0.5 * e * e


# --- the problem's fixed structure ----------------------------------------------------------------------------
def pose_major(problem: BAProblem) -> tuple[BAProblem, np.ndarray]:
    """The problem with its observations sorted by pose (each pose's are then one contiguous run, transformed
    by one matrix product), and the permutation (``sorted[i] = original[perm[i]]``)."""
    obs_pose = np.asarray(problem.obs_pose)
    change = np.flatnonzero(obs_pose[1:] != obs_pose[:-1]) + 1  # where a run of one pose's observations starts
    if not len(change) or np.all(obs_pose[change] > obs_pose[change - 1]):
        return problem, np.arange(len(obs_pose))
    if len(change) <= 4 * len(problem.poses):
        # a few runs (a live window's observations come keyframe by keyframe): the runs put in order, the same
        # permutation as the stable sort's
        starts, ends = np.concatenate([[0], change]), np.concatenate([change, [len(obs_pose)]])
        order = np.argsort(obs_pose[starts], kind="stable").tolist()
        perm = np.concatenate([np.arange(starts[i], ends[i]) for i in order])
    else:  # (a stable sort of 16-bit integers is numpy's radix sort: a few times faster than of 64-bit ones)
        perm = np.argsort(obs_pose.astype(np.int16) if len(problem.poses) < 2**15 else obs_pose, kind="stable")
    # (``np.take`` along an axis: a tenth of the time of a fancy index of the (O, 2) rows)
    return dataclasses.replace(problem, obs_pose=np.take(obs_pose, perm), obs_point=np.take(problem.obs_point, perm),
                               obs_uv=np.take(problem.obs_uv, perm, axis=0)), perm


@dataclass
class _Chunk:
    """Landmarks eliminated together through one dense block: their observations by free poses, each one's
    chunk-local landmark row and pose column, and the camera-system indices those columns are."""

    points: np.ndarray  # the landmarks
    obs: np.ndarray  # their observations by free poses
    dest: np.ndarray  # (3, 6, len(obs)) where each observation's W block goes in the chunk's (n, 3, 6 m) block
    n_cols: int
    idx: np.ndarray | slice  # their rows/columns of the camera system


@dataclass
class _Layout:
    free: np.ndarray  # (F,) pose indices of the unknown poses
    col: np.ndarray  # (P,) column block of a pose, -1 where fixed
    obs_point: np.ndarray  # (O,) landmark of each observation
    obs_col: np.ndarray  # (O,) column block of the observing pose, -1 where fixed
    pose_starts: np.ndarray  # (P + 1,) each pose's run of observations (they are pose-major)
    n_points: int
    chunks: list[_Chunk]
    batches: list[tuple[int, int]]  # runs of chunks whose blocks the kernels make in one launch
    # no pose sees a point twice (the landmark-pose blocks can be assigned, not summed); None: not needed (the
    # landmarks eliminated on the device by observations), not found
    unique_pairs: bool | None
    prior_idx: np.ndarray  # free poses with a prior
    prior_R: np.ndarray  # their whitening
    tie_R: np.ndarray
    prior_inv: np.ndarray  # their priors' inverses
    tie_inv: np.ndarray  # the ties' T_i_j^-1
    kernels: object = None  # schur_kernels.ObservationKernels on a Warp device; None: numpy
    # the camera system's lower bandwidth (entries) where it is solved as a band matrix (``_camera_band``), held
    # as an (6F, band + 1) array B with B[j, i - j] = S[i, j] (i >= j): B.T is LAPACK's lower band storage;
    # None: dense (6F, 6F)
    band: int | None = None
    # the pose system's blocks (rows, columns) that can be non-zero (``_pose_blocks``)
    pose_blocks: tuple = ()
    # the tile's side where the dense camera system is factorised on the kernels' device (``DEVICE_DENSE_MIN_FREE_
    # POSES``); the pose system is then held as its lower blocks that can be non-zero alone, (k, 6, 6) in the order
    # of their keys row F + column (``device_block_keys``), the free poses' diagonal blocks at ``device_diagonal``
    camera_tile: int | None = None
    device_block_keys: np.ndarray | None = None
    device_diagonal: np.ndarray | None = None


def _greedy_cuts(first: np.ndarray, last: np.ndarray, views: np.ndarray) -> list[int]:
    """Where to cut landmarks (in ``_chunks``' order; their first and last free poses and their views) into
    chunks: a chunk grows while its dense update, landmarks x (its span of poses)^2, stays within CHUNK_WASTE of
    their own blocks' sum (views^2), up to CHUNK_POINTS landmarks and CHUNK_ENTRIES entries. Landmarks of one span
    are taken together (a Python step per distinct span, not per landmark)."""
    change = np.flatnonzero((first[1:] != first[:-1]) | (last[1:] != last[:-1])) + 1
    run_start = np.concatenate([[0], change]).tolist()
    run_end = run_start[1:] + [len(first)]
    sq = views.astype(np.int64) ** 2
    run_sq = np.add.reduceat(sq, run_start).tolist()
    fs, ls = first[run_start].tolist(), last[run_start].tolist()
    cuts, lo, span_f, span_l, own = [0], 0, 0, -1, 0.0
    for r, (a, b) in enumerate(zip(run_start, run_end)):
        pos, per = a, run_sq[r] / (b - a)
        while pos < b:
            if pos > lo:  # does this run (or its head) join the open chunk?
                f, l_ = min(span_f, fs[r]), max(span_l, ls[r])
                width = l_ - f + 1
                take = min(b - pos, CHUNK_POINTS - (pos - lo), max(0, CHUNK_ENTRIES // (18 * width) - (pos - lo)))
                if take > 0 and (pos - lo + take) * width * width <= CHUNK_WASTE * (own + take * per):
                    span_f, span_l, own, pos = f, l_, own + take * per, pos + take
                    continue
                cuts.append(pos)
            lo, span_f, span_l = pos, fs[r], ls[r]
            take = max(1, min(b - pos, CHUNK_POINTS, CHUNK_ENTRIES // (18 * (span_l - span_f + 1))))
            own, pos = take * per, pos + take
    cuts.append(len(first))
    return cuts


def _chunks(obs_point: np.ndarray, obs_col: np.ndarray, n_points: int, n_free: int) -> list[_Chunk]:
    """The landmarks cut into elimination chunks. A chunk's cost is its dense block's update of the camera
    system, (3 x its landmarks) x (6 x the span of its poses)^2, against the sum of its landmarks' own
    (3 x 6 x track)^2: landmarks are taken in the order of (first free pose // CHUNK_FIRST_BIN, last free
    pose), so that neighbours share their span, and a chunk grows while its cost stays within CHUNK_WASTE of
    that sum (long tracks of a slow sweep: a chunk of the first pose's landmarks alone spans the longest track
    among them, several times the cost), up to CHUNK_POINTS landmarks and CHUNK_ENTRIES entries (``_greedy_cuts``).
    A problem of a few poses (a local window) is cut every CHUNK_POINTS landmarks: few chunks, few launches."""
    seen = obs_col >= 0
    first = np.full(n_points, np.iinfo(np.int64).max)
    np.minimum.at(first, obs_point[seen], obs_col[seen])
    last = np.full(n_points, -1, np.int64)
    np.maximum.at(last, obs_point[seen], obs_col[seen])
    views = np.bincount(obs_point[seen], minlength=n_points)
    point_order = np.lexsort((first, last, first // CHUNK_FIRST_BIN))
    point_order = point_order[first[point_order] < n_free]
    rank = np.empty(n_points, np.int64)
    rank[point_order] = np.arange(len(point_order))
    by_rank = np.flatnonzero(seen)
    by_rank = by_rank[np.argsort(rank[obs_point[by_rank]], kind="stable")]
    starts = np.searchsorted(rank[obs_point[by_rank]], np.arange(len(point_order) + 1))
    if not len(point_order):
        return []
    if n_free <= CHUNK_DENSE_POSES:
        # a local window: its dense updates are small whatever the chunks, their count is what costs
        cuts = list(range(0, len(point_order), CHUNK_POINTS)) + [len(point_order)]
    else:
        cuts = _greedy_cuts(first[point_order], last[point_order], views[point_order])
    chunks, j, c = [], 0, 1
    while j < len(point_order):
        hi = cuts[c]
        while True:  # (a chunk whose poses are not one run can still be too wide: halve it)
            obs = by_rank[starts[j]:starts[hi]]
            cols = np.flatnonzero(np.bincount(obs_col[obs], minlength=n_free))
            if (hi - j) * 18 * len(cols) <= CHUNK_ENTRIES or hi - j <= 1:
                break
            hi = j + max(1, (hi - j) // 2)
        row, local, width = rank[obs_point[obs]] - j, np.searchsorted(cols, obs_col[obs]), 6 * len(cols)
        dest = (row * 3 * width + 6 * local)[None, None, :] + (np.arange(3)[:, None] * width
                                                                + np.arange(6)[None, :])[:, :, None]
        run = cols[-1] - cols[0] + 1 == len(cols)  # its poses are one run: the camera system's block is a slice
        idx = slice(6 * int(cols[0]), 6 * int(cols[-1]) + 6) if run else (6 * cols[:, None] + np.arange(6)).ravel()
        chunks.append(_Chunk(point_order[j:hi], obs, dest, len(cols), idx))
        j = hi
        c += j == cuts[c]
    return chunks


def _unique_pairs(obs_point: np.ndarray, obs_pose: np.ndarray, n_points: int, n_poses: int) -> bool:
    """Whether no pose sees a landmark twice."""
    pair = obs_point * n_poses + obs_pose
    if n_points * n_poses <= 16 * len(pair) + 4096:  # a window's landmark x pose table is small: count into it
        return len(pair) == 0 or int(np.bincount(pair, minlength=n_points * n_poses).max()) <= 1
    pair = np.sort(pair)  # (a sort: numpy's hashed unique is slower here)
    return not np.any(pair[1:] == pair[:-1])


CAMERA_SOLVERS = ("auto", "dense", "banded", "dense-device")


def _camera_band(obs_point: np.ndarray, obs_col: np.ndarray, n_points: int, n_free: int, tie_cols: np.ndarray,
                 camera_solver: str) -> tuple[int | None, np.ndarray | None]:
    """(the camera system's lower bandwidth in entries, the order of the free poses that gives it: None where
    theirs) where the camera system is to be solved as a band matrix, else (None, None). Its block pattern: the
    free poses that see a common landmark, and the tied ones. "auto": banded for more than BAND_MIN_FREE_POSES free
    poses where the bandwidth, in the poses' own order (a map's keyframes in time) or after a reverse
    Cuthill-McKee order where that is narrower, is at most 1 / BAND_MAX_SHARE of the width; "banded": always
    (in the narrower order); "dense": never."""
    if camera_solver not in CAMERA_SOLVERS:
        raise ValueError(f"camera_solver '{camera_solver}': use one of {', '.join(CAMERA_SOLVERS)}")
    if (camera_solver in ("dense", "dense-device") or not n_free
            or (camera_solver == "auto" and n_free <= BAND_MIN_FREE_POSES)):
        return None, None
    seen = obs_col >= 0
    first = np.full(n_points, n_free, np.int64)
    np.minimum.at(first, obs_point[seen], obs_col[seen])
    last = np.full(n_points, -1, np.int64)
    np.maximum.at(last, obs_point[seen], obs_col[seen])
    spans = np.concatenate([(last - first)[last >= 0], np.abs(tie_cols[:, 0] - tie_cols[:, 1])])
    width = int(spans.max(initial=0))
    order = None
    if camera_solver == "auto" and _clique_bound(obs_point[seen], obs_col[seen], n_points) * BAND_MAX_SHARE > n_free:
        return None, None  # (no order is narrow enough: the same answer as the reverse Cuthill-McKee order's)
    if (width + 1) * BAND_MAX_SHARE > n_free:  # too wide in this order: a reverse Cuthill-McKee order's?
        import scipy.sparse
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        incidence = scipy.sparse.csr_matrix((np.ones(int(seen.sum())), (obs_point[seen], obs_col[seen])),
                                            shape=(n_points, n_free))
        graph = (incidence.T @ incidence).tocoo()
        rows, cols = np.concatenate([graph.row, tie_cols[:, 0]]), np.concatenate([graph.col, tie_cols[:, 1]])
        pattern = scipy.sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_free, n_free))
        rcm = reverse_cuthill_mckee(pattern + pattern.T, symmetric_mode=True)
        position = np.empty(n_free, np.int64)
        position[rcm] = np.arange(n_free)
        rcm_width = int(np.abs(position[rows] - position[cols]).max(initial=0))
        if rcm_width < width:
            width, order = rcm_width, rcm
    if camera_solver == "auto" and (width + 1) * BAND_MAX_SHARE > n_free:
        return None, None
    return 6 * width + 5, order


def _device_blocks(n_free: int, tie_cols: np.ndarray) -> np.ndarray:
    """The keys (row F + column, increasing) of the pose system's lower blocks that can be non-zero: the free
    poses' diagonal blocks and the lower one of each pair of tied free poses, each once."""
    ties = tie_cols[(tie_cols >= 0).all(axis=1)].reshape(-1, 2)
    rows = np.concatenate([np.arange(n_free), ties.max(axis=1)]).astype(np.int64)
    cols = np.concatenate([np.arange(n_free), ties.min(axis=1)]).astype(np.int64)
    return np.unique(rows * n_free + cols)


def _clique_bound(obs_point: np.ndarray, obs_col: np.ndarray, n_points: int, candidates: int = 8) -> int:
    """A lower bound on the camera system's bandwidth + 1 (in poses) in every order of its poses: the poses that
    see one landmark are all coupled, so the first and the last of them in any order are as many apart; counted
    exactly (distinct poses) for the ``candidates`` landmarks of the most observations. A long-lived track of a
    live map (seen by most keyframes) shows at once that no order makes its system narrow, without the product
    of the incidence matrix that a reverse Cuthill-McKee order needs (docs/benchmarks.md, session 17)."""
    if not len(obs_point):
        return 0
    views = np.bincount(obs_point, minlength=n_points)
    top = np.argpartition(views, -min(candidates, n_points))[-candidates:]
    among = np.isin(obs_point, top)
    stride = int(obs_col.max()) + 1
    keys = np.unique(obs_point[among].astype(np.int64) * stride + obs_col[among])  # (distinct landmark-pose pairs)
    return int(np.bincount(keys // stride).max(initial=0))


def _layout(p: BAProblem, device: str = "numpy", device_schur: bool = False,
            gpu_reductions: bool | None = None, workspace=None, camera_solver: str = "auto",
            camera_tile: int = DEVICE_TILE) -> _Layout:
    """The structure of a pose-major problem (``pose_major``), its observations on Warp ``device`` unless
    that is "numpy"; with ``device_schur`` the landmarks are eliminated there too (``_solve_damped``), with
    ``gpu_reductions`` its sums and medians taken a GPU's ways (opt-in; ``ObservationKernels``); its device
    arrays cut from ``workspace``'s buffers where given (``schur_kernels.SchurWorkspace``); its camera system
    dense or banded as ``camera_solver`` asks (``_camera_band``), and dense ones factorised on the device in tiles
    of ``camera_tile`` where ``_dense_on_device`` says."""
    n_poses, n_points = len(p.poses), len(p.points)
    fixed = np.asarray(p.fixed, bool)
    free = np.flatnonzero(~fixed)
    col = np.full(n_poses, -1, np.int64)
    col[free] = np.arange(len(free))
    obs_point = np.asarray(p.obs_point, np.int64)
    obs_col = col[p.obs_pose]
    tie_cols = col[np.asarray(p.tie_pairs, np.int64).reshape(-1, 2)]
    band, order = _camera_band(obs_point, obs_col, n_points, len(free), tie_cols[(tie_cols >= 0).all(axis=1)],
                               camera_solver)
    if order is not None:  # (the free poses' columns in the narrower order)
        free = free[order]
        col[free] = np.arange(len(free))
        obs_col = col[p.obs_pose]
    dense_on_device = _dense_on_device(device, device_schur, band, len(free), camera_solver)
    block_keys = (_device_blocks(len(free), col[np.asarray(p.tie_pairs, np.int64).reshape(-1, 2)])
                  if dense_on_device else None)
    # (the observations are pose-major: each pose's run found by a search, not a count)
    pose_starts = np.searchsorted(p.obs_pose, np.arange(n_poses + 1))
    on_device = device_schur and device != "numpy"
    # (the device's elimination needs no chunks, nor, unless by pose pairs, to know whether the pairs are unique)
    unique_pairs = None if on_device and not gpu_reductions else _unique_pairs(obs_point, p.obs_pose, n_points,
                                                                              n_poses)
    chunks = [] if on_device else _chunks(obs_point, obs_col, n_points, len(free))
    has_prior = np.ones(n_poses, bool) if p.has_prior is None else np.asarray(p.has_prior, bool)
    prior_idx = np.flatnonzero(has_prior & ~fixed)
    kernels = None
    if device != "numpy":
        from lapreco_hil.mapping.schur_kernels import ObservationKernels

        kernels = ObservationKernels(
            p, obs_col, len(free), device, schur_on_device=device_schur, gpu_reductions=gpu_reductions,
            unique_pairs=unique_pairs, workspace=workspace, band=band,
            camera_tile=camera_tile if dense_on_device else None,
            camera_blocks=None if block_keys is None else (block_keys // len(free), block_keys % len(free)))
    batches, first, entries = [], 0, 0
    for i, ch in enumerate(chunks):
        size = 18 * len(ch.points) * ch.n_cols
        if i > first and entries + size > BATCH_ENTRIES:
            batches.append((first, i))
            first, entries = i, 0
        entries += size
    if chunks:
        batches.append((first, len(chunks)))
    lay = _Layout(free, col, obs_point, obs_col, pose_starts, n_points, chunks, batches, unique_pairs, prior_idx,
                  whitening(np.asarray(p.prior_covs)[prior_idx]), whitening(np.asarray(p.tie_covs)),
                  np.linalg.inv(np.asarray(p.prior_poses)[prior_idx]) if len(prior_idx) else np.zeros((0, 4, 4)),
                  np.linalg.inv(p.tie_T) if len(p.tie_pairs) else np.zeros((0, 4, 4)), kernels, band)
    lay.pose_blocks = _pose_blocks(lay, np.asarray(p.tie_pairs, np.int64).reshape(-1, 2))
    if dense_on_device:
        diagonal = np.arange(len(free))
        lay.camera_tile, lay.device_block_keys = camera_tile, block_keys
        lay.device_diagonal = np.searchsorted(block_keys, diagonal * len(free) + diagonal)
    return lay


def _dense_on_device(device: str, device_schur: bool, band: int | None, n_free: int, camera_solver: str) -> bool:
    """Whether the dense camera system is factorised on the kernels' device: asked ("dense-device"), or by "auto"
    on a CUDA device that eliminates the landmarks there, past DEVICE_DENSE_MIN_FREE_POSES free poses."""
    if camera_solver == "dense-device":
        if device == "numpy" or not device_schur:
            raise ValueError("camera_solver 'dense-device' needs the landmarks eliminated on a Warp device: use "
                             "device cpu or cuda with device_schur on")
        return n_free > 0
    return (camera_solver == "auto" and band is None and device_schur and device.startswith("cuda")
            and n_free > DEVICE_DENSE_MIN_FREE_POSES)


def _to_points(lay: _Layout, values: np.ndarray) -> np.ndarray:
    """Sum per-observation values (O,) into their landmarks (N,)."""
    return np.bincount(lay.obs_point, values, minlength=lay.n_points)


# --- residuals, Jacobians, errors -------------------------------------------------------------------------------
# Per-observation quantities are kept component-major ((component, O) arrays): every arithmetic pass then runs
# over contiguous memory, a few times faster in numpy than the (O, 2, 6) layout's strided columns.
@dataclass
class _Linear:
    """One linearisation: the normal equations' blocks (landmark-pose blocks per observation)."""

    Hcc: np.ndarray  # (6F, 6F) pose block, priors and ties included
    gc: np.ndarray  # (6F,)
    Hpp: np.ndarray | None  # (N, 3, 3); None: on the device
    gp: np.ndarray | None  # (N, 3); None: on the device
    W: np.ndarray | None  # (3, 6, O) s Jp^T Jc per observation (zero where the pose is fixed); None: on the device
    error0: float  # the linear system's error at zero (0.5 |b|^2, the weighted one LM compares with)


def _project(p: BAProblem, lay: _Layout, poses: np.ndarray, points: np.ndarray):
    """(residual u, residual v, x/z, y/z, z, in front): (O,) each; behind the camera the residual is GTSAM's
    constant 2 fx and z is 1."""
    Xw = points[lay.obs_point]
    Xc = np.empty_like(Xw)
    R, t, ps = poses[:, :3, :3], poses[:, :3, 3], lay.pose_starts
    for i in range(len(poses)):
        run = slice(ps[i], ps[i + 1])
        Xc[run] = (Xw[run] - t[i]) @ R[i]  # R^T (X - t), row-wise
    Xc = Xc.T.copy()
    front = Xc[2] > 0
    zs = np.where(front, Xc[2], 1.0)
    xn, yn = Xc[0] / zs, Xc[1] / zs
    ru = p.K[0, 0] * xn + (p.K[0, 2] - p.obs_uv[:, 0])
    rv = p.K[1, 1] * yn + (p.K[1, 2] - p.obs_uv[:, 1])
    if not front.all():
        ru[~front] = rv[~front] = 2.0 * p.K[0, 0]
    return ru, rv, xn, yn, zs, front


def _jacobians(p: BAProblem, lay: _Layout, poses: np.ndarray, xn, yn, zs, front):
    """d residual / d pose tangent (2, 6, O) and d residual / d point (2, 3, O); zero behind the camera."""
    fx, fy = p.K[0, 0], p.K[1, 1]
    a, b = fx / zs, fy / zs
    n = len(zs)
    Jc = np.empty((2, 6, n))
    Jc[0, 0] = fx * xn * yn
    Jc[0, 1] = -fx * (1.0 + xn * xn)
    Jc[0, 2] = fx * yn
    Jc[0, 3] = -a
    Jc[0, 4] = 0.0
    Jc[0, 5] = a * xn
    Jc[1, 0] = fy * (1.0 + yn * yn)
    Jc[1, 1] = -(fy / fx) * Jc[0, 0]
    Jc[1, 2] = -fy * xn
    Jc[1, 3] = 0.0
    Jc[1, 4] = -b
    Jc[1, 5] = b * yn
    # d(pixel)/d(camera point) times R^T: rows of each observation's camera rotation, repeated over its run
    Rcw = np.repeat(np.transpose(poses[:, :3, :3], (0, 2, 1)).reshape(-1, 9), np.diff(lay.pose_starts), axis=0).T
    Jp = np.empty((2, 3, n))
    for k in range(3):
        Jp[0, k] = a * (Rcw[k] - xn * Rcw[6 + k])
        Jp[1, k] = b * (Rcw[3 + k] - yn * Rcw[6 + k])
    if not front.all():
        Jc[:, :, ~front] = 0.0
        Jp[:, :, ~front] = 0.0
    return Jc, Jp


def _reprojection(p: BAProblem, lay: _Layout, poses: np.ndarray, points: np.ndarray, jacobians: bool,
                  behind: float | None = None):
    """Residuals (O, 2) and, with ``jacobians``, their Jacobians wrt the pose (O, 2, 6) and the point
    (O, 2, 3). Behind the camera: GTSAM's constant error 2 fx with zero Jacobians (or ``behind``)."""
    if lay.kernels is not None and not jacobians and behind is not None:
        lay.kernels.set_state(poses, points)
        return lay.kernels.residuals(behind)
    ru, rv, xn, yn, zs, front = _project(p, lay, poses, points)
    r = np.column_stack([ru, rv])
    if behind is not None:
        r[~front] = behind
    if not jacobians:
        return r
    Jc, Jp = _jacobians(p, lay, poses, xn, yn, zs, front)
    return r, np.transpose(Jc, (2, 0, 1)), np.transpose(Jp, (2, 0, 1))


def _pose_errors(p: BAProblem, lay: _Layout, poses: np.ndarray) -> list[tuple]:
    """The priors' and ties' errors at ``poses``, what their loss and Jacobians need: per kind of factor
    (whitened error (n, 6), error (n, 6), its whitening (n, 6, 6), its poses (prior: (i,), tie: (i, j)),
    a tie's T_i^-1 T_j (n, 4, 4) or None, 0.5 |whitened error|^2). A state keeps them with its poses: the error
    at a trial's poses is the next linearisation's."""
    out = []
    if len(lay.prior_idx):
        i = lay.prior_idx
        e = se3_log(lay.prior_inv @ poses[i])
        out.append((np.einsum("nij,nj->ni", lay.prior_R, e), e, lay.prior_R, (i,), None))
    if len(p.tie_pairs):
        i, j = p.tie_pairs[:, 0], p.tie_pairs[:, 1]
        B = np.linalg.inv(poses[i]) @ poses[j]
        e = se3_log(lay.tie_inv @ B)
        out.append((np.einsum("nij,nj->ni", lay.tie_R, e), e, lay.tie_R, (i, j), B))
    return [(*f, 0.5 * float(np.sum(f[0] * f[0]))) for f in out]


def _pose_jacobians(errors: list[tuple]) -> list[tuple]:
    """[(whitened error (n, 6), [(pose idx (n,), whitened J (n, 6, 6))])] of ``_pose_errors``' factors."""
    out = []
    for err, e, R, idx, B, _ in errors:
        J = R @ right_jacobian_inverse(e)
        out.append((err, [(idx[0], J)] if B is None else [(idx[0], -J @ adjoint(np.linalg.inv(B))), (idx[1], J)]))
    return out


def _pose_factors(p: BAProblem, lay: _Layout, poses: np.ndarray, jacobians: bool):
    """Whitened prior and tie errors, and (optionally) their Jacobians: [(error (n, 6), [(pose idx (n,),
    J (n, 6, 6))])]."""
    errors = _pose_errors(p, lay, poses)
    if jacobians:
        return _pose_jacobians(errors)
    return [(f[0], []) for f in errors]


def _pose_normal_terms(lay: _Layout, errors: list[tuple]) -> list[tuple]:
    """The pose factors' terms of the normal equations, for ``_with_pose_factors`` (made while the device
    linearises): per factor and pose, (free column blocks, J^T e) and [((column blocks a, :, b, :), Ja^T Jb)]."""
    out = []
    for err, jac in _pose_jacobians(errors):
        for idx_a, Ja in jac:
            ca = lay.col[idx_a]
            ok = ca >= 0
            blocks = []
            for idx_b, Jb in jac:
                cb = lay.col[idx_b]
                both = ok & (cb >= 0)
                blocks.append(((ca[both], slice(None), cb[both], slice(None)),
                               np.transpose(Ja[both], (0, 2, 1)) @ Jb[both]))
            out.append((ca[ok], np.einsum("nji,nj->ni", Ja[ok], err[ok]), blocks))
    return out


def _plus_pose_factors(p: BAProblem, lay: _Layout, poses, total: float, errors: list | None = None) -> float:
    """``total`` (the reprojection losses) plus 0.5 |whitened error|^2 of the priors and ties (``errors``: their
    ``_pose_errors`` at ``poses``, where known)."""
    for f in _pose_errors(p, lay, poses) if errors is None else errors:
        total += f[-1]
    return total


def _error(p: BAProblem, lay: _Layout, poses, points, sigma: float, loss: str, k: float,
           errors: list | None = None) -> float:
    """GTSAM's graph.error: the sum of the reprojection losses plus 0.5 |whitened error|^2 of priors, ties."""
    if lay.kernels is not None:
        lay.kernels.set_state(poses, points)
        total = lay.kernels.error(sigma, loss, k)
    else:
        ru, rv = _project(p, lay, poses, points)[:2]
        total = float(np.sum(robust_loss(loss, np.sqrt(ru * ru + rv * rv) / sigma, k)))
    return _plus_pose_factors(p, lay, poses, total, errors)


def _start_linearize_on_device(p: BAProblem, lay: _Layout, poses, sigma: float, loss: str, k: float,
                               lam: float | None = None, errors: list | None = None) -> tuple[list, list]:
    """Start ``_linearize_on_device``'s linearisation on the device and make the pose factors' terms while it
    works: (their ``_pose_errors``, ``_pose_normal_terms``) for ``_linearize_on_device(started=...)``."""
    on_device = lay.kernels.schur_on_device
    lay.kernels.launch_linearize(sigma, loss, k, lam if on_device else None, landmarks=not on_device)
    errors = _pose_errors(p, lay, poses) if errors is None else errors
    return errors, _pose_normal_terms(lay, errors)


def _linearize_on_device(p: BAProblem, lay: _Layout, poses, sigma: float, loss: str, k: float,
                         lam: float | None = None, errors: list | None = None,
                         started: tuple | None = None) -> _Linear:
    """``_linearize`` by the kernels at their current state (``poses`` on the host); the landmark blocks stay on
    the device where the elimination runs there (``_Linear.Hpp``, ``gp`` None), and are eliminated at ``lam``
    with it where given (``ObservationKernels.launch_linearize``). The host makes the pose factors' terms while
    the device works; ``started``: ``_start_linearize_on_device``'s, where it started already."""
    errors, terms = started or _start_linearize_on_device(p, lay, poses, sigma, loss, k, lam, errors)
    blocks, grads, weighted_sq, Hpp, gp = lay.kernels.read_linearize()
    Hcc = _camera_system_of_diagonal_blocks(lay, blocks)
    return _with_pose_factors(lay, Hcc, grads.ravel(), Hpp, gp, None, 0.5 * weighted_sq, errors, terms)


def _linearize(p: BAProblem, lay: _Layout, poses, points, sigma: float, loss: str, k: float,
               errors: list | None = None) -> _Linear:
    if lay.kernels is not None:
        lay.kernels.set_state(poses, points)
        return _linearize_on_device(p, lay, poses, sigma, loss, k, errors=errors)
    errors = _pose_errors(p, lay, poses) if errors is None else errors
    ru, rv, xn, yn, zs, front = _project(p, lay, poses, points)
    Jc, Jp = _jacobians(p, lay, poses, xn, yn, zs, front)
    r2 = ru * ru + rv * rv
    s = robust_weight(loss, np.sqrt(r2) / sigma, k) / sigma**2  # whitening and the robust reweighting, squared
    su, sv = s * ru, s * rv
    error0 = 0.5 * float(np.sum(s * r2))
    sJp = s * Jp
    Hpp = np.empty((lay.n_points, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            Hpp[:, a, b] = Hpp[:, b, a] = _to_points(lay, sJp[0, a] * Jp[0, b] + sJp[1, a] * Jp[1, b])
    gp = np.column_stack([_to_points(lay, Jp[0, a] * su + Jp[1, a] * sv) for a in range(3)])
    W = np.empty((3, 6, len(s)))
    for a in range(3):
        for b in range(6):  # one contiguous pass each (a broadcast product is 3x slower here)
            np.multiply(sJp[0, a], Jc[0, b], out=W[a, b])
            W[a, b] += sJp[1, a] * Jc[1, b]
    n_free = len(lay.free)
    blocks = np.zeros((n_free, 6, 6))
    gc = np.zeros(6 * n_free)
    if n_free:
        W[:, :, lay.obs_col < 0] = 0.0
        Jw = np.sqrt(s) * Jc  # whitened Jacobian rows; each pose's observations are one run
        for c, i in enumerate(lay.free.tolist()):
            run = slice(lay.pose_starts[i], lay.pose_starts[i + 1])
            blocks[c] = Jw[0, :, run] @ Jw[0, :, run].T + Jw[1, :, run] @ Jw[1, :, run].T
            gc[6 * c:6 * c + 6] = Jc[0, :, run] @ su[run] + Jc[1, :, run] @ sv[run]
    Hcc = _camera_system_of_diagonal_blocks(lay, blocks)
    return _with_pose_factors(lay, Hcc, gc, Hpp, gp, W, error0, errors, _pose_normal_terms(lay, errors))


def _with_pose_factors(lay: _Layout, Hcc, gc, Hpp, gp, W, error0: float, errors: list, terms: list) -> _Linear:
    """The linearisation with the priors' and ties' terms (``_pose_errors``, ``_pose_normal_terms``) added to
    the pose blocks."""
    n_free = len(lay.free)
    g2 = gc.reshape(n_free, 6)
    for f in errors:
        error0 += f[-1]
    if lay.camera_tile is not None:  # (the lower blocks alone: the factorisation reads the lower triangle)
        for cols, g, blocks in terms:
            np.add.at(g2, cols, g)
            for index, H in blocks:
                rows, columns = index[0], index[2]
                lower = rows >= columns
                at = np.searchsorted(lay.device_block_keys, rows[lower] * n_free + columns[lower])
                np.add.at(Hcc, at, H[lower])
    elif lay.band is None:
        H4 = Hcc.reshape(n_free, 6, n_free, 6)  # a view: (pose, row, pose, column)
        for cols, g, blocks in terms:
            np.add.at(g2, cols, g)
            for index, H in blocks:
                np.add.at(H4, index, H)
    else:
        for cols, g, blocks in terms:
            np.add.at(g2, cols, g)
            for index, H in blocks:
                flat, lower = _band_entries(lay.band, index[0], index[2])
                np.add.at(Hcc.ravel(), flat[lower], H[lower])
    return _Linear(Hcc, gc, Hpp, gp, W, error0)


# --- the camera system as a band matrix (``_Layout.band``) -----------------------------------------------------
def _band_entries(band: int, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the entries of the 6 x 6 blocks (rows[n], cols[n]) of the camera system lie in its band array
    (flat indices, (n, 6, 6)), and which of them are in its lower triangle (the band array holds those alone)."""
    i = 6 * np.asarray(rows, np.int64)[:, None, None] + np.arange(6)[None, :, None]
    j = 6 * np.asarray(cols, np.int64)[:, None, None] + np.arange(6)[None, None, :]
    lower = i >= j
    return np.where(lower, j * (band + 1) + (i - j), 0), lower


def _camera_system_of_diagonal_blocks(lay, blocks: np.ndarray) -> np.ndarray:
    """The camera system's start, its free poses' 6x6 diagonal blocks: dense, in the layout's band storage, or
    as the lower blocks that can be non-zero (``_Layout.camera_tile``)."""
    if lay.band is not None:
        return _band_of_diagonal_blocks(lay.band, blocks)
    if lay.camera_tile is not None:
        H = np.zeros((len(lay.device_block_keys), 6, 6))
        H[lay.device_diagonal] = blocks
        return H
    n_free = len(blocks)
    Hcc = np.zeros((6 * n_free, 6 * n_free))
    diagonal = np.arange(n_free)
    Hcc.reshape(n_free, 6, n_free, 6)[diagonal, :, diagonal, :] = blocks
    return Hcc


def _band_of_diagonal_blocks(band: int, blocks: np.ndarray) -> np.ndarray:
    """The band array (6F, band + 1) of the block diagonal ``blocks`` (F, 6, 6)."""
    B = np.zeros((6 * len(blocks), band + 1))
    diagonal = np.arange(len(blocks))
    flat, lower = _band_entries(band, diagonal, diagonal)
    B.ravel()[flat[lower]] = blocks[lower]
    return B


def _subtract_gram_band(B: np.ndarray, band: int, idx, Z: np.ndarray) -> None:
    """B -= the lower band of Z^T Z on rows/columns ``idx`` (a slice, or increasing indices) of the camera system
    held as a band array (``_Layout.band``). The rows and columns j..j+w of a band array are a (w x w) matrix of
    leading dimension ``band`` in Fortran's view (entry (i, j) at i + band j), so a block of at most ``band`` wide
    is one BLAS dsyrk in place; a wider one (entries beyond the band are zero: no landmark couples those poses)
    goes through a dense Gram matrix."""
    rows, width = Z.shape
    if not rows or not width:
        return
    if isinstance(idx, slice) and width <= band:
        assert B.flags.c_contiguous and Z.flags.c_contiguous and B.shape[1] == band + 1
        c = ctypes.c_int
        _dsyrk()(b"L", b"N", ctypes.byref(c(width)), ctypes.byref(c(rows)), ctypes.byref(ctypes.c_double(-1.0)),
                 Z.ctypes.data, ctypes.byref(c(width)), ctypes.byref(ctypes.c_double(1.0)),
                 B.ctypes.data + 8 * idx.start * (band + 1), ctypes.byref(c(band)))
        return
    at = np.arange(idx.start, idx.stop) if isinstance(idx, slice) else np.asarray(idx)
    G = scipy.linalg.blas.dsyrk(1.0, Z.T, trans=0, lower=1)
    p, q = np.tril_indices(width)
    i, j = at[p], at[q]
    near = i - j <= band
    B.ravel()[j[near] * (band + 1) + (i - j)[near]] -= G[p[near], q[near]]


def _wide_dense(lay: _Layout) -> bool:
    """A dense camera system past BAND_MIN_FREE_POSES (a final pass, never a local window): its damped system is
    made from the pose system's blocks that can be non-zero (``_pose_blocks``) alone, not by whole-matrix passes
    (an identity as wide, its sum, a copy: each tens of MB at a few thousand wide)."""
    return lay.band is None and len(lay.free) > BAND_MIN_FREE_POSES


def _pose_blocks(lay: _Layout, tie_pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) blocks of the pose system where it can be non-zero: the free poses' diagonal blocks
    (their observations and priors) and the blocks of the ties between two free poses."""
    ca, cb = lay.col[tie_pairs[:, 0]], lay.col[tie_pairs[:, 1]]
    both = (ca >= 0) & (cb >= 0)
    diagonal = np.arange(len(lay.free))
    return (np.concatenate([diagonal, ca[both], cb[both]]), np.concatenate([diagonal, cb[both], ca[both]]))


def _damped_blocks(lay: _Layout, lin: _Linear, lam: float) -> tuple[tuple, np.ndarray]:
    """The damped pose system's possibly non-zero blocks: (their index into a (F, 6, F, 6) view, (k, 6, 6)
    values); lambda added on the diagonal blocks' diagonals (H + lambda I there, as the whole sum makes them)."""
    n_free = len(lay.free)
    rows, cols = lay.pose_blocks
    index = (rows, slice(None), cols, slice(None))
    D = lin.Hcc.reshape(n_free, 6, n_free, 6)[index]
    D[rows == cols] += lam * np.eye(6)
    return index, D


def _damped(lay: _Layout, lin: _Linear, lam: float) -> np.ndarray:
    """The pose system damped by lambda: its band array (the diagonal is its first column), or dense (a wide one
    from its possibly non-zero blocks alone, the same values: ``_wide_dense``)."""
    if lay.band is not None:
        S = lin.Hcc.copy()
        S[:, 0] += lam
        return S
    n6 = lin.Hcc.shape[0]
    if not _wide_dense(lay):
        return lin.Hcc + lam * np.eye(n6)
    S = np.zeros((n6, n6))
    index, D = _damped_blocks(lay, lin, lam)
    S.reshape(len(lay.free), 6, len(lay.free), 6)[index] = D
    return S


def _damped_minus(lay: _Layout, lin: _Linear, lam: float, M: np.ndarray) -> np.ndarray:
    """The damped pose system minus ``M`` (the landmarks' eliminated blocks, the same shape: dense or a band
    array): (H + lambda I) - M. A wide dense one is made in ``M`` itself (taken): -M, then (H + lambda I) - M on
    the pose system's possibly non-zero blocks; the same values (a - b is a + (-b)), zeros' signs aside."""
    if not _wide_dense(lay):
        S = _damped(lay, lin, lam)
        S -= M
        return S
    np.negative(M, out=M)
    index, D = _damped_blocks(lay, lin, lam)
    M4 = M.reshape(len(lay.free), 6, len(lay.free), 6)
    M4[index] = D + M4[index]
    return M


# --- one damped step ------------------------------------------------------------------------------------------------
def _cholesky3(V: np.ndarray):
    """Closed-form Cholesky factors (l11, l21, l22, l31, l32, l33) of (N, 3, 3) symmetric matrices; None unless
    every one is positive definite (LAPACK's test: a pivot <= 0 or NaN fails)."""
    d1 = V[:, 0, 0]
    if not np.all(d1 > 0):
        return None
    l11 = np.sqrt(d1)
    l21, l31 = V[:, 1, 0] / l11, V[:, 2, 0] / l11
    d2 = V[:, 1, 1] - l21 * l21
    if not np.all(d2 > 0):
        return None
    l22 = np.sqrt(d2)
    l32 = (V[:, 2, 1] - l31 * l21) / l22
    d3 = V[:, 2, 2] - l31 * l31 - l32 * l32
    if not np.all(d3 > 0):
        return None
    return l11, l21, l22, l31, l32, np.sqrt(d3)


def _forward(L, X: np.ndarray) -> np.ndarray:
    """L^-1 X for X (N, 3, ...) (L from ``_cholesky3``, broadcast over the trailing axes)."""
    l11, l21, l22, l31, l32, l33 = (v.reshape(v.shape + (1,) * (X.ndim - 2)) for v in L)
    Z = np.empty_like(X)
    Z[:, 0] = X[:, 0] / l11
    Z[:, 1] = (X[:, 1] - l21 * Z[:, 0]) / l22
    Z[:, 2] = (X[:, 2] - l31 * Z[:, 0] - l32 * Z[:, 1]) / l33
    return Z


def _backward(L, Z: np.ndarray) -> np.ndarray:
    """L^-T Z for Z (N, 3)."""
    l11, l21, l22, l31, l32, l33 = L
    Y = np.empty_like(Z)
    Y[:, 2] = Z[:, 2] / l33
    Y[:, 1] = (Z[:, 1] - l32 * Y[:, 2]) / l22
    Y[:, 0] = (Z[:, 0] - l21 * Y[:, 1] - l31 * Y[:, 2]) / l11
    return Y


def _solve_damped(lay: _Layout, lin: _Linear, lam: float, timing: dict):
    """The step (pose tangents (F, 6), point moves (N, 3)) of the damped system, landmarks eliminated;
    None where it is not positive definite (a landmark left with one weighted view is singular along its ray
    to the damping's precision: GTSAM's elimination throws IndeterminateSystemException there, and lambda
    grows). The host's elimination (chunk by chunk through BLAS); the device's is ``_DeviceState.solve``'s."""
    assert lay.kernels is None or not lay.kernels.schur_on_device
    t0 = time.perf_counter()
    L = _cholesky3(lin.Hpp + lam * np.eye(3))
    if L is None:
        timing["schur_s"] += time.perf_counter() - t0
        return None
    Lg = _forward(L, lin.gp[:, :, None])[:, :, 0]  # L^-1 gp
    n6 = lin.Hcc.shape[0]
    band = lay.band
    # (its lower triangle is what the factorisation reads)
    S = _damped(lay, lin, lam)
    rhs = -lin.gc.copy()
    on_device = lay.kernels is not None and lay.unique_pairs
    if on_device:
        lay.kernels.set_landmark_factors(np.column_stack(L))
    W = lin.W  # (3, 6, O)
    if lay.kernels is not None and not on_device:
        W = np.transpose(lay.kernels.W_host(), (1, 2, 0))
    for b, (first, stop) in enumerate(lay.batches):
        chunks = lay.chunks[first:stop]
        sizes = [18 * len(ch.points) * ch.n_cols for ch in chunks]
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        # every landmark of a chunk seen by every one of its poses (a local window): each entry is written
        dense = lay.unique_pairs and all(len(ch.obs) == len(ch.points) * ch.n_cols for ch in chunks)
        Zs = lay.kernels.whitened_batch(b, chunks, offsets, dense) if on_device else None
        for i, ch in enumerate(chunks):
            n_c = len(ch.points)
            if on_device:
                Z = Zs[offsets[i]:offsets[i + 1]].reshape(3 * n_c, -1)  # L^-1 W: S -= Z^T Z
            else:
                Wd = (np.empty if dense else np.zeros)((n_c, 3, 6 * ch.n_cols))
                if lay.unique_pairs:
                    Wd.ravel()[ch.dest] = W[:, :, ch.obs]
                else:
                    np.add.at(Wd.ravel(), ch.dest, W[:, :, ch.obs])
                Z = _forward(tuple(v[ch.points] for v in L), Wd).reshape(3 * n_c, -1)  # L^-1 W: S -= Z^T Z
            if band is not None:
                _subtract_gram_band(S, band, ch.idx, Z)
            elif isinstance(ch.idx, slice):
                _subtract_gram(S, ch.idx, Z)
            else:
                S[np.ix_(ch.idx, ch.idx)] -= scipy.linalg.blas.dsyrk(1.0, Z.T, trans=0, lower=1)
            rhs[ch.idx] += Z.T @ Lg[ch.points].ravel()
    t1 = time.perf_counter()
    timing["schur_s"] += t1 - t0
    dc = _solve_camera_system(S, rhs) if band is None else _solve_band_system(S, rhs)
    if dc is None:
        timing["solve_s"] += time.perf_counter() - t1
        return None
    # back-substitution: dp = -V^-1 (gp + W^T dc) per landmark
    x = lin.gp.copy()
    if n6:
        if lay.kernels is not None:
            x += lay.kernels.w_times_step(dc.reshape(-1, 6))
        else:
            dc_of_obs = np.vstack([dc.reshape(-1, 6), np.zeros((1, 6))])[lay.obs_col].T  # fixed poses: row -1
            x += np.column_stack([_to_points(lay, np.einsum("bo,bo->o", W[a], dc_of_obs)) for a in range(3)])
    dp = -_backward(L, _forward(L, x[:, :, None])[:, :, 0])
    timing["solve_s"] += time.perf_counter() - t1
    return dc.reshape(-1, 6), dp


def _solve_camera_system(S: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """The damped camera system's solution by its Cholesky factor (S's lower triangle); None where it is not
    positive definite."""
    if not len(rhs):
        return np.zeros(0)
    # (LAPACK's potrf and potrs, as scipy's cho_factor and cho_solve call them, without their wrappers' checks:
    # half their time on a window's system)
    factor, info = scipy.linalg.lapack.dpotrf(S, lower=1, clean=0)
    if info > 0:
        return None
    dc, info_solve = scipy.linalg.lapack.dpotrs(factor, rhs, lower=1)
    if info < 0 or info_solve < 0:
        raise ValueError(f"LAPACK potrf/potrs: illegal argument {min(info, info_solve)}")
    return dc if np.all(np.isfinite(dc)) else None


def _solve_band_system(B: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """``_solve_camera_system`` of a camera system held as a band array (``_Layout.band``; overwritten): LAPACK's
    banded Cholesky (pbtrf, pbtrs) on its transpose, LAPACK's lower band storage as it lies."""
    if not len(rhs):
        return np.zeros(0)
    factor, info = scipy.linalg.lapack.dpbtrf(B.T, lower=1, overwrite_ab=1)
    if info > 0:
        return None
    dc, info_solve = scipy.linalg.lapack.dpbtrs(factor, rhs, lower=1)
    if info < 0 or info_solve < 0:
        raise ValueError(f"LAPACK pbtrf/pbtrs: illegal argument {min(info, info_solve)}")
    return dc if np.all(np.isfinite(dc)) else None


def _eliminate_on_device(lay: _Layout, lin: _Linear, lam: float, timing: dict) -> np.ndarray | None:
    """The damped camera system's solution (F, 6) with the landmarks eliminated on the kernels' device (a
    handful of launches, the camera system (6F x 6F) and a flag read back in one copy, the host solving it);
    None where it is not positive definite."""
    t0 = time.perf_counter()
    if lay.camera_tile is not None:  # (solved there: the host's seconds launching, then waiting)
        lay.kernels.launch_camera_solve(lam, lin.Hcc, lin.gc)
        t1 = time.perf_counter()
        timing["schur_s"] += t1 - t0
        dc = lay.kernels.read_camera_solve()
        timing["solve_s"] += time.perf_counter() - t1
        return None if dc is None else dc.reshape(-1, 6)
    eliminated = lay.kernels.schur_complement(lam)
    if eliminated is None:
        timing["schur_s"] += time.perf_counter() - t0
        return None
    M, r = eliminated
    S = _damped_minus(lay, lin, lam, M)  # (its lower triangle: what the factorisation reads; a band array's all)
    rhs = r - lin.gc
    t1 = time.perf_counter()
    timing["schur_s"] += t1 - t0
    dc = _solve_camera_system(S, rhs) if lay.band is None else _solve_band_system(S, rhs)
    timing["solve_s"] += time.perf_counter() - t1
    return None if dc is None else dc.reshape(-1, 6)


# --- the solver's state: in host arrays (numpy) or on the kernels' device -------------------------------------------
@dataclass
class _Step:
    """A damped step and what LM asks of it."""

    dc: np.ndarray  # (F, 6) the free poses' tangents
    dp: np.ndarray | None  # (N, 3) the landmarks' moves; None: on the device
    g_dot: float  # g . d
    step2: float  # |d|^2
    poses: np.ndarray  # (P, 4, 4) the trial poses
    reprojection_error: float | None = None  # the trial's, where the device evaluated it with the step
    pose_errors: list | None = None  # the trial poses' ``_pose_errors``, once made


def _trial_poses(lay: _Layout, poses: np.ndarray, dc: np.ndarray) -> np.ndarray:
    trial = poses.copy()
    if len(lay.free):
        trial[lay.free] = poses[lay.free] @ se3_exp(dc)
    return trial


class _HostState:
    """The numpy path's state: poses and landmarks in host arrays."""

    def __init__(self, p: BAProblem, lay: _Layout, poses: np.ndarray, points: np.ndarray) -> None:
        self.p, self.lay, self.poses, self._points, self._trial = p, lay, poses, points, None
        self._pose_errors = None  # the pose factors' ``_pose_errors`` at ``poses``, once made

    def pose_errors(self) -> list:
        if self._pose_errors is None:
            self._pose_errors = _pose_errors(self.p, self.lay, self.poses)
        return self._pose_errors

    def points(self) -> np.ndarray:
        return self._points

    def residuals(self, behind: float) -> np.ndarray:
        return _reprojection(self.p, self.lay, self.poses, self._points, jacobians=False, behind=behind)

    def start(self, sigma: float, loss: str, k: float, lam: float) -> None:
        """(the device's way of starting a linearisation early: nothing to do here)"""

    def error(self, sigma: float, loss: str, k: float) -> float:
        return _error(self.p, self.lay, self.poses, self._points, sigma, loss, k, self.pose_errors())

    def linearize(self, sigma: float, loss: str, k: float, lam: float) -> _Linear:
        return _linearize(self.p, self.lay, self.poses, self._points, sigma, loss, k, self.pose_errors())

    def solve(self, lin: _Linear, lam: float, sigma: float, loss: str, k: float, timing: dict) -> _Step | None:
        step = _solve_damped(self.lay, lin, lam, timing)
        if step is None:
            return None
        dc, dp = step
        return _Step(dc, dp, float(dc.ravel() @ lin.gc + dp.ravel() @ lin.gp.ravel()),
                     float(dc.ravel() @ dc.ravel() + dp.ravel() @ dp.ravel()), _trial_poses(self.lay, self.poses, dc))

    def trial_error(self, step: _Step, sigma: float, loss: str, k: float) -> float:
        self._trial = self._points + step.dp
        step.pose_errors = _pose_errors(self.p, self.lay, step.poses)
        return _error(self.p, self.lay, step.poses, self._trial, sigma, loss, k, step.pose_errors)

    def accept(self, step: _Step) -> None:
        self.poses, self._points, self._pose_errors = step.poses, self._trial, step.pose_errors


class _DeviceState:
    """The Warp path's state: the landmarks stay on the kernels' device from the solve's start to its end (read
    back once); the poses, a few, on both sides (the host's pose factors and camera system need them; each trial's
    are uploaded once). A step is applied and its error evaluated there, one read-back each (``ObservationKernels``);
    the host works on the pose factors between a launch and its read-back."""

    def __init__(self, p: BAProblem, lay: _Layout, poses: np.ndarray, points: np.ndarray) -> None:
        self.p, self.lay, self.kernels, self.poses = p, lay, lay.kernels, poses
        self.kernels.set_state(poses, points)
        self._pose_errors = None  # the pose factors' ``_pose_errors`` at ``poses``, once made
        self._started = None  # ((sigma, loss, k, lambda), its pose-factor terms) of a linearisation started

    def pose_errors(self) -> list:
        if self._pose_errors is None:
            self._pose_errors = _pose_errors(self.p, self.lay, self.poses)
        return self._pose_errors

    def points(self) -> np.ndarray:
        return self.kernels.points()

    def residuals(self, behind: float) -> np.ndarray:
        return self.kernels.residuals(behind)

    def start(self, sigma: float, loss: str, k: float, lam: float) -> None:
        """Start the linearisation that LM asks for after the error (read back with it: one wait fewer)."""
        self._started = (sigma, loss, k, lam), _start_linearize_on_device(self.p, self.lay, self.poses, sigma, loss,
                                                                          k, lam, self.pose_errors())

    def error(self, sigma: float, loss: str, k: float) -> float:
        return _plus_pose_factors(self.p, self.lay, self.poses, self.kernels.error(sigma, loss, k), self.pose_errors())

    def linearize(self, sigma: float, loss: str, k: float, lam: float) -> _Linear:
        """(with the landmarks eliminated at ``lam``, the damping LM tries first, where that runs here)"""
        started = self._started[1] if self._started and self._started[0] == (sigma, loss, k, lam) else None
        self._started = None
        return _linearize_on_device(self.p, self.lay, self.poses, sigma, loss, k, lam, self.pose_errors(), started)

    def solve(self, lin: _Linear, lam: float, sigma: float, loss: str, k: float, timing: dict) -> _Step | None:
        """The step, its trial state made on the device and its reprojection error evaluated there with it (LM
        reads it only where the model predicts a decrease: the same decisions, one read-back fewer), the trial
        poses' pose-factor errors made on the host meanwhile."""
        if self.kernels.schur_on_device:
            dc = _eliminate_on_device(self.lay, lin, lam, timing)
            if dc is None:
                return None
            t0 = time.perf_counter()
            trial = _trial_poses(self.lay, self.poses, dc)
            self.kernels.launch_back_substitute(dc, trial, sigma, loss, k)
            pose_errors = _pose_errors(self.p, self.lay, trial)
            dp_gp, dp_dp, error = self.kernels.read_step()
            timing["solve_s"] += time.perf_counter() - t0
            return _Step(dc, None, float(dc.ravel() @ lin.gc) + dp_gp, float(dc.ravel() @ dc.ravel()) + dp_dp,
                         trial, error, pose_errors)
        step = _solve_damped(self.lay, lin, lam, timing)  # the landmarks eliminated through host BLAS
        if step is None:
            return None
        dc, dp = step
        t0 = time.perf_counter()
        trial = _trial_poses(self.lay, self.poses, dc)
        self.kernels.launch_try_step(dp, trial, sigma, loss, k)
        pose_errors = _pose_errors(self.p, self.lay, trial)
        error = self.kernels.read_step()[2]
        timing["error_s"] += time.perf_counter() - t0
        return _Step(dc, None, float(dc.ravel() @ lin.gc + dp.ravel() @ lin.gp.ravel()),
                     float(dc.ravel() @ dc.ravel() + dp.ravel() @ dp.ravel()), trial, error, pose_errors)

    def trial_error(self, step: _Step, sigma: float, loss: str, k: float) -> float:
        return _plus_pose_factors(self.p, self.lay, step.poses, step.reprojection_error, step.pose_errors)

    def accept(self, step: _Step) -> None:
        self.kernels.accept()
        self.poses, self._pose_errors = step.poses, step.pose_errors


def _new_state(p: BAProblem, lay: _Layout):
    if lay.kernels is None:  # (the host's state moves its own copies)
        return _HostState(p, lay, np.array(p.poses, float), np.array(p.points, float))
    return _DeviceState(p, lay, np.array(p.poses, float), np.asarray(p.points, float))  # (the landmarks uploaded)


# --- Levenberg-Marquardt as GTSAM runs it -------------------------------------------------------------------------
def _lm(state, sigma: float, loss: str, k: float, max_iterations: int, timing: dict):
    """One LM run from ``state`` (left at its result): (error before, error after, iterations, per-iteration
    times, damped systems solved: one per lambda tried)."""
    t0 = time.perf_counter()
    started_s = 0.0
    if max_iterations:  # (the first linearisation starts before the error: a device reads both back at once)
        state.start(sigma, loss, k, LAMBDA_INITIAL)
        started_s = time.perf_counter() - t0
        timing["linearize_s"] += started_s
        t0 = time.perf_counter()
    error = state.error(sigma, loss, k)
    timing["error_s"] += time.perf_counter() - t0
    error_before = error
    lam, iterations, per_iteration, solves = LAMBDA_INITIAL, 0, [], 0
    if max_iterations == 0 or error <= 0.0:
        return error_before, error, iterations, per_iteration, solves
    while True:
        it_times = {k_: timing[k_] for k_ in _new_timing()}
        if not per_iteration:  # (its linearisation started before the error)
            it_times["linearize_s"] -= started_s
        t0 = time.perf_counter()
        lin = state.linearize(sigma, loss, k, lam)
        timing["linearize_s"] += time.perf_counter() - t0
        new_error, accepted = error, False
        while True:
            solves += 1
            step = state.solve(lin, lam, sigma, loss, k, timing)
            stop_searching = success = False
            if step is not None:
                # the undamped linear model's decrease: -g.d - d^T H d / 2, with (H + lam I) d = -g
                linear_change = -0.5 * step.g_dot + 0.5 * lam * step.step2
                if linear_change >= 0:
                    t0 = time.perf_counter()
                    trial_error = state.trial_error(step, sigma, loss, k)
                    timing["error_s"] += time.perf_counter() - t0
                    cost_change = error - trial_error
                    if linear_change > np.finfo(float).eps * lin.error0:
                        success = cost_change / linear_change > MIN_MODEL_FIDELITY
                    stop_searching = abs(cost_change) < RELATIVE_ERROR_TOL * error
            if success:
                state.accept(step)
                new_error, accepted = trial_error, True
                lam = max(0.0, lam / LAMBDA_FACTOR)
                iterations += 1
                break
            if stop_searching:
                break
            lam *= LAMBDA_FACTOR
            if lam >= LAMBDA_UPPER:
                log.debug("LM gives up: cannot decrease the error with the largest lambda")
                break
        per_iteration.append({k_: timing[k_] - it_times[k_] for k_ in it_times})
        decrease = error - new_error
        converged = (not accepted or new_error <= 0.0 or decrease / error <= RELATIVE_ERROR_TOL
                     or decrease <= ABSOLUTE_ERROR_TOL)
        error = new_error
        if iterations >= max_iterations or converged or not np.isfinite(error):
            break
    return error_before, error, iterations, per_iteration, solves


@functools.cache
def _check_device(device: str) -> str:
    """"numpy", or the Warp device (cpu, cuda, cuda:N) that runs the per-observation kernels. (Once per name:
    resolving initialises Warp, a temporary file's redirection each time.)"""
    if device == "numpy":
        return device
    from lapreco_hil.warp_device import resolve_device

    return resolve_device(device)


def _device_schur(device: str, asked: bool | None, camera_solver: str = "auto") -> bool:
    if device == "numpy":
        return False
    if asked is None:  # (the camera system solved on the device needs the landmarks eliminated there)
        return device.startswith("cuda") or camera_solver == "dense-device"
    return bool(asked)


def _new_timing() -> dict:
    return {"linearize_s": 0.0, "schur_s": 0.0, "solve_s": 0.0, "error_s": 0.0}


def _unsorted(values: np.ndarray, perm: np.ndarray) -> np.ndarray:
    out = np.empty_like(values)
    out[perm] = values
    return out


def _setup(problem: BAProblem, device: str, device_schur: bool | None, gpu_reductions: bool | None = None,
           workspace=None, camera_solver: str = "auto", camera_tile: int = DEVICE_TILE):
    """(the pose-major problem, its permutation, its layout, the seconds it took)."""
    device = _check_device(device)
    t0 = time.perf_counter()
    p, perm = pose_major(problem)
    lay = _layout(p, device, _device_schur(device, device_schur, camera_solver), gpu_reductions, workspace,
                  camera_solver, camera_tile)
    return p, perm, lay, time.perf_counter() - t0


def _camera_stats(lay: _Layout) -> dict:
    """How the camera system was held and solved: "dense" (the host's LAPACK), "dense-device" (the kernels'
    device, ``camera_tile``: its tiles' side), or "banded" with its lower bandwidth (entries)."""
    solver = "banded" if lay.band is not None else "dense" if lay.camera_tile is None else "dense-device"
    return {"camera_solver": solver, "camera_band": lay.band, "camera_tile": lay.camera_tile}


def _device_ops(lay: _Layout) -> dict:
    """What the kernels' device was asked for during the solve (``ObservationKernels.ops``); {} on numpy."""
    return dict(lay.kernels.ops) if lay.kernels is not None else {}


def solve_schur(problem: BAProblem, pixel_sigma: float = 1.0, loss: str | None = "cauchy", k: float = 2.0,
                max_iterations: int = 15, device: str = "cpu", blas_threads: int = 1,
                device_schur: bool | None = None, camera_solver: str = "auto",
                camera_tile: int = DEVICE_TILE) -> BAResult:
    """``bundle_adjustment.solve`` (one LM run, fixed pixel sigma and m-estimator) on the reduced camera system.
    ``device``: the Warp device of the per-observation kernels (cpu, cuda, cuda:N), or "numpy" (no Warp);
    ``blas_threads``: the BLAS threads of the camera system's products and factorisation (``_blas_threads``);
    ``device_schur``: eliminate the landmarks on the kernels' device (one launch summing every landmark's block
    into the camera system by atomics, which only a GPU does fast) instead of chunk by chunk through host BLAS;
    None: on CUDA devices only; ``camera_solver``: the camera system held and factorised "dense", "banded" (LAPACK's
    banded Cholesky, the free poses in a reverse Cuthill-McKee order where that narrows the band) or "auto"
    (banded for a problem of more than BAND_MIN_FREE_POSES free poses whose band is narrow: ``_camera_band``;
    else dense, factorised on a CUDA device that eliminates the landmarks, past DEVICE_DENSE_MIN_FREE_POSES free
    poses, by the host's LAPACK otherwise) or "dense-device" (dense, factorised on the kernels' Warp device by a
    blocked Cholesky of tiles of ``camera_tile``: ``dense_cholesky``; the landmarks eliminated there); the same
    answers to round-off."""
    t0 = time.perf_counter()
    p, perm, lay, setup_s = _setup(problem, device, device_schur, camera_solver=camera_solver,
                                   camera_tile=camera_tile)
    timing = _new_timing()
    state = _new_state(p, lay)
    with _blas_threads(blas_threads):
        e0, e1, its, per_it, solves = _lm(state, pixel_sigma, loss or "none", k, max_iterations, timing)
    r = state.residuals(np.inf)
    residuals = _unsorted(np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2), perm)
    return BAResult(state.poses, state.points(), residuals, e0, e1, its, time.perf_counter() - t0,
                    {"timing": {**timing, "setup_s": setup_s}, "iteration_timing": per_it, "solves": solves,
                     "device_ops": _device_ops(lay), **_camera_stats(lay)})


def final_ba_profile(problem: BAProblem, result: BAResult) -> dict:
    """A final pass's size and where its time went, for a run's report: free poses, landmarks, observations, the
    longest track, the camera system's solver ("dense", "dense-device" with its tile's side, "banded" with its
    bandwidth), per stage LM iterations, damped systems solved and seconds
    (linearise, Schur complement, solve, error), and the seconds outside LM."""
    stats = result.stats
    views = np.bincount(np.asarray(problem.obs_point), minlength=len(problem.points))
    return {"free_poses": int(len(problem.poses) - np.count_nonzero(problem.fixed)),
            "landmarks": int(len(problem.points)), "observations": int(len(problem.obs_point)),
            "track_views_mean_max": [float(views.mean()) if len(views) else 0.0, int(views.max(initial=0))],
            "solve_s": result.seconds, "camera_solver": stats.get("camera_solver"),
            "camera_band": stats.get("camera_band"), "camera_tile": stats.get("camera_tile"),
            "stages": [{"loss": st.get("loss"), "iterations": st.get("iterations"), "solves": st.get("solves"),
                        "timing": st.get("timing", {})} for st in stats.get("stages", [])],
            "timing": stats.get("timing", {})}


def _norms(r: np.ndarray) -> np.ndarray:
    """(O,) lengths of residuals (O, 2), +inf where not finite (behind the camera)."""
    norms = r[:, 0] * r[:, 0]  # (the norms in place: three times faster than by powers)
    norms += r[:, 1] * r[:, 1]
    np.sqrt(norms, out=norms)
    norms[~np.isfinite(norms)] = np.inf
    return norms


def _robust_scale(p: BAProblem, state, schedule: RobustSchedule, with_norms: bool = False):
    """``pixel_sigma`` of the state's residuals, their medians found on the kernels' device where it does
    (``ObservationKernels.residual_mad``: one scalar read back), else on the host in the residuals' read-back
    itself (it is the solver's own: a Warp device's host mirror, valid until its next read-back, or the host
    state's new array); and with ``with_norms`` the residuals' lengths (``_norms``, found first), else None."""
    kernels = getattr(state, "kernels", None)
    if kernels is not None and kernels.gpu_reductions:
        count, mad, *r = kernels.residual_mad(with_norms)
        mad = mad if count else None
        norms = _norms(r[0]) if with_norms else None
    else:
        r = state.residuals(np.nan) if kernels is None else kernels.residuals(np.nan, copy=False)
        norms = _norms(r) if with_norms else None  # (before the MAD reorders the components)
        mad = mad_in_place(r)
    sigma = sigma_of_mad(mad) / np.sqrt(redundancy(p))  # (as pixel_sigma)
    return float(min(max(sigma, schedule.sigma_floor_px), schedule.sigma_ceiling_px)), norms


def solve_robust_schur(problem: BAProblem, schedule: RobustSchedule, device: str = "cpu",
                       blas_threads: int = 1, device_schur: bool | None = None,
                       gpu_reductions: bool | None = None, workspace=None, camera_solver: str = "auto",
                       camera_tile: int = DEVICE_TILE) -> BAResult:
    """``bundle_adjustment.solve_robust`` on the reduced camera system: the same stages (the redundancy-corrected
    MAD scale re-estimated before each, GTSAM's Cauchy and Tukey), the same inlier threshold and ``stats`` keys,
    plus ``timing``: seconds spent linearising, forming the Schur complement, solving, evaluating the error, and
    outside LM on the problem's layout (``setup_s``) and the robust scales (``scale_s``); per stage
    ``iteration_timing`` and ``solves`` (the damped systems solved); ``device_ops``: the kernels' launches,
    uploads, downloads and allocations ({} on numpy); ``camera_solver``, ``camera_band``, ``camera_tile``: how the
    camera system was held and solved (on the device, "dense-device", ``schur_s`` is the host's launching of the
    elimination and the factorisation, ``solve_s`` its wait for the step). ``device``, ``blas_threads``,
    ``device_schur``, ``camera_solver`` and ``camera_tile`` as ``solve_schur``'s; ``gpu_reductions``: the kernels'
    sums and the robust scales' medians taken a GPU's ways (``ObservationKernels``: the scales by sorts there, one
    scalar read back instead of the residuals; the same values, the sums to round-off); opt-in (None: off) until
    re-measured live on a GPU: in session 14's live run with it a window's pose-pair table overran into the next
    buffer (fixed in session 15; docs/benchmarks.md).
    ``workspace``: a ``schur_kernels.SchurWorkspace`` whose device buffers (a GPU's page-locked mirrors, the
    recorded launches) the solve uses instead of its own, kept by a caller that solves window after window (the
    BA worker); the same answers. Ignored on numpy."""
    if workspace is None or device == "numpy":
        return _solve_robust_schur(problem, schedule, device, blas_threads, device_schur, gpu_reductions, None,
                                   camera_solver, camera_tile)
    with workspace.claim():
        return _solve_robust_schur(problem, schedule, device, blas_threads, device_schur, gpu_reductions, workspace,
                                   camera_solver, camera_tile)


def _solve_robust_schur(problem: BAProblem, schedule: RobustSchedule, device: str, blas_threads: int,
                        device_schur: bool | None, gpu_reductions: bool | None, workspace,
                        camera_solver: str, camera_tile: int) -> BAResult:
    t0 = time.perf_counter()
    p, perm, lay, setup_s = _setup(problem, device, device_schur, gpu_reductions, workspace, camera_solver,
                                   camera_tile)
    state = _new_state(p, lay)
    stages, iterations = [], 0
    initial_error = final_error = scale_s = 0.0
    timing = _new_timing()
    for n, stage in enumerate(schedule.stages):
        t1 = time.perf_counter()
        sigma = _robust_scale(p, state, schedule)[0]
        scale_s += time.perf_counter() - t1
        stage_timing = _new_timing()
        with _blas_threads(blas_threads):
            e0, e1, its, per_it, solves = _lm(state, sigma, stage.loss, stage.k, stage.iterations, stage_timing)
        for key in timing:
            timing[key] += stage_timing[key]
        final_error = e1
        if n == 0:
            initial_error = e0
        iterations += its
        stages.append({"loss": stage.loss, "sigma_px": sigma, "k": stage.k, "iterations": its,
                       "error_before": e0, "error_after": e1, "timing": stage_timing,
                       "iteration_timing": per_it, "solves": solves})
    t1 = time.perf_counter()
    sigma_final, residuals = _robust_scale(p, state, schedule, with_norms=True)
    scale_s += time.perf_counter() - t1
    threshold = schedule.inlier_threshold_px(sigma_final)
    residuals = _unsorted(residuals, perm)
    return BAResult(state.poses, state.points(), residuals, initial_error, final_error, iterations,
                    time.perf_counter() - t0,
                    {"stages": stages, "sigma_px": sigma_final, "inlier_threshold_px": threshold,
                     "inlier_obs": residuals <= threshold, "timing": {**timing, "setup_s": setup_s, "scale_s": scale_s},
                     "device_ops": _device_ops(lay), **_camera_stats(lay)})
