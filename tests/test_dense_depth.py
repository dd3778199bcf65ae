"""Depth maps by multi-view stereo (lapreco_hil.dense.depth) on keyframes rendered by the simulator's own
renderer, against its true depth, and on the Hamlyn phantom's real stereo pair. Warp's CPU device by default; the
same tests run on CUDA with LAPRECO_TEST_DEVICE=cuda:0."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from lapreco_hil.config import DepthConfig
from lapreco_hil.dense.types import KeyframeView
from lapreco_hil.errors import ConfigError, ReconstructionError

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")
SWEEP = DepthConfig(method="sweep")  # the plane sweep (the pipeline's default is "patchmatch" since session 17)
SIZE = (256, 192)
HAMLYN = Path(__file__).parent / "data" / "hamlyn-phantom-stereo"


@pytest.fixture(scope="module")
def sheet(warp_cpu):
    """Five keyframes of a wavy textured sheet at 75 mm (the reference, four 6 mm aside) and their true depths."""
    from lapreco_hil.bench.dense import sheet_keyframes

    return sheet_keyframes(SIZE, 5, DEVICE)


@pytest.fixture(scope="module")
def sheet_maps(sheet):
    from lapreco_hil.dense.depth import compute_depths

    return compute_depths(sheet[0], SWEEP, DEVICE)


def _errors_mm(depth_map, truth):
    kept = depth_map.valid & (truth > 0)
    return np.abs(depth_map.depth_m[kept] - truth[kept]) * 1e3


def test_depth_on_a_textured_surface_is_sub_millimetre_and_dense(sheet, sheet_maps):
    views, truths = sheet
    for kf_id, depth_map in sheet_maps.items():
        err = _errors_mm(depth_map, truths[kf_id])
        funnel = depth_map.stats["funnel"]
        # measured on the CPU: medians 0.13-0.16 mm at 70-80 mm, none beyond 5 mm, 88-93% of the textured pixels
        assert np.median(err) < 0.25, kf_id
        assert np.mean(err > 5.0) <= 0.005, kf_id
        assert np.mean(err > 1.0) <= 0.02, kf_id
        assert funnel["geometry_agrees"] >= 0.8 * funnel["textured"], funnel
        assert funnel["geometry_agrees"] == np.count_nonzero(depth_map.valid)
        assert np.all((depth_map.confidence > 0) == depth_map.valid)
        assert depth_map.K is not None and np.allclose(depth_map.T_world_camera, views[kf_id].T_world_camera)
        assert set(depth_map.stats["times_ms"]) >= {"prepare_ms", "coarse_sweep_ms", "fine_sweep_ms", "checks_ms"}


def test_the_geometric_check_drops_depths_the_sources_contradict(sheet, warp_cpu):
    """Forward-backward through the sources' depth maps: a source map that says the surface is 10% farther
    everywhere confirms nothing; the sources' true maps confirm almost everything."""
    from lapreco_hil.dense.depth import DepthEstimator
    from lapreco_hil.dense.types import DepthMap

    views, truths = sheet
    estimator = DepthEstimator(SWEEP, DEVICE)
    depth_map = estimator.compute(views[0], views[1:])
    true_maps = [DepthMap(v.kf_id, truths[v.kf_id], np.ones_like(truths[v.kf_id]), v.K, v.T_world_camera)
                 for v in views[1:]]
    wrong_maps = [dataclasses.replace(m, depth_m=m.depth_m * 1.1) for m in true_maps]
    kept = np.count_nonzero(depth_map.valid)
    assert np.count_nonzero(estimator.check_geometry(depth_map, true_maps).valid) >= 0.95 * kept
    assert np.count_nonzero(estimator.check_geometry(depth_map, wrong_maps).valid) == 0
    # the same check inside compute, for the sources whose maps are given
    given = {m.kf_id: m for m in wrong_maps[:2]}
    checked = estimator.compute(views[0], views[1:], source_depths=given)
    assert checked.stats["geometric_sources"] == [1, 2]
    assert checked.stats["funnel"]["geometry_agrees"] == np.count_nonzero(checked.valid) == 0
    checked = estimator.compute(views[0], views[1:], source_depths={m.kf_id: m for m in true_maps})
    assert checked.stats["funnel"]["geometry_agrees"] >= 0.95 * checked.stats["funnel"]["supported"]


