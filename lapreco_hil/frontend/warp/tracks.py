"""Track bookkeeping on the device: which tracks survive a frame, their compaction into the next buffers, the
live count and whether to detect, the new tracks' commit, and the frame's results packed for the host."""

from __future__ import annotations

import warp as wp

from lapreco_hil.frontend.warp.sampling import in_view

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})

RESULT_HEADER = 3  # [count, n_new, n_tracked] before the ids in pack_results' integer buffer


@wp.kernel
def _lk_keep(pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
             count: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    """Without the drift check: keep what LK tracked into the field of view."""
    f = wp.tid()
    if f >= count[0]:
        keep[f] = 0
        return
    keep[f] = wp.where(status[f] == 1 and in_view(mask, pts[f]), 1, 0)


@wp.kernel
def _scatter_tracks(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32),
                    src_pts: wp.array(dtype=wp.vec2), before: wp.array(dtype=wp.vec2), src_A: wp.array(dtype=wp.mat22),
                    src_patches: wp.array2d(dtype=float), src_ids: wp.array(dtype=wp.int32),
                    dst_pts: wp.array(dtype=wp.vec2), dst_steps: wp.array(dtype=wp.vec2),
                    dst_A: wp.array(dtype=wp.mat22), dst_patches: wp.array2d(dtype=float),
                    dst_ids: wp.array(dtype=wp.int32)):
    """Compaction on the device: a kept track moves to its slot (exclusive prefix sum of the keep flags), with
    its step in this frame (from ``before``, its position in the previous frame)."""
    t, k = wp.tid()
    if keep[t] == 0:
        return
    s = slot[t]
    dst_patches[s, k] = src_patches[t, k]
    if k == 0:
        dst_pts[s] = src_pts[t]
        dst_steps[s] = src_pts[t] - before[t]
        dst_A[s] = src_A[t]
        dst_ids[s] = src_ids[t]


@wp.kernel
def _scatter_rescue(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32),
                    src_state: wp.array(dtype=wp.int32), src_patches: wp.array2d(dtype=float),
                    dst_state: wp.array(dtype=wp.int32), dst_patches: wp.array2d(dtype=float)):
    """The rescue's per-track state (``drift_check.TRACK_*``, first patch on the smoothed image) compacted as
    ``_scatter_tracks`` compacts the others."""
    t, k = wp.tid()
    if keep[t] == 0:
        return
    s = slot[t]
    dst_patches[s, k] = src_patches[t, k]
    if k == 0:
        dst_state[s] = src_state[t]


@wp.kernel
def _count_kept(keep: wp.array(dtype=wp.int32), slot: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                redetect_below: int, detect: wp.array(dtype=wp.int32), n_new: wp.array(dtype=wp.int32)):
    """After the compaction: the live count, whether to look for new corners, and no new tracks yet."""
    last = keep.shape[0] - 1
    c = slot[last] + keep[last]
    count[0] = c
    detect[0] = wp.where(c < redetect_below, 1, 0)
    n_new[0] = 0


@wp.kernel
def _count_tracked(pts: wp.array(dtype=wp.vec2), status: wp.array(dtype=wp.int32), mask: wp.array2d(dtype=wp.uint8),
                   count: wp.array(dtype=wp.int32), n_tracked: wp.array(dtype=wp.int32)):
    """The funnel's count of tracks LK followed into the field of view (before the drift check)."""
    f = wp.tid()
    if f < count[0] and status[f] == 1 and in_view(mask, pts[f]):
        wp.atomic_add(n_tracked, 0, 1)


@wp.kernel
def _pack_results(pts: wp.array(dtype=wp.vec2), ids: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                  n_new: wp.array(dtype=wp.int32), n_tracked: wp.array(dtype=wp.int32),
                  remap: wp.array2d(dtype=wp.vec2), out_f: wp.array(dtype=wp.vec4), out_i: wp.array(dtype=wp.int32)):
    """The frame's results in two buffers, so two copies bring them to the host: per track (x, y, source x,
    source y) and [count, n_new, n_tracked, ids...]. The source is where the track lies in the distorted frame
    (the undistortion map, sampled bilinearly at its position): the host reads the track's colour there."""
    t = wp.tid()
    if t == 0:
        out_i[0] = count[0]
        out_i[1] = n_new[0]
        out_i[2] = n_tracked[0]
    if t >= count[0]:
        return
    h = remap.shape[0]
    w = remap.shape[1]
    p = pts[t]
    x = wp.clamp(p[0], 0.0, float(w - 1))
    y = wp.clamp(p[1], 0.0, float(h - 1))
    x0 = wp.min(int(x), w - 2)
    y0 = wp.min(int(y), h - 2)
    fx = x - float(x0)
    fy = y - float(y0)
    top = remap[y0, x0] * (1.0 - fx) + remap[y0, x0 + 1] * fx
    bot = remap[y0 + 1, x0] * (1.0 - fx) + remap[y0 + 1, x0 + 1] * fx
    src = top * (1.0 - fy) + bot * fy
    out_f[t] = wp.vec4(p[0], p[1], src[0], src[1])
    out_i[RESULT_HEADER + t] = ids[t]


