"""A truncated signed distance volume of bounded memory: depth maps in, a coloured mesh and surface points out.

Sparse: only 8^3-voxel blocks near a surface exist. A depth map's blocks are found by a kernel (the rays'
truncation bands), claimed in a hash table on the device, and given blocks from a pool that grows up to
``FusionConfig.max_blocks``; past the cap, the blocks no depth map has touched for longest are dropped, so
memory stays flat over a run of any length. Voxel sums are fixed point (``dense.warp.tsdf``): ``deintegrate``
takes a map out exactly, which is how a keyframe moved by bundle adjustment is re-fused.

A map is fused without the host waiting for the device (``TsdfVolume``'s docstring says how); the host looks at
the block counts when the next map comes.

Meshing runs on the host: the blocks are assembled into dense chunks of 8^3 blocks (with a one-voxel apron
from their neighbours) and contoured with VTK's flying edges; vertices whose cell touches an unobserved voxel
are dropped, so the mesh has no skin where the volume knows nothing. Each chunk's piece is kept, and an
extraction contours again only the chunks that maps touched since the last one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pyvista as pv

from lapreco_hil.config import FusionConfig
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.geometry import inv_T
from lapreco_hil.warp_device import device_lock, init_warp

log = logging.getLogger(__name__)

CHUNK_BLOCKS = 8  # a meshing chunk is 8^3 blocks (64^3 voxels)
VOXEL_BYTES = 20  # int32 weight, int32 weight x tsdf, 3 x int32 weight x colour
FIRST_CAPACITY = 1024  # blocks in the pool at first; it grows by half (or as needed) up to max_blocks
# threads of the voxel update, striding over the active blocks' voxels (about two per core of a large GPU)
INTEGRATE_THREADS = 1 << 18


@dataclass
class VolumeStats:
    integrations: int = 0
    deintegrations: int = 0
    evicted_blocks: int = 0  # dropped at the cap, oldest first
    unallocated_blocks: int = 0  # a depth map needed more blocks than the cap holds: those parts not fused
    refilled_blocks: int = 0  # blocks a map found no room for at first, fused once the pool had grown
    peak_blocks: int = 0
    # host work that costs on a GPU: kernel launches and copies issued, and waits for the device (a read-back
    # or an event); the steady state of ``integrate`` is 4 launches, 4 copies and one wait on the map before
    launches: int = 0
    copies: int = 0
    waits: int = 0
    meshed_chunks: int = 0  # chunks the last extraction contoured (the others were kept from before)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class TsdfVolume:
    """``integrate`` / ``deintegrate`` depth maps (their own K and T_world_camera) with a colour image of the
    same view; ``extract_mesh`` / ``extract_points``. ``device``: a Warp device ("cpu", "cuda:0").

    A map's integration is queued on the device without waiting for it: its inputs go up through pinned
    buffers, its blocks are claimed, allocated and updated by three kernels that read the block counts on the
    device, and the counts come back asynchronously. They are looked at when the next map comes (or a read-out
    asks): the pool then grows (or drops its oldest blocks at the cap) ahead of the next map, and the blocks a
    map found no room for are fused into the grown pool from its inputs, still on the device."""

    def __init__(self, config: FusionConfig, device: str = "cpu") -> None:
        self.wp = init_warp()
        from lapreco_hil.dense.warp import tsdf as kernels

        self.k = kernels
        self.config = config
        self.device = str(self.wp.get_device(device))
        self.is_cuda = self.device.startswith("cuda")
        self.voxel_m = float(config.voxel_m)
        self.trunc_m = float(config.truncation_voxels * config.voxel_m)
        self.max_blocks = int(config.max_blocks)
        self.slot_bits = max(4, int(np.ceil(np.log2(2 * self.max_blocks))))  # load factor <= 1/2
        self.stats = VolumeStats()
        self._stamp = 0
        self._born = 0  # integrations so far: a block remembers the one that allocated it
        self.n_blocks = 0  # blocks in use as of the last look at the counts
        self._max_new = 0  # the most blocks one map claimed: the room kept free ahead of the next map
        self._pending = None  # the last map queued and not looked at yet (its parameters; inputs in the buffers)
        self._event = None
        self._inputs_shape = None
        self._mesh_cache = None  # (min_weight, {chunk: its mesh piece}) of the last extraction
        self._meshed_stamp = 0
        wp = self.wp
        with device_lock(self.device):
            n_slots = 1 << self.slot_bits
            self.slot_keys = wp.full(n_slots, kernels.EMPTY, dtype=wp.int64, device=self.device)
            self.slot_block = wp.full(n_slots, -1, dtype=int, device=self.device)
            self.slot_stamp = wp.zeros(n_slots, dtype=int, device=self.device)
            self.counts = wp.zeros(kernels.N_COUNTS, dtype=int, device=self.device)
            self.counts_host = wp.zeros(kernels.N_COUNTS, dtype=int, device="cpu", pinned=self.is_cuda)
            self._allocate_pool(min(FIRST_CAPACITY, self.max_blocks))

    def _launch(self, kernel, dim, inputs) -> None:
        self.wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)
        self.stats.launches += 1

    def _read(self, array) -> np.ndarray:
        """A device array on the host (a wait for the device on CUDA)."""
        self.stats.waits += int(self.is_cuda)
        return array.numpy()

    # --- memory ---------------------------------------------------------------------------------------------
    def _allocate_pool(self, capacity: int) -> None:
        wp, n = self.wp, capacity * self.k.BLOCK_VOXELS
        self.capacity = capacity
        self.w_sum = wp.zeros(n, dtype=wp.int32, device=self.device)
        self.d_sum = wp.zeros(n, dtype=wp.int32, device=self.device)
        self.c_sum = wp.zeros(n, dtype=wp.vec3i, device=self.device)
        self.block_key = wp.zeros(capacity, dtype=wp.int64, device=self.device)
        self.block_born = wp.zeros(capacity, dtype=int, device=self.device)
        self.block_used = wp.zeros(capacity, dtype=int, device=self.device)
        self.active = wp.zeros(capacity, dtype=int, device=self.device)

    @property
    def memory_bytes(self) -> int:
        """Device memory held: the block pool and the hash table."""
        return self.capacity * (self.k.BLOCK_VOXELS * VOXEL_BYTES + 8 + 4 + 4 + 4) + (1 << self.slot_bits) * 16

    def _set_pool_count(self, n: int) -> None:
        self.n_blocks = n
        counts = np.zeros(self.k.N_COUNTS, np.int32)
        counts[self.k.COUNT_POOL] = n
        self.counts.assign(counts)
        self.stats.copies += 1

    def _rebuild(self, keep: np.ndarray, capacity: int) -> None:
        """The pool with only blocks ``keep`` (in that order, indices into the current pool), ``capacity``
        blocks large, and the hash table rebuilt for them."""
        wp, k = self.wp, self.k
        keys = self._read(self.block_key)[keep]
        born = self._read(self.block_born)[keep]
        used = self._read(self.block_used)[keep]
        old_w, old_d, old_c = self.w_sum, self.d_sum, self.c_sum
        self._allocate_pool(capacity)
        if len(keep):
            order = wp.array(keep.astype(np.int32), dtype=int, device=self.device)
            self._launch(k.gather_blocks, len(keep) * k.BLOCK_VOXELS,
                         [order, old_w, old_d, old_c, self.w_sum, self.d_sum, self.c_sum])
            self.block_key.assign(np.concatenate([keys, np.zeros(capacity - len(keep), np.int64)]))
            self.block_born.assign(np.concatenate([born, np.zeros(capacity - len(keep), np.int32)]))
            self.block_used.assign(np.concatenate([used, np.zeros(capacity - len(keep), np.int32)]))
        self.slot_keys.fill_(k.EMPTY)
        self.slot_block.fill_(-1)
        self.slot_stamp.zero_()
        if len(keep):
            self._launch(k.insert_blocks, len(keep), [self.block_key, self.slot_bits, self.slot_keys,
                                                     self.slot_block, self.counts])
        if len(keep) < self.n_blocks:
            self._mesh_cache = None  # blocks dropped: their chunks' pieces must go too
        self._set_pool_count(len(keep))

    def _occupied(self) -> np.ndarray:
        """Per block in use: how many of its voxels hold weight."""
        wp = self.wp
        out = wp.zeros(max(self.n_blocks, 1), dtype=int, device=self.device)
        if self.n_blocks:
            self._launch(self.k.block_weights, self.n_blocks * self.k.BLOCK_VOXELS, [self.n_blocks, self.w_sum, out])
        return self._read(out)[:self.n_blocks]

    def _make_room(self, needed: int) -> None:
        """Room in the pool for ``needed`` more blocks: grow it (up to the cap), else drop empty blocks and then
        the ones unused for longest (never one the last map touched)."""
        total = self.n_blocks + needed
        if total <= self.capacity:
            return
        stamped = (self._read(self.slot_stamp) == self._stamp)
        slot_block = self._read(self.slot_block)
        protected = np.zeros(self.n_blocks, bool)
        protected[slot_block[stamped & (slot_block >= 0) & (slot_block < self.n_blocks)]] = True
        if self.capacity < self.max_blocks:
            capacity = min(self.max_blocks, max(total, self.capacity + self.capacity // 2))  # by half: less idle pool
            self._rebuild(np.arange(self.n_blocks), capacity)
            if total <= self.capacity:
                return
        keep = (self._occupied() > 0) | protected  # an empty block this map touches would only be claimed again
        used = self._read(self.block_used)[:self.n_blocks]
        excess = int(keep.sum()) + needed - self.max_blocks
        if excess > 0:
            # a margin of an eighth of the cap, so the next maps do not each pay for a rebuild
            candidates = np.flatnonzero(keep & ~protected)
            excess = min(excess + self.max_blocks // 8, len(candidates))
            drop = candidates[np.argsort(used[candidates], kind="stable")[:excess]]
            keep[drop] = False
            self.stats.evicted_blocks += len(drop)
            log.debug("fusion: %d blocks dropped at the cap of %d", len(drop), self.max_blocks)
        self._rebuild(np.flatnonzero(keep), self.capacity)

    def _settle(self) -> None:
        """Look at the counts of the last map queued (waiting for it, which by the next keyframe has long
        finished): the blocks in use, and the blocks it found no room for, fused now into a grown pool while its
        inputs are still in the buffers (exactly what the first pass would have added)."""
        last, self._pending = self._pending, None
        if last is None:
            return
        k = self.k
        if self._event is not None:
            self.wp.synchronize_event(self._event)
        self.stats.waits += int(self.is_cuda)
        counts = np.array(self.counts_host.numpy())
        n_used, refused = int(counts[k.COUNT_POOL]), int(counts[k.COUNT_REFUSED])
        self.n_blocks = min(n_used, self.capacity)
        if last["insert"]:
            self._max_new = max(self._max_new, int(counts[k.COUNT_NEW]))
        if refused:
            self._set_pool_count(self.n_blocks)  # the refused blocks' pool indices were counted past the end
            if self.capacity < self.max_blocks or self.n_blocks > 0:
                self._make_room(refused)
                self._stamp += 1
                self._queue(last, only_new=True)
                self._pending = None
                self.wp.synchronize_device(self.device)
                counts = np.array(self.counts.numpy())
                self.stats.waits += int(self.is_cuda)
                self.stats.refilled_blocks += int(counts[k.COUNT_ACTIVE])
                refused = int(counts[k.COUNT_REFUSED])
                self.n_blocks = min(int(counts[k.COUNT_POOL]), self.capacity)
                if refused:
                    self._set_pool_count(self.n_blocks)
            if refused:
                self.stats.unallocated_blocks += refused
                log.debug("fusion: %d blocks of a depth map found no room under the cap", refused)
        self.stats.peak_blocks = max(self.stats.peak_blocks, self.n_blocks)

    def _reserve(self) -> None:
        """Room for the next map ahead of it: as many free blocks as a map has claimed at most so far (the pool
        grows, or drops its oldest blocks at the cap)."""
        needed = max(self._max_new, 1)
        if self.n_blocks + needed > self.capacity:
            self._make_room(needed)

    # --- fusion ---------------------------------------------------------------------------------------------
    def _upload(self, depth: DepthMap, colour: np.ndarray | None) -> None:
        """The map's depth, confidence and colour into the device buffers (through pinned host buffers on
        CUDA, so the copies are asynchronous); arrays already on this device are copied device to device."""
        import cv2

        wp = self.wp
        h, w = depth.depth_m.shape
        if self._inputs_shape != (h, w):
            self._inputs_shape = (h, w)
            self.in_depth = wp.zeros((h, w), dtype=wp.float32, device=self.device)
            self.in_conf = wp.zeros((h, w), dtype=wp.float32, device=self.device)
            self.in_colour = wp.zeros((h, w, 3), dtype=wp.uint8, device=self.device)
            self.in_weight = wp.zeros((h, w), dtype=wp.int32, device=self.device)
            self.in_depth_q = wp.zeros((h, w), dtype=wp.uint16, device=self.device)
            self.in_conf_q = wp.zeros((h, w), dtype=wp.uint8, device=self.device)
            if self.is_cuda:
                self.stage = [wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
                              for a in (self.in_depth, self.in_conf, self.in_colour)]
        if colour is None:
            colour = np.full((h, w, 3), 200, np.uint8)
        elif not isinstance(colour, wp.array) and colour.shape[:2] != (h, w):
            colour = cv2.resize(colour, (w, h), interpolation=cv2.INTER_AREA)
        for i, (dst, src) in enumerate(((self.in_depth, depth.depth_m), (self.in_conf, depth.confidence),
                                        (self.in_colour, colour))):
            if isinstance(src, wp.array):
                wp.copy(dst, src)
            elif self.is_cuda:
                np.copyto(self.stage[i].numpy(), src, casting="unsafe")
                wp.copy(dst, self.stage[i])
            else:
                np.copyto(dst.numpy(), src, casting="unsafe")
                continue
            self.stats.copies += 1

    def integrate(self, depth: DepthMap, colour: np.ndarray | None = None, weight_scale: float = 1.0,
                  quantise: tuple[float, int] | None = None) -> int:
        """Fuse one depth map (weighted by its confidence x ``weight_scale``) with its view's colour (RGB uint8,
        resized to the map where the sizes differ). ``depth.depth_m`` / ``confidence`` / ``colour`` may be
        Warp arrays on the volume's device (a depth map made there: nothing goes through the host).
        ``quantise`` (depth step in metres, confidence steps): the map is quantised on the device as it will be
        kept, and fused so; ``quantised_map`` gives the quantised map back (a kept map fused again with the same
        ``quantise`` gives the same integers). Returns the map's integration number, which ``deintegrate``
        needs to take it out again."""
        with device_lock(self.device):
            self._settle()
            self._reserve()
            self._born += 1
            self._apply(depth, colour, weight_scale, sign=1, born_limit=-1, quantise=quantise)
            self.stats.integrations += 1
            if self.stats.integrations == 1:
                self._settle()  # the first map sets how much room to keep ahead (_max_new)
            return self._born

    def deintegrate(self, depth: DepthMap, colour: np.ndarray | None = None, weight_scale: float = 1.0,
                    integration: int | None = None, quantise: tuple[float, int] | None = None) -> None:
        """Take out a map integrated before, with the same map, colour, pose, weight and ``quantise`` (the exact
        inverse). ``integration`` (what ``integrate`` returned) keeps blocks dropped at the cap and allocated
        again later from being charged for it; None: every block the map touches."""
        with device_lock(self.device):
            self._settle()
            self._apply(depth, colour, weight_scale, sign=-1,
                        born_limit=self._born if integration is None else int(integration), quantise=quantise)
            self.stats.deintegrations += 1

    def quantised_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The last map integrated with ``quantise``, as quantised on the device: (depth steps (H, W) uint16,
        confidence steps (H, W) uint8). Waits for the device."""
        with device_lock(self.device):
            self.stats.waits += int(self.is_cuda)
            return self.in_depth_q.numpy().copy(), self.in_conf_q.numpy().copy()

    def _apply(self, depth: DepthMap, colour, weight_scale: float, sign: int, born_limit: int,
               quantise: tuple[float, int] | None = None) -> None:
        self._upload(depth, colour)
        K = np.asarray(depth.K, float)
        T = np.asarray(depth.T_world_camera, float)
        steps = (0.0, 0.0) if quantise is None else (float(np.float32(1.0) / np.float32(quantise[0])),
                                                      float(quantise[1]))
        self._stamp += 1
        self._queue({"insert": sign > 0, "sign": sign, "weight_scale": float(weight_scale), "born": self._born,
                     "born_limit": born_limit, "K": K, "T": T, "steps": steps}, only_new=False)

    def _queue(self, job: dict, only_new: bool) -> None:
        """The map in the input buffers through the three kernels, with no wait; its counts come back
        asynchronously (``_settle`` looks at them)."""
        wp, k = self.wp, self.k
        K, T = job["K"], job["T"]
        Tcw = inv_T(T)
        intr = wp.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        h, w = self._inputs_shape
        insert = int(job["insert"])
        # (a refill runs it again on the map already quantised in place: the same integers)
        self._launch(k.prepare_map, (h, w), [self.in_depth, self.in_conf, job["weight_scale"], *job["steps"],
                                             self.in_weight, self.in_depth_q, self.in_conf_q, self.counts])
        self._launch(k.touch_blocks, (h, w), [self.in_depth, self.in_weight, intr,
                                              wp.mat33(*T[:3, :3].astype(np.float32).ravel()),
                                              wp.vec3(*T[:3, 3].astype(np.float32)), self.trunc_m, self.voxel_m, 1,
                                              insert, self._stamp, self.slot_bits, self.slot_keys, self.slot_stamp,
                                              self.counts])
        self._launch(k.collect_blocks, 1 << self.slot_bits,
                     [self.slot_keys, self.slot_stamp, self.slot_block, self._stamp, insert, int(only_new),
                      job["born"], job["born_limit"], self.capacity, self.block_key, self.block_born,
                      self.block_used, self.counts, self.active])
        # a fixed number of threads striding over the active blocks' voxels: the count stays on the device
        threads = min(self.capacity * k.BLOCK_VOXELS, INTEGRATE_THREADS)
        self._launch(k.integrate_voxels, threads,
                     [threads, self.active, self.counts, self.block_key, self.in_depth, self.in_weight,
                      self.in_colour, intr, wp.mat33(*Tcw[:3, :3].astype(np.float32).ravel()),
                      wp.vec3(*Tcw[:3, 3].astype(np.float32)), self.trunc_m, self.voxel_m, int(job["sign"]),
                      self.w_sum, self.d_sum, self.c_sum])
        wp.copy(self.counts_host, self.counts)
        self.stats.copies += 1
        if self.is_cuda:
            self._event = wp.get_stream(self.device).record_event()
        self._pending = job

    # --- read-out -------------------------------------------------------------------------------------------
    def blocks(self, min_weight: float = 0.0, indices: np.ndarray | None = None):
        """The blocks holding weight, sorted by key: (keys (N,), weight (N, 8, 8, 8) in confidence units,
        tsdf (N, 8, 8, 8) in [-1, 1] (NaN where the weight is at most ``min_weight``), colour (N, 8, 8, 8, 3)
        float RGB). Voxel (i, j, k) of a block is x = i, y = j, z = k, stored [k, j, i]. ``indices``: only
        these blocks of the pool (gathered on the device, so only they are copied to the host)."""
        wp, bv = self.wp, self.k.BLOCK_VOXELS
        with device_lock(self.device):
            self._settle()
            keys = self._read(self.block_key)[:self.n_blocks].copy()
            if indices is None:
                n, src = self.n_blocks, (self.w_sum, self.d_sum, self.c_sum)
            else:
                indices = np.asarray(indices, np.int64)
                n, keys = len(indices), keys[indices]
                src = (wp.zeros(max(n, 1) * bv, dtype=wp.int32, device=self.device),
                       wp.zeros(max(n, 1) * bv, dtype=wp.int32, device=self.device),
                       wp.zeros(max(n, 1) * bv, dtype=wp.vec3i, device=self.device))
                if n:
                    order = wp.array(indices.astype(np.int32), dtype=int, device=self.device)
                    self._launch(self.k.gather_blocks, n * bv, [order, self.w_sum, self.d_sum, self.c_sum, *src])
            w = self._read(src[0])[:n * bv].reshape(n, 8, 8, 8).copy()
            d = src[1].numpy()[:n * bv].reshape(n, 8, 8, 8).copy()
            c = src[2].numpy()[:n * bv].reshape(n, 8, 8, 8, 3).copy()
        held = (w != 0).reshape(n, bv).any(axis=1)  # (an empty volume: n = 0)
        order = np.argsort(keys[held], kind="stable")
        keys, w, d, c = keys[held][order], w[held][order], d[held][order], c[held][order]
        weight = w / self.k.W_SCALE
        with np.errstate(invalid="ignore", divide="ignore"):
            tsdf = np.where(weight > min_weight, d / np.maximum(w, 1) / self.k.TSDF_SCALE, np.nan)
            colour = c / np.maximum(w, 1)[..., None]
        return keys, weight, tsdf.astype(np.float32), colour.astype(np.float32)

    def raw_blocks(self) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Each block holding weight: key -> (weight, weight x tsdf, weight x colour) as stored (fixed point)."""
        with device_lock(self.device):
            self._settle()
            n, bv = self.n_blocks, self.k.BLOCK_VOXELS
            keys = self.block_key.numpy()[:n]
            w = self.w_sum.numpy()[:n * bv].reshape(n, bv)
            d = self.d_sum.numpy()[:n * bv].reshape(n, bv)
            c = self.c_sum.numpy()[:n * bv].reshape(n, bv, 3)
            return {int(keys[i]): (w[i].copy(), d[i].copy(), c[i].copy()) for i in range(n) if w[i].any()}

    @property
    def blocks_in_use(self) -> int:
        with device_lock(self.device):
            self._settle()
            return self.n_blocks

    def extract_mesh(self, min_weight: float | None = None) -> pv.PolyData:
        """The zero level set as a triangle mesh (metres, world frame) with per-vertex "RGB" (uint8) and
        "Normals" (unit, pointing out of the surface towards the cameras).

        Incremental: each meshing chunk's piece is kept, and only the chunks holding (or bordering) a block
        that a map touched since the last extraction are read from the device and contoured again; dropping
        blocks at the cap, or another ``min_weight``, meshes everything again."""
        min_weight = self.config.mesh_min_weight if min_weight is None else min_weight
        with device_lock(self.device):
            self._settle()
            n = self.n_blocks
            keys = self._read(self.block_key)[:n]
            used = self._read(self.block_used)[:n]
            if self._mesh_cache is None or self._mesh_cache[0] != min_weight:
                self._mesh_cache = (min_weight, {})
                changed = np.ones(n, bool)
            else:
                changed = used > self._meshed_stamp
            self._meshed_stamp = self._stamp
            pieces = self._mesh_cache[1]
            contributes = chunk_membership(keys)  # (block, chunk) pairs: its own chunk and the aprons it fills
            dirty = {tuple(c) for b, c in contributes if changed[b]}
            selected = sorted({b for b, c in contributes if tuple(c) in dirty})
            self.stats.meshed_chunks = len(dirty)
            if not dirty:
                return join_pieces(list(pieces.values()), self.voxel_m)
            bkeys, _, tsdf, colour = self.blocks(min_weight, indices=np.array(selected, np.int64))
        for c in dirty:
            pieces.pop(c, None)
        pieces.update(chunk_pieces(bkeys, tsdf, colour, self.voxel_m, only=dirty))
        return join_pieces(list(pieces.values()), self.voxel_m)

    def extract_points(self, min_weight: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Surface points: the zero crossings of the TSDF along voxel edges (the mesh's vertices), with their
        normals and colours: (points (N, 3) metres, normals (N, 3), colours (N, 3) uint8)."""
        mesh = self.extract_mesh(min_weight)
        if mesh.n_points == 0:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        return (np.asarray(mesh.points, float), np.asarray(mesh.point_data["Normals"], float),
                np.asarray(mesh.point_data["RGB"], np.uint8))


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Block coordinates (N, 3) of packed keys (dense.warp.tsdf.pack_key)."""
    from lapreco_hil.dense.warp.tsdf import KEY_BITS, KEY_MASK, KEY_OFFSET

    keys = np.asarray(keys, np.int64)
    return np.stack([((keys >> (2 * KEY_BITS)) & KEY_MASK) - KEY_OFFSET, ((keys >> KEY_BITS) & KEY_MASK) - KEY_OFFSET,
                     (keys & KEY_MASK) - KEY_OFFSET], axis=1)


def chunk_membership(keys: np.ndarray) -> list[tuple[int, tuple]]:
    """(block index, chunk) for each meshing chunk a block fills: its own, and the apron (index CHUNK_BLOCKS)
    of the chunks before it along the axes where it is the chunk's first block: marching cubes needs the voxel
    layer just past a chunk's last."""
    if len(keys) == 0:
        return []
    S = CHUNK_BLOCKS
    coords = unpack_keys(keys)
    chunk = np.floor_divide(coords, S)
    local = coords - chunk * S
    out = []
    for o in np.ndindex(2, 2, 2):
        o = np.array(o)
        sel = np.flatnonzero(np.all((o == 0) | (local == 0), axis=1))
        out.extend(zip(sel.tolist(), map(tuple, (chunk[sel] - o).tolist())))
    return out