@pytest.mark.parametrize("radius, near_share, same_depth_share", [(3, 0.95, 0.995), (2, 0.9, 0.98)])
def test_the_sliding_and_the_windowed_sweep_give_the_same_depth_map(sheet, warp_cpu, radius, near_share,
                                                                   same_depth_share):
    """The CPU's window sums (sliding along rows, then columns) and CUDA's (each window row from its taps, slid
    down a band of rows) are the same sums in another order: the ZNCC volumes agree to float rounding (the
    variance's cancellation makes it about 1e-3 on the faintest windows), and so do the depth maps. Radius 3
    (7x7, the default) runs the windowed sweep's ring kernel, 2 its general one (a 5x5 window's variance cancels
    more: 92% of its fine scores agree within 1e-4, all within 4e-3, and 98.3% of its depths within 0.01 mm)."""
    from lapreco_hil.dense.depth import DepthEstimator

    views, truths = sheet
    maps, volumes = {}, {}
    for sweep in ("sliding", "windowed"):
        estimator = DepthEstimator(DepthConfig(method="sweep", window_radius_px=radius), DEVICE, sweep=sweep)
        maps[sweep] = estimator.compute(views[0], views[1:])
        planes = maps[sweep].stats["planes"]
        volumes[sweep] = (estimator.coarse.zncc.numpy()[:, :planes].copy(), estimator.fine.zncc.numpy().copy())
        assert estimator.sweep == sweep
    for level in (0, 1):
        a, b = volumes["sliding"][level], volumes["windowed"][level]
        scored = (a > -1.5) & (b > -1.5)
        # the same windows have a score but for the few at the texture threshold, where rounding decides
        assert np.mean((a > -1.5) != (b > -1.5)) < 1e-3 * np.mean(scored)
        # (on CUDA, fused multiply-adds move the faintest few further: 0.0145 at most measured on the H100)
        diff = np.abs(a - b)[scored]
        assert np.quantile(diff, 0.9999) < 5e-3 and diff.max() < 0.03
        assert np.mean(np.abs(a - b)[scored] < 1e-4) > near_share
    a, b = maps["sliding"], maps["windowed"]
    both = a.valid & b.valid
    assert np.count_nonzero(a.valid != b.valid) <= 0.002 * np.count_nonzero(a.valid)
    diff = np.abs(a.depth_m[both] - b.depth_m[both])
    # a parabola through nearly equal scores moves the most, by a fraction of a plane (at 75 mm)
    assert diff.max() < 0.5e-3 and np.mean(diff < 0.01e-3) > same_depth_share and np.median(diff) < 1e-6
    with pytest.raises(ConfigError, match="sweep 'tiles'"):
        DepthEstimator(SWEEP, DEVICE, sweep="tiles")


def _select_plane_reference(zncc, k, min_scored):
    """select_plane's rule written plainly (numpy, per pixel): a plane's score is the mean of its k best sources
    (NO_SCORE with fewer than k scored), the best plane with a parabola through its neighbours, the highest local
    maximum apart from the best plane and its neighbours."""
    n_src, n_planes, h, w = zncc.shape
    plane, best, second = (np.zeros((h, w), np.float32) for _ in range(3))
    for y in range(h):
        for x in range(w):
            c = np.full(n_planes, -2.0, np.float32)
            for p in range(n_planes):
                z = np.sort(zncc[:, p, y, x])[::-1][:k]
                if np.all(z > -1.5):
                    c[p] = np.float32(np.float32(z.sum(dtype=np.float32)) / np.float32(k))
            b = int(np.argmax(c)) if np.any(c > -2.0) else -1
            best[y, x] = c[b] if b >= 0 else -2.0
            if np.count_nonzero(c > -1.5) < min_scored:
                b = -1
            padded = np.concatenate([[-2.0], c, [-2.0]])
            maxima = [p for p in range(n_planes) if c[p] > -2.0 and c[p] >= padded[p] and c[p] >= padded[p + 2]
                      and (p < b - 1 or p > b + 1)]
            second[y, x] = max((c[p] for p in maxima), default=-2.0)
            plane[y, x] = b
            if 0 < b < n_planes - 1 and c[b - 1] > -1.5 and c[b + 1] > -1.5:
                den = c[b - 1] - 2.0 * c[b] + c[b + 1]
                if den < -1e-6:
                    plane[y, x] += np.clip(0.5 * (c[b - 1] - c[b + 1]) / den, -0.5, 0.5)
    return plane, best, second


@pytest.mark.parametrize("k", [1, 2, 3])
def test_select_plane_keeps_the_best_plane_and_the_highest_other_local_maximum(warp_cpu, k):
    """select_plane reads each score once and keeps only the four highest local maxima: on scores with ties,
    plateaus and unscored planes it finds what the plain rule does."""
    import warp as wp

    from lapreco_hil.dense.warp import plane_sweep as kernels

    rng = np.random.default_rng(k)
    n_src, n_planes, h, w = 4, 12, 6, 40
    zncc = np.round(rng.uniform(-1.0, 1.0, (n_src, n_planes, h, w)), 1).astype(np.float32)  # ties and plateaus
    zncc[rng.random(zncc.shape) < 0.2] = kernels.NO_SCORE
    arrays = [wp.array(zncc, device=DEVICE)] + [wp.zeros((h, w), dtype=float, device=DEVICE) for _ in range(3)]
    wp.launch(kernels.select_plane, dim=(h, w), device=DEVICE,
              inputs=[arrays[0], n_src, n_planes, k, 5] + arrays[1:])
    expected = _select_plane_reference(zncc, k, 5)
    for got, want in zip(arrays[1:], expected):
        np.testing.assert_allclose(got.numpy(), want, atol=1e-6)
    assert np.any(expected[2] > -2.0) and np.any(expected[0] > 0)


