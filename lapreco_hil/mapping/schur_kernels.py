"""Warp kernels for the Schur-complement bundle adjustment's per-observation work (one thread per observation):
linearisation (residual, Jacobians, robust weight, and their sums into the landmark and pose blocks), the
reprojection error and residuals, the landmark elimination's whitened blocks (for the host's BLAS), or the whole
elimination into the camera system (atomics: a GPU's way), and the back-substitution. On Warp's
CPU device they are compiled C++ (single-threaded), a few times faster than the same passes in numpy; on CUDA
they run on the GPU. Float64 throughout, as GTSAM computes.

``ObservationKernels`` holds a problem's fixed arrays and the solver's state (current and trial) on the device and
launches the kernels; the host (``schur.py``) keeps the LM logic, the dense camera system and its Cholesky
factorisation, except where that is done here too (``camera_tile``: the damped system formed in the storage of
``dense_cholesky``, factorised and solved there, the step alone read back). The sums can reduce a GPU's way
(``gpu_reductions``, opt-in: fewer atomics, a window's elimination by pose pairs, the robust scale by sorts); by default
one observation's terms at a time.
"""

from __future__ import annotations

import contextlib

import numpy as np

from lapreco_hil.warp_device import device_lock, init_warp

wp = init_warp()
wp.set_module_options({"enable_backward": False})

mat36d = wp.types.matrix(shape=(3, 6), dtype=wp.float64)
vec6d = wp.types.vector(length=6, dtype=wp.float64)

LOSS_CODES = {"none": 0, "cauchy": 1, "tukey": 2, "huber": 3}


@wp.func
def _weight(loss: int, e: wp.float64, k: wp.float64) -> wp.float64:
    """GTSAM's m-estimator weights (whitened units), as ``schur.robust_weight``."""
    if loss == 1:
        return k * k / (k * k + e * e)
    if loss == 2:
        if e <= k:
            q = wp.float64(1.0) - (e / k) * (e / k)
            return q * q
        return wp.float64(0.0)
    if loss == 3:
        if e <= k:
            return wp.float64(1.0)
        return k / e
    return wp.float64(1.0)


@wp.func
def _loss(loss: int, e: wp.float64, k: wp.float64) -> wp.float64:
    """GTSAM's m-estimator losses, as ``schur.robust_loss``."""
    if loss == 1:
        return wp.float64(0.5) * k * k * wp.log(wp.float64(1.0) + (e / k) * (e / k))
    if loss == 2:
        if e <= k:
            q = wp.float64(1.0) - (e / k) * (e / k)
            return k * k / wp.float64(6.0) * (wp.float64(1.0) - q * q * q)
        return k * k / wp.float64(6.0)
    if loss == 3:
        if e <= k:
            return wp.float64(0.5) * e * e
        return k * e - wp.float64(0.5) * k * k
    return wp.float64(0.5) * e * e


@wp.func
def _camera_point(T: wp.mat44d, X: wp.vec3d) -> wp.vec3d:
    """R^T (X - t) for the pose T = [R t; 0 1]."""
    d0 = X[0] - T[0, 3]
    d1 = X[1] - T[1, 3]
    d2 = X[2] - T[2, 3]
    return wp.vec3d(T[0, 0] * d0 + T[1, 0] * d1 + T[2, 0] * d2, T[0, 1] * d0 + T[1, 1] * d1 + T[2, 1] * d2,
                    T[0, 2] * d0 + T[1, 2] * d1 + T[2, 2] * d2)


@wp.func
def _observation_terms(o: int, obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
                       uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d), X: wp.array(dtype=wp.vec3d),
                       K: wp.vec4d, inv_sigma: wp.float64, k: wp.float64, loss: int):
    """An observation's residual (ru, rv), its Jacobians' rows by the pose tangent (ju, jv) and by the landmark
    (pu, pv), and its weight s (whitening and robust reweighting, squared)."""
    i = obs_pose[o]
    j = obs_point[o]
    Tm = T[i]
    Xc = _camera_point(Tm, X[j])
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    fx = K[0]
    fy = K[1]
    # behind the camera: GTSAM's constant error 2 fx, no gradient
    ru = wp.float64(2.0) * fx
    rv = wp.float64(2.0) * fx
    ju = wp.spatial_vectord()
    jv = wp.spatial_vectord()
    pu = wp.vec3d()
    pv = wp.vec3d()
    if Xc[2] > zero:
        z = Xc[2]
        xn = Xc[0] / z
        yn = Xc[1] / z
        ru = fx * xn + K[2] - uv[o][0]
        rv = fy * yn + K[3] - uv[o][1]
        a = fx / z
        b = fy / z
        # d residual / d (rotation, translation) of T Exp(xi)
        ju = wp.spatial_vectord(fx * xn * yn, -fx * (one + xn * xn), fx * yn, -a, zero, a * xn)
        jv = wp.spatial_vectord(fy * (one + yn * yn), -fy * xn * yn, -fy * xn, zero, -b, b * yn)
        # d residual / d X = d(pixel)/d(camera point) R^T; the rows of R^T are the columns of R
        c0 = wp.vec3d(Tm[0, 0], Tm[1, 0], Tm[2, 0])
        c1 = wp.vec3d(Tm[0, 1], Tm[1, 1], Tm[2, 1])
        c2 = wp.vec3d(Tm[0, 2], Tm[1, 2], Tm[2, 2])
        pu = a * (c0 - xn * c2)
        pv = b * (c1 - yn * c2)
    r2 = ru * ru + rv * rv
    s = _weight(loss, wp.sqrt(r2) * inv_sigma, k) * inv_sigma * inv_sigma
    return s, ru, rv, ju, jv, pu, pv


@wp.func
def _landmark_terms(j: int, s: wp.float64, ru: wp.float64, rv: wp.float64, pu: wp.vec3d, pv: wp.vec3d,
                    W: wp.array(dtype=mat36d), Hpp: wp.array(dtype=wp.mat33d), gp: wp.array(dtype=wp.vec3d)):
    wp.atomic_add(Hpp, j, s * (wp.outer(pu, pu) + wp.outer(pv, pv)))
    wp.atomic_add(gp, j, s * (pu * ru + pv * rv))


@wp.func
def _landmark_pose_block(s: wp.float64, ju: wp.spatial_vectord, jv: wp.spatial_vectord, pu: wp.vec3d,
                         pv: wp.vec3d) -> mat36d:
    """s Jp^T Jc: the observation's landmark-pose block."""
    Wo = mat36d()
    for a_ in range(3):
        for b_ in range(6):
            Wo[a_, b_] = s * (pu[a_] * ju[b_] + pv[a_] * jv[b_])
    return Wo


@wp.func
def _add_pose_terms(pose_system: wp.array(dtype=wp.float64), n_free: int, c: int, H: wp.spatial_matrixd,
                    g: wp.spatial_vectord):
    """A free pose's block and gradient terms summed into ``pose_system`` (``_linearize``)."""
    for a_ in range(6):
        for b_ in range(6):
            wp.atomic_add(pose_system, 36 * c + 6 * a_ + b_, H[a_, b_])
        wp.atomic_add(pose_system, 36 * n_free + 6 * c + a_, g[a_])


@wp.kernel
def _linearize(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
               obs_col: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d),
               X: wp.array(dtype=wp.vec3d), K: wp.vec4d, inv_sigma: wp.float64, k: wp.float64, loss: int,
               n_free: int, W: wp.array(dtype=mat36d), Hpp: wp.array(dtype=wp.mat33d),
               gp: wp.array(dtype=wp.vec3d), pose_system: wp.array(dtype=wp.float64)):
    """Each observation's terms summed into its landmark's block (Hpp, gp) and its free pose's, in
    ``pose_system``: the pose blocks (F x 36), then the pose gradients (F x 6), then the sum of s |r|^2. (The
    default: one observation per thread; ``_linearize_runs``: the opt-in GPU reductions'.)"""
    o = wp.tid()
    j = obs_point[o]
    s, ru, rv, ju, jv, pu, pv = _observation_terms(o, obs_pose, obs_point, uv, T, X, K, inv_sigma, k, loss)
    r2 = ru * ru + rv * rv
    wp.atomic_add(pose_system, 42 * n_free, s * r2)
    wp.atomic_add(Hpp, j, s * (wp.outer(pu, pu) + wp.outer(pv, pv)))
    wp.atomic_add(gp, j, s * (pu * ru + pv * rv))
    c = obs_col[o]
    Wo = mat36d()
    if c >= 0:
        for a_ in range(3):
            for b_ in range(6):
                Wo[a_, b_] = s * (pu[a_] * ju[b_] + pv[a_] * jv[b_])
        Hc = s * (wp.outer(ju, ju) + wp.outer(jv, jv))
        g = s * (ju * ru + jv * rv)
        for a_ in range(6):
            for b_ in range(6):
                wp.atomic_add(pose_system, 36 * c + 6 * a_ + b_, Hc[a_, b_])
            wp.atomic_add(pose_system, 36 * n_free + 6 * c + a_, g[a_])
    W[o] = Wo


