"""Sums over a tiled block that every lane of the block receives, for LK and the drift check (one block per
feature). Tiled kernels stride their lane loops by ``wp.block_dim()``: Warp's CPU device runs a tiled launch with
one lane per block, so a constant stride would silently use a fraction of the window there."""

from __future__ import annotations

import warp as wp

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

vec44 = wp.types.vector(length=44, dtype=wp.float32)  # upper triangle of an 8x8 normal matrix (36) + gradient (8)
vec66 = wp.types.vector(length=66, dtype=wp.float32)  # ECC's sums (global_motion.py): moments, J, J'J, J'I, J'T

# --- block sums --------------------------------------------------------------------------------------------
# LK and the drift check sum per-lane values over their block once per iteration, and every lane needs the sum.
# wp.tile_sum followed by an extraction takes four barriers and a serial pass by one thread (its result lives in
# lane 0 and is broadcast through shared memory). Here each warp reduces by butterfly shuffles, so every lane
# ends with its warp's sum, and one barrier lets every lane add the warps' sums. Two shared buffers alternate
# with the caller's count of block sums: a lane can only write a buffer again after the next barrier, which
# every lane reaches only once it has read the previous sum. On the CPU a tiled launch has one lane per block,
# whose value is the sum. Every lane of a block must make the same calls (uniform control flow).
_BLOCK_SUM_SNIPPET = """
#if defined(__CUDA_ARCH__)
    static_assert(WP_TILE_BLOCK_DIM % 32 == 0, "block sums need whole warps");
    constexpr int N = sizeof(v) / sizeof(float);
    constexpr int WARPS = WP_TILE_BLOCK_DIM / 32;
    __shared__ float partials[2][WARPS][N];
    auto s = v;
    float* c = reinterpret_cast<float*>(&s);
    #pragma unroll
    for (int i = 0; i < N; ++i) {
        float x = c[i];
        #pragma unroll
        for (int o = 16; o > 0; o >>= 1)
            x += __shfl_xor_sync(0xffffffffu, x, o);
        c[i] = x;
    }
    if (WARPS == 1)
        return s;
    const int buf = parity & 1;
    if ((threadIdx.x & 31) == 0) {
        #pragma unroll
        for (int i = 0; i < N; ++i)
            partials[buf][threadIdx.x >> 5][i] = c[i];
    }
    __syncthreads();
    #pragma unroll
    for (int i = 0; i < N; ++i) {
        float t = partials[buf][0][i];
        #pragma unroll
        for (int w = 1; w < WARPS; ++w)
            t += partials[buf][w][i];
        c[i] = t;
    }
    return s;
#else
    static_assert(WP_TILE_BLOCK_DIM == 1, "block sums on the CPU need one lane per block (enable_cpu_blocks off)");
    return v;
#endif
"""


@wp.func_native(_BLOCK_SUM_SNIPPET)
def block_sum1(v: float, parity: int) -> float: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def block_sum3(v: wp.vec3, parity: int) -> wp.vec3: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def block_sum4(v: wp.vec4, parity: int) -> wp.vec4: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def block_sum44(v: vec44, parity: int) -> vec44: ...


@wp.func_native(_BLOCK_SUM_SNIPPET)
def block_sum66(v: vec66, parity: int) -> vec66: ...


# An exclusive prefix sum of one int per lane over a tiled block (Hillis-Steele in shared memory), for kernels that
# must rank items in order inside a conditional graph node, where wp.utils.array_scan's temporary allocation is not
# allowed. Every lane of the block must call it (uniform control flow). On the CPU a tiled launch has one lane: 0.
_BLOCK_SCAN_SNIPPET = """
#if defined(__CUDA_ARCH__)
    __shared__ int scan[WP_TILE_BLOCK_DIM];
    __syncthreads();
    scan[threadIdx.x] = v;
    __syncthreads();
    for (int o = 1; o < WP_TILE_BLOCK_DIM; o <<= 1) {
        int t = threadIdx.x >= o ? scan[threadIdx.x - o] : 0;
        __syncthreads();
        scan[threadIdx.x] += t;
        __syncthreads();
    }
    return scan[threadIdx.x] - v;
#else
    static_assert(WP_TILE_BLOCK_DIM == 1, "block scans on the CPU need one lane per block (enable_cpu_blocks off)");
    return 0;
#endif
"""


@wp.func_native(_BLOCK_SCAN_SNIPPET)
def block_exclusive_scan(v: int) -> int: ...