def test_a_keyframe_is_prepared_once_and_again_when_its_image_changes(sheet, warp_cpu):
    """The estimator keeps prepared views by kf_id: the maps are those of a fresh estimator, a keyframe's image
    is prepared once however often it is a source, a changed image under the same kf_id is prepared again, and
    more keyframes than the cache holds push out the least recently used."""
    from lapreco_hil.dense.depth import FUNNEL, DepthEstimator

    views, _ = sheet
    estimator = DepthEstimator(dataclasses.replace(SWEEP, cached_views=5), DEVICE)
    first = estimator.compute(views[0], views[1:])
    assert first.stats["prepared"] == [0, 1, 2, 3, 4]
    again = estimator.compute(views[0], views[1:])
    assert again.stats["prepared"] == []
    # the same image in other arrays (a keyframe decoded again): its fingerprint tells it is prepared already
    copies = [dataclasses.replace(v, colour=v.colour.copy(), mask=v.mask.copy()) for v in views[1:]]
    assert estimator.compute(views[0], copies).stats["prepared"] == []
    assert np.array_equal(again.depth_m, first.depth_m) and np.array_equal(again.confidence, first.confidence)
    assert again.stats["funnel"] == first.stats["funnel"]
    # the funnel is counted on the device: the same as counting the codes here
    counts = np.bincount(estimator.rejection_codes().ravel(), minlength=len(FUNNEL))
    assert again.stats["funnel"] == {name: int(counts[i:].sum()) for i, name in enumerate(FUNNEL[:-1])}

    # a source whose image changed (the same kf_id): prepared again, and the map is a fresh estimator's
    shifted = dataclasses.replace(views[2], colour=np.roll(views[2].colour, 3, axis=1))
    changed = estimator.compute(views[0], [views[1], shifted, views[3], views[4]])
    assert changed.stats["prepared"] == [2]
    fresh = DepthEstimator(SWEEP, DEVICE).compute(views[0], [views[1], shifted, views[3], views[4]])
    assert np.array_equal(changed.depth_m, fresh.depth_m)
    assert not np.array_equal(changed.depth_m, first.depth_m)

    # another reference among the same keyframes prepares nothing; a sixth keyframe pushes out the least
    # recently used (cached_views=5)
    assert estimator.compute(views[1], [views[0], views[3]]).stats["prepared"] == []
    extra = dataclasses.replace(views[4], kf_id=9)
    assert estimator.compute(views[0], [views[1], extra]).stats["prepared"] == [9]
    assert estimator.compute(views[0], [views[1], shifted]).stats["prepared"] == [2]  # pushed out by 9
    estimator.forget(0)
    assert estimator.compute(views[0], [views[1], shifted]).stats["prepared"] == [0]
    with pytest.raises(ReconstructionError, match="repeat"):
        estimator.compute(views[0], [views[1], views[1]])
    with pytest.raises(ReconstructionError, match="its own source"):
        estimator.compute(views[0], [views[1], dataclasses.replace(views[0], T_world_camera=views[2].T_world_camera)])


def test_a_depth_map_handed_out_is_never_overwritten(sheet, warp_cpu):
    """Depth maps come out in the estimator's own host buffers (page-locked from CUDA), reused only once no map
    refers to them: maps kept while more are computed (more than it keeps buffers) stay as they were."""
    from lapreco_hil.dense.depth import HOST_BUFFERS, DepthEstimator

    views, _ = sheet
    estimator = DepthEstimator(SWEEP, DEVICE)
    held = []
    for i in range(HOST_BUFFERS + 2):
        ref = views[i % len(views)]
        depth_map = estimator.compute(ref, [v for v in views if v is not ref])
        held.append((depth_map, depth_map.depth_m.copy(), depth_map.confidence.copy()))
    assert not np.array_equal(held[0][1], held[1][1])
    for depth_map, depth, confidence in held:
        assert np.array_equal(depth_map.depth_m, depth) and np.array_equal(depth_map.confidence, confidence)
    # a buffer no map refers to any more is the next map's (no allocation per map)
    held.clear()
    address = estimator.compute(views[0], views[1:]).depth_m.__array_interface__["data"][0]
    assert estimator.compute(views[1], views[2:]).depth_m.__array_interface__["data"][0] == address


def test_a_map_waits_for_the_device_once_and_counts_what_it_asks(sheet, warp_cpu):
    """A map's steps are queued and waited for once; a profile (a wait at each step's end) makes the same map.
    ``stats["device_ops"]`` counts what the device was asked: after the first map no allocation, the new
    reference's colour and the small parameters uploaded (the mask the views share is there already), the map
    and the funnel's counts read back in one wait; a map left on the device reads back the counts only."""
    from lapreco_hil.dense.depth import DEVICE_OPS, FUNNEL, DepthEstimator

    views, _ = sheet
    h, w = views[0].colour.shape[:2]
    estimator = DepthEstimator(SWEEP, DEVICE)
    first = estimator.compute(views[0], views[1:])
    ops = first.stats["device_ops"]
    assert set(ops) == set(DEVICE_OPS) and ops["allocations"] > 10 and not first.stats["profiled"]
    assert ops["uploads"] == 5 + 1 + 1  # five colours, the shared mask once, the parameters
    estimator.forget(0)
    steady = estimator.compute(views[0], views[1:])
    launches = 23 if estimator.sweep == "sliding" else 21  # (the windowed sweep sums a window in one launch)
    uploaded = h * w * 3 + 25 * 4 * 4  # the colour; A, b and the slot of 4 sources, float32 words
    assert steady.stats["device_ops"] == {
        "launches": launches, "uploads": 2, "uploaded_bytes": uploaded, "downloads": 2,
        "downloaded_bytes": 2 * h * w * 4 + len(FUNNEL) * 4, "synchronisations": 1, "allocations": 0}
    assert np.array_equal(steady.depth_m, first.depth_m) and np.array_equal(steady.confidence, first.confidence)

    estimator.profile = True
    estimator.forget(0)
    profiled = estimator.compute(views[0], views[1:])
    assert profiled.stats["profiled"] and profiled.stats["funnel"] == first.stats["funnel"]
    assert np.array_equal(profiled.depth_m, first.depth_m) and np.array_equal(profiled.confidence,
                                                                              first.confidence)
    steps = ("setup_ms", "prepare_ms", "coarse_sweep_ms", "fine_sweep_ms", "checks_ms", "download_ms")
    assert set(profiled.stats["times_ms"]) == set(steady.stats["times_ms"]) == {*steps, "total_ms"}
    assert profiled.stats["device_ops"] == dict(steady.stats["device_ops"], synchronisations=len(steps))
    estimator.profile = False

    kept = estimator.compute(views[0], views[1:], on_device=True)  # (every view cached: nothing prepared)
    assert kept.stats["device_ops"] == {
        "launches": launches - 5, "uploads": 1, "uploaded_bytes": 25 * 4 * 4, "downloads": 1,
        "downloaded_bytes": len(FUNNEL) * 4, "synchronisations": 1, "allocations": 0}
    np.testing.assert_array_equal(kept.depth_m.numpy(), first.depth_m)