@wp.kernel
def _linearize_runs(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
                    obs_col: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d),
                    X: wp.array(dtype=wp.vec3d), K: wp.vec4d, inv_sigma: wp.float64, k: wp.float64, loss: int,
                    n_free: int, per_thread: int, n_obs: int, W: wp.array(dtype=mat36d),
                    Hpp: wp.array(dtype=wp.mat33d), gp: wp.array(dtype=wp.vec3d),
                    pose_system: wp.array(dtype=wp.float64)):
    """``_linearize`` a GPU's way: a thread takes ``per_thread`` consecutive observations (pose-major: mostly
    one pose's) and sums their pose terms before adding them in (the sum of s |r|^2 took an atomic per
    observation on one address)."""
    first = wp.tid() * per_thread
    H_sum = wp.spatial_matrixd()
    g_sum = wp.spatial_vectord()
    sr2_sum = wp.float64(0.0)
    c_sum = int(-1)
    for o in range(first, wp.min(first + per_thread, n_obs)):
        s, ru, rv, ju, jv, pu, pv = _observation_terms(o, obs_pose, obs_point, uv, T, X, K, inv_sigma, k, loss)
        sr2_sum += s * (ru * ru + rv * rv)
        _landmark_terms(obs_point[o], s, ru, rv, pu, pv, W, Hpp, gp)
        c = obs_col[o]
        Wo = mat36d()
        if c >= 0:
            Wo = _landmark_pose_block(s, ju, jv, pu, pv)
            if c != c_sum:
                if c_sum >= 0:
                    _add_pose_terms(pose_system, n_free, c_sum, H_sum, g_sum)
                H_sum = wp.spatial_matrixd()
                g_sum = wp.spatial_vectord()
                c_sum = c
            H_sum += s * (wp.outer(ju, ju) + wp.outer(jv, jv))
            g_sum += s * (ju * ru + jv * rv)
        W[o] = Wo
    if c_sum >= 0:
        _add_pose_terms(pose_system, n_free, c_sum, H_sum, g_sum)
    if first < n_obs:
        wp.atomic_add(pose_system, 42 * n_free, sr2_sum)


@wp.func
def _observation_loss(o: int, obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
                      uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d), X: wp.array(dtype=wp.vec3d),
                      K: wp.vec4d, inv_sigma: wp.float64, k: wp.float64, loss: int) -> wp.float64:
    Xc = _camera_point(T[obs_pose[o]], X[obs_point[o]])
    ru = wp.float64(2.0) * K[0]
    rv = wp.float64(2.0) * K[0]
    if Xc[2] > wp.float64(0.0):
        ru = K[0] * Xc[0] / Xc[2] + K[2] - uv[o][0]
        rv = K[1] * Xc[1] / Xc[2] + K[3] - uv[o][1]
    return _loss(loss, wp.sqrt(ru * ru + rv * rv) * inv_sigma, k)


@wp.kernel
def _error(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2d),
           T: wp.array(dtype=wp.mat44d), X: wp.array(dtype=wp.vec3d), K: wp.vec4d, inv_sigma: wp.float64,
           k: wp.float64, loss: int, slot: int, total: wp.array(dtype=wp.float64)):
    """The sum of the reprojection losses, into ``total[slot]``."""
    o = wp.tid()
    wp.atomic_add(total, slot, _observation_loss(o, obs_pose, obs_point, uv, T, X, K, inv_sigma, k, loss))


@wp.kernel
def _error_runs(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
                uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d), X: wp.array(dtype=wp.vec3d),
                K: wp.vec4d, inv_sigma: wp.float64, k: wp.float64, loss: int, slot: int, per_thread: int,
                n_obs: int, total: wp.array(dtype=wp.float64)):
    """``_error`` a GPU's way: a thread sums ``per_thread`` consecutive observations' losses before adding
    them in."""
    first = wp.tid() * per_thread
    loss_sum = wp.float64(0.0)
    for o in range(first, wp.min(first + per_thread, n_obs)):
        loss_sum += _observation_loss(o, obs_pose, obs_point, uv, T, X, K, inv_sigma, k, loss)
    if first < n_obs:
        wp.atomic_add(total, slot, loss_sum)


@wp.kernel
def _residuals(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
               uv: wp.array(dtype=wp.vec2d), T: wp.array(dtype=wp.mat44d), X: wp.array(dtype=wp.vec3d),
               K: wp.vec4d, behind: wp.float64, r: wp.array(dtype=wp.vec2d)):
    """Each observation's reprojection residual, ``behind`` in both where the point is behind the camera."""
    o = wp.tid()
    Xc = _camera_point(T[obs_pose[o]], X[obs_point[o]])
    if Xc[2] > wp.float64(0.0):
        r[o] = wp.vec2d(K[0] * Xc[0] / Xc[2] + K[2] - uv[o][0], K[1] * Xc[1] / Xc[2] + K[3] - uv[o][1])
    else:
        r[o] = wp.vec2d(behind, behind)


@wp.kernel
def _scale_keys(r: wp.array(dtype=wp.vec2d), keys: wp.array(dtype=wp.float64)):
    """The residual components as sort keys, +inf where not finite (behind the camera: NaN): the robust scale
    ignores those, as ``robust.mad_sigma`` does."""
    o = wp.tid()
    for c in range(2):
        v = r[o][c]
        if wp.isfinite(v):
            keys[2 * o + c] = v
        else:
            keys[2 * o + c] = wp.float64(wp.inf)


