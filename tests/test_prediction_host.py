"""The live path's host prediction (``frontend.epipolar``: start depths, the small-motion test, the track budget's
and the pyramid's measures) against plain per-track reference computations written from their definitions: a
track at its depth moved by the rigid motion and projected, a brute-force nearest-neighbour median, a sorted
median. The fast path shares one projection set-up across depths, counts instead of sorting, and looks ids up
in a table; it must give the same answers."""

import numpy as np
import pytest

from lapreco_hil.config import TrackerConfig
from lapreco_hil.frontend import epipolar, track_budget, track_capacity
from lapreco_hil.frontend.image import predicted_levels
from lapreco_hil.types import FrameMotion

SIZE = (1920, 1080)
K = np.array([[1100.0, 0.0, 960.0], [0.0, 1050.0, 540.0], [0.0, 0.0, 1.0]])


def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def ref_project(uv, depth, K_src, K_dst, T):
    out = np.full((len(uv), 2), np.nan)
    for i, ((u, v), z) in enumerate(zip(uv, np.broadcast_to(depth, len(uv)))):
        ray = np.array([(u - K_src[0, 2]) / K_src[0, 0], (v - K_src[1, 2]) / K_src[1, 1], 1.0])
        p = T[:3, :3] @ (z * ray) + T[:3, 3]
        if p[2] > 1e-9:
            out[i] = K_dst[0, 0] * p[0] / p[2] + K_dst[0, 2], K_dst[1, 1] * p[1] / p[2] + K_dst[1, 2]
    return out


def ref_own(ids, known_ids, known_depth):
    table = dict(zip(known_ids.tolist(), known_depth.tolist()))
    depth = np.array([table.get(i, np.nan) for i in ids.tolist()])
    depth[~(depth > 0)] = np.nan
    return depth


def ref_borrow(uv, depth, size):
    out = depth.copy()
    has = np.flatnonzero(np.isfinite(depth))
    for i in np.flatnonzero(~np.isfinite(depth)):
        dist = np.linalg.norm(uv[has] - uv[i], axis=1)
        nearest = has[np.argsort(dist)[:epipolar.NEIGHBOURS]]
        nearest = nearest[np.linalg.norm(uv[nearest] - uv[i], axis=1) <= epipolar.NEIGHBOUR_RADIUS * max(size)]
        out[i] = np.median(depth[nearest]) if len(nearest) else np.nan
    return out


def ref_moved(uv, depth, T):
    known = np.isfinite(depth)
    moved = np.linalg.norm(ref_project(uv[known], depth[known], K, K, T) - uv[known], axis=1)
    return moved[np.isfinite(moved)]


def ref_small(uv, depth, T):
    moved = ref_moved(uv, depth, T)
    return np.isfinite(depth).sum() >= 10 and len(moved) > 0 and np.median(moved) < epipolar.SMALL_MOTION_PX


def ref_settle(uv, depth, T, depth_range):
    out = depth.copy()
    near, far = depth_range
    mid = 2.0 / (1.0 / near + 1.0 / far)
    for i in np.flatnonzero(~np.isfinite(depth)):
        a, b, c = (ref_project(uv[i:i + 1], z, K, K, T)[0] for z in (near, far, mid))
        reach = max(np.linalg.norm(a - c), np.linalg.norm(b - c))
        if reach <= epipolar.SHORT_LINE_PX:
            out[i] = far
    return out


def ref_start_depths(uv, ids, motion):
    T = motion.T_cur_prev
    depth = ref_own(ids, motion.track_ids, motion.depth_m)
    if ref_small(uv, depth, T):
        return None
    settled = np.isfinite(depth).sum() >= 10
    depth = ref_borrow(uv, depth, SIZE)
    if not settled and ref_small(uv, depth, T):
        return None
    return ref_settle(uv, depth, T, motion.depth_range_m)


def ref_uncertainty(uv, ids, depth, motion):
    own_ids = set(motion.track_ids[motion.depth_m > 0].tolist())
    near, far = motion.depth_range_m
    spread = []
    for (u, v), i, z in zip(uv, ids.tolist(), depth):
        if not np.isfinite(z):
            spread.append(epipolar.SECOND_RADIUS * 2.0 ** epipolar.SWEEP_LEVEL)
            continue
        relative = epipolar.OWN_DEPTH_SPREAD if i in own_ids else epipolar.BORROWED_DEPTH_SPREAD
        ends = (near, far) if i not in own_ids and z == far else (z * (1 - relative), z * (1 + relative))
        at = ref_project(np.array([[u, v]]), z, K, K, motion.T_cur_prev)[0]
        moved = [np.linalg.norm(ref_project(np.array([[u, v]]), e, K, K, motion.T_cur_prev)[0] - at) for e in ends]
        spread.append(max(moved) if np.all(np.isfinite(moved)) else 1e6)
    return max(epipolar.POSE_UNCERTAINTY_PX, np.percentile(spread, epipolar.START_QUANTILE))


