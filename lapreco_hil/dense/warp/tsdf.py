"""Warp kernels of the sparse TSDF volume (lapreco_hil.dense.fusion holds the host side).

The volume is a pool of 8^3-voxel blocks found through an open-addressing hash table (linear probing, keys
claimed with ``wp.atomic_cas``). A block's key packs its integer block coordinates (21 bits each, offset to
unsigned: +-4 km at 4 mm blocks). Voxel sums are int32 fixed point (weight in 1/W_SCALE, weight x tsdf in
1/(W_SCALE x TSDF_SCALE), weight x colour): integration adds and deintegration subtracts the very same integers,
so taking a depth map out again restores the volume bit for bit.
"""

from __future__ import annotations

import warp as wp

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

BLOCK = 8  # voxels per block side
BLOCK_SLICE = BLOCK * BLOCK
BLOCK_VOXELS = BLOCK * BLOCK * BLOCK
EMPTY = -1  # a free hash slot's key
W_SCALE = 64  # confidence 1.0 weighs 64 units
W_MAX = 1024  # one integration weighs at most this (weight_scale 16): sums stay far from int32's range
TSDF_SCALE = 1024  # tsdf in [-1, 1] as +-1024 units
KEY_BITS = 21
KEY_SHIFT_X = 2 * KEY_BITS
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
HASH_MULTIPLIER = 0x9E3779B97F4A7C15  # Fibonacci hashing: the key times 2^64 / golden ratio, top bits


@wp.func
def pack_key(bx: int, by: int, bz: int) -> wp.int64:
    return ((wp.int64(bx + KEY_OFFSET) & wp.int64(KEY_MASK)) << wp.int64(KEY_SHIFT_X)) \
        | ((wp.int64(by + KEY_OFFSET) & wp.int64(KEY_MASK)) << wp.int64(KEY_BITS)) \
        | (wp.int64(bz + KEY_OFFSET) & wp.int64(KEY_MASK))


@wp.func
def unpack_key(key: wp.int64) -> wp.vec3i:
    bx = int((key >> wp.int64(KEY_SHIFT_X)) & wp.int64(KEY_MASK)) - KEY_OFFSET
    by = int((key >> wp.int64(KEY_BITS)) & wp.int64(KEY_MASK)) - KEY_OFFSET
    bz = int(key & wp.int64(KEY_MASK)) - KEY_OFFSET
    return wp.vec3i(bx, by, bz)


@wp.func
def home_slot(key: wp.int64, slot_bits: int) -> int:
    h = wp.uint64(key) * wp.uint64(HASH_MULTIPLIER)
    return int(h >> wp.uint64(64 - slot_bits))


@wp.func
def find_slot(slot_keys: wp.array(dtype=wp.int64), key: wp.int64, slot_bits: int) -> int:
    """The slot holding ``key``, or -1."""
    n = slot_keys.shape[0]
    s = home_slot(key, slot_bits)
    for _probe in range(n):
        k = slot_keys[s]
        if k == key:
            return s
        if k == wp.int64(EMPTY):
            return -1
        s = (s + 1) & (n - 1)
    return -1


@wp.func
def claim_slot(slot_keys: wp.array(dtype=wp.int64), key: wp.int64, slot_bits: int, counts: wp.array(dtype=int)) -> int:
    """The slot holding ``key``, claimed if it is not there yet (counted in counts[COUNT_NEW]); -1 when the table
    is full."""
    n = slot_keys.shape[0]
    s = home_slot(key, slot_bits)
    for _probe in range(n):
        k = slot_keys[s]
        if k == key:
            return s
        if k == wp.int64(EMPTY):
            old = wp.atomic_cas(slot_keys, s, wp.int64(EMPTY), key)
            if old == wp.int64(EMPTY):
                wp.atomic_add(counts, 1, 1)  # COUNT_NEW
                return s
            if old == key:
                return s
        s = (s + 1) & (n - 1)
    return -1


# counts: [0] blocks of the pool in use (kept from map to map), [1] slots a map claimed, [2] blocks active for the
# map, [3] blocks the pool could not give; [1:] start at 0 for each map (reset_map_counts)
COUNT_POOL = 0
COUNT_NEW = 1
COUNT_ACTIVE = 2
COUNT_REFUSED = 3
N_COUNTS = 4


@wp.func
def pixel_weight(confidence: float, weight_scale: float) -> int:
    """A pixel's integer weight: confidence (clipped to [0, 1]; NaN: 0) x weight_scale in 1/W_SCALE steps, at
    most W_MAX. Computed on the device for integration and de-integration alike, so both use the same integer."""
    if not (confidence > 0.0):
        return 0
    w = int(wp.floor(wp.min(confidence, 1.0) * weight_scale * float(W_SCALE) + 0.5))
    return wp.min(w, W_MAX)