def test_a_mask_is_uploaded_again_only_for_another_mask(sheet, warp_cpu):
    """The device keeps the last mask it was given: a view bringing the same array is prepared without it, one
    bringing another array (equal or not) or none gets its own, and every map is a fresh estimator's."""
    from lapreco_hil.dense.depth import DepthEstimator

    views, _ = sheet
    estimator = DepthEstimator(SWEEP, DEVICE)
    estimator.compute(views[0], views[1:])
    cut = views[0].mask.copy()
    cut[:, :60] = False
    for mask, uploads in ((views[0].mask.copy(), 3), (cut, 3), (cut, 2), (None, 2), (views[0].mask, 3)):
        ref = dataclasses.replace(views[0], mask=mask)
        estimator.forget(0)
        depth_map = estimator.compute(ref, views[1:])
        assert depth_map.stats["device_ops"]["uploads"] == uploads, mask is cut
        fresh = DepthEstimator(SWEEP, DEVICE).compute(ref, views[1:])
        assert np.array_equal(depth_map.depth_m, fresh.depth_m) and depth_map.stats["funnel"] == fresh.stats["funnel"]
        if mask is cut:
            assert not depth_map.valid[:, :60].any() and depth_map.valid[:, 60:].any()
        if mask is None:
            assert depth_map.stats["funnel"]["in_view"] == depth_map.depth_m.size


def test_an_estimators_maps_are_a_fresh_estimators_whatever_came_before(sheet, warp_cpu):
    """The estimator replays the launches it recorded, with each map's own values (depth range, planes, poses):
    maps made one after another by one estimator are those of a fresh estimator each."""
    from lapreco_hil.dense.depth import DepthEstimator

    views, truths = sheet
    near = float(np.percentile(truths[0][truths[0] > 0], 50))
    estimator = DepthEstimator(SWEEP, DEVICE)
    planes = set()
    for ref_i, depth_range in ((0, None), (0, (0.05, 0.12)), (2, None), (0, (near, 0.2)), (2, (0.03, 0.3))):
        ref = views[ref_i]
        if depth_range is not None:
            ref = dataclasses.replace(ref, depth_range_m=depth_range)
        sources = [v for v in views if v.kf_id != ref.kf_id][:3]
        kept = estimator.compute(ref, sources)
        fresh = DepthEstimator(SWEEP, DEVICE).compute(ref, sources)
        assert np.array_equal(kept.depth_m, fresh.depth_m) and np.array_equal(kept.confidence, fresh.confidence)
        assert kept.stats["funnel"] == fresh.stats["funnel"] and kept.stats["planes"] == fresh.stats["planes"]
        planes.add(kept.stats["planes"])
    assert len(planes) >= 3


def test_the_homography_terms_of_every_source_at_once_are_those_of_each_alone(sheet):
    """The plane homographies' terms, made for every source in one go, are bit for bit those of the formula one
    source at a time (source pixel ~ K_src R K_ref^-1 (x, y, 1) + rho K_src t), at both levels; and so is the
    largest image motion between the nearest and the farthest plane."""
    from lapreco_hil.dense.depth import _half_K, _homography_terms, _max_shift_px

    views, _ = sheet
    rng = np.random.default_rng(3)
    moved = [dataclasses.replace(v, K=v.K * rng.uniform(0.9, 1.1, (3, 3)) * [[1, 1, 1], [0, 1, 1], [0, 0, 0]]
                                 + np.diag([0, 0, 1.0])) for v in views]
    for ref, sources in ((views[0], views[1:]), (moved[2], [moved[0], moved[4], moved[1]])):
        (A_c, b_c), (A_f, b_f) = _homography_terms(ref, sources)
        for i, src in enumerate(sources):
            T = np.linalg.inv(np.asarray(src.T_world_camera, float)) @ np.asarray(ref.T_world_camera, float)
            R, t = T[:3, :3], T[:3, 3]
            for A, b, K_ref, K_src in ((A_c, b_c, _half_K(ref.K), _half_K(src.K)), (A_f, b_f, ref.K, src.K)):
                assert np.array_equal(A[i], K_src @ R @ np.linalg.inv(K_ref)) and np.array_equal(b[i], K_src @ t)
        xs, ys = np.meshgrid(np.linspace(0, 127, 5), np.linspace(0, 95, 5))
        pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        shifts = []
        for A, b in zip(A_c, b_c):
            lo, hi = A @ pts + 5.0 * b[:, None], A @ pts + 20.0 * b[:, None]
            shifts.append(np.max(np.hypot(*(hi[:2] / hi[2] - lo[:2] / lo[2]))))
        assert _max_shift_px(A_c, b_c, (128, 96), 5.0, 20.0) == max(shifts) > 1.0


