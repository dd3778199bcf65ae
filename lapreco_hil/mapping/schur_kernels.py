"""Warp kernels for the Schur-complement bundle adjustment's per-observation work (one thread per observation):
linearisation (residual, Jacobians, robust weight, and their sums into the landmark and pose blocks), the
reprojection error and residuals, the landmark elimination's whitened blocks (for the host's BLAS), or the whole
elimination into the camera system (atomics: a GPU's way), and the back-substitution. On Warp's
CPU device they are compiled C++ (single-threaded), a few times faster than the same passes in numpy; on CUDA
they run on the GPU. Float64 throughout, as GTSAM computes.

``ObservationKernels`` holds a problem's fixed arrays on the device and launches the kernels; the host
(``schur.py``) keeps the LM logic, the dense camera system and its Cholesky factorisation.
"""

from __future__ import annotations

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
def _camera_point(R: wp.mat33d, t: wp.vec3d, X: wp.vec3d) -> wp.vec3d:
    return wp.transpose(R) @ (X - t)


@wp.kernel
def _linearize(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
               obs_col: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2d), R: wp.array(dtype=wp.mat33d),
               t: wp.array(dtype=wp.vec3d), X: wp.array(dtype=wp.vec3d), K: wp.vec4d, inv_sigma: wp.float64,
               k: wp.float64, loss: int, W: wp.array(dtype=mat36d), Hpp: wp.array(dtype=wp.mat33d),
               gp: wp.array(dtype=wp.vec3d), Hcc: wp.array(dtype=wp.spatial_matrixd),
               gc: wp.array(dtype=wp.spatial_vectord), weighted_sq: wp.array(dtype=wp.float64)):
    o = wp.tid()
    i = obs_pose[o]
    j = obs_point[o]
    Rm = R[i]
    Xc = _camera_point(Rm, t[i], X[j])
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
        c0 = wp.vec3d(Rm[0, 0], Rm[1, 0], Rm[2, 0])
        c1 = wp.vec3d(Rm[0, 1], Rm[1, 1], Rm[2, 1])
        c2 = wp.vec3d(Rm[0, 2], Rm[1, 2], Rm[2, 2])
        pu = a * (c0 - xn * c2)
        pv = b * (c1 - yn * c2)
    r2 = ru * ru + rv * rv
    s = _weight(loss, wp.sqrt(r2) * inv_sigma, k) * inv_sigma * inv_sigma
    wp.atomic_add(weighted_sq, 0, s * r2)
    wp.atomic_add(Hpp, j, s * (wp.outer(pu, pu) + wp.outer(pv, pv)))
    wp.atomic_add(gp, j, s * (pu * ru + pv * rv))
    c = obs_col[o]
    Wo = mat36d()
    if c >= 0:
        for a_ in range(3):
            for b_ in range(6):
                Wo[a_, b_] = s * (pu[a_] * ju[b_] + pv[a_] * jv[b_])
        wp.atomic_add(Hcc, c, s * (wp.outer(ju, ju) + wp.outer(jv, jv)))
        wp.atomic_add(gc, c, s * (ju * ru + jv * rv))
    W[o] = Wo


@wp.kernel
def _error(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2d),
           R: wp.array(dtype=wp.mat33d), t: wp.array(dtype=wp.vec3d), X: wp.array(dtype=wp.vec3d), K: wp.vec4d,
           inv_sigma: wp.float64, k: wp.float64, loss: int, total: wp.array(dtype=wp.float64)):
    o = wp.tid()
    Xc = _camera_point(R[obs_pose[o]], t[obs_pose[o]], X[obs_point[o]])
    ru = wp.float64(2.0) * K[0]
    rv = wp.float64(2.0) * K[0]
    if Xc[2] > wp.float64(0.0):
        ru = K[0] * Xc[0] / Xc[2] + K[2] - uv[o][0]
        rv = K[1] * Xc[1] / Xc[2] + K[3] - uv[o][1]
    wp.atomic_add(total, 0, _loss(loss, wp.sqrt(ru * ru + rv * rv) * inv_sigma, k))