@wp.func
def _sorted_median(keys: wp.array(dtype=wp.float64), n: int) -> wp.float64:
    """The median of sorted ``keys[:n]``, as ``robust._median_in_place`` gives it (the middle value or the mean
    of the two)."""
    if n % 2 == 1:
        return keys[n // 2]
    return (keys[n // 2 - 1] + keys[n // 2]) / wp.float64(2.0)


@wp.kernel
def _median_of_sorted(keys: wp.array(dtype=wp.float64), n_keys: int, count_them: int,
                      sums: wp.array(dtype=wp.float64)):
    """``sums[1]``: the median of the finite ones of sorted ``keys[:n_keys]`` (unchanged where there are none),
    ``sums[0]`` their count, found here (the first +inf, by bisection) with ``count_them``."""
    n = int(0)
    if count_them != 0:
        hi = n_keys
        while n < hi:
            mid = (n + hi) // 2
            if keys[mid] < wp.float64(wp.inf):
                n = mid + 1
            else:
                hi = mid
        sums[0] = wp.float64(n)
    else:
        n = int(sums[0])
    if n > 0:
        sums[1] = _sorted_median(keys, n)


@wp.kernel
def _median_deviations(sums: wp.array(dtype=wp.float64), keys: wp.array(dtype=wp.float64)):
    """In place, |component - median| of the finite components sorted in ``keys`` (+inf for the others), as
    ``robust.mad_sigma`` subtracts it (``sums``: ``_median_of_sorted``'s count and median)."""
    i = wp.tid()
    if i < int(sums[0]):
        keys[i] = wp.abs(keys[i] - sums[1])
    else:
        keys[i] = wp.float64(wp.inf)


@wp.kernel
def _whitened_batch(obs: wp.array(dtype=wp.int32), base: wp.array(dtype=wp.int64), width: wp.array(dtype=wp.int64),
                    obs_point: wp.array(dtype=wp.int32), W: wp.array(dtype=mat36d), L: wp.array(dtype=vec6d),
                    Z: wp.array(dtype=wp.float64)):
    """Z = L^-1 W of each observation of a run of chunks (L: its landmark's Cholesky factor), written where its
    block goes in its chunk's dense (landmarks x 3, 6 x poses) matrix, the chunks' matrices laid one after the other
    in Z: each observation's place (``base``) and its chunk's row length (``width``)."""
    n = wp.tid()
    z = _whiten(L[obs_point[obs[n]]], W[obs[n]])
    w = width[n]
    for b in range(6):
        col = base[n] + wp.int64(b)
        Z[col] = z[0, b]
        Z[col + w] = z[1, b]
        Z[col + w + w] = z[2, b]


@wp.kernel
def _w_times_step(obs_point: wp.array(dtype=wp.int32), obs_col: wp.array(dtype=wp.int32),
                  W: wp.array(dtype=mat36d), dc: wp.array(dtype=vec6d), out: wp.array(dtype=wp.vec3d)):
    """Sum of W_o dc over each landmark's observations (the back-substitution's right-hand side)."""
    o = wp.tid()
    c = obs_col[o]
    if c >= 0:
        wp.atomic_add(out, obs_point[o], W[o] @ dc[c])


@wp.func
def _whiten(l: vec6d, Wo: mat36d) -> mat36d:
    """L^-1 W for a landmark's Cholesky factor l (l11 l21 l22 l31 l32 l33)."""
    z = mat36d()
    for b in range(6):
        z0 = Wo[0, b] / l[0]
        z1 = (Wo[1, b] - l[1] * z0) / l[2]
        z[0, b] = z0
        z[1, b] = z1
        z[2, b] = (Wo[2, b] - l[3] * z0 - l[4] * z1) / l[5]
    return z


@wp.func
def _add_block(M: wp.array(dtype=wp.float64), n6: int, row: int, col: int, za: mat36d, zb: mat36d,
               both: bool):
    """M[6 row.., 6 col..] += za^T zb (and its transpose too when ``both``: the two views of a point by one pose)."""
    for a in range(6):
        for b in range(6):
            v = za[0, a] * zb[0, b] + za[1, a] * zb[1, b] + za[2, a] * zb[2, b]
            if both:
                v += zb[0, a] * za[0, b] + zb[1, a] * za[1, b] + zb[2, a] * za[2, b]
            wp.atomic_add(M, (6 * row + a) * n6 + 6 * col + b, v)


@wp.kernel
def _landmark_factors(Hpp: wp.array(dtype=wp.mat33d), gp: wp.array(dtype=wp.vec3d), lam: wp.float64,
                      L: wp.array(dtype=vec6d), Lg: wp.array(dtype=wp.vec3d), failed: wp.array(dtype=wp.float64)):
    """Each landmark's damped block's Cholesky factor (as ``schur._cholesky3``) and L^-1 gp; ``failed`` counts
    the blocks that are not positive definite (a pivot <= 0 or NaN, LAPACK's test)."""
    j = wp.tid()
    V = Hpp[j]
    zero = wp.float64(0.0)
    d1 = V[0, 0] + lam
    if not (d1 > zero):
        wp.atomic_add(failed, 0, wp.float64(1.0))
        return
    l11 = wp.sqrt(d1)
    l21 = V[1, 0] / l11
    l31 = V[2, 0] / l11
    d2 = V[1, 1] + lam - l21 * l21
    if not (d2 > zero):
        wp.atomic_add(failed, 0, wp.float64(1.0))
        return
    l22 = wp.sqrt(d2)
    l32 = (V[2, 1] - l31 * l21) / l22
    d3 = V[2, 2] + lam - l31 * l31 - l32 * l32
    if not (d3 > zero):
        wp.atomic_add(failed, 0, wp.float64(1.0))
        return
    l33 = wp.sqrt(d3)
    L[j] = vec6d(l11, l21, l22, l31, l32, l33)
    g = gp[j]
    y0 = g[0] / l11
    y1 = (g[1] - l21 * y0) / l22
    Lg[j] = wp.vec3d(y0, y1, (g[2] - l31 * y0 - l32 * y1) / l33)


@wp.func
def _add_band_block(M: wp.array(dtype=wp.float64), band: int, row: int, col: int, za: mat36d, zb: mat36d,
                    both: bool):
    """``_add_block`` into the camera system held as a band array (``schur._Layout.band``): entry (i, j), i >= j,
    at j (band + 1) + i - j; the entries above the diagonal (a diagonal block's upper half) are left out."""
    for a in range(6):
        for b in range(6):
            i = 6 * row + a
            j = 6 * col + b
            if i >= j:
                v = za[0, a] * zb[0, b] + za[1, a] * zb[1, b] + za[2, a] * zb[2, b]
                if both:
                    v += zb[0, a] * za[0, b] + zb[1, a] * za[1, b] + zb[2, a] * za[2, b]
                wp.atomic_add(M, j * (band + 1) + i - j, v)


def _make_schur_blocks(add_block, doc: str):
    """The kernel that sums the landmarks' eliminated blocks into the camera system through ``add_block``
    (``_add_block``: a dense array, its stride 6 x free poses; ``_add_band_block``: a band array, its bandwidth),
    one thread per observation by a free pose (``pm_obs``: grouped by landmark; ``pm_end``: the end of its
    landmark's group): with z = L^-1 W, M += z_a^T z_b for this observation a and each later one b of its
    landmark, in M's lower block triangle (diagonal blocks whole), and r += z_a^T L^-1 gp."""

    @wp.kernel(module="unique", enable_backward=False)
    def schur_blocks(pm_obs: wp.array(dtype=wp.int32), pm_end: wp.array(dtype=wp.int32),
                     obs_point: wp.array(dtype=wp.int32), obs_col: wp.array(dtype=wp.int32),
                     W: wp.array(dtype=mat36d), L: wp.array(dtype=vec6d), Lg: wp.array(dtype=wp.vec3d), stride: int,
                     M: wp.array(dtype=wp.float64), r: wp.array(dtype=wp.float64)):
        n = wp.tid()
        o = pm_obs[n]
        j = obs_point[o]
        l = L[j]
        za = _whiten(l, W[o])
        ca = obs_col[o]
        lg = Lg[j]
        for b in range(6):
            wp.atomic_add(r, 6 * ca + b, za[0, b] * lg[0] + za[1, b] * lg[1] + za[2, b] * lg[2])
        add_block(M, stride, ca, ca, za, za, False)
        for m in range(n + 1, pm_end[n]):
            ob = pm_obs[m]
            zb = _whiten(l, W[ob])
            cb = obs_col[ob]
            if ca > cb:
                add_block(M, stride, ca, cb, za, zb, False)
            elif ca < cb:
                add_block(M, stride, cb, ca, zb, za, False)
            else:
                add_block(M, stride, ca, ca, za, zb, True)

    schur_blocks.__doc__ = doc
    return schur_blocks


_schur_blocks = _make_schur_blocks(_add_block, "The camera system's sums into a dense array (stride 6 x free poses).")
_schur_blocks_band = _make_schur_blocks(_add_band_block, "The same sums in the same order per entry into a band "
                                        "array (``schur._Layout.band``; stride: the bandwidth).")


@wp.kernel
def _window_table(obs_point: wp.array(dtype=wp.int32), obs_col: wp.array(dtype=wp.int32), n_free: int,
                  table: wp.array(dtype=wp.int32)):
    """``table[landmark x F + free pose]``: the observation of a landmark by a free pose (-1 where none: filled
    before), for ``_schur_window``."""
    o = wp.tid()
    c = obs_col[o]
    if c >= 0:
        table[obs_point[o] * n_free + c] = o


@wp.kernel
def _whiten_observations(obs_point: wp.array(dtype=wp.int32), obs_col: wp.array(dtype=wp.int32),
                         W: wp.array(dtype=mat36d), L: wp.array(dtype=vec6d), Z: wp.array(dtype=wp.vec3d)):
    """Z = L^-1 W of each observation by a free pose (L: its landmark's Cholesky factor), for ``_schur_window``:
    its six columns, ``Z[6 o + b]`` (a thread there reads the one it needs)."""
    o = wp.tid()
    if obs_col[o] >= 0:
        z = _whiten(L[obs_point[o]], W[o])
        for b in range(6):
            Z[6 * o + b] = wp.vec3d(z[0, b], z[1, b], z[2, b])


@wp.kernel
def _schur_window(table: wp.array(dtype=wp.int32), Z: wp.array(dtype=wp.vec3d), Lg: wp.array(dtype=wp.vec3d),
                  n_free: int, n_points: int, per_thread: int, M: wp.array(dtype=wp.float64),
                  r: wp.array(dtype=wp.float64)):
    """``_schur_blocks``' sums the way a window's few poses allow (each landmark seen once by a pose:
    ``_window_table``; Z: ``_whiten_observations``' columns): a thread per pose pair (ca >= cb, the lower block
    triangle's), block row a and run of ``per_thread`` landmarks sums row a of z_a^T z_b over the landmarks that
    both poses see, and for a diagonal pair z_a^T L^-1 gp, before adding them in: a few atomics per thread, not
    per landmark."""
    t = wp.tid()
    a = t % 6
    rest = t // 6
    n_pairs = n_free * (n_free + 1) // 2
    q = rest % n_pairs
    first = (rest // n_pairs) * per_thread
    # the pair of the lower triangle's q-th entry, row by row: ca (ca + 1) / 2 <= q < (ca + 1) (ca + 2) / 2
    ca = int(wp.floor((wp.sqrt(wp.float64(8 * q + 1)) - wp.float64(1.0)) / wp.float64(2.0)))
    while ca * (ca + 1) // 2 > q:
        ca = ca - 1
    while (ca + 1) * (ca + 2) // 2 <= q:
        ca = ca + 1
    cb = q - ca * (ca + 1) // 2
    m_sum = vec6d()
    r_sum = wp.float64(0.0)
    for j in range(first, wp.min(first + per_thread, n_points)):
        oa = table[j * n_free + ca]
        ob = table[j * n_free + cb]
        if oa >= 0 and ob >= 0:
            za = Z[6 * oa + a]
            b0 = 6 * ob
            m_sum += vec6d(wp.dot(za, Z[b0]), wp.dot(za, Z[b0 + 1]), wp.dot(za, Z[b0 + 2]), wp.dot(za, Z[b0 + 3]),
                           wp.dot(za, Z[b0 + 4]), wp.dot(za, Z[b0 + 5]))
            if ca == cb:
                r_sum += wp.dot(za, Lg[j])
    n6 = 6 * n_free
    for b in range(6):
        wp.atomic_add(M, (6 * ca + a) * n6 + 6 * cb + b, m_sum[b])
    if ca == cb:
        wp.atomic_add(r, 6 * ca + a, r_sum)


@wp.func
def _solve_move(l: vec6d, x: wp.vec3d):
    """A landmark's move dp = -V^-1 x, V = L L^T (x: gp + the sum of W dc over its observations)."""
    y0 = x[0] / l[0]
    y1 = (x[1] - l[1] * y0) / l[2]
    y2 = (x[2] - l[3] * y0 - l[4] * y1) / l[5]
    u2 = y2 / l[5]
    u1 = (y1 - l[4] * u2) / l[2]
    u0 = (y0 - l[1] * u1 - l[3] * u2) / l[0]
    return -wp.vec3d(u0, u1, u2)


@wp.kernel
def _move_points(solve: int, L: wp.array(dtype=vec6d), gp: wp.array(dtype=wp.vec3d), Wdc: wp.array(dtype=wp.vec3d),
                 X: wp.array(dtype=wp.vec3d), per_thread: int, n_points: int, dp: wp.array(dtype=wp.vec3d),
                 X_trial: wp.array(dtype=wp.vec3d), sums: wp.array(dtype=wp.float64)):
    """The trial landmarks X + dp, and d.gp and d.d summed into ``sums`` (LM's model decrease needs both), a
    thread's ``per_thread`` landmarks' before adding them in (as ``_linearize``). With ``solve`` the moves are
    solved here first, by ``schur_complement``'s factors (``_solve_move``: the back-substitution), else they are
    the host's, in ``dp``."""
    first = wp.tid() * per_thread
    gd = wp.float64(0.0)
    dd = wp.float64(0.0)
    for j in range(first, wp.min(first + per_thread, n_points)):
        d = dp[j]
        if solve != 0:
            d = _solve_move(L[j], gp[j] + Wdc[j])
            dp[j] = d
        X_trial[j] = X[j] + d
        if j == first:
            gd = wp.dot(d, gp[j])
            dd = wp.dot(d, d)
        else:
            gd += wp.dot(d, gp[j])
            dd += wp.dot(d, d)
    if first < n_points:
        wp.atomic_add(sums, 0, gd)
        wp.atomic_add(sums, 1, dd)


@wp.kernel
def _move_points_gathered(pm_obs: wp.array(dtype=wp.int32), pm_starts: wp.array(dtype=wp.int32),
                          obs_col: wp.array(dtype=wp.int32), W: wp.array(dtype=mat36d), dc: wp.array(dtype=vec6d),
                          L: wp.array(dtype=vec6d), gp: wp.array(dtype=wp.vec3d), X: wp.array(dtype=wp.vec3d),
                          dp: wp.array(dtype=wp.vec3d), X_trial: wp.array(dtype=wp.vec3d),
                          sums: wp.array(dtype=wp.float64)):
    """``_move_points``' solve, a thread per landmark, the sum of W dc over its observations by free poses
    gathered here (``pm_obs``: grouped by landmark, ``pm_starts``: each one's range of them) instead of summed into
    a buffer by ``_w_times_step``'s atomics first: a launch fewer per step, the same sums in the same order."""
    j = wp.tid()
    x = wp.vec3d()
    for n in range(pm_starts[j], pm_starts[j + 1]):
        o = pm_obs[n]
        x += W[o] @ dc[obs_col[o]]
    d = _solve_move(L[j], gp[j] + x)
    dp[j] = d
    X_trial[j] = X[j] + d
    wp.atomic_add(sums, 0, wp.dot(d, gp[j]))
    wp.atomic_add(sums, 1, wp.dot(d, d))


@wp.kernel
def _negated_camera_system(S: wp.array2d(dtype=wp.float64), n6: int, r: wp.array(dtype=wp.float64),
                           inputs: wp.array(dtype=wp.float64)):
    """The damped camera system's start in the dense Cholesky's storage (``dense_cholesky``), a thread per entry
    of its padded rows and its right-hand side's row: -M in the lower triangle (the landmarks' eliminated sum,
    made there), the identity on the padding, the right-hand side r - gc (``inputs``: lambda, gc, ...)."""
    t = wp.tid()
    padded = S.shape[1]
    i = t // padded
    j = t - i * padded
    if i < n6:
        if j <= i:
            S[i, j] = -S[i, j]
    elif i < padded:
        if i == j:
            S[i, j] = wp.float64(1.0)
    elif j < n6:
        S[i, j] = r[j] - inputs[1 + j]


@wp.kernel
def _add_pose_blocks(S: wp.array2d(dtype=wp.float64), n6: int, rows: wp.array(dtype=wp.int32),
                     cols: wp.array(dtype=wp.int32), inputs: wp.array(dtype=wp.float64)):
    """(H + lambda I) + (-M) on the pose system's lower blocks that can be non-zero (``rows``, ``cols``: each
    once), a thread per entry, their lower triangle: H's blocks follow lambda and gc in ``inputs``. The host's sum
    (``schur._damped_minus``), in its order: the same values."""
    t = wp.tid()
    b = t // 36
    e = t - 36 * b
    a = e // 6
    i = 6 * rows[b] + a
    j = 6 * cols[b] + e - 6 * a
    if i >= j:
        h = inputs[1 + n6 + t]
        if i == j:
            h = h + inputs[0]
        S[i, j] = h + S[i, j]


# with a GPU's reductions, a thread of ``_linearize`` and ``_error`` sums this many consecutive observations, and
# one of ``_schur_window`` this many landmarks' blocks of one pose pair, before their atomics
GPU_OBS_PER_THREAD = 16
GPU_POINTS_PER_THREAD = 16
# a problem of at most this many free poses, each landmark seen once by a pose, has its landmarks eliminated by
# ``_schur_window`` there (a thread per pose pair, block row and run of landmarks: its work grows as poses^2)
WINDOW_POSES = 32

# the parts of an arena start on multiples of 32 words (256 bytes of float64: CUDA's allocation alignment)
_ALIGN_WORDS = 32


class _Mirror:
    """A device array's host side, allocated once: on a CUDA device a host array (one ``wp.copy`` each way,
    nothing allocated per transfer), or ``host``, a part of a workspace's page-locked mirror of the arena the array
    is part of (``pinned``: an upload from it runs after the call returns); on the CPU device the array's own
    memory (nothing copied)."""

    def __init__(self, array, host=None) -> None:
        self.array, self.pinned = array, host is not None
        if host is None:
            host = array if array.device.is_cpu else wp.empty(array.shape, dtype=array.dtype, device="cpu")
        self.host = host
        self.view = self.host.numpy()  # zero-copy


class SchurWorkspace:
    """The Schur solver's device buffers kept from one solve to the next by their owner (the BA worker: one per
    process, its windows solved one after another), so that a window allocates nothing: per Warp device, the
    arena of the solver's arrays, the problem's index arrays and, on a GPU, their page-locked host mirrors (faster
    transfers, which pageable memory could not be: a page-locked allocation costs more than a window's solve),
    and the kernels' recorded launches (``launches``).
    Each buffer is sized by capacity: it grows to the largest window's need (a quarter more, so that windows
    growing a little at a time do not reallocate each time) and never shrinks; each solve cuts its parts from it
    by its own counts (``ObservationKernels``). One solve at a time: two would share the buffers (``claim``)."""

    GROWTH = 1.25

    def __init__(self) -> None:
        self._buffers: dict = {}  # (device, role) -> wp.array
        self._launches: dict = {}  # device -> {kernel key: (recorded launch, its arguments, its size)}
        self._claimed = False

    @contextlib.contextmanager
    def claim(self):
        """Held by a solve while it uses the buffers."""
        if self._claimed:
            raise RuntimeError("a SchurWorkspace serves one solve at a time: give each thread its own")
        self._claimed = True
        try:
            yield self
        finally:
            self._claimed = False

    def buffer(self, device: str, role: str, n: int, dtype, pinned: bool = False):
        """A 1-D buffer of at least ``n`` elements of ``dtype`` (``pinned``: page-locked host memory mirroring
        ``device``'s) and whether it was allocated now. Its contents are the last solve's."""
        key = (str(device), role)
        buf = self._buffers.get(key)
        if buf is not None and buf.shape[0] >= n:
            return buf, False
        capacity = max(int(n), 1) if buf is None else max(int(n), int(self.GROWTH * buf.shape[0]))
        self._buffers[key] = None  # (the old one freed first)
        buf = (wp.empty(capacity, dtype=dtype, device="cpu", pinned=True) if pinned
               else wp.empty(capacity, dtype=dtype, device=device))
        self._buffers[key] = buf
        return buf, True

    def launches(self, device: str) -> dict:
        """The launches recorded on ``device`` (``ObservationKernels._launch``), kept for the next solve: a
        replay's parameters are set again where they differ (every array of a new solve), its size where that
        does, so that a window records none but at the first."""
        return self._launches.setdefault(str(device), {})

    def capacity(self, device: str, role: str) -> int:
        """A buffer's elements (0: none yet)."""
        buf = self._buffers.get((str(device), role))
        return 0 if buf is None else int(buf.shape[0])


class ObservationKernels:
    """A pose-major problem's observations and the solver's state on a Warp device, and the launches over them
    (each under the device's lock, which threads driving one device take turns through:
    ``warp_device.device_lock``).

    The state (the poses, as (P,) 4x4 matrices, and the landmarks) stays here across LM iterations: a trial state
    is written beside the current one (the trial poses uploaded, the landmarks moved here) and ``accept`` makes it
    current. Every buffer is allocated once per solve; the host reads back one buffer per step it needs (the
    pose system, the eliminated camera system, the trial's sums) into a host array allocated once; the work that
    one waits for is started by a ``launch_*`` and read by a ``read_*`` (or with ``error``), so that the host works
    in between. ``ops`` counts launches (memsets and sorts included), uploads, downloads (and their bytes) and
    allocations: on the CPU device a download is a read of the array's memory, on CUDA a copy and a wait."""

    def __init__(self, p, obs_col: np.ndarray, n_free: int, device: str, schur_on_device: bool = False,
                 gpu_reductions: bool | None = None, unique_pairs: bool = False,
                 workspace: SchurWorkspace | None = None, band: int | None = None,
                 camera_tile: int | None = None, camera_blocks: tuple | None = None) -> None:
        """``workspace``: the buffers to cut the arrays from (kept across solves by their owner); None: allocated
        for this solve. ``band``: the camera system's lower bandwidth where the landmarks eliminated here go into
        a band array (6F, band + 1) (``schur._Layout.band``); None: a dense (6F, 6F) one. ``camera_tile``: the
        dense camera system factorised and solved here too, by ``dense_cholesky`` in tiles of this side
        (``launch_camera_solve``; the landmarks eliminated here), its pose system's lower blocks that can be
        non-zero ``camera_blocks`` (rows, columns: each block once); None: read back for the host."""
        self.band = band
        if camera_tile is not None and (band is not None or not schur_on_device):
            raise ValueError("the camera system is solved on the device only dense, its landmarks eliminated there")
        self.camera_tile = camera_tile
        self.device = device
        self._cuda = wp.get_device(device) if wp.get_device(device).is_cuda else None
        self._workspace = workspace
        # with a workspace on a GPU: its page-locked mirror of the arena, and the host address ranges uploaded
        # from it since the last wait (``_host_write``)
        self._arena = self._arena_host = None
        self._pending: list[tuple[int, int]] = []
        self._host = {}  # host mirrors, made at first use
        if workspace is not None and self._cuda is not None:
            # (a solve that failed may have left copies from the workspace's page-locked buffers in the stream)
            wp.synchronize_stream(self._cuda.stream)
        # a GPU's ways of reducing (opt-in until re-measured live: docs/benchmarks.md, sessions 14-15): the robust
        # scale's medians by two sorts here (one scalar read back, not the residuals and the host's selections),
        # sums taken per thread over several observations before their atomics (a few addresses take them all), a
        # window's landmarks eliminated by pose pairs (``_schur_window``). The CPU device adds one observation's
        # terms at a time, in order: the sums of the numpy path's order of old, not the GPU's (which differ by
        # round-off, as its atomics' order does anyway)
        self.gpu_reductions = bool(gpu_reductions)
        self.per_thread = GPU_OBS_PER_THREAD if self.gpu_reductions else 1
        self.ops = {"launches": 0, "uploads": 0, "downloads": 0, "allocations": 0, "uploaded_bytes": 0,
                    "downloaded_bytes": 0}
        self.n_obs, self.n_points, self.n_free = len(p.obs_pose), len(p.points), n_free
        self.K = wp.vec4d(float(p.K[0, 0]), float(p.K[1, 1]), float(p.K[0, 2]), float(p.K[1, 2]))
        N, O = self.n_points, self.n_obs
        self.schur_on_device = bool(schur_on_device)
        self._arenas = []  # the allocations that the arrays below are parts of
        # the problem's index arrays, one upload; with the elimination here, the observations by free poses
        # grouped by landmark, each with the end of its landmark's group
        indices = {"obs_pose": p.obs_pose, "obs_point": p.obs_point, "obs_col": obs_col}
        # the landmarks eliminated here by pose pairs (``_schur_window``) or by observations (``_schur_blocks``)
        self.window = (self.schur_on_device and self.gpu_reductions and bool(unique_pairs)
                       and 0 < n_free <= WINDOW_POSES and band is None and camera_tile is None)
        if self.schur_on_device and not self.window:
            obs_point = np.asarray(p.obs_point)
            by_free = np.asarray(obs_col) >= 0
            pm = None if by_free.all() else np.flatnonzero(by_free)  # (None: every observation)
            points = obs_point if pm is None else obs_point[pm]
            # (a stable sort of small integers is numpy's radix sort)
            order = np.argsort(points.astype(np.int16 if N < 2**15 else np.int64), kind="stable")
            pm, points = (order if pm is None else pm[order]), points[order]
            starts = np.zeros(N + 1, np.int64)
            np.cumsum(np.bincount(points, minlength=N), out=starts[1:])
            indices["pm_obs"] = pm
            indices["pm_end"] = starts[1:][points]
            indices["pm_starts"] = starts
            self.n_pm = len(pm)
        if camera_tile is not None:
            indices["block_rows"], indices["block_cols"] = camera_blocks
            self.n_blocks = len(camera_blocks[0])
        for name, view in self._upload_arena(indices).items():
            setattr(self, name, view)
        # every other buffer: parts of one allocation. ``work``: what a linearisation sums into (``linear``, one
        # memset): Hpp (N x 9), gp (N x 3), the pose system (42 F + 1); then, where the landmarks are eliminated
        # here, the camera system (``eliminated``), read back with the pose system in one copy (``system``).
        # T0, X0 and T1, X1: the current and the trial state (``cur`` indexes the current one). ``step_sums``: a
        # step's sum of W dc per landmark and its sums (d.gp, d.d, the trial's reprojection error).
        n6, n_system = 6 * n_free, 42 * n_free + 1
        n_table = N * n_free if self.window else 0
        n_camera = n6 * n6 if band is None else n6 * (band + 1)  # (the camera system: dense or a band array)
        n_eliminated = n_camera + n6 + 1 if self.schur_on_device else 0
        if camera_tile is not None:
            # r and the flag first (read back with the pose system), then the dense Cholesky's storage: M made in
            # its padded rows, factorised there, the solution in its last tile row (``dense_cholesky``)
            from lapreco_hil.mapping import dense_cholesky

            self.cholesky = dense_cholesky.DeviceCholesky(n6, device, camera_tile)
            self.storage_shape = dense_cholesky.storage_shape(n6, camera_tile)
            start = 12 * N + n_system
            storage_at = -(-(start + n6 + 1) // _ALIGN_WORDS) * _ALIGN_WORDS - start
            n_eliminated = storage_at + self.storage_shape[0] * self.storage_shape[1]
        # (T0, dc, T1 in that order: a step's tangents and its trial poses, into either state's, are one range)
        parts = {"W": (O, mat36d), "work": (12 * N + n_system + n_eliminated, wp.float64),
                 "T0": (len(p.poses), wp.mat44d), "dc": (max(n_free, 1), vec6d), "T1": (len(p.poses), wp.mat44d),
                 "X0": (N, wp.vec3d), "X1": (N, wp.vec3d), "dp": (N, wp.vec3d), "step_sums": (3 * N + 3, wp.float64),
                 "L": (N, vec6d), "Lg": (N, wp.vec3d), "residual": (O, wp.vec2d), "uv": (O, wp.vec2d)}
        if self.window:
            parts.update({"table": (n_table, wp.int32), "Z": (6 * O, wp.vec3d)})
        if camera_tile is not None:
            # lambda, gc and the pose system's blocks (``launch_camera_solve``: one upload), the pivots that failed
            parts.update({"camera_inputs": (1 + n6 + 36 * self.n_blocks, wp.float64), "camera_info": (1, wp.int32)})
        if self.gpu_reductions:
            # the residual components, then their deviations, sorted (a radix sort's keys and values take twice
            # their count); the count of finite ones and the median
            parts.update({"scale_keys": (4 * O, wp.float64), "scale_values": (4 * O, wp.int32),
                          "scale_sums": (2, wp.float64)})
        arena = self._alloc_arena(parts)
        if self.gpu_reductions:
            self.scale_keys, self.scale_values, self.scale_sums = (
                arena[k] for k in ("scale_keys", "scale_values", "scale_sums"))
        self.W, self.dp, self.dc, self.L, self.Lg, self.residual, self.uv = (
            arena[k] for k in ("W", "dp", "dc", "L", "Lg", "residual", "uv"))
        self._upload(self.uv, np.asarray(p.obs_uv, np.float64))
        self.T, self.X, self.cur = [arena["T0"], arena["T1"]], [arena["X0"], arena["X1"]], 0
        # T0 to T1's end as float64: a step's upload (``_upload_parts``)
        self._step_inputs = self._view(arena["T0"], 0, (arena["T1"].ptr - arena["T0"].ptr) // 8 + 16 * len(p.poses),
                                       wp.float64)
        self.work = work = arena["work"]
        self.step_sums = arena["step_sums"]
        self.linear = self._view(work, 0, 12 * N + n_system, wp.float64)
        self.Hpp = self._view(work, 0, N, wp.mat33d)
        self.gp = self._view(work, 9 * N, N, wp.vec3d)
        self.pose_system = self._view(work, 12 * N, n_system, wp.float64)
        self.Wdc = self._view(self.step_sums, 0, N, wp.vec3d)
        self.sums = self._view(self.step_sums, 3 * N, 3, wp.float64)
        if camera_tile is not None:
            # r (6F), the count of landmark blocks not positive definite, then the storage (M in its padded rows)
            start = 12 * N + n_system
            self.eliminated = self._view(work, start, n_eliminated, wp.float64)
            self.r = self._view(work, start, n6, wp.float64)
            self.failed = self._view(work, start + n6, 1, wp.float64)
            self.system = self._view(work, 12 * N, n_system + n6 + 1, wp.float64)
            rows, padded = self.storage_shape
            self.storage = wp.array(ptr=work.ptr + 8 * (start + storage_at), shape=(rows, padded), dtype=wp.float64,
                                    device=work.device)
            self.M = self._view(work, start + storage_at, padded * padded, wp.float64)
            self.camera_solution = self.cholesky.solution(self.storage)
            self.camera_inputs, self.camera_info = arena["camera_inputs"], arena["camera_info"]
        elif self.schur_on_device:
            # M (6F x 6F, or its band array), r (6F), the count of landmark blocks not positive definite
            start = 12 * N + n_system
            self.eliminated = self._view(work, start, n_eliminated, wp.float64)
            self.M = self._view(work, start, n_camera, wp.float64)
            self.r = self._view(work, start + n_camera, n6, wp.float64)
            self.failed = self._view(work, start + n_camera + n6, 1, wp.float64)
            self.system = self._view(work, 12 * N, n_system + n_eliminated, wp.float64)
        # recorded launches (``_launch``), a workspace's kept from solve to solve
        self._commands = {} if workspace is None else workspace.launches(device)
        if self.window:
            self.table, self.Z = arena["table"], arena["Z"]
            self.table.fill_(-1)
            self.ops["launches"] += 1
            self._launch(_window_table, O, [self.obs_point, self.obs_col, n_free], [self.table])
        self._eliminated_at = None  # (lambda, the camera system) eliminated with the last linearisation
        # the linearisation started: its damping (None: no elimination with it), whether the landmark blocks are
        # read back, the array to read back (None: read already) and its read-back where ``error`` brought it
        self._linearized_at, self._landmarks_read = None, False
        self._linearization = self._linearization_view = None
        self._chunks: dict[int, tuple] = {}

    # --- buffers and transfers -------------------------------------------------------------------------------
    def _alloc(self, n: int, dtype):
        self.ops["allocations"] += 1
        return wp.empty(max(int(n), 1), dtype=dtype, device=self.device)

    def _upload_new(self, values: np.ndarray, dtype):
        self.ops["allocations"] += 1
        self.ops["uploads"] += 1
        self.ops["uploaded_bytes"] += values.nbytes
        return wp.array(values if len(values) else np.zeros((1,) + values.shape[1:], values.dtype), dtype=dtype,
                        device=self.device)

    @staticmethod
    def _offsets(sizes: dict) -> tuple[dict, int]:
        """Each part's offset in an arena of ``sizes`` (in words), every part starting on a multiple of
        _ALIGN_WORDS; and the arena's size."""
        offsets, end = {}, 0
        for name, size in sizes.items():
            offsets[name] = end
            end += -(-max(size, 1) // _ALIGN_WORDS) * _ALIGN_WORDS
        return offsets, end

    def _alloc_arena(self, parts: dict) -> dict:
        """One float64 allocation cut into arrays: {name: (length, dtype)} -> {name: array}."""
        # (each part's words rounded up: an odd count of int32 rounded down left its last element inside the next
        # part, where that part's writes overwrote it)
        sizes = {k: -(-max(n, 1) * wp.types.type_size_in_bytes(dtype) // 8) for k, (n, dtype) in parts.items()}
        offsets, total = self._offsets(sizes)
        if self._workspace is None:
            arena = self._alloc(total, wp.float64)
        else:  # (one arena per solve: its parts and its mirror's are cut from the workspace's by this solve's counts)
            arena = self._workspace_buffer("arena", total, wp.float64)
            self._arena = arena
            if self._host_arena_mirror():
                self._arena_host = self._workspace_buffer("arena_host", total, wp.float64,
                                                          pinned=self._cuda is not None)
        self._arenas.append(arena)  # (its parts are views: they do not keep it)
        return {k: self._view(arena, offsets[k], n, dtype) for k, (n, dtype) in parts.items()}

    def _workspace_buffer(self, role: str, n: int, dtype, pinned: bool = False):
        buf, allocated = self._workspace.buffer(self.device, role, n, dtype, pinned)
        self.ops["allocations"] += int(allocated)
        return buf

    def _host_arena_mirror(self) -> bool:
        """Whether the arena's parts are mirrored on the host by the parts of one workspace buffer (page-locked):
        with a workspace on a GPU. (A test makes it so on the CPU device too: the transfers' offsets.)"""
        return self._workspace is not None and self._cuda is not None

    def _upload_arena(self, values: dict) -> dict:
        """Integer arrays uploaded as int32 in one copy (each converted as it is written): {name: values} ->
        {name: array}."""
        offsets, total = self._offsets({k: len(v) for k, v in values.items()})
        if self._workspace is None:
            host = np.zeros(total, np.int32)
            for k, v in values.items():
                host[offsets[k]:offsets[k] + len(v)] = v
            arena = self._upload_new(host, wp.int32)
        else:
            # (the gaps between the parts are left as they are: nothing reads them)
            arena = self._workspace_buffer("indices", total, wp.int32)
            staging = arena if self._cuda is None else self._workspace_buffer("indices_host", total, wp.int32,
                                                                              pinned=True)
            host = staging.numpy()
            for k, v in values.items():
                host[offsets[k]:offsets[k] + len(v)] = v
            if staging is not arena:
                with device_lock(self.device):
                    wp.copy(arena, staging, count=total)
                self._pending.append((staging.ptr, staging.ptr + 4 * total))
            self.ops["uploads"] += 1
            self.ops["uploaded_bytes"] += 4 * total
        self._arenas.append(arena)
        return {k: wp.array(ptr=arena.ptr + 4 * offsets[k], shape=(max(len(v), 1),), dtype=wp.int32,
                            device=arena.device) for k, v in values.items()}

    @staticmethod
    def _view(base, offset: int, n: int, dtype):
        """Elements [offset, offset + n x dtype's length) of a float64 ``base`` as an array of ``dtype``."""
        return wp.array(ptr=base.ptr + 8 * offset, shape=(max(int(n), 1),), dtype=dtype, device=base.device)

    def _mirror(self, array) -> _Mirror:
        key = (array.ptr, array.dtype, array.shape)
        if key not in self._host:
            arena = self._arena
            if self._arena_host is not None and arena.ptr <= array.ptr < arena.ptr + 8 * arena.shape[0]:
                # (the part of the workspace's page-locked mirror at the array's offset in the arena)
                host = wp.array(ptr=self._arena_host.ptr + (array.ptr - arena.ptr), shape=array.shape,
                                dtype=array.dtype, device="cpu")
                self._host[key] = _Mirror(array, host)
            else:
                if not array.device.is_cpu:
                    self.ops["allocations"] += 1
                self._host[key] = _Mirror(array)
        return self._host[key]

    def _host_write(self, m: _Mirror, start: int, stop: int) -> None:
        """Before the host writes bytes [start, stop) of mirror ``m`` for an upload: an upload from page-locked
        memory is read by the copy when the stream reaches it, so where one of those bytes is still to be read
        (uploaded since the last wait), wait for the stream first."""
        if not m.pinned:
            return
        lo, hi = m.host.ptr + start, m.host.ptr + stop
        if any(a < hi and lo < b for a, b in self._pending):
            self._wait_for_uploads()
        self._pending.append((lo, hi))

    def _wait_for_uploads(self) -> None:
        if self._pending and self._cuda is not None:
            wp.synchronize_stream(self._cuda.stream)
        self._pending.clear()

    def _upload(self, array, values: np.ndarray) -> None:
        """``values`` into the device array (their shape: its numpy view's, or a leading part of it)."""
        m = self._mirror(array)
        self._host_write(m, 0, m.view[:len(values)].nbytes)
        m.view[:len(values)] = values
        if m.host is not array:
            with device_lock(self.device):
                wp.copy(array, m.host, count=len(values))
        self.ops["uploads"] += 1
        self.ops["uploaded_bytes"] += m.view[:len(values)].nbytes

    def _upload_parts(self, region, parts) -> None:
        """[(array, values)] of arrays that are parts of float64 ``region`` uploaded in one copy of the range they
        span (``values``: float64, each part's leading elements; the padding between parts goes along)."""
        m = self._mirror(region)
        lo = hi = None
        flats = []
        for array, values in parts:
            start = (array.ptr - region.ptr) // 8
            flat = np.asarray(values, np.float64).reshape(-1)
            flats.append((start, flat))
            lo = start if lo is None else min(lo, start)
            hi = start + flat.size if hi is None else max(hi, start + flat.size)
        self._host_write(m, 8 * lo, 8 * hi)
        for start, flat in flats:
            m.view[start:start + flat.size] = flat
        if m.host is not region:
            with device_lock(self.device):
                wp.copy(region, m.host, dest_offset=lo, src_offset=lo, count=hi - lo)
        self.ops["uploads"] += 1
        self.ops["uploaded_bytes"] += 8 * (hi - lo)

    def _download(self, *arrays) -> list[np.ndarray]:
        """The arrays' host mirrors' views, after one wait for the copies (valid until the next download)."""
        views = []
        with device_lock(self.device):
            for array in arrays:
                m = self._mirror(array)
                if m.host is not array:
                    wp.copy(m.host, array)
                self.ops["downloads"] += 1
                self.ops["downloaded_bytes"] += m.view.nbytes
                views.append(m.view)
            if self._cuda is not None:  # (the stream the copies went on: the device's current one)
                wp.synchronize_stream(self._cuda.stream)
            self._pending.clear()
        return views

    def _launch(self, kernel, dim: int, inputs, outputs) -> None:
        """Launch by a command recorded at the kernel's first launch (``wp.launch(record_cmd=True)``), only the
        parameters that differ from its last launch's set again (the current and the trial state's arrays swap,
        the scalars change per stage, a new solve's arrays are all new), and its size where that differs: a replay
        costs a fifth of a launch's argument packing."""
        if dim <= 0:
            return
        args = [*inputs, *outputs]
        recorded = self._commands.get(kernel.key)
        if recorded is None:
            command = wp.launch(kernel, dim=dim, device=self.device, inputs=inputs, outputs=outputs,
                                record_cmd=True)
        else:
            command, last, last_dim = recorded
            if dim != last_dim:
                command.set_dim(dim)
            for i, (a, b) in enumerate(zip(args, last)):
                if a is not b and (isinstance(a, wp.array) or isinstance(b, wp.array) or a != b):
                    command.set_param_at_index(i, a)
        self._commands[kernel.key] = (command, args, dim)
        command.launch()
        self.ops["launches"] += 1

    def _zero(self, array) -> None:
        array.zero_()
        self.ops["launches"] += 1

    # --- the state -----------------------------------------------------------------------------------------------
    def set_state(self, poses: np.ndarray, points: np.ndarray) -> None:
        """Upload a state as the current one."""
        self._upload(self.T[self.cur], np.ascontiguousarray(poses, np.float64))
        self._upload(self.X[self.cur], np.ascontiguousarray(points, np.float64))

    def points(self) -> np.ndarray:
        """(N, 3) the current landmarks (a copy)."""
        return self._download(self.X[self.cur])[0][:self.n_points].copy()

    def accept(self) -> None:
        """The last trial state (``try_step``, ``back_substitute``) becomes the current one."""
        self.cur = 1 - self.cur

    # --- the launches --------------------------------------------------------------------------------------------
    def linearize(self, sigma: float, loss: str, k: float, landmarks: bool, lam: float | None = None):
        """``launch_linearize`` and ``read_linearize`` at once."""
        self.launch_linearize(sigma, loss, k, lam, landmarks)
        return self.read_linearize()

    def launch_linearize(self, sigma: float, loss: str, k: float, lam: float | None = None,
                         landmarks: bool = False) -> None:
        """Start a linearisation at the current state, read back by ``read_linearize`` (the host works on its pose
        factors meanwhile), or with the next ``error``. With ``lam`` (the elimination on the device) the landmarks
        are eliminated at that damping too, read back with the pose system in one copy, for
        ``schur_complement(lam)``; with ``landmarks`` their blocks are read back too (the host eliminates them)."""
        with device_lock(self.device):
            self._zero(self.linear if lam is None else self.work)  # (``work``: ``linear`` and ``eliminated``)
            inputs = [self.obs_pose, self.obs_point, self.obs_col, self.uv, self.T[self.cur], self.X[self.cur], self.K,
                      1.0 / sigma, float(k), LOSS_CODES[loss], self.n_free]
            outputs = [self.W, self.Hpp, self.gp, self.pose_system]
            if self.per_thread > 1:
                self._launch(_linearize_runs, -(-self.n_obs // self.per_thread),
                             inputs + [self.per_thread, self.n_obs], outputs)
            else:
                self._launch(_linearize, self.n_obs, inputs, outputs)
            if lam is not None:
                self._eliminate(lam, zeroed=True)
        self._linearized_at, self._landmarks_read = lam, landmarks
        self._linearization = self.system if lam is not None else self.linear if landmarks else self.pose_system
        self._linearization_view = None

    def read_linearize(self):
        """The linearisation ``launch_linearize`` started: (pose blocks (F, 6, 6), pose gradients (F, 6), sum of
        s |r|^2, and with its ``landmarks`` Hpp (N, 3, 3) and gp (N, 3), else None, None: they stay here).
        Copies."""
        lam, landmarks, flat = self._linearized_at, self._landmarks_read, self._linearization_view
        if flat is None:
            with device_lock(self.device):
                flat = self._download(self._linearization)[0]
        self._linearization = self._linearization_view = None
        F, N = self.n_free, self.n_points
        system = flat[12 * N:] if landmarks else flat
        blocks = system[:36 * F].reshape(F, 6, 6).copy()
        grads = system[36 * F:42 * F].reshape(F, 6).copy()
        weighted_sq = float(system[42 * F])
        Hpp = flat[:9 * N].reshape(N, 3, 3).copy() if landmarks else None
        gp = flat[9 * N:12 * N].reshape(N, 3).copy() if landmarks else None
        # (the camera system solved here stays here: only that it was eliminated, and at which damping)
        self._eliminated_at = (None if lam is None else (lam, None) if self.camera_tile is not None
                               else (lam, self._camera_system(system[42 * F + 1:])))
        return blocks, grads, weighted_sq, Hpp, gp

    def W_host(self) -> np.ndarray:
        """(O, 3, 6): the last linearisation's s Jp^T Jc per observation."""
        return self._download(self.W)[0].copy()

    def residuals(self, behind: float, copy: bool = True) -> np.ndarray:
        """(O, 2) reprojection residuals at the current state, ``behind`` where the point is behind the camera
        (without ``copy``: the read-back's view, valid until the next download)."""
        with device_lock(self.device):
            self._launch(_residuals, self.n_obs,
                         [self.obs_pose, self.obs_point, self.uv, self.T[self.cur], self.X[self.cur], self.K,
                          float(behind)], [self.residual])
            r = self._download(self.residual)[0][:self.n_obs]
            return r.copy() if copy else r

    def residual_mad(self, with_residuals: bool = False):
        """The median absolute deviation about the median of the current state's finite residual components
        (``robust.mad_sigma``'s, before its factor), by two sorts here (``gpu_reductions``): (their count, the
        MAD), and with ``with_residuals`` the (O, 2) residuals too (NaN behind the camera; a copy), in one
        read-back."""
        O = self.n_obs
        with device_lock(self.device):
            self._launch(_residuals, O,
                         [self.obs_pose, self.obs_point, self.uv, self.T[self.cur], self.X[self.cur], self.K,
                          float("nan")], [self.residual])
            self._launch_mad()
            views = self._download(*([self.scale_sums, self.residual] if with_residuals else [self.scale_sums]))
        count, mad = int(views[0][0]), float(views[0][1])
        return (count, mad, views[1][:O].copy()) if with_residuals else (count, mad)

    def _launch_mad(self) -> None:
        """``scale_sums``: the count of the finite components in ``residual`` and their MAD about their median."""
        O, keys, values, sums = self.n_obs, self.scale_keys, self.scale_values, self.scale_sums
        self._zero(sums)
        self._launch(_scale_keys, O, [self.residual], [keys])
        self._sort(keys, values, 2 * O)
        self._launch(_median_of_sorted, 1, [keys, 2 * O, 1], [sums])  # their count and median
        self._launch(_median_deviations, 2 * O, [sums], [keys])
        self._sort(keys, values, 2 * O)
        self._launch(_median_of_sorted, 1, [keys, 2 * O, 0], [sums])  # their deviations' median

    def _sort(self, keys, values, n: int) -> None:
        """``keys[:n]`` sorted in place (a radix sort: ``keys`` and ``values`` hold 2 n)."""
        with wp.ScopedDevice(self.device):  # (the sort runs in the current device's context and stream)
            wp.utils.radix_sort_pairs(keys, values, n)
        self.ops["launches"] += 1

    def _error_launch(self, state: int, sigma: float, loss: str, k: float, slot: int) -> None:
        inputs = [self.obs_pose, self.obs_point, self.uv, self.T[state], self.X[state], self.K, 1.0 / sigma,
                  float(k), LOSS_CODES[loss], slot]
        if self.per_thread > 1:
            self._launch(_error_runs, -(-self.n_obs // self.per_thread), inputs + [self.per_thread, self.n_obs],
                         [self.sums])
        else:
            self._launch(_error, self.n_obs, inputs, [self.sums])

    def error(self, sigma: float, loss: str, k: float) -> float:
        """The sum of the reprojection losses at the current state; a linearisation started and not read back
        yet (``launch_linearize``) comes back with it, in one wait."""
        with device_lock(self.device):
            self._zero(self.sums)
            self._error_launch(self.cur, sigma, loss, k, 2)
            if self._linearization is not None and self._linearization_view is None:
                sums, self._linearization_view = self._download(self.sums, self._linearization)
            else:
                sums = self._download(self.sums)[0]
            return float(sums[2])

    def set_landmark_factors(self, L: np.ndarray) -> None:
        """Every landmark's damped Cholesky factor (N, 6: l11 l21 l22 l31 l32 l33), for ``whitened_batch``."""
        self._upload(self.L, np.ascontiguousarray(L, np.float64))

    def whitened_batch(self, key, chunks, offsets, dense: bool) -> np.ndarray:
        """Consecutive chunks' dense L^-1 W blocks in one launch, laid one after the other from ``offsets``
        (flat; chunk i's is ``Z[offsets[i]:offsets[i + 1]].reshape(3 x landmarks, 6 x poses)``); ``key`` names
        the batch (its index arrays stay on the device). Valid until the next download."""
        d = self.device
        if key not in self._chunks:
            self._chunks[key] = (
                self._upload_new(np.concatenate([np.asarray(c.obs, np.int32) for c in chunks]), wp.int32),
                self._upload_new(np.concatenate([c.dest[0, 0] + o for c, o in zip(chunks, offsets)]).astype(np.int64),
                                 wp.int64),
                self._upload_new(np.concatenate([np.full(len(c.obs), 6 * c.n_cols, np.int64) for c in chunks]),
                                 wp.int64),
                self._alloc(int(offsets[-1]), wp.float64))
        obs, base, width, Z = self._chunks[key]
        with device_lock(d):
            if not dense:
                self._zero(Z)
            self._launch(_whitened_batch, obs.shape[0], [obs, base, width, self.obs_point, self.W, self.L], [Z])
            return self._download(Z)[0]

    def w_times_step(self, dc: np.ndarray) -> np.ndarray:
        """(N, 3): the sum of W_o dc over each landmark's observations (a copy)."""
        self._upload(self.dc, np.ascontiguousarray(dc, np.float64).reshape(-1, 6))
        with device_lock(self.device):
            self._zero(self.Wdc)
            self._launch(_w_times_step, self.n_obs, [self.obs_point, self.obs_col, self.W, self.dc], [self.Wdc])
            return self._download(self.Wdc)[0][:self.n_points].copy()

    def _eliminate(self, lam: float, zeroed: bool = False) -> None:
        if not zeroed:
            self._zero(self.eliminated)
        self._launch(_landmark_factors, self.n_points, [self.Hpp, self.gp, float(lam)], [self.L, self.Lg, self.failed])
        if self.window:
            n_runs = -(-self.n_points // GPU_POINTS_PER_THREAD)
            self._launch(_whiten_observations, self.n_obs, [self.obs_point, self.obs_col, self.W, self.L], [self.Z])
            self._launch(_schur_window, 6 * (self.n_free * (self.n_free + 1) // 2) * n_runs,
                         [self.table, self.Z, self.Lg, self.n_free, self.n_points, GPU_POINTS_PER_THREAD],
                         [self.M, self.r])
        elif self.band is not None:
            self._launch(_schur_blocks_band, self.n_pm,
                         [self.pm_obs, self.pm_end, self.obs_point, self.obs_col, self.W, self.L, self.Lg,
                          self.band], [self.M, self.r])
        else:  # (a dense array's rows: the camera system's, or the dense Cholesky's padded ones)
            stride = 6 * self.n_free if self.camera_tile is None else self.storage_shape[1]
            self._launch(_schur_blocks, self.n_pm,
                         [self.pm_obs, self.pm_end, self.obs_point, self.obs_col, self.W, self.L, self.Lg,
                          stride], [self.M, self.r])

    def _camera_system(self, flat: np.ndarray):
        """(M, r) copied from a read-back ``eliminated`` (M dense (6F, 6F) or a band array (6F, band + 1)); None
        where a landmark block failed."""
        n6 = 6 * self.n_free
        width = n6 if self.band is None else self.band + 1
        if flat[n6 * width + n6]:
            return None
        return flat[:n6 * width].reshape(n6, width).copy(), flat[n6 * width:n6 * width + n6].copy()

    def schur_complement(self, lam: float):
        """The landmarks eliminated at damping ``lam``, on the device: (M (6F, 6F): the sum of W^T V^-1 W in its
        lower block triangle, r (6F,): the sum of W^T V^-1 gp), or None where a landmark's damped block is not
        positive definite. One read-back (M, r and the flag), none where the last linearisation eliminated them
        at this damping (``linearize``). Copies."""
        if self._eliminated_at is not None and self._eliminated_at[0] == lam:
            eliminated, self._eliminated_at = self._eliminated_at[1], None
            return eliminated
        with device_lock(self.device):
            self._eliminate(lam)
            return self._camera_system(self._download(self.eliminated)[0])

    def launch_camera_solve(self, lam: float, blocks: np.ndarray, gc: np.ndarray) -> None:
        """Start the damped camera system's solution here (``camera_tile``): the landmarks eliminated at damping
        ``lam`` (unless the last linearisation did, at this damping), the system (H + lambda I) - M formed from
        the pose system's lower blocks ``blocks`` (``camera_blocks``' (k, 6, 6)) and the right-hand side r - gc,
        factorised and solved by the dense Cholesky (``read_camera_solve``). One upload (lambda, gc, the blocks)."""
        self._upload(self.camera_inputs, np.concatenate([[lam], gc, np.asarray(blocks, np.float64).reshape(-1)]))
        n6 = 6 * self.n_free
        with device_lock(self.device):
            if self._eliminated_at is None or self._eliminated_at[0] != lam:
                self._eliminate(lam)
            self._eliminated_at = None  # (the factorisation overwrites it)
            padded = self.storage_shape[1]
            self._launch(_negated_camera_system, (padded + 1) * padded, [self.storage, n6, self.r, self.camera_inputs],
                         [])
            self._launch(_add_pose_blocks, 36 * self.n_blocks,
                         [self.storage, n6, self.block_rows, self.block_cols, self.camera_inputs], [])
            self.cholesky.launch(self.storage, self.camera_info)
            self.ops["launches"] += self.cholesky.launches + 1  # (info's memset too)

    def read_camera_solve(self) -> np.ndarray | None:
        """The step (6F,) that ``launch_camera_solve`` started (a copy), or None where the damped system is not
        positive definite: a landmark's block or a pivot of the camera system's factorisation (<= 0 or NaN, as
        LAPACK's potrf fails), or a step that is not finite. One wait: the step and two flags read back."""
        with device_lock(self.device):
            x, info, failed = self._download(self.camera_solution, self.camera_info, self.failed)
        if failed[0] or info[0]:
            return None
        x = x[:6 * self.n_free].copy()
        return x if np.all(np.isfinite(x)) else None

    def read_step(self):
        """(d.gp, d.d, the trial's reprojection error) of the step ``launch_back_substitute`` or
        ``launch_try_step`` started: one read-back."""
        with device_lock(self.device):
            sums = self._download(self.sums)[0]
        return float(sums[0]), float(sums[1]), float(sums[2])

    def back_substitute(self, dc: np.ndarray, trial_poses: np.ndarray, sigma: float, loss: str, k: float):
        """``launch_back_substitute`` and ``read_step`` at once."""
        self.launch_back_substitute(dc, trial_poses, sigma, loss, k)
        return self.read_step()

    def launch_back_substitute(self, dc: np.ndarray, trial_poses: np.ndarray, sigma: float, loss: str,
                               k: float) -> None:
        """Start the landmarks' moves -V^-1 (gp + sum of W dc) by ``schur_complement``'s factors, applied here to
        make the trial state with ``trial_poses``, and the trial's reprojection error (``read_step``)."""
        # (the upload first, the tangents and the trial poses in one copy: one from pageable memory waits for the
        # stream)
        self._upload_parts(self._step_inputs, [(self.dc, dc if len(dc) else np.zeros(6)),
                                               (self.T[1 - self.cur], trial_poses)])
        with device_lock(self.device):
            if not self.window:  # (each landmark's observations grouped: ``_schur_blocks``')
                self._zero(self.sums)
                self._launch(_move_points_gathered, self.n_points,
                             [self.pm_obs, self.pm_starts, self.obs_col, self.W, self.dc, self.L, self.gp,
                              self.X[self.cur]], [self.dp, self.X[1 - self.cur], self.sums])
            else:
                self._zero(self.step_sums)
                self._launch(_w_times_step, self.n_obs, [self.obs_point, self.obs_col, self.W, self.dc], [self.Wdc])
                self._launch(_move_points, -(-self.n_points // self.per_thread),
                             [1, self.L, self.gp, self.Wdc, self.X[self.cur], self.per_thread, self.n_points],
                             [self.dp, self.X[1 - self.cur], self.sums])
            self._error_launch(1 - self.cur, sigma, loss, k, 2)

    def try_step(self, dp: np.ndarray, trial_poses: np.ndarray, sigma: float, loss: str, k: float):
        """``launch_try_step`` and ``read_step`` at once."""
        self.launch_try_step(dp, trial_poses, sigma, loss, k)
        return self.read_step()

    def launch_try_step(self, dp: np.ndarray, trial_poses: np.ndarray, sigma: float, loss: str, k: float) -> None:
        """Start the trial state of landmark moves ``dp`` (N, 3) solved on the host and ``trial_poses``, and its
        reprojection error (``read_step``)."""
        self._upload(self.dp, np.ascontiguousarray(dp, np.float64))
        self._upload(self.T[1 - self.cur], np.ascontiguousarray(trial_poses, np.float64))
        with device_lock(self.device):
            self._zero(self.sums)
            self._launch(_move_points, -(-self.n_points // self.per_thread),
                         [0, self.L, self.gp, self.Wdc, self.X[self.cur], self.per_thread, self.n_points],
                         [self.dp, self.X[1 - self.cur], self.sums])
            self._error_launch(1 - self.cur, sigma, loss, k, 2)
