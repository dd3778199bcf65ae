"""A dense symmetric positive-definite system factorised and solved on a Warp device, in float64: a right-looking
blocked Cholesky written as Warp tile kernels, so that a system that is already on the device (the Schur solver's
reduced camera system, thousands wide for a final pass) is neither read back nor factorised on the host; only its
solution and a flag come back.

The system lives in a ``storage`` array of (padded + tile) x padded float64 (``storage_shape``): its lower triangle
in the leading (n, n) block, the identity on the padding up to a whole number of tiles (``padded``), the
right-hand side in row ``padded``. ``DeviceCholesky.launch`` then, per block column k of tiles:

1. factorises the diagonal tile (``wp.tile_cholesky_inplace``) and counts its pivots that are not positive (<= 0
   or NaN: LAPACK's potrf test) into ``info``;
2. solves the panel below it, A_ik L_kk^-T (``wp.tile_lower_solve`` on the transposed tile), the right-hand side's
   tile row with it: that is the forward substitution, L y = b, done by the factorisation's own launches;
3. updates the trailing lower triangle, A_ij -= L_ik L_jk^T for k < j <= i (``wp.tile_matmul``), one launch over
   its tiles, the right-hand side's tile row included;

and then solves L^T x = y, one launch per block column from the last (x_k = L_kk^-T y_k, and y_j -= L_kj^T x_k
for the blocks j < k in parallel), leaving x in row ``padded + 1``. The factor overwrites the lower triangle.

On a CUDA device the whole sequence is recorded once per storage as a CUDA graph and replayed (a few hundred
launches for one replay's cost); on Warp's CPU device (tests) the tile kernels run one thread per block, and the
launches go one by one. The tile operations use cuSolverDx / cuBLASDx where Warp is built with libmathdx
(``wp.config.enable_mathdx_solver``, ``enable_mathdx_gemm``), its cooperative fallback otherwise.

``solve_spd`` is the host's way in (upload, factorise, solve, read back), for tests and benchmarks; the Schur
solver forms its damped camera system in a storage of its own on the device (``schur_kernels``).
"""

from __future__ import annotations

import functools
import logging
from types import SimpleNamespace

import numpy as np

from lapreco_hil.warp_device import device_lock, init_warp

wp = init_warp()

log = logging.getLogger(__name__)

# the tile's side: 32 x 32 float64 (8 KB) fits three to a block in the default 48 KB of shared memory; 64 x 64
# (32 KB) needs 96 KB for the trailing update's three tiles (an H100 gives a block up to 227 KB)
TILE = 32
TILES = (16, 32, 64)
# threads per block on a GPU (on Warp's CPU device a block is one thread)
CUDA_BLOCK_DIM = 128


