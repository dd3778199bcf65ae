"""A truncated signed distance volume of bounded memory: depth maps in, a coloured mesh and surface points out.

Sparse: only 8^3-voxel blocks near a surface exist. A depth map's blocks are found by a kernel (the rays'
truncation bands), claimed in a hash table on the device, and given blocks from a pool that grows up to
``FusionConfig.max_blocks``; past the cap, the blocks no depth map has touched for longest are dropped, so
memory stays flat over a run of any length. Voxel sums are fixed point (``dense.warp.tsdf``): ``deintegrate``
takes a map out exactly, which is how a keyframe moved by bundle adjustment is re-fused.

Meshing runs on the host: the blocks are assembled into dense chunks of 8^3 blocks (with a one-voxel apron
from their neighbours) and contoured with VTK's flying edges; vertices whose cell touches an unobserved voxel
are dropped, so the mesh has no skin where the volume knows nothing.
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
FIRST_CAPACITY = 1024  # blocks in the pool at first; it doubles up to max_blocks


@dataclass
class VolumeStats:
    integrations: int = 0
    deintegrations: int = 0
    evicted_blocks: int = 0  # dropped at the cap, oldest first
    unallocated_blocks: int = 0  # a depth map needed more blocks than the cap holds: those parts not fused
    peak_blocks: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class TsdfVolume:
    """``integrate`` / ``deintegrate`` depth maps (their own K and T_world_camera) with a colour image of the
    same view; ``extract_mesh`` / ``extract_points``. ``device``: a Warp device ("cpu", "cuda:0")."""

    def __init__(self, config: FusionConfig, device: str = "cpu") -> None:
        self.wp = init_warp()
        from lapreco_hil.dense.warp import tsdf as kernels

        self.k = kernels
        self.config = config
        self.device = str(self.wp.get_device(device))
        self.voxel_m = float(config.voxel_m)
        self.trunc_m = float(config.truncation_voxels * config.voxel_m)
        self.max_blocks = int(config.max_blocks)
        self.slot_bits = max(4, int(np.ceil(np.log2(2 * self.max_blocks))))  # load factor <= 1/2
        self.stats = VolumeStats()
        self._stamp = 0
        self._born = 0  # integrations so far: a block remembers the one that allocated it
        self.n_blocks = 0
        wp = self.wp
        with device_lock(self.device):
            n_slots = 1 << self.slot_bits
            self.slot_keys = wp.full(n_slots, kernels.EMPTY, dtype=wp.int64, device=self.device)
            self.slot_block = wp.full(n_slots, -1, dtype=int, device=self.device)
            self.slot_stamp = wp.zeros(n_slots, dtype=int, device=self.device)
            self.n_new = wp.zeros(1, dtype=int, device=self.device)
            self.counters = wp.zeros(3, dtype=int, device=self.device)
            self._allocate_pool(min(FIRST_CAPACITY, self.max_blocks))

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

    def _rebuild(self, keep: np.ndarray, capacity: int) -> None:
        """The pool with only blocks ``keep`` (in that order, indices into the current pool), ``capacity``
        blocks large, and the hash table rebuilt for them."""
        wp, k = self.wp, self.k
        keys = self.block_key.numpy()[keep]
        born = self.block_born.numpy()[keep]
        used = self.block_used.numpy()[keep]
        old_w, old_d, old_c = self.w_sum, self.d_sum, self.c_sum
        self._allocate_pool(capacity)
        if len(keep):
            order = wp.array(keep.astype(np.int32), dtype=int, device=self.device)
            wp.launch(k.gather_blocks, dim=len(keep) * k.BLOCK_VOXELS,
                      inputs=[order, old_w, old_d, old_c, self.w_sum, self.d_sum, self.c_sum], device=self.device)
            self.block_key.assign(np.concatenate([keys, np.zeros(capacity - len(keep), np.int64)]))
            self.block_born.assign(np.concatenate([born, np.zeros(capacity - len(keep), np.int32)]))
            self.block_used.assign(np.concatenate([used, np.zeros(capacity - len(keep), np.int32)]))
        self.slot_keys.fill_(k.EMPTY)
        self.slot_block.fill_(-1)
        self.slot_stamp.zero_()
        self.n_new.zero_()
        if len(keep):
            wp.launch(k.insert_blocks, dim=len(keep), inputs=[self.block_key, self.slot_bits, self.slot_keys,
                                                               self.slot_block, self.n_new], device=self.device)
        self.n_blocks = len(keep)

    def _occupied(self) -> np.ndarray:
        """Per block in use: how many of its voxels hold weight."""
        wp = self.wp
        out = wp.zeros(max(self.n_blocks, 1), dtype=int, device=self.device)
        if self.n_blocks:
            wp.launch(self.k.block_weights, dim=self.n_blocks * self.k.BLOCK_VOXELS,
                      inputs=[self.n_blocks, self.w_sum, out], device=self.device)
        return out.numpy()[:self.n_blocks]

    def _make_room(self, needed: int) -> None:
        """Room in the pool for ``needed`` more blocks: grow it (up to the cap), else drop empty blocks and then
        the ones unused for longest (never one the map being fused touches)."""
        total = self.n_blocks + needed
        if total <= self.capacity:
            return
        stamped = (self.slot_stamp.numpy() == self._stamp)
        slot_block = self.slot_block.numpy()
        protected = np.zeros(self.n_blocks, bool)
        protected[slot_block[stamped & (slot_block >= 0) & (slot_block < self.n_blocks)]] = True
        if self.capacity < self.max_blocks:
            capacity = min(self.max_blocks, max(total, 2 * self.capacity))
            self._rebuild(np.arange(self.n_blocks), capacity)
            if total <= self.capacity:
                return
        keep = (self._occupied() > 0) | protected  # an empty block this map touches would only be claimed again
        used = self.block_used.numpy()[:self.n_blocks]
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

    # --- fusion ---------------------------------------------------------------------------------------------
    def _inputs(self, depth: DepthMap, colour: np.ndarray | None, weight_scale: float):
        import cv2

        wp = self.wp
        h, w = depth.depth_m.shape
        weight = np.floor(np.clip(np.nan_to_num(depth.confidence), 0.0, 1.0) * weight_scale * self.k.W_SCALE + 0.5)
        weight = np.minimum(weight, self.k.W_MAX).astype(np.int32)
        d = np.nan_to_num(np.asarray(depth.depth_m, np.float32))
        if colour is None:
            colour = np.full((h, w, 3), 200, np.uint8)
        elif colour.shape[:2] != (h, w):
            colour = cv2.resize(colour, (w, h), interpolation=cv2.INTER_AREA)
        K = np.asarray(depth.K, float)
        intr = wp.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        T = np.asarray(depth.T_world_camera, float)
        Tcw = inv_T(T)
        return (wp.array(d, dtype=wp.float32, device=self.device),
                wp.array(weight, dtype=wp.int32, device=self.device),
                wp.array(np.ascontiguousarray(colour, np.uint8), dtype=wp.uint8, device=self.device), intr,
                wp.mat33(*T[:3, :3].astype(np.float32).ravel()), wp.vec3(*T[:3, 3].astype(np.float32)),
                wp.mat33(*Tcw[:3, :3].astype(np.float32).ravel()), wp.vec3(*Tcw[:3, 3].astype(np.float32)))

    def integrate(self, depth: DepthMap, colour: np.ndarray | None = None, weight_scale: float = 1.0) -> int:
        """Fuse one depth map (weighted by its confidence x ``weight_scale``) with its view's colour (RGB uint8,
        resized to the map where the sizes differ). Returns the map's integration number, which
        ``deintegrate`` needs to take it out again."""
        with device_lock(self.device):
            self._born += 1
            self._apply(depth, colour, weight_scale, sign=1, born_limit=-1)
            self.stats.integrations += 1
            return self._born

    def deintegrate(self, depth: DepthMap, colour: np.ndarray | None = None, weight_scale: float = 1.0,
                    integration: int | None = None) -> None:
        """Take out a map integrated before, with the same map, colour, pose and weight (the exact inverse).
        ``integration`` (what ``integrate`` returned) keeps blocks dropped at the cap and allocated again later
        from being charged for it; None: every block the map touches."""
        with device_lock(self.device):
            self._apply(depth, colour, weight_scale, sign=-1,
                        born_limit=self._born if integration is None else int(integration))
            self.stats.deintegrations += 1

    def _apply(self, depth: DepthMap, colour, weight_scale: float, sign: int, born_limit: int) -> None:
        wp, k = self.wp, self.k
        d, weight, col, intr, R_wc, t_wc, R_cw, t_cw = self._inputs(depth, colour, weight_scale)
        h, w = depth.depth_m.shape
        insert = 1 if sign > 0 else 0
        self._stamp += 1

        def touch():
            self.n_new.zero_()
            wp.launch(k.touch_blocks, dim=(h, w), inputs=[d, weight, intr, R_wc, t_wc, self.trunc_m, self.voxel_m,
                                                          1, insert, self._stamp, self.slot_bits, self.slot_keys,
                                                          self.slot_stamp, self.n_new], device=self.device)
            return int(self.n_new.numpy()[0])

        needed = touch()
        if needed and self.n_blocks + needed > self.capacity:
            self._make_room(needed)
            self._stamp += 1
            touch()  # the rebuilt table: claim this map's blocks again (as many: the ones it touched were kept)
        self.counters.assign(np.array([self.n_blocks, 0, 0], np.int32))
        wp.launch(k.collect_blocks, dim=1 << self.slot_bits,
                  inputs=[self.slot_keys, self.slot_stamp, self.slot_block, self._stamp, insert, self._born,
                          born_limit, self.capacity, self.block_key, self.block_born, self.block_used, self.counters,
                          self.active], device=self.device)
        n_used, n_active, refused = (int(v) for v in self.counters.numpy())
        self.n_blocks = min(n_used, self.capacity)
        self.stats.unallocated_blocks += refused
        self.stats.peak_blocks = max(self.stats.peak_blocks, self.n_blocks)
        if refused:
            log.debug("fusion: %d blocks of a depth map found no room under the cap", refused)
        if n_active:
            wp.launch(k.integrate_voxels, dim=n_active * k.BLOCK_VOXELS,
                      inputs=[self.active, self.block_key, d, weight, col, intr, R_cw, t_cw, self.trunc_m,
                              self.voxel_m, int(sign), self.w_sum, self.d_sum, self.c_sum], device=self.device)

    # --- read-out -------------------------------------------------------------------------------------------
    def blocks(self, min_weight: float = 0.0):
        """The blocks holding weight, sorted by key: (keys (N,), weight (N, 8, 8, 8) in confidence units,
        tsdf (N, 8, 8, 8) in [-1, 1] (NaN where the weight is at most ``min_weight``), colour (N, 8, 8, 8, 3)
        float RGB). Voxel (i, j, k) of a block is x = i, y = j, z = k, stored [k, j, i]."""
        with device_lock(self.device):
            n, bv = self.n_blocks, self.k.BLOCK_VOXELS
            keys = self.block_key.numpy()[:n].copy()
            w = self.w_sum.numpy()[:n * bv].reshape(n, 8, 8, 8).copy()
            d = self.d_sum.numpy()[:n * bv].reshape(n, 8, 8, 8).copy()
            c = self.c_sum.numpy()[:n * bv].reshape(n, 8, 8, 8, 3).copy()
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
            n, bv = self.n_blocks, self.k.BLOCK_VOXELS
            keys = self.block_key.numpy()[:n]
            w = self.w_sum.numpy()[:n * bv].reshape(n, bv)
            d = self.d_sum.numpy()[:n * bv].reshape(n, bv)
            c = self.c_sum.numpy()[:n * bv].reshape(n, bv, 3)
            return {int(keys[i]): (w[i].copy(), d[i].copy(), c[i].copy()) for i in range(n) if w[i].any()}

    @property
    def blocks_in_use(self) -> int:
        return self.n_blocks

    def extract_mesh(self, min_weight: float | None = None) -> pv.PolyData:
        """The zero level set as a triangle mesh (metres, world frame) with per-vertex "RGB" (uint8) and
        "Normals" (unit, pointing out of the surface towards the cameras)."""
        min_weight = self.config.mesh_min_weight if min_weight is None else min_weight
        keys, _, tsdf, colour = self.blocks(min_weight)
        return mesh_blocks(keys, tsdf, colour, self.voxel_m)

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


def mesh_blocks(keys: np.ndarray, tsdf: np.ndarray, colour: np.ndarray, voxel_m: float) -> pv.PolyData:
    """Marching cubes (VTK flying edges) over blocks (``TsdfVolume.blocks``: tsdf NaN where unobserved),
    chunk by chunk; the chunks' seams are welded."""
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    if len(keys) == 0:
        return pv.PolyData()
    B, S = 8, CHUNK_BLOCKS
    coords = unpack_keys(keys)
    chunk = np.floor_divide(coords, S)
    local = coords - chunk * S
    # each block fills its own chunk, and the apron (index S) of the chunks before it along the axes where it
    # is the first block: marching cubes needs the voxel layer just past a chunk's last
    pieces = {}
    for o in np.ndindex(2, 2, 2):
        o = np.array(o)
        sel = np.all((o == 0) | (local == 0), axis=1)
        for b in np.flatnonzero(sel):
            c = tuple(chunk[b] - o)
            pieces.setdefault(c, []).append((b, tuple(local[b] + S * o)))
    n = S * B + 1
    meshes = []
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
        image = pv.ImageData(dimensions=(n, n, n), spacing=(voxel_m,) * 3,
                             origin=tuple((np.array(c) * S * B + 0.5) * voxel_m))
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
            meshes.append(kept)
    if not meshes:
        return pv.PolyData()
    # the chunks' seam vertices are computed twice (the same voxels, origins that round apart): welded here;
    # vertices no triangle kept are let go
    mesh = pv.merge(meshes, merge_points=False).clean(tolerance=1e-3 * voxel_m, absolute=True)
    normals = np.asarray(mesh.point_data["Normals"], float)
    # VTK's contour normals follow the gradient's negative; the TSDF grows towards the cameras
    normals = -normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    out = pv.PolyData(np.asarray(mesh.points, float), mesh.faces)
    out.point_data["RGB"] = np.clip(np.round(np.asarray(mesh.point_data["colour"])), 0, 255).astype(np.uint8)
    out.point_data["Normals"] = normals
    return out