def test_no_depth_outside_the_mask_nor_on_a_saturated_highlight(sheet, warp_cpu):
    from lapreco_hil.dense.depth import DepthEstimator, highlight_mask

    views, truths = sheet
    ref = views[0]
    mask = ref.mask.copy()
    mask[:, :60] = False  # a field of view cut on the left
    colour = ref.colour.copy()
    cv2.circle(colour, (170, 100), 12, (255, 255, 255), -1)  # a saturated specular highlight
    blob = np.zeros(mask.shape, np.uint8)
    cv2.circle(blob, (170, 100), 12, 1, -1)
    highlight = highlight_mask(colour, device=DEVICE)
    assert highlight[blob > 0].all() and np.count_nonzero(highlight) < 3 * np.count_nonzero(blob)
    assert not highlight_mask(ref.colour, device=DEVICE).any()  # the tissue's own colours are not highlights
    estimator = DepthEstimator(SWEEP, DEVICE)
    depth_map = estimator.compute(dataclasses.replace(ref, colour=colour, mask=mask), views[1:])
    assert not depth_map.valid[~mask].any()
    assert not depth_map.valid[highlight].any()
    assert np.count_nonzero(depth_map.valid[mask & ~highlight]) >= 0.85 * np.count_nonzero(mask & ~highlight)
    funnel = depth_map.stats["funnel"]
    assert funnel["in_view"] == np.count_nonzero(mask)
    assert funnel["in_view"] - funnel["not_highlight"] == np.count_nonzero(mask & highlight)
    # the same highlight in one source only: the best 2 of 4 sources score without it, so the reference keeps it
    spoilt = [dataclasses.replace(views[1], colour=colour)] + list(views[2:])
    kept = estimator.compute(ref, spoilt).valid
    assert np.count_nonzero(kept[blob > 0]) >= 0.8 * np.count_nonzero(blob)


def test_depth_outside_the_landmarks_range_is_dropped(sheet, warp_cpu):
    from lapreco_hil.dense.depth import compute_depth

    views, truths = sheet
    near = float(np.percentile(truths[0][truths[0] > 0], 50))
    # a sweep from the middle of the surface's depths outwards: the nearer half lies outside it
    depth_map = compute_depth(dataclasses.replace(views[0], depth_range_m=(near, 0.2)), views[1:], SWEEP,
                              DEVICE)
    nearer = (truths[0] > 0) & (truths[0] < near * 0.97)
    assert np.count_nonzero(depth_map.valid[nearer]) <= 0.02 * np.count_nonzero(nearer)
    funnel = depth_map.stats["funnel"]
    assert funnel["matched"] - funnel["in_range"] > 0.2 * np.count_nonzero(nearer)
    err = _errors_mm(depth_map, truths[0])
    assert np.median(err) < 0.25


def test_bad_input_is_a_clear_error(sheet, warp_cpu):
    from lapreco_hil.dense.depth import compute_depth

    views, _ = sheet
    small = dataclasses.replace(views[1], colour=views[1].colour[:100, :100])
    with pytest.raises(ReconstructionError, match="one size"):
        compute_depth(views[0], [small], SWEEP, DEVICE)
    with pytest.raises(ReconstructionError, match="at least one source"):
        compute_depth(views[0], [], SWEEP, DEVICE)
    with pytest.raises(ConfigError, match=r"\[depth\] min_planes"):
        compute_depth(views[0], views[1:], DepthConfig(method="sweep", min_planes=20, max_planes=10), DEVICE)


def _view(kf_id, eye_mm, target=(0.0, 0.0, 0.1), reference=None, size=(64, 48)):
    from lapreco_hil.geometry import make_T

    eye = np.asarray(eye_mm, float) * 1e-3
    z = np.asarray(target) - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    return KeyframeView(kf_id, np.zeros((size[1], size[0], 3), np.uint8), K,
                        make_T(np.column_stack([x, np.cross(z, x), z]), eye), depth_range_m=(0.08, 0.12),
                        reference=reference)


def test_choose_sources_prefers_a_useful_baseline_and_the_stereo_partner():
    from lapreco_hil.dense.depth import choose_sources

    ref = _view(0, (0, 0, 0))
    partner = _view(1, (1, 0, 0), reference=0)  # a stereo partner: its angle (0.6 deg) does not matter
    tiny = _view(2, (1.5, 0, 0))  # 0.9 deg: no depth resolution
    good = _view(3, (14, 0, 0))  # 8 deg
    fair = _view(4, (0, 30, 0))  # 17 deg
    wide = _view(5, (80, 0, 0))  # 39 deg: windows no longer look alike
    away = _view(6, (10, 0, 0), target=(0.3, 0.0, 0.1))  # looks elsewhere: no overlap
    chosen = choose_sources(ref, [ref, wide, fair, away, tiny, good, partner], 4)
    assert [v.kf_id for v in chosen] == [1, 3, 4]
    assert [v.kf_id for v in choose_sources(ref, [fair, good], 1)] == [3]
    # the partner's own reference keyframe is its partner
    assert [v.kf_id for v in choose_sources(partner, [ref, tiny], 2)] == [0]