@wp.kernel
def _residuals(obs_pose: wp.array(dtype=wp.int32), obs_point: wp.array(dtype=wp.int32),
               uv: wp.array(dtype=wp.vec2d), R: wp.array(dtype=wp.mat33d), t: wp.array(dtype=wp.vec3d),
               X: wp.array(dtype=wp.vec3d), K: wp.vec4d, behind: wp.float64, r: wp.array(dtype=wp.vec2d)):
    """Each observation's reprojection residual, ``behind`` in both where the point is behind the camera."""
    o = wp.tid()
    Xc = _camera_point(R[obs_pose[o]], t[obs_pose[o]], X[obs_point[o]])
    if Xc[2] > wp.float64(0.0):
        r[o] = wp.vec2d(K[0] * Xc[0] / Xc[2] + K[2] - uv[o][0], K[1] * Xc[1] / Xc[2] + K[3] - uv[o][1])
    else:
        r[o] = wp.vec2d(behind, behind)


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
                      L: wp.array(dtype=vec6d), Lg: wp.array(dtype=wp.vec3d), failed: wp.array(dtype=wp.int32)):
    """Each landmark's damped block's Cholesky factor (as ``schur._cholesky3``) and L^-1 gp; ``failed`` counts
    the blocks that are not positive definite (a pivot <= 0 or NaN, LAPACK's test)."""
    j = wp.tid()
    V = Hpp[j]
    zero = wp.float64(0.0)
    d1 = V[0, 0] + lam
    if not (d1 > zero):
        wp.atomic_add(failed, 0, 1)
        return
    l11 = wp.sqrt(d1)
    l21 = V[1, 0] / l11
    l31 = V[2, 0] / l11
    d2 = V[1, 1] + lam - l21 * l21
    if not (d2 > zero):
        wp.atomic_add(failed, 0, 1)
        return
    l22 = wp.sqrt(d2)
    l32 = (V[2, 1] - l31 * l21) / l22
    d3 = V[2, 2] + lam - l31 * l31 - l32 * l32
    if not (d3 > zero):
        wp.atomic_add(failed, 0, 1)
        return
    l33 = wp.sqrt(d3)
    L[j] = vec6d(l11, l21, l22, l31, l32, l33)
    g = gp[j]
    y0 = g[0] / l11
    y1 = (g[1] - l21 * y0) / l22
    Lg[j] = wp.vec3d(y0, y1, (g[2] - l31 * y0 - l32 * y1) / l33)


@wp.kernel
def _schur_blocks(pm_obs: wp.array(dtype=wp.int32), pm_end: wp.array(dtype=wp.int32),
                  obs_point: wp.array(dtype=wp.int32), obs_col: wp.array(dtype=wp.int32),
                  W: wp.array(dtype=mat36d), L: wp.array(dtype=vec6d), Lg: wp.array(dtype=wp.vec3d), n6: int,
                  M: wp.array(dtype=wp.float64), r: wp.array(dtype=wp.float64)):
    """The landmarks' eliminated blocks summed into the camera system, one thread per observation by a free
    pose (``pm_obs``: grouped by landmark; ``pm_end``: the end of its landmark's group): with z = L^-1 W,
    M += z_a^T z_b for this observation a and each later one b of its landmark, in M's lower block triangle
    (diagonal blocks whole), and r += z_a^T L^-1 gp."""
    n = wp.tid()
    o = pm_obs[n]
    j = obs_point[o]
    l = L[j]
    za = _whiten(l, W[o])
    ca = obs_col[o]
    lg = Lg[j]
    for b in range(6):
        wp.atomic_add(r, 6 * ca + b, za[0, b] * lg[0] + za[1, b] * lg[1] + za[2, b] * lg[2])
    _add_block(M, n6, ca, ca, za, za, False)
    for m in range(n + 1, pm_end[n]):
        ob = pm_obs[m]
        zb = _whiten(l, W[ob])
        cb = obs_col[ob]
        if ca > cb:
            _add_block(M, n6, ca, cb, za, zb, False)
        elif ca < cb:
            _add_block(M, n6, cb, ca, zb, za, False)
        else:
            _add_block(M, n6, ca, ca, za, zb, True)