@wp.kernel
def prepare_map(depth: wp.array2d(dtype=wp.float32), confidence: wp.array2d(dtype=wp.float32), weight_scale: float,
                depth_steps: float, confidence_steps: float, weight: wp.array2d(dtype=wp.int32),
                depth_q: wp.array2d(dtype=wp.uint16), confidence_q: wp.array2d(dtype=wp.uint8),
                counts: wp.array(dtype=int)):
    """Each pixel's integer weight (once per map, not once per voxel that looks at it); the first thread also
    sets the map's counts to 0 (one launch for both). With ``depth_steps`` > 0 the map is first quantised as it
    is kept (depth in 1/depth_steps m, uint16, 0 where none or out of range; confidence in 1/confidence_steps,
    uint8, 0 where there is no depth) into ``depth_q`` / ``confidence_q`` and fused as quantised: a kept map,
    fused again, quantises to the same integers."""
    y, x = wp.tid()
    c = confidence[y, x]
    if depth_steps > 0.0:
        d = depth[y, x]
        q = float(0.0)
        if d > 0.0:
            q = wp.floor(d * depth_steps + 0.5)
        if q >= 65536.0:
            q = 0.0
        cq = float(0.0)
        if q > 0.0 and c > 0.0:
            cq = wp.floor(wp.min(c, 1.0) * confidence_steps + 0.5)
        depth_q[y, x] = wp.uint16(int(q))
        confidence_q[y, x] = wp.uint8(int(cq))
        depth[y, x] = q / depth_steps
        c = cq / confidence_steps
    weight[y, x] = pixel_weight(c, weight_scale)
    if y == 0 and x == 0:
        for i in range(COUNT_NEW, N_COUNTS):
            counts[i] = 0


@wp.kernel
def touch_blocks(depth: wp.array2d(dtype=wp.float32), weight: wp.array2d(dtype=wp.int32), intr: wp.vec4, R_wc: wp.mat33, t_wc: wp.vec3, trunc_m: float, voxel_m: float,
                 stride: int, insert: int, stamp: int, slot_bits: int, slot_keys: wp.array(dtype=wp.int64),
                 slot_stamp: wp.array(dtype=int), counts: wp.array(dtype=int)):
    """Every block the truncation band of a pixel's depth crosses is stamped (and, when ``insert``, claimed):
    the ray from depth - trunc to depth + trunc, sampled a voxel apart."""
    y0, x0 = wp.tid()
    y = y0 * stride
    x = x0 * stride
    if y >= depth.shape[0] or x >= depth.shape[1]:
        return
    d = depth[y, x]
    if not (d > 0.0) or weight[y, x] <= 0:
        return
    ray = wp.vec3((float(x) - intr[2]) / intr[0], (float(y) - intr[3]) / intr[1], 1.0)
    block_m = voxel_m * float(BLOCK)
    steps = int(wp.ceil(2.0 * trunc_m / voxel_m)) + 1
    last = wp.int64(EMPTY)
    for i in range(steps):
        z = d - trunc_m + float(i) * voxel_m
        if z > 0.0:
            p = R_wc * (ray * z) + t_wc
            key = pack_key(int(wp.floor(p[0] / block_m)), int(wp.floor(p[1] / block_m)),
                           int(wp.floor(p[2] / block_m)))
            if key != last:
                last = key
                s = int(-1)
                if insert != 0:
                    s = claim_slot(slot_keys, key, slot_bits, counts)
                else:
                    s = find_slot(slot_keys, key, slot_bits)
                if s >= 0 and slot_stamp[s] != stamp:
                    slot_stamp[s] = stamp


@wp.kernel
def collect_blocks(slot_keys: wp.array(dtype=wp.int64), slot_stamp: wp.array(dtype=int),
                   slot_block: wp.array(dtype=int), stamp: int, insert: int, only_new: int, born: int,
                   born_limit: int, capacity: int, block_key: wp.array(dtype=wp.int64),
                   block_born: wp.array(dtype=int), block_used: wp.array(dtype=int), counts: wp.array(dtype=int),
                   active: wp.array(dtype=int)):
    """The stamped slots' blocks into ``active`` (counts[COUNT_ACTIVE]); a claimed slot gets a block from the
    pool first (counts[COUNT_POOL]; counts[COUNT_REFUSED]: blocks the pool could not give). ``only_new``: only
    the blocks given now (a map's blocks refused before, once the pool has room). With ``born_limit`` >= 0 only
    blocks allocated by then (a deintegration: a block born later never held that map)."""
    s = wp.tid()
    if slot_stamp[s] != stamp:
        return
    b = slot_block[s]
    if b < 0:
        if insert == 0:
            return
        b = wp.atomic_add(counts, COUNT_POOL, 1)
        if b >= capacity:
            wp.atomic_add(counts, COUNT_REFUSED, 1)
            return
        slot_block[s] = b
        block_key[b] = slot_keys[s]
        block_born[b] = born
    elif only_new != 0:
        return
    if born_limit >= 0 and block_born[b] > born_limit:
        return
    block_used[b] = stamp
    i = wp.atomic_add(counts, COUNT_ACTIVE, 1)
    active[i] = b