@pytest.fixture(scope="module")
def instrument_scenes(warp_cpu):
    """The liver world with its instrument, five keyframes 0.6-1.2 s apart: the instrument where the simulator
    moves it at each keyframe's time, and (control) held still where it is at the reference's time."""
    from lapreco_hil.bench.dense import world_keyframes

    return {kind: world_keyframes("liver", SIZE, 5, DEVICE, instrument=kind) for kind in ("moving", "static")}


def test_a_moving_instrument_gets_no_depth(instrument_scenes):
    """Views taken at different times see the instrument in different places: no plane makes them agree, so the
    multi-view checks leave (almost) no depth on it; held still, the same instrument gets depth where it is not
    a highlight, so it is the motion that the checks reject, not its looks."""
    from lapreco_hil.dense.depth import compute_depths

    kept = {}
    for kind, (views, truths, tools) in instrument_scenes.items():
        maps = compute_depths(views, SWEEP, DEVICE)
        kept[kind] = sum(np.count_nonzero(maps[v.kf_id].valid & tools[v.kf_id]) for v in views if v.kf_id in maps)
        kept[kind + "_pixels"] = sum(np.count_nonzero(t) for t in tools)
        if kind == "moving":
            # the tissue around it keeps its depth and its accuracy
            err = np.concatenate([_errors_mm(maps[k], truths[k]) for k in maps])
            # (measured: median 0.22 mm, 0.7% beyond 5 mm)
            assert np.median(err) < 0.4 and np.mean(err > 5.0) < 0.015
    # measured: moving 0 of 9423 instrument pixels kept, static 107
    assert kept["moving"] <= 0.002 * kept["moving_pixels"], kept
    assert kept["static"] >= max(50, 20 * kept["moving"]), kept


def test_a_view_pair_with_a_moving_instrument_keeps_no_depth_on_it(instrument_scenes):
    """The reference with each other keyframe as a pair, each view against the other, then forward-backward
    through each other's maps. Two views cannot tell an instrument that moved along the epipolar line from a
    nearer one: measured 0, 27, 0 and 0 instrument pixels kept of 2096, 0.3% in all, and 2470-8300 tissue
    pixels per pair."""
    from lapreco_hil.dense.depth import DepthEstimator

    views, truths, tools = instrument_scenes["moving"]
    estimator = DepthEstimator(SWEEP, DEVICE)
    on_tool = 0
    for other in views[1:]:
        map_a, map_b = estimator.compute(views[0], [other]), estimator.compute(other, [views[0]])
        checked = estimator.check_geometry(map_a, [map_b])
        on_tool += np.count_nonzero(checked.valid & tools[0])
        assert np.count_nonzero(checked.valid & ~tools[0]) >= 2000  # the tissue keeps its depth
    assert on_tool <= 0.01 * len(views[1:]) * np.count_nonzero(tools[0])


def _hamlyn_pair():
    """The Hamlyn phantom's pair undistorted into the left camera's K (the right image resampled), its poses
    (metres), and the sparse points of LK matches checked forward-backward, triangulated in the left camera."""
    K_left = np.loadtxt(HAMLYN / "calib.left.intrinsic.txt")
    K_right = np.loadtxt(HAMLYN / "calib.right.intrinsic.txt")
    dist_left = np.loadtxt(HAMLYN / "calib.left.distortion.txt")
    dist_right = np.loadtxt(HAMLYN / "calib.right.distortion.txt")
    T_right_left = np.loadtxt(HAMLYN / "calib.l2r.4x4")
    T_right_left[:3, 3] *= 1e-3
    left = cv2.imread(str(HAMLYN / "f7_dynamic_deint_L_0100.png"))
    right = cv2.imread(str(HAMLYN / "f7_dynamic_deint_R_0100.png"))
    h, w = left.shape[:2]
    left = cv2.undistort(left, K_left, dist_left)
    map_x, map_y = cv2.initUndistortRectifyMap(K_right, dist_right, None, K_left, (w, h), cv2.CV_32FC1)
    right = cv2.remap(right, map_x, map_y, cv2.INTER_LINEAR)
    grey_l, grey_r = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY), cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
    corners = cv2.goodFeaturesToTrack(grey_l, 1000, 0.01, 5, blockSize=7)
    lk = dict(winSize=(21, 21), maxLevel=3)
    ahead, st, _ = cv2.calcOpticalFlowPyrLK(grey_l, grey_r, corners, None, **lk)
    back, st_back, _ = cv2.calcOpticalFlowPyrLK(grey_r, grey_l, ahead, None, **lk)
    ok = (st.ravel() == 1) & (st_back.ravel() == 1) & (np.linalg.norm(back - corners, axis=2).ravel() < 0.5)
    p_l, p_r = corners[ok].reshape(-1, 2).T, ahead[ok].reshape(-1, 2).T
    P_r = K_left @ T_right_left[:3]
    X = cv2.triangulatePoints(K_left @ np.eye(4)[:3], P_r, p_l, p_r)
    X = X[:3] / X[3]
    q = P_r @ np.vstack([X, np.ones(X.shape[1])])
    good = (X[2] > 0) & (np.linalg.norm(q[:2] / q[2] - p_r, axis=0) < 1.0)
    return left, right, K_left, T_right_left, X[:, good], p_l[:, good]