@wp.kernel
def _back_substitute(L: wp.array(dtype=vec6d), gp: wp.array(dtype=wp.vec3d), Wdc: wp.array(dtype=wp.vec3d),
                     dp: wp.array(dtype=wp.vec3d)):
    """Each landmark's move: dp = -V^-1 (gp + sum of W dc), V = L L^T."""
    j = wp.tid()
    l = L[j]
    x = gp[j] + Wdc[j]
    y0 = x[0] / l[0]
    y1 = (x[1] - l[1] * y0) / l[2]
    y2 = (x[2] - l[3] * y0 - l[4] * y1) / l[5]
    u2 = y2 / l[5]
    u1 = (y1 - l[4] * u2) / l[2]
    u0 = (y0 - l[1] * u1 - l[3] * u2) / l[0]
    dp[j] = -wp.vec3d(u0, u1, u2)


class ObservationKernels:
    """A pose-major problem's observations on a Warp device, and the launches over them (each under the
    device's lock, which threads driving one device take turns through: ``warp_device.device_lock``)."""

    def __init__(self, p, obs_col: np.ndarray, n_free: int, device: str, schur_on_device: bool = False) -> None:
        self.device = device
        self.n_obs, self.n_points, self.n_free = len(p.obs_pose), len(p.points), n_free
        self.K = wp.vec4d(float(p.K[0, 0]), float(p.K[1, 1]), float(p.K[0, 2]), float(p.K[1, 2]))
        self.obs_pose = wp.array(np.asarray(p.obs_pose, np.int32), dtype=wp.int32, device=device)
        self.obs_point = wp.array(np.asarray(p.obs_point, np.int32), dtype=wp.int32, device=device)
        self.obs_col = wp.array(np.asarray(obs_col, np.int32), dtype=wp.int32, device=device)
        self.uv = wp.array(np.ascontiguousarray(p.obs_uv, np.float64), dtype=wp.vec2d, device=device)
        self.W = wp.empty(self.n_obs, dtype=mat36d, device=device)  # (written whole by each linearisation)
        self.Hpp = wp.zeros(self.n_points, dtype=wp.mat33d, device=device)
        self.gp = wp.zeros(self.n_points, dtype=wp.vec3d, device=device)
        self.Hcc = wp.zeros(max(n_free, 1), dtype=wp.spatial_matrixd, device=device)
        self.gc = wp.zeros(max(n_free, 1), dtype=wp.spatial_vectord, device=device)
        self.scalar = wp.zeros(1, dtype=wp.float64, device=device)
        self.Wdc = wp.zeros(self.n_points, dtype=wp.vec3d, device=device)
        self._chunks: dict[int, tuple] = {}
        self.R = wp.empty(len(p.poses), dtype=wp.mat33d, device=device)
        self.t = wp.empty(len(p.poses), dtype=wp.vec3d, device=device)
        self.X = wp.empty(self.n_points, dtype=wp.vec3d, device=device)
        # the camera system's elimination on the device (``schur_complement``): observations by free poses
        # grouped by landmark, each with the end of its landmark's group
        self.schur_on_device = bool(schur_on_device)
        if self.schur_on_device:
            obs_point = np.asarray(p.obs_point, np.int64)
            pm = np.flatnonzero(np.asarray(obs_col) >= 0)
            pm = pm[np.argsort(obs_point[pm], kind="stable")]
            ends = np.searchsorted(obs_point[pm], obs_point[pm], side="right")
            self.n_pm = len(pm)
            self.pm_obs = wp.array(pm.astype(np.int32), dtype=wp.int32, device=device)
            self.pm_end = wp.array(ends.astype(np.int32), dtype=wp.int32, device=device)
            self.L = wp.zeros(self.n_points, dtype=vec6d, device=device)
            self.Lg = wp.zeros(self.n_points, dtype=wp.vec3d, device=device)
            self.failed = wp.zeros(1, dtype=wp.int32, device=device)
            self.M = wp.zeros(max(36 * n_free * n_free, 1), dtype=wp.float64, device=device)
            self.r = wp.zeros(max(6 * n_free, 1), dtype=wp.float64, device=device)
            self.dc = wp.zeros(max(n_free, 1), dtype=vec6d, device=device)
            self.dp = wp.zeros(self.n_points, dtype=wp.vec3d, device=device)

    def _state(self, poses: np.ndarray, points: np.ndarray):
        """The state copied into the device's arrays (no allocation per call)."""
        self.R.assign(np.ascontiguousarray(poses[:, :3, :3], np.float64))
        self.t.assign(np.ascontiguousarray(poses[:, :3, 3], np.float64))
        self.X.assign(np.ascontiguousarray(points, np.float64))
        return self.R, self.t, self.X

    def linearize(self, poses, points, sigma: float, loss: str, k: float):
        """(Hpp (N, 3, 3), None where the elimination is on the device; gp (N, 3), pose blocks (F, 6, 6), pose
        gradients (F, 6), sum of s |r|^2) at the given state."""
        R, t, X = self._state(poses, points)
        with device_lock(self.device):
            for a in (self.Hpp, self.gp, self.Hcc, self.gc, self.scalar):
                a.zero_()
            wp.launch(_linearize, dim=self.n_obs, device=self.device,
                      inputs=[self.obs_pose, self.obs_point, self.obs_col, self.uv, R, t, X, self.K, 1.0 / sigma,
                              float(k), LOSS_CODES[loss]],
                      outputs=[self.W, self.Hpp, self.gp, self.Hcc, self.gc, self.scalar])
        # W stays on the device (read by ``whitened_batch``, ``w_times_step``; ``W_host`` where needed), and
        # so do the landmark blocks where the elimination runs here
        return (None if self.schur_on_device else self.Hpp.numpy(), self.gp.numpy(), self.Hcc.numpy()[:self.n_free],
                self.gc.numpy()[:self.n_free], float(self.scalar.numpy()[0]))

    def W_host(self) -> np.ndarray:
        """(O, 3, 6): the last linearisation's s Jp^T Jc per observation."""
        return self.W.numpy()

    def residuals(self, poses, points, behind: float) -> np.ndarray:
        """(O, 2) reprojection residuals at the given state, ``behind`` where the point is behind the camera."""
        R, t, X = self._state(poses, points)
        if not hasattr(self, "residual"):
            self.residual = wp.zeros(self.n_obs, dtype=wp.vec2d, device=self.device)
        with device_lock(self.device):
            wp.launch(_residuals, dim=self.n_obs, device=self.device,
                      inputs=[self.obs_pose, self.obs_point, self.uv, R, t, X, self.K, float(behind)],
                      outputs=[self.residual])
        return self.residual.numpy().copy()

    def error(self, poses, points, sigma: float, loss: str, k: float) -> float:
        """The sum of the reprojection losses at the given state."""
        R, t, X = self._state(poses, points)
        with device_lock(self.device):
            self.scalar.zero_()
            wp.launch(_error, dim=self.n_obs, device=self.device,
                      inputs=[self.obs_pose, self.obs_point, self.uv, R, t, X, self.K, 1.0 / sigma, float(k),
                              LOSS_CODES[loss]], outputs=[self.scalar])
        return float(self.scalar.numpy()[0])

    def set_landmark_factors(self, L: np.ndarray) -> None:
        """Every landmark's damped Cholesky factor (N, 6: l11 l21 l22 l31 l32 l33), for ``whitened_batch``."""
        self.L = wp.array(np.ascontiguousarray(L, np.float64), dtype=vec6d, device=self.device)

    def whitened_batch(self, key, chunks, offsets, dense: bool) -> np.ndarray:
        """Consecutive chunks' dense L^-1 W blocks in one launch, laid one after the other from ``offsets``
        (flat; chunk i's is ``Z[offsets[i]:offsets[i + 1]].reshape(3 x landmarks, 6 x poses)``); ``key`` names
        the batch (its index arrays stay on the device)."""
        d = self.device
        if key not in self._chunks:
            self._chunks[key] = (
                wp.array(np.concatenate([np.asarray(c.obs, np.int32) for c in chunks]), dtype=wp.int32, device=d),
                wp.array(np.concatenate([c.dest[0, 0] + o for c, o in zip(chunks, offsets)]).astype(np.int64),
                         dtype=wp.int64, device=d),
                wp.array(np.concatenate([np.full(len(c.obs), 6 * c.n_cols, np.int64) for c in chunks]),
                         dtype=wp.int64, device=d),
                wp.zeros(int(offsets[-1]), dtype=wp.float64, device=d))
        obs, base, width, Z = self._chunks[key]
        with device_lock(d):
            if not dense:
                Z.zero_()
            wp.launch(_whitened_batch, dim=obs.shape[0], device=d,
                      inputs=[obs, base, width, self.obs_point, self.W, self.L], outputs=[Z])
        return Z.numpy()

    def w_times_step(self, dc: np.ndarray) -> np.ndarray:
        """(N, 3): the sum of W_o dc over each landmark's observations."""
        step = wp.array(np.ascontiguousarray(dc, np.float64), dtype=vec6d, device=self.device)
        with device_lock(self.device):
            self.Wdc.zero_()
            wp.launch(_w_times_step, dim=self.n_obs, device=self.device,
                      inputs=[self.obs_point, self.obs_col, self.W, step], outputs=[self.Wdc])
        return self.Wdc.numpy()

    def schur_complement(self, lam: float):
        """The landmarks eliminated at damping ``lam``, on the device: (M (6F, 6F): the sum of W^T V^-1 W in its
        lower block triangle, r (6F,): the sum of W^T V^-1 gp), or None where a landmark's damped block is not
        positive definite. Read back: M, r and a flag."""
        d = self.device
        with device_lock(d):
            self.failed.zero_()
            self.M.zero_()
            self.r.zero_()
            wp.launch(_landmark_factors, dim=self.n_points, device=d, inputs=[self.Hpp, self.gp, float(lam)],
                      outputs=[self.L, self.Lg, self.failed])
            wp.launch(_schur_blocks, dim=self.n_pm, device=d,
                      inputs=[self.pm_obs, self.pm_end, self.obs_point, self.obs_col, self.W, self.L, self.Lg,
                              6 * self.n_free], outputs=[self.M, self.r])
        if int(self.failed.numpy()[0]):
            return None
        n6 = 6 * self.n_free
        return self.M.numpy()[:n6 * n6].reshape(n6, n6), self.r.numpy()[:n6]

    def back_substitute(self, dc: np.ndarray) -> np.ndarray:
        """(N, 3): each landmark's move -V^-1 (gp + sum of W dc) by ``schur_complement``'s factors."""
        d = self.device
        self.dc.assign(np.ascontiguousarray(dc, np.float64).reshape(-1, 6) if len(dc) else np.zeros((1, 6)))
        with device_lock(d):
            self.Wdc.zero_()
            if self.n_free:
                wp.launch(_w_times_step, dim=self.n_obs, device=d,
                          inputs=[self.obs_point, self.obs_col, self.W, self.dc], outputs=[self.Wdc])
            wp.launch(_back_substitute, dim=self.n_points, device=d, inputs=[self.L, self.gp, self.Wdc],
                      outputs=[self.dp])
        return self.dp.numpy()