@wp.func
def integrate_voxel(tid: int, active: wp.array(dtype=int), block_key: wp.array(dtype=wp.int64),
                    depth: wp.array2d(dtype=wp.float32), weight: wp.array2d(dtype=wp.int32), colour: wp.array3d(dtype=wp.uint8), intr: wp.vec4, R_cw: wp.mat33,
                    t_cw: wp.vec3, trunc_m: float, voxel_m: float, sign: int, w_sum: wp.array(dtype=wp.int32),
                    d_sum: wp.array(dtype=wp.int32), c_sum: wp.array(dtype=wp.vec3i)):
    a = tid // BLOCK_VOXELS
    v = tid - a * BLOCK_VOXELS
    b = active[a]
    bc = unpack_key(block_key[b])
    i = v % BLOCK
    j = (v // BLOCK) % BLOCK
    k = v // BLOCK_SLICE
    p = wp.vec3((float(bc[0] * BLOCK + i) + 0.5) * voxel_m, (float(bc[1] * BLOCK + j) + 0.5) * voxel_m,
                (float(bc[2] * BLOCK + k) + 0.5) * voxel_m)
    pc = R_cw * p + t_cw
    z = pc[2]
    if z <= 1.0e-6:
        return
    px = int(wp.floor(intr[0] * pc[0] / z + intr[2] + 0.5))
    py = int(wp.floor(intr[1] * pc[1] / z + intr[3] + 0.5))
    if px < 0 or py < 0 or px >= depth.shape[1] or py >= depth.shape[0]:
        return
    d = depth[py, px]
    wq = weight[py, px]
    if not (d > 0.0) or wq <= 0:
        return
    sdf = d - z
    if sdf < -trunc_m:
        return
    tsdf = wp.min(1.0, sdf / trunc_m)
    dq = int(wp.floor(tsdf * float(TSDF_SCALE) + 0.5))
    idx = b * BLOCK_VOXELS + v
    w = sign * wq
    w_sum[idx] = w_sum[idx] + w
    d_sum[idx] = d_sum[idx] + w * dq
    c_sum[idx] = c_sum[idx] + wp.vec3i(w * int(colour[py, px, 0]), w * int(colour[py, px, 1]),
                                       w * int(colour[py, px, 2]))


@wp.kernel
def integrate_voxels(threads: int, active: wp.array(dtype=int), counts: wp.array(dtype=int),
                     block_key: wp.array(dtype=wp.int64),
                     depth: wp.array2d(dtype=wp.float32), weight: wp.array2d(dtype=wp.int32),
                     colour: wp.array3d(dtype=wp.uint8), intr: wp.vec4, R_cw: wp.mat33,
                     t_cw: wp.vec3, trunc_m: float, voxel_m: float, sign: int, w_sum: wp.array(dtype=wp.int32),
                     d_sum: wp.array(dtype=wp.int32), c_sum: wp.array(dtype=wp.vec3i)):
    """The voxels of the active blocks (counts[COUNT_ACTIVE] of them, read on the device: the host never waits
    for the count), a fixed number of threads striding over them. Each voxel centre is projected into the depth
    map (nearest pixel), the signed distance along the optical axis truncated to [-1, 1] (voxels farther behind
    than the band are left), added (sign +1) or taken out (sign -1) with the pixel's weight and colour."""
    n = counts[COUNT_ACTIVE] * BLOCK_VOXELS
    tid = wp.tid()
    while tid < n:
        integrate_voxel(tid, active, block_key, depth, weight, colour, intr, R_cw, t_cw, trunc_m, voxel_m, sign,
                        w_sum, d_sum, c_sum)
        tid += threads


@wp.kernel
def block_weights(n_blocks: int, w_sum: wp.array(dtype=wp.int32), out: wp.array(dtype=int)):
    """Per block: how many of its voxels hold weight (0: an empty block, free to go)."""
    tid = wp.tid()
    b = tid // BLOCK_VOXELS
    if b < n_blocks and w_sum[tid] != 0:
        wp.atomic_add(out, b, 1)


@wp.kernel
def gather_blocks(order: wp.array(dtype=int), src_w: wp.array(dtype=wp.int32), src_d: wp.array(dtype=wp.int32),
                  src_c: wp.array(dtype=wp.vec3i), dst_w: wp.array(dtype=wp.int32), dst_d: wp.array(dtype=wp.int32),
                  dst_c: wp.array(dtype=wp.vec3i)):
    """Block ``order[i]`` of the source pool becomes block i of the destination (compaction, growth)."""
    tid = wp.tid()
    a = tid // BLOCK_VOXELS
    v = tid - a * BLOCK_VOXELS
    src = order[a] * BLOCK_VOXELS + v
    dst_w[tid] = src_w[src]
    dst_d[tid] = src_d[src]
    dst_c[tid] = src_c[src]


@wp.kernel
def insert_blocks(block_key: wp.array(dtype=wp.int64), slot_bits: int, slot_keys: wp.array(dtype=wp.int64),
                  slot_block: wp.array(dtype=int), counts: wp.array(dtype=int)):
    """Rebuild of the table: block b's key into a slot that points at b."""
    b = wp.tid()
    s = claim_slot(slot_keys, block_key[b], slot_bits, counts)
    if s >= 0:
        slot_block[s] = b