def mesh_blocks(keys: np.ndarray, tsdf: np.ndarray, colour: np.ndarray, voxel_m: float) -> pv.PolyData:
    """Marching cubes (VTK flying edges) over blocks (``TsdfVolume.blocks``: tsdf NaN where unobserved),
    chunk by chunk; the chunks' seams are welded."""
    return join_pieces(list(chunk_pieces(keys, tsdf, colour, voxel_m).values()), voxel_m)


def chunk_pieces(keys: np.ndarray, tsdf: np.ndarray, colour: np.ndarray, voxel_m: float,
                 only: set | None = None) -> dict:
    """Each chunk's mesh piece (None where it has no surface) by VTK's flying edges; ``only``: these chunks."""
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    if len(keys) == 0:
        return {c: None for c in only or ()}
    B, S = 8, CHUNK_BLOCKS
    coords = unpack_keys(keys)
    chunk = np.floor_divide(coords, S)
    local = coords - chunk * S
    pieces = {}
    for b, c in chunk_membership(keys):
        if only is None or c in only:
            pieces.setdefault(c, []).append((b, tuple(local[b] + S * (chunk[b] - np.array(c)))))
    n = S * B + 1
    out = {c: None for c in only or ()}
    for c, members in pieces.items():
        if all(max(pos) == S for _, pos in members):
            continue  # only aprons: the chunk itself is empty
        grid_t = np.full((S * B + B,) * 3, np.nan, np.float32)
        grid_c = np.zeros((S * B + B,) * 3 + (3,), np.float32)
        for b, (li, lj, lk) in members:
            grid_t[lk * B:(lk + 1) * B, lj * B:(lj + 1) * B, li * B:(li + 1) * B] = tsdf[b]
            grid_c[lk * B:(lk + 1) * B, lj * B:(lj + 1) * B, li * B:(li + 1) * B] = colour[b]
        grid_t, grid_c = grid_t[:n, :n, :n], grid_c[:n, :n, :n]
        observed = np.isfinite(grid_t)
        if not observed.any() or np.nanmin(grid_t) > 0 or np.nanmax(grid_t) < 0:
            continue
        # in voxel units from integer origins: a seam vertex comes out bit for bit the same from both chunks
        image = pv.ImageData(dimensions=(n, n, n), spacing=(1.0, 1.0, 1.0), origin=tuple(np.array(c) * S * B))
        image.point_data["tsdf"] = np.where(observed, grid_t, 1.0).ravel()  # [z, y, x] in C order: x fastest
        image.point_data["observed"] = observed.astype(np.float32).ravel()
        image.point_data["colour"] = grid_c.reshape(-1, 3)
        alg = vtkFlyingEdges3D()
        alg.SetInputData(image)
        alg.SetInputArrayToProcess(0, 0, 0, 0, "tsdf")
        alg.SetValue(0, 0.0)
        alg.SetComputeNormals(True)
        alg.SetComputeScalars(False)
        alg.InterpolateAttributesOn()
        alg.Update()
        piece = pv.wrap(alg.GetOutput())
        if piece.n_cells == 0:
            continue
        # a vertex on an edge to an unobserved voxel has "observed" < 1: its triangles are no surface
        triangles = piece.faces.reshape(-1, 4)  # flying edges makes triangles only
        bad = np.asarray(piece.point_data["observed"]) < 0.999
        triangles = triangles[~bad[triangles[:, 1:]].any(axis=1)]
        if len(triangles):
            kept = pv.PolyData(np.asarray(piece.points), triangles.ravel())
            for name in ("Normals", "colour"):
                kept.point_data[name] = np.asarray(piece.point_data[name])
            out[c] = kept
    return out