def _sgbm_left_points(left, right, K, T_right_left):
    """OpenCV's StereoSGBM on the rectified pair, its points taken back into the left camera: the pixels (u, v)
    they land on and their depths."""
    h, w = left.shape[:2]
    # (distortion as zeros and the translation as a column: OpenCV 5 refuses None and a flat vector here)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K, np.zeros(5), K, np.zeros(5), (w, h),
                                                np.ascontiguousarray(T_right_left[:3, :3]),
                                                T_right_left[:3, 3].reshape(3, 1).copy(), alpha=0)
    rect = [cv2.remap(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY),
                      *cv2.initUndistortRectifyMap(K, np.zeros(5), R, P, (w, h), cv2.CV_32FC1), cv2.INTER_LINEAR)
            for img, R, P in ((left, R1, P1), (right, R2, P2))]
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1)
    disparity = sgbm.compute(*rect).astype(np.float32) / 16.0
    points = cv2.reprojectImageTo3D(disparity, Q)[disparity > 0].T
    points = R1.T @ points  # rectified left camera -> left camera
    q = K @ points
    u, v = np.round(q[0] / q[2]).astype(int), np.round(q[1] / q[2]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (points[2] > 0)
    return u[inside], v[inside], points[2, inside]


def test_the_hamlyn_phantom_pair_gets_a_dense_consistent_depth_map(warp_cpu):
    """Real endoscope images of a smooth silicone heart, 5.5 mm baseline at about 63 mm. No ground truth comes
    with them: the depth map must agree with the pair's sparse triangulated points, with OpenCV's StereoSGBM on
    the rectified pair where both are confident, and with itself left to right. A narrow-baseline pair of smooth
    silicone takes a wider window (11x11) and a depth tolerance of about one pixel of disparity (3%)."""
    from lapreco_hil.dense.depth import DepthEstimator

    left, right, K, T_right_left, X, p_left = _hamlyn_pair()
    assert X.shape[1] >= 60
    depth_range = (float(np.percentile(X[2], 1)) * 0.9, float(np.percentile(X[2], 99)) * 1.1)
    view_l = KeyframeView(0, left[:, :, ::-1].copy(), K, np.eye(4), None, depth_range)
    view_r = KeyframeView(1, right[:, :, ::-1].copy(), K, np.linalg.inv(T_right_left), None, depth_range)
    # (best_k 1: the 11x11 window at both levels, as chosen here, is not grown for the one source)
    config = dataclasses.replace(SWEEP, window_radius_px=5, best_k=1, geometric_max_rel=0.03)
    estimator = DepthEstimator(config, DEVICE)
    map_l = estimator.compute(view_l, [view_r])
    map_r = estimator.compute(view_r, [view_l])
    checked = estimator.check_geometry(map_l, [map_r])
    funnel = checked.stats["funnel"]
    # measured: 58% of the textured pixels pass the photometric checks, 75% of those are supported and agree
    # left to right
    assert funnel["views_agree"] >= 0.5 * funnel["textured"], funnel
    assert funnel["geometry_agrees"] >= 0.65 * funnel["views_agree"], funnel

    # the sparse points (measured: median 0.42 mm, 78 of 95 with a depth)
    u = np.round(p_left).astype(int)
    dense_z = map_l.depth_m[u[1], u[0]]
    has = dense_z > 0
    assert has.sum() >= 0.7 * len(dense_z)
    assert np.median(np.abs(dense_z[has] - X[2, has])) < 0.6e-3

    # StereoSGBM on the rectified pair, its points taken back into the left camera (measured: median 0.48 mm,
    # 5.2% beyond 2 mm, over 41000 pixels; one pixel of disparity is 1.85 mm here)
    u, v, z = _sgbm_left_points(left, right, K, T_right_left)
    ours = map_l.depth_m[v, u]
    confident = (ours > 0) & (map_l.confidence[v, u] > 0.3)
    diff = np.abs(ours[confident] - z[confident])
    assert confident.sum() >= 20000
    assert np.median(diff) < 0.8e-3 and np.mean(diff > 2e-3) < 0.15


def test_the_kernels_compile_for_cuda(sm90_ptx):
    """CI has no GPU: the plane sweep's kernels still compile for an H100 (sm_90)."""
    from lapreco_hil.dense.warp import plane_sweep

    ptx = sm90_ptx(plane_sweep)
    assert ".entry" in ptx and "sweep_cols" in ptx and "warp_samples" in ptx and "sweep_window" in ptx


def test_the_bench_times_each_step_with_the_sources_cached_and_all_prepared(warp_cpu):
    from lapreco_hil.bench.dense import bench_depth, format_table

    result = bench_depth(DEVICE, (128, 96), 2, 1, scene="sheet", method="sweep")
    steps = {"setup_ms", "prepare_ms", "coarse_sweep_ms", "fine_sweep_ms", "checks_ms", "download_ms"}
    # the map as a mapper runs it (one wait: each step's host time), and the stepped profile
    assert set(result["steps_ms"]) == steps and set(result["cold_steps_ms"]) == steps
    assert set(result["host_steps_ms"]) == steps and result["total_ms"] > 0 and result["profiled_total_ms"] > 0
    assert result["device_ops"]["synchronisations"] == 1 and result["device_ops"]["allocations"] == 0
    assert "stepped profile" in format_table(result) and "launches" in format_table(result)
    assert result["sweep"] == ("sliding" if DEVICE == "cpu" else "windowed")
    assert result["accuracy"]["kept"] > 0.5 * result["funnel"]["textured"]
    assert bool(result["device_ms"]) == DEVICE.startswith("cuda")  # the GPU's own time per kernel and copy
    assert "every view prepared" in format_table(result)
    routes = result["fusion_routes"]  # the map fused from host inputs and from device inputs
    assert set(routes) == {"host_inputs", "device_inputs"}
    assert all(r["integrate_ms"] > 0 and r["total_ms"] >= r["integrate_ms"] for r in routes.values())
    assert "from host inputs" in format_table(result) and "from device inputs" in format_table(result)


def test_a_dense_surface_keeps_one_estimator_so_each_keyframe_is_prepared_once(sheet, warp_cpu):
    """The dense surface's depth function (``stereo_functions``) keeps its estimator: a keyframe prepared as one
    map's source is not prepared again as the next map's reference; a new config gets a new estimator."""
    from lapreco_hil.dense.surface import stereo_functions

    views, _ = sheet
    depth_fn, _, why = stereo_functions()
    assert why is None
    config = SWEEP
    assert depth_fn(views[0], views[1:3], config, DEVICE).stats["prepared"] == [0, 1, 2]
    assert depth_fn(views[1], [views[0], views[2]], config, DEVICE).stats["prepared"] == []
    assert depth_fn(views[1], [views[0]], dataclasses.replace(config, window_radius_px=2),
                    DEVICE).stats["prepared"] == [1, 0]


def test_a_map_left_on_the_device_fuses_into_the_same_volume_as_the_downloaded_one(sheet, warp_cpu):
    """``compute(on_device=True)`` leaves the map in the estimator's device buffers (only its funnel comes back),
    the reference's colour is the one its cached view holds there, and the volume fuses both with no host trip:
    the same integers as the map downloaded and fused from the host."""
    import warp as wp

    from lapreco_hil.config import FusionConfig
    from lapreco_hil.dense.depth import DepthEstimator
    from lapreco_hil.dense.fusion import TsdfVolume
    from lapreco_hil.dense.surface import KEPT_STEPS

    views, _ = sheet
    estimator = DepthEstimator(SWEEP, DEVICE)
    host_map = estimator.compute(views[0], views[1:])
    device_map = estimator.compute(views[0], views[1:], on_device=True)
    assert isinstance(device_map.depth_m, wp.array) and isinstance(device_map.confidence, wp.array)
    assert device_map.stats["kept_pixels"] == np.count_nonzero(host_map.valid) > 0
    assert device_map.stats["funnel"] == host_map.stats["funnel"]
    np.testing.assert_array_equal(device_map.depth_m.numpy(), host_map.depth_m)
    colour = estimator.view_colour(views[0].kf_id)
    np.testing.assert_array_equal(colour.numpy(), views[0].colour)
    assert estimator.view_colour(99) is None
    volumes = []
    for depth_map, c in ((host_map, views[0].colour), (device_map, colour)):
        volume = TsdfVolume(FusionConfig(), DEVICE)
        volume.integrate(depth_map, c, quantise=KEPT_STEPS)
        volumes.append((volume.raw_blocks(), volume.quantised_map()))
    (a, qa), (b, qb) = volumes
    assert len(a) > 100 and a.keys() == b.keys()
    assert all(np.array_equal(x, y) for k in a for x, y in zip(a[k], b[k]))
    assert all(np.array_equal(x, y) for x, y in zip(qa, qb))


def test_a_dense_surface_fuses_stereo_maps_from_the_device_as_it_would_from_the_host(sheet, warp_cpu):
    """The live surface's stereo (KeptEstimator) hands its maps over on the device: nothing is downloaded into
    the estimator's host buffers, and the volume and the kept (PNG) maps are those of the host route."""
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.config import PipelineConfig
    from lapreco_hil.dense.depth import KeptEstimator
    from lapreco_hil.dense.surface import DenseSurface, nearest_views

    views, _ = sheet
    K = views[0].K
    camera = CameraModel(views[0].size[0], views[0].size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    on_device = KeptEstimator()
    kept_host = KeptEstimator()

    def host_route(ref, sources, config, device):  # the same estimator without compute_on_device
        return kept_host(ref, sources, config, device)

    surfaces = []
    for depth_fn in (on_device, host_route):
        dense = DenseSurface(camera, PipelineConfig(), DEVICE, depth_fn=depth_fn, sources_fn=nearest_views)
        for v in views:
            dense.add_view(v.kf_id, v.colour[:, :, ::-1].copy(), v.T_world_camera)
        assert dense.fuse_pending({0, 1, 2}) == 3
        dense.report()  # (waits for the PNG encodings)
        surfaces.append(dense)
    assert on_device._estimator._host_buffers == [] and kept_host._estimator._host_buffers != []
    (a, b) = (s.volume.raw_blocks() for s in surfaces)
    assert len(a) > 100 and a.keys() == b.keys()
    assert all(np.array_equal(x, y) for k in a for x, y in zip(a[k], b[k]))
    for kf_id in (0, 1, 2):
        x, y = (s.views[kf_id] for s in surfaces)
        assert x.depth_png == y.depth_png and x.confidence_png == y.confidence_png and x.reach_m == y.reach_m > 0