def padded_width(n: int, tile: int = TILE) -> int:
    """``n`` rounded up to a whole number of tiles."""
    return -(-int(n) // tile) * tile


def storage_shape(n: int, tile: int = TILE) -> tuple[int, int]:
    """The (rows, columns) of a system's storage: the padded matrix, then one tile row (the right-hand side in its
    first row, the solution in its second)."""
    padded = padded_width(n, tile)
    return padded + tile, padded


def _check_tile(tile: int) -> int:
    if tile not in TILES:
        raise ValueError(f"dense Cholesky tile {tile}: use one of {', '.join(map(str, TILES))}")
    return int(tile)


@functools.cache
def _kernels(tile: int, block_dim: int, mathdx: bool | None = None) -> SimpleNamespace:
    """The tile kernels of a tile's side, compiled for ``block_dim`` threads per block (each in a module of its own:
    ``warp_device.preload_kernels`` loads them with the module's block size); ``mathdx``: their tile operations by
    libmathdx (cuSolverDx, cuBLASDx) on a GPU or by Warp's own code (None: Warp's configuration)."""
    T = tile
    f64 = wp.float64
    options = {"enable_backward": False, "block_dim": block_dim}
    if mathdx is not None:
        options.update({"enable_mathdx_gemm": bool(mathdx), "enable_mathdx_solver": bool(mathdx)})

    @wp.kernel(module="unique", module_options=options)
    def factor_diagonal(A: wp.array2d(dtype=wp.float64), k: int, info: wp.array(dtype=wp.int32)):
        """A_kk = L_kk L_kk^T (its trailing updates done), and its pivots that are not positive counted."""
        _block, lane = wp.tid()
        a = wp.tile_load(A, shape=(T, T), offset=(k * T, k * T), storage="shared")
        wp.tile_cholesky_inplace(a)
        wp.tile_store(A, a, offset=(k * T, k * T))
        for r in range(lane, T, wp.block_dim()):
            if not (a[r, r] > f64(0.0)):  # (NaN: a pivot below zero earlier in the tile, or before it)
                wp.atomic_add(info, 0, 1)

    @wp.kernel(module="unique", module_options=options)
    def solve_panel(A: wp.array2d(dtype=wp.float64), k: int):
        """A_ik = A_ik L_kk^-T for the tiles below the diagonal (block b: tile row k + 1 + b, the right-hand
        side's row last)."""
        block, _lane = wp.tid()
        i = k + 1 + block
        l_kk = wp.tile_load(A, shape=(T, T), offset=(k * T, k * T), storage="shared")
        a = wp.tile_load(A, shape=(T, T), offset=(i * T, k * T), storage="shared")
        x = wp.tile_transpose(a)
        wp.tile_lower_solve_inplace(l_kk, x)  # L_kk x = A_ik^T
        wp.tile_store(A, wp.tile_transpose(x), offset=(i * T, k * T))

    @wp.kernel(module="unique", module_options=options)
    def update_trailing(A: wp.array2d(dtype=wp.float64), k: int, m: int):
        """A_ij -= L_ik L_jk^T over the trailing lower triangle of ``m`` tile rows (block t: its t-th tile row by
        row, (r, c) with c <= r), then the right-hand side's tile row (its ``m`` tiles)."""
        t, _lane = wp.tid()
        n_triangle = m * (m + 1) // 2
        r = int((wp.sqrt(f64(8 * t + 1)) - f64(1.0)) / f64(2.0))
        while r * (r + 1) // 2 > t:  # (the float's root corrected to the integer one)
            r -= 1
        while (r + 1) * (r + 2) // 2 <= t:
            r += 1
        c = t - r * (r + 1) // 2
        if t >= n_triangle:
            r = m
            c = t - n_triangle
        i = k + 1 + r
        j = k + 1 + c
        a = wp.tile_load(A, shape=(T, T), offset=(i * T, j * T), storage="shared")
        l_ik = wp.tile_load(A, shape=(T, T), offset=(i * T, k * T), storage="shared")
        l_jk = wp.tile_load(A, shape=(T, T), offset=(j * T, k * T), storage="shared")
        wp.tile_matmul(l_ik, wp.tile_transpose(l_jk), a, alpha=f64(-1.0))
        wp.tile_store(A, a, offset=(i * T, j * T))

    @wp.kernel(module="unique", module_options=options)
    def solve_backward(A: wp.array2d(dtype=wp.float64), y: wp.array2d(dtype=wp.float64),
                       x: wp.array2d(dtype=wp.float64), k: int):
        """x_k = L_kk^-T y_k (block 0 stores it), and y_j -= L_kj^T x_k for j < k (block j): every block solves
        x_k itself, and none writes y_k. ``y``, ``x``: the storage's right-hand side's and solution's rows seen as
        columns (padded, 1)."""
        block, _lane = wp.tid()
        l_kk = wp.tile_load(A, shape=(T, T), offset=(k * T, k * T), storage="shared")
        y_k = wp.tile_load(y, shape=(T, 1), offset=(k * T, 0), storage="shared")
        x_k = wp.tile_upper_solve(wp.tile_transpose(l_kk), y_k)
        if block == 0:
            wp.tile_store(x, x_k, offset=(k * T, 0))
        if block < k:
            l_kj = wp.tile_load(A, shape=(T, T), offset=(k * T, block * T), storage="shared")
            y_j = wp.tile_load(y, shape=(T, 1), offset=(block * T, 0), storage="shared")
            wp.tile_matmul(wp.tile_transpose(l_kj), x_k, y_j, alpha=f64(-1.0))
            wp.tile_store(y, y_j, offset=(block * T, 0))

    return SimpleNamespace(factor_diagonal=factor_diagonal, solve_panel=solve_panel, update_trailing=update_trailing,
                           solve_backward=solve_backward)


def block_dim_of(device) -> int:
    """Threads per block of the kernels on ``device``: one on Warp's CPU device."""
    return 1 if wp.get_device(device).is_cpu else CUDA_BLOCK_DIM


def kernels_of(tile: int, device, mathdx: bool | None = None) -> SimpleNamespace:
    """The tile kernels for ``device`` (compiled at their first launch or by ``load``)."""
    return _kernels(_check_tile(tile), block_dim_of(device), mathdx)


def load(tile: int, device, mathdx: bool | None = None) -> None:
    """Compile and load the kernels of ``tile`` on ``device`` now (a run's start), not at the first solve."""
    for kernel in vars(kernels_of(tile, device, mathdx)).values():
        wp.load_module(kernel.module, device=str(device), block_dim=block_dim_of(device))


class DeviceCholesky:
    """The factorisation and solve of an ``n``-wide system held in a storage array (``storage_shape``) on
    ``device``, enqueued on its stream by ``launch``: the factor overwrites the storage's lower triangle, the
    solution is its row ``padded + 1`` (``solution``), and ``info`` (int32, zeroed by ``launch``) counts the
    pivots that were not positive. ``graph``: record the launches once per storage as a CUDA graph and replay
    it (None: on CUDA devices; on Warp's CPU device, Warp's recorded graph); ``mathdx`` as ``_kernels``'."""

    def __init__(self, n: int, device, tile: int = TILE, graph: bool | None = None,
                 mathdx: bool | None = None) -> None:
        self.n, self.tile, self.device = int(n), _check_tile(tile), wp.get_device(device)
        self.padded = padded_width(n, tile)
        self.n_tiles = self.padded // tile
        self.block_dim = block_dim_of(self.device)
        self.mathdx = mathdx
        self.kernels = _kernels(self.tile, self.block_dim, mathdx)
        self.graph = self.device.is_cuda if graph is None else bool(graph)
        self._graphs: dict = {}  # (storage's address, info's address) -> recorded graph
        self._commands: dict | None = None  # (storage's, info's address) -> recorded launches (no graph)
        self.launches = 3 * self.n_tiles - 1 + self.n_tiles  # (per solve: the factorisation's, then the solve's)

    def solution(self, storage):
        """The solution's row of ``storage``, its first ``n`` entries (a view)."""
        return wp.array(ptr=storage.ptr + 8 * (self.padded + 1) * self.padded, shape=(max(self.n, 1),),
                        dtype=wp.float64, device=storage.device)

    def _column(self, storage, row: int):
        """A row of ``storage`` seen as a (padded, 1) column (a view)."""
        return wp.array(ptr=storage.ptr + 8 * row * self.padded, shape=(self.padded, 1), dtype=wp.float64,
                        device=storage.device)

    def _check(self, storage, info) -> None:
        if tuple(storage.shape) != storage_shape(self.n, self.tile) or storage.dtype != wp.float64:
            raise ValueError(f"dense Cholesky storage {tuple(storage.shape)} {storage.dtype}: expected float64 "
                             f"{storage_shape(self.n, self.tile)} for n = {self.n}, tile {self.tile}")
        if info.dtype != wp.int32:
            raise ValueError("dense Cholesky info: expected an int32 array")

    def _record(self, storage, info) -> list:
        """Every launch of one factorisation and solve, recorded (``wp.launch(record_cmd=True)``)."""
        kn, nt, bd, d = self.kernels, self.n_tiles, self.block_dim, self.device
        commands = []

        def add(kernel, dim, inputs):
            commands.append(wp.launch(kernel, dim=[dim, bd], inputs=inputs, block_dim=bd, device=d, record_cmd=True))

        for k in range(nt):
            m = nt - k - 1
            add(kn.factor_diagonal, 1, [storage, k, info])
            add(kn.solve_panel, m + 1, [storage, k])  # (the right-hand side's row among them)
            if m:
                add(kn.update_trailing, m * (m + 1) // 2 + m, [storage, k, m])
        y, x = self._column(storage, self.padded), self._column(storage, self.padded + 1)
        for k in range(nt - 1, -1, -1):
            add(kn.solve_backward, max(k, 1), [storage, y, x, k])
        return commands

    def launch(self, storage, info) -> None:
        """Enqueue the factorisation and solve of ``storage`` (the system formed there), ``info`` zeroed first.
        Nothing waits: read ``solution(storage)`` and ``info`` back after the stream."""
        self._check(storage, info)
        key = (storage.ptr, info.ptr)
        with device_lock(self.device):
            info.zero_()
            if self.graph:
                graph = self._graphs.get(key)
                if graph is None:
                    graph = self._capture(storage, info)
                if graph is not None:
                    wp.capture_launch(graph)
                    return
            if self._commands is None:
                self._commands = {}
            commands = self._commands.get(key)
            if commands is None:
                commands = self._commands[key] = self._record(storage, info)
            for command in commands:
                command.launch()

    def _capture(self, storage, info):
        """The launches recorded as a CUDA graph (None where capture fails: they are then launched one by one)."""
        load(self.tile, self.device, self.mathdx)  # (a capture cannot compile)
        try:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                for command in self._record(storage, info):
                    command.launch()
        except Exception as e:  # (a driver refusing the capture: the launches still work)
            log.warning("dense Cholesky: CUDA graph capture failed (%s); launching one by one", e)
            self.graph = False
            return None
        self._graphs[(storage.ptr, info.ptr)] = capture.graph
        return capture.graph


def to_storage(S: np.ndarray, rhs: np.ndarray, tile: int = TILE) -> np.ndarray:
    """The host's storage of a system: S's lower triangle, identity padding, ``rhs`` in row ``padded``."""
    n = len(rhs)
    rows, padded = storage_shape(n, tile)
    out = np.zeros((rows, padded))
    out[:n, :n] = np.tril(S)
    diagonal = np.arange(n, padded)
    out[diagonal, diagonal] = 1.0
    out[padded, :n] = rhs
    return out


def solve_spd(S: np.ndarray, rhs: np.ndarray, device="cpu", tile: int = TILE) -> np.ndarray | None:
    """x with S x = rhs (S: symmetric, its lower triangle read) by the blocked Cholesky on Warp ``device``; None
    where S is not positive definite (a pivot <= 0 or NaN) or x is not finite, as ``schur._solve_camera_system``
    answers. Uploads the system and reads back x: for tests and benchmarks."""
    S, rhs = np.asarray(S, np.float64), np.asarray(rhs, np.float64)
    if S.ndim != 2 or S.shape != (len(rhs), len(rhs)):
        raise ValueError(f"solve_spd: S {S.shape} and rhs {rhs.shape} do not make a square system")
    if not len(rhs):
        return np.zeros(0)
    chol = DeviceCholesky(len(rhs), device, tile)
    storage = wp.array(to_storage(S, rhs, tile), dtype=wp.float64, device=chol.device)
    info = wp.zeros(1, dtype=wp.int32, device=chol.device)
    chol.launch(storage, info)
    x = chol.solution(storage).numpy()[:len(rhs)].copy()
    if int(info.numpy()[0]):
        return None
    return x if np.all(np.isfinite(x)) else None