def join_pieces(pieces: list, voxel_m: float) -> pv.PolyData:
    """The chunks' pieces (vertices in voxel units) as one mesh in metres: seams welded, "RGB" uint8 and unit
    "Normals" out of the surface; vertices no kept triangle uses are let go."""
    meshes = [p for p in pieces if p is not None]
    if not meshes:
        return pv.PolyData()
    points = np.concatenate([np.asarray(m.points, np.float32) for m in meshes])
    normals = np.concatenate([np.asarray(m.point_data["Normals"], float) for m in meshes])
    colour = np.concatenate([np.asarray(m.point_data["colour"], float) for m in meshes])
    offsets = np.cumsum([0] + [m.n_points for m in meshes[:-1]])
    triangles = np.concatenate([m.faces.reshape(-1, 4)[:, 1:] + o for m, o in zip(meshes, offsets)])
    # a seam vertex is computed by both chunks from the same two voxels at the same integer coordinates: equal
    # bits, so an exact match welds them
    rows = np.ascontiguousarray(points).view(np.dtype((np.void, 12))).ravel()
    _, first_all, inverse_all = np.unique(rows, return_index=True, return_inverse=True)
    welded = first_all[inverse_all.ravel()][triangles]
    # a vertex on a voxel's corner (tsdf exactly 0) is shared by its edges: their triangles collapse to nothing
    triangles = triangles[(welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2]) &
                          (welded[:, 0] != welded[:, 2])]
    used = np.zeros(len(points), bool)
    used[triangles.ravel()] = True
    _, first, inverse = np.unique(rows[used], return_index=True, return_inverse=True)
    remap = np.full(len(points), -1, np.int64)
    remap[np.flatnonzero(used)] = inverse.ravel()
    keep = np.flatnonzero(used)[first]
    tri = remap[triangles]
    out = pv.PolyData((points[keep].astype(float) + 0.5) * voxel_m,
                      np.hstack([np.full((len(tri), 1), 3), tri]).ravel())
    # VTK's contour normals follow the gradient's negative; the TSDF grows towards the cameras
    n = -normals[keep]
    out.point_data["RGB"] = np.clip(np.round(colour[keep]), 0, 255).astype(np.uint8)
    out.point_data["Normals"] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return out