@wp.kernel
def _commit_new_tracks(taken: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                       n_new: wp.array(dtype=wp.int32), next_id: wp.array(dtype=wp.int32)):
    n = taken[0]
    count[0] = count[0] + n
    next_id[0] = next_id[0] + n
    n_new[0] = n


# --- host wrappers: a device and preallocated outputs --------------------------------------------------------
def lk_keep(pts: wp.array, status: wp.array, mask: wp.array, count: wp.array, keep: wp.array, device) -> None:
    """``keep`` <- LK's verdict and the field-of-view test (without the drift check)."""
    wp.launch(_lk_keep, dim=keep.shape[0], inputs=[pts, status, mask, count, keep], device=device)


def compact_tracks(keep: wp.array, slot: wp.array, src_pts: wp.array, before: wp.array, src_A: wp.array,
                   src_patches: wp.array, src_ids: wp.array, dst_pts: wp.array, dst_steps: wp.array,
                   dst_A: wp.array, dst_patches: wp.array, dst_ids: wp.array, device) -> None:
    """The kept tracks moved to the front of the destination buffers, in order (``slot``: scratch for their
    exclusive prefix sum), with their steps in this frame."""
    wp.utils.array_scan(keep, slot, inclusive=False)
    wp.launch(_scatter_tracks, dim=(keep.shape[0], src_patches.shape[1]), inputs=[
        keep, slot, src_pts, before, src_A, src_patches, src_ids, dst_pts, dst_steps, dst_A, dst_patches, dst_ids],
        device=device)


def compact_rescue(keep: wp.array, slot: wp.array, src_state: wp.array, src_patches: wp.array,
                   dst_state: wp.array, dst_patches: wp.array, device) -> None:
    """After ``compact_tracks`` (its ``slot``): the kept tracks' rescue state moved as their other arrays were."""
    wp.launch(_scatter_rescue, dim=(keep.shape[0], src_patches.shape[1]),
              inputs=[keep, slot, src_state, src_patches, dst_state, dst_patches], device=device)


def count_kept(keep: wp.array, slot: wp.array, count: wp.array, redetect_below: int, detect: wp.array,
               n_new: wp.array, device) -> None:
    """After ``compact_tracks``: ``count`` <- the live tracks, ``detect`` <- whether to look for new corners."""
    wp.launch(_count_kept, dim=1, inputs=[keep, slot, count, redetect_below, detect, n_new], device=device)


def commit_new_tracks(taken: wp.array, count: wp.array, n_new: wp.array, next_id: wp.array, device) -> None:
    """The ``taken[0]`` new tracks join the live ones (count, next id, n_new)."""
    wp.launch(_commit_new_tracks, dim=1, inputs=[taken, count, n_new, next_id], device=device)


def count_tracked(pts: wp.array, status: wp.array, mask: wp.array, count: wp.array, n_tracked: wp.array,
                  device) -> None:
    """``n_tracked[0]`` <- the tracks LK followed into the field of view."""
    n_tracked.zero_()
    wp.launch(_count_tracked, dim=pts.shape[0], inputs=[pts, status, mask, count, n_tracked], device=device)


def pack_results(pts: wp.array, ids: wp.array, count: wp.array, n_new: wp.array, n_tracked: wp.array,
                 remap: wp.array, out_f: wp.array, out_i: wp.array, device) -> None:
    """The frame's results into ``out_f`` (x, y, source x, source y per track) and ``out_i`` ([count, n_new,
    n_tracked, ids...]), for two copies to the host."""
    wp.launch(_pack_results, dim=pts.shape[0], inputs=[pts, ids, count, n_new, n_tracked, remap, out_f, out_i],
              device=device)