def scene(seed, n, known_fraction, scale, cluster=False):
    """Tracks over a 1080p image (``cluster``: half of them in two clumps, the rest sparse), ids a shuffled
    window (or, every third seed, spread too widely for the id table), a motion of a few mm and a degree times
    ``scale``, and a few tracks that the motion takes behind the camera."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], SIZE, (n, 2))
    if cluster:
        uv[: n // 2] = rng.normal([500, 300], 40, (n // 2, 2))
    ids = rng.permutation(n) + 5000
    if seed % 3 == 0:
        ids = ids * 1000
    has = rng.random(n) < known_fraction
    z = rng.uniform(0.04, 0.12, n)
    z[rng.random(n) < 0.02] = -0.05  # (a landmark behind the previous camera: no own depth)
    T = np.eye(4)
    T[:3, :3] = rotation(rng.normal(size=3), np.deg2rad(rng.uniform(0.2, 1.5)) * scale)
    T[:3, 3] = rng.normal(0, 0.002, 3) * scale
    T[2, 3] = -0.06 if seed % 4 == 0 else T[2, 3]  # (this seed's nearest tracks end behind the new camera)
    return uv, ids.astype(np.int64), FrameMotion(T, ids[has].astype(np.int64), z[has], (0.03, 0.2))


CASES = [(seed, n, known, scale, seed % 2 == 1)
         for seed, (n, known, scale) in enumerate([(400, 0.8, 1.0), (400, 0.8, 0.15), (300, 0.03, 1.0),
                                                    (300, 0.03, 0.1), (500, 0.5, 0.4), (200, 0.0, 1.0),
                                                    (350, 1.0, 1.0), (350, 0.95, 0.3), (25, 0.2, 1.0),
                                                    (600, 0.7, 0.25), (300, 0.3, 0.05), (450, 0.6, 2.0)])]


@pytest.mark.parametrize("seed,n,known,scale,cluster", CASES)
def test_start_depths_and_the_plan_equal_the_plain_reference(seed, n, known, scale, cluster):
    uv, ids, motion = scene(seed, n, known, scale, cluster)
    T = motion.T_cur_prev
    own = ref_own(ids, motion.track_ids, motion.depth_m)
    assert np.array_equal(epipolar.own_depths(ids, motion.track_ids, motion.depth_m), own, equal_nan=True)
    np.testing.assert_allclose(epipolar.project(uv, np.nan_to_num(own, nan=0.07), K, K, T),
                               ref_project(uv, np.nan_to_num(own, nan=0.07), K, K, T), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(epipolar.borrow_depths(uv, own, SIZE), ref_borrow(uv, own, SIZE), rtol=1e-15)

    expected = ref_start_depths(uv, ids, motion)
    got = epipolar.start_depths(uv, ids, motion, K, SIZE)
    moved = ref_moved(uv, own, T)
    if len(moved) and abs(np.median(moved) - epipolar.SMALL_MOTION_PX) < 1e-6:
        pytest.skip("the median motion within rounding of the threshold")
    assert (got is None) == (expected is None)
    if expected is None:
        return
    np.testing.assert_allclose(got, expected, rtol=1e-15)
    np.testing.assert_allclose(epipolar.settle_short_lines(uv, own, K, T, motion.depth_range_m),
                               ref_settle(uv, own, T, motion.depth_range_m), rtol=0)

    reference_motion = np.median(ref_moved(uv, expected, T)) if np.isfinite(expected).any() else None
    got_motion = epipolar.start_motion_px(uv, got, K, T)
    assert got_motion == reference_motion if reference_motion is None else got_motion == pytest.approx(
        reference_motion, rel=1e-9)
    reference_uncertainty = ref_uncertainty(uv, ids, expected, motion)
    assert epipolar.start_uncertainty_px(uv, ids, got, motion, K) == pytest.approx(reference_uncertainty, rel=1e-9)
    # (the fast-motion threshold just above or below this frame's motion: either budget, as the reference says)
    fast_px = (reference_motion or 10.0) * (1.02 if seed % 2 else 0.98)
    cfg = TrackerConfig(max_features=n, reduced_predicted_levels=True, fast_motion_px=fast_px)
    assert epipolar.prediction_plan(cfg, 4, SIZE, uv, ids, got, motion, K) == (
        track_budget(cfg, reference_motion), predicted_levels(cfg, 4, *SIZE, reference_uncertainty))


def test_the_small_motion_count_is_the_median_exactly():
    """Counting below the threshold decides as the median does, the two middle values of an even count
    straddling it included."""
    rng = np.random.default_rng(5)
    t = epipolar.SMALL_MOTION_PX
    cases = [[1, 2, 9, 10], [7, 9], [7.5, 8.6], [6, 9.9], [8, 8], [7.99, 8.0], [1, 9, 9], [1, 2, 9], [8.0],
             [7.999], [3, 8, 8, 20]]
    cases += [rng.uniform(0, 2 * t, int(rng.integers(1, 40))) for _ in range(300)]
    for values in cases:
        values = np.asarray(values, float)
        assert epipolar._median_below(values ** 2, t) == (np.median(values) < t), values


def test_few_known_tracks_borrow_from_all_of_them_and_none_in_reach_stays_searched():
    uv = np.array([[100.0, 100.0], [110.0, 100.0], [100.0, 120.0], [105.0, 105.0], [1900.0, 1000.0]])
    depth = np.array([0.05, 0.07, 0.10, np.nan, np.nan])
    out = epipolar.borrow_depths(uv, depth, SIZE)
    assert out[3] == pytest.approx(0.07) and np.isnan(out[4])  # (288 px of reach: the far corner has none)
    assert np.array_equal(out[:3], depth[:3])


@pytest.mark.parametrize("pattern", ["band", "hole", "sparse", "outside", "few"])
def test_borrowed_depths_where_the_tracks_without_one_gather_equal_the_plain_reference(pattern):
    """The tree is built only on the known tracks that can be a query's neighbours (a grid's cells around the
    queries): the same borrowed depths as the brute-force median over every known track, whether the queries
    gather in a band the motion uncovers (a few cells around them suffice), fill a hole among the landmarks
    (fewer than NEIGHBOURS near: their whole reach), are few and scattered, or lie among sparse or
    out-of-image tracks."""
    rng = np.random.default_rng(11)
    n = 3000 if pattern != "sparse" else 60
    uv = rng.uniform([0, 0], SIZE, (n, 2))
    depth = rng.uniform(0.04, 0.12, n)
    if pattern == "band":
        query = uv[:, 0] < 150
    elif pattern == "hole":
        query = np.linalg.norm(uv - [900, 500], axis=1) < 200
    elif pattern == "sparse":
        query = rng.random(n) < 0.5
    elif pattern == "few":  # (each query's own cells: its nearest six are often beyond its 3 x 3 block)
        query = rng.random(n) < 0.03
    else:
        uv[:20] += [2500, 0]  # (tracks far off the image: LK garbage the front-ends would drop)
        query = rng.random(n) < 0.3
    depth[query] = np.nan
    expected = ref_borrow(uv, depth, SIZE)
    np.testing.assert_allclose(epipolar.borrow_depths(uv, depth, SIZE), expected, rtol=1e-15)
    candidate = epipolar._neighbour_candidates(uv, ~query, epipolar.NEIGHBOURS, epipolar.NEIGHBOUR_RADIUS * max(SIZE))
    assert candidate is None or not candidate[query].any()
    if pattern == "band":
        assert candidate is not None and candidate[~query].mean() < 0.3  # (the tree: a strip along the band)
    if pattern == "hole":  # (its middle borrows from landmarks 200-288 px away, beyond its cells' 7 x 7 blocks)
        assert np.isfinite(expected[np.linalg.norm(uv - [900, 500], axis=1) < 30]).all()
        assert candidate is not None and not candidate[~query].all()


def test_the_plan_from_the_small_motion_tests_work_is_the_plan_made_afresh():
    """The Warp front-end's plan reuses ``own_start_depths``' projections (``OwnStartDepths.moved_sq``, ``terms``):
    the budget and levels are those ``prediction_plan`` makes from the plan's depths alone, for slow and fast
    motions, with the budget's option and the reduced levels on."""
    rng = np.random.default_rng(7)
    K = np.array([[1100.0, 0, 960], [0, 1100.0, 540], [0, 0, 1]])
    size = (1920, 1080)
    uv = rng.uniform([0, 0], size, (1500, 2))
    ids = np.arange(1500, dtype=np.int64)
    own = rng.random(1500) < 0.7
    cfg = TrackerConfig(reduced_predicted_levels=True)
    budgets = set()
    for scale in (1.0, 3.0, 12.0, 30.0):
        T = np.eye(4)
        T[:3, 3] = np.array([1.2, 0.6, 1.5]) * 1e-3 * scale
        motion = FrameMotion(T, ids[own], rng.uniform(0.04, 0.12, own.sum()), (0.03, 0.3))
        got = epipolar.own_start_depths(uv, ids, motion, K, size)
        assert got is not None and got.moved_sq is not None
        afresh = epipolar.prediction_plan(cfg, 5, size, uv, ids, got.plan, motion, K)
        reused = epipolar.prediction_plan(cfg, 5, size, uv, ids, got.plan, motion, K, got.moved_sq, got.terms)
        assert reused == afresh
        budgets.add(afresh[0])
    assert budgets == {cfg.max_features, track_capacity(cfg)}  # both budgets met
