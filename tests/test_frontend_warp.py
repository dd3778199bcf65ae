"""The Warp front-end on Warp's CPU device (CI has no GPU; the same tests run on CUDA with
LAPRECO_TEST_DEVICE=cuda:0): every kernel against OpenCV or a known answer."""

import os

import cv2
import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.types import Frame

DEVICE = os.environ.get("LAPRECO_TEST_DEVICE", "cpu")


@pytest.fixture(scope="module")
def wp(warp_cpu):
    import warp

    return warp


def texture_u8(rng, h=240, w=320, blur=1.5):
    base = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), blur)
    base = (base - base.min()) / (base.max() - base.min())
    return (40 + 180 * base).astype(np.uint8)


def bgr(gray):
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)


def warped(img, dx, dy, angle=0.0, scale=1.0, gain=1.0, bias=0.0):
    h, w = img.shape[:2]
    M = cv2.getRotationMatrix2D((w / 2, h / 2), np.degrees(angle), scale)
    M[:, 2] += [dx, dy]
    out = cv2.warpAffine(img.astype(np.float32), M, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(out * gain + bias, 0, 255).astype(np.uint8), M


PLAIN = dict(shading_sigma_px=0.0, min_brightness=0.0, fov_margin_px=0.0)


def frontend(cam, **overrides):
    from lapreco_hil.frontend.warp import WarpFrontEnd

    return WarpFrontEnd(cam, TrackerConfig(**{**PLAIN, **overrides}), DEVICE)


def test_undistortion_matches_cv2_remap(wp, rng):
    cam = CameraModel.from_paper_model(320, 240, 230.0, 230.0, 161.0, 118.0, k=(-0.28, 0.09, -0.012),
                                       t=(0.0006, -0.0004), p=(0.0008, -0.0006))
    fe = frontend(cam)
    image = bgr(texture_u8(rng, blur=2.0))
    fe._to_staging(image)
    fe._prepare_kernels()
    ours = fe._pyr[fe._cur].numpy()[: 320 * 240].reshape(240, 320) * 255.0  # level 0: plain intensity here
    mx, my = cam.undistort_maps()
    ref = cv2.cvtColor(cv2.remap(image, mx, my, cv2.INTER_LINEAR), cv2.COLOR_BGR2GRAY).astype(np.float32)
    diff = np.abs(ours - ref)[5:-5, 5:-5]
    # OpenCV interpolates with 5-bit weights and rounds to 8 bits: about one grey level apart at most
    assert diff.max() <= 1.5, diff.max()
    assert diff.mean() < 0.4
    # each track's colour comes from the distorted frame, at the source of its undistorted position
    image[..., 0] = 255 - image[..., 0]  # channels that differ, so their order shows too
    obs = frontend(cam).process(Frame(image, 0, 0))
    assert len(obs) > 50
    undistorted = cv2.remap(image, mx, my, cv2.INTER_LINEAR).astype(np.float32)
    uv = obs.uv.astype(np.float32)[None]
    under = cv2.remap(undistorted, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR)[0][:, ::-1]
    off = np.abs(obs.colors - under)
    assert off.max() <= 2.0, off.max()  # measured 1 (rounding); 89 if sampled at the undistorted position


def test_shading_removal_matches_the_opencv_baseline(wp, rng):
    """Level 0 with shading removal is the OpenCV baseline's log high-pass (log - GaussianBlur(log, sigma)),
    though the Warp front-end takes the blur at half resolution."""
    from lapreco_hil.frontend.image import HIGHPASS_RANGE, LOG_OFFSET, remove_shading, shading_sigma_px

    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    fe = frontend(cam, shading_sigma_px=0.75, pyramid_levels=3)  # on the coarsest of 3 levels: 6 px at full res
    assert shading_sigma_px(fe.config, fe.pyramid_levels) == 6.0
    yy, xx = np.mgrid[0:240, 0:320]
    shading = 0.35 + 0.65 * np.exp(-((xx - 150) ** 2 + (yy - 110) ** 2) / (2 * 90.0**2))  # a scope-tip light
    gray = (texture_u8(rng) * shading).astype(np.uint8)
    fe._to_staging(bgr(gray))
    fe._prepare_kernels()
    ours = fe._pyr[fe._cur].numpy()[: 320 * 240].reshape(240, 320)
    ref = np.clip(remove_shading(gray, 6.0), -HIGHPASS_RANGE, HIGHPASS_RANGE)
    inner = np.abs(ours - ref)[20:-20, 20:-20]  # the blurs' borders differ (replicate vs reflect-101)
    assert inner.max() < 0.01 and inner.mean() < 0.002, (inner.max(), inner.mean())  # measured 0.0031, 0.0005
    # the shading is gone: the high-pass has the same spread in the dim corner as in the lit centre
    assert 0.7 < ours[20:70, 250:300].std() / ours[90:140, 130:180].std() < 1.4
    # the full-resolution shading level is the blurred log image
    np.testing.assert_allclose(fe._lit.numpy()[20:-20, 20:-20],
                               cv2.GaussianBlur(np.log(gray.astype(np.float32) + LOG_OFFSET), (0, 0), 6.0)[20:-20, 20:-20],
                               atol=0.03)


def test_pyramid_gradients_and_min_eigenvalue_match_opencv(wp, rng):
    from lapreco_hil.frontend.warp import corners

    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    fe = frontend(cam)
    gray = texture_u8(rng)
    fe._to_staging(bgr(gray))
    fe._prepare_kernels()
    offs, ws, hs = fe._lv
    pyr = fe._pyr[fe._cur].numpy()
    level0 = pyr[: ws[0] * hs[0]].reshape(hs[0], ws[0])
    np.testing.assert_allclose(level0, gray / 255.0, atol=1e-5)
    level1 = pyr[offs[1]: offs[1] + ws[1] * hs[1]].reshape(hs[1], ws[1])
    ref1 = cv2.pyrDown(gray.astype(np.float32) / 255.0)  # its border reflected (BORDER_REFLECT_101), as LK's
    np.testing.assert_allclose(level1, ref1, atol=1e-5)
    gx = fe._gx[fe._cur].numpy()[: ws[0] * hs[0]].reshape(hs[0], ws[0])
    refx = cv2.Sobel(gray.astype(np.float32) / 255.0, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    np.testing.assert_allclose(gx[1:-1, 1:-1], refx[1:-1, 1:-1], atol=1e-5)
    # the coarser levels, which only LK reads, carry OpenCV LK's Scharr derivatives (border reflected)
    for g, dx, dy in ((fe._gx, 1, 0), (fe._gy, 0, 1)):
        g1 = g[fe._cur].numpy()[offs[1]: offs[1] + ws[1] * hs[1]].reshape(hs[1], ws[1])
        np.testing.assert_allclose(g1, cv2.Scharr(level1, cv2.CV_32F, dx, dy, scale=1 / 32), atol=1e-5)
    corners.structure_rows(fe._gx[fe._cur], fe._gy[fe._cur], ws[0], hs[0], 7, fe._rows, DEVICE)
    corners.selection_begin(fe._stamp, fe._max_eig, DEVICE)  # a new occupancy stamp: none yet
    corners.min_eigenvalue(fe._rows, ws[0], hs[0], 7, fe._mask, fe._lit, -1e30, fe._occ, fe._stamp, fe._eig,
                           fe._max_eig, DEVICE)
    eig = fe._eig.numpy()
    assert fe._max_eig.numpy()[0] == pytest.approx(eig.max())  # no occupancy: the best anywhere
    # cornerMinEigenVal normalises by the window area and its own Sobel scale: compare up to one factor
    ref = cv2.cornerMinEigenVal(gray.astype(np.float32) / 255.0, 7, 3)[10:-10, 10:-10]
    ours = eig[10:-10, 10:-10]
    factor = np.median(ref / np.maximum(ours, 1e-12))
    np.testing.assert_allclose(ours * factor, ref, rtol=1e-3, atol=1e-3 * ref.max())


def test_detection_recalls_goodfeaturestotrack(wp, rng):
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    cfg = dict(max_features=300, min_distance_px=8.0, quality_level=0.01, block_size=7)
    fe = frontend(cam, **cfg)
    gray = texture_u8(rng)
    obs = fe.process(Frame(bgr(gray), 0, 0))
    ref = cv2.goodFeaturesToTrack(gray, maxCorners=300, qualityLevel=0.01, minDistance=8.0, blockSize=7).reshape(-1, 2)
    d = np.linalg.norm(ref[:, None] - obs.uv[None], axis=2).min(axis=1)
    recall = (d <= 1.5).mean()
    assert len(obs) >= 0.8 * len(ref)
    assert recall >= 0.85, recall  # measured 0.9+ on this texture
    pair = np.linalg.norm(obs.uv[:, None] - obs.uv[None], axis=2) + np.eye(len(obs)) * 1e9
    assert pair.min() >= 8.0  # the minimum distance holds


@pytest.mark.parametrize("motion", [
    dict(dx=1.37, dy=-0.62),
    dict(dx=0.8, dy=0.9, angle=0.03),
    dict(dx=-0.6, dy=0.4, scale=1.03),
    dict(dx=2.21, dy=1.13, gain=1.25, bias=-12.0),
])
def test_tracking_known_subpixel_motion_at_least_as_well_as_opencv(wp, rng, motion):
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd

    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    gray = texture_u8(rng)
    moved, M = warped(gray, **motion)
    errors = {}
    for name in ("warp", "opencv"):
        cfg = dict(max_features=200, window_px=21, drift_check=True)
        fe = frontend(cam, **cfg) if name == "warp" else OpenCVFrontEnd(cam, TrackerConfig(**{**PLAIN, **cfg}))
        a = fe.process(Frame(bgr(gray), 0, 0))
        b = fe.process(Frame(bgr(moved), 40_000_000, 1))
        # each track's colour is the image under it (no lens distortion here: the image at its position)
        if name == "warp":  # sampled bilinearly at the sub-pixel position
            uv = b.uv.astype(np.float32)[None]
            under = cv2.remap(moved, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
            assert np.abs(b.colors.astype(int) - under[:, None].astype(int)).max() <= 1
        else:  # the nearest pixel
            xy = np.clip(np.round(b.uv).astype(int), 0, [319, 239])
            assert np.array_equal(b.colors, np.repeat(moved[xy[:, 1], xy[:, 0], None], 3, axis=1))
        common, ia, ib = np.intersect1d(a.track_ids, b.track_ids, return_indices=True)
        truth = a.uv[ia] @ M[:, :2].T + M[:, 2]
        inner = np.all((a.uv[ia] > 25) & (a.uv[ia] < [295, 215]), axis=1)
        errors[name] = np.median(np.linalg.norm(b.uv[ib][inner] - truth[inner], axis=1))
        assert inner.sum() > 50
    assert errors["warp"] <= errors["opencv"] * 1.1 + 0.005, errors
    assert errors["warp"] < 0.1, errors  # measured 0.02-0.065 px on these pairs


def highlight_sequence(rng, n=8, amplitude=120.0, sigma=5.0, step=2.5):
    """Static texture under a specular highlight (an unsaturated bright blob) that slides 2.5 px a frame:
    corners on its rim mix highlight and texture, and LK follows the highlight."""
    base = texture_u8(rng, blur=1.2).astype(np.float32)
    yy, xx = np.mgrid[:240, :320]
    frames, centres = [], []
    for k in range(n):
        c = np.array([120.0 + step * k, 120.0])
        blob = amplitude * np.exp(-((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (2 * sigma**2))
        frames.append(np.clip(base * 0.5 + blob, 0, 255).astype(np.uint8))
        centres.append(c)
    return frames, centres


@pytest.mark.parametrize("impl", ["warp", "opencv"])
def test_drift_check_drops_tracks_riding_a_moving_highlight(wp, rng, impl):
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd

    frames, centres = highlight_sequence(rng)
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    survivors = {}
    for check in (True, False):
        cfg = dict(max_features=300, min_distance_px=5.0, drift_check=check)
        fe = frontend(cam, **cfg) if impl == "warp" else OpenCVFrontEnd(cam, TrackerConfig(**{**PLAIN, **cfg}))
        first = fe.process(Frame(bgr(frames[0]), 0, 0))
        d = np.linalg.norm(first.uv - centres[0], axis=1)
        on_blob, far = first.track_ids[d < 12.5], first.track_ids[d > 40.0]
        assert len(on_blob) >= 5 and len(far) > 100
        for k, img in enumerate(frames[1:], 1):
            last = fe.process(Frame(bgr(img), k * 40_000_000, k))
        survivors[check] = (np.isin(on_blob, last.track_ids).mean(), np.isin(far, last.track_ids).mean())
    # without the check the highlight's tracks slide along with it; with it they are dropped...
    assert survivors[False][0] > 0.8, survivors
    assert survivors[True][0] <= 0.4, survivors
    # ...and the tracks on the static texture are kept
    assert survivors[True][1] > 0.95, survivors


def test_lk_window_samples_stay_inside_the_image_wherever_the_window_goes(wp):
    """A diverging LK step (a near-singular window) can put a window anywhere, NaN and infinity included. Its
    samples are reflected at the border (OpenCV's BORDER_REFLECT_101, as its LK) and clamped to the image, never
    read out of bounds: on CUDA a saturated
    float-to-int conversion once made an unclamped window pass a bounds test and read out of bounds."""
    from lapreco_hil.frontend.warp import lk

    @wp.kernel
    def probe(img: wp.array(dtype=float), xs: wp.array(dtype=float), out: wp.array(dtype=float)):
        i = wp.tid()
        # pixel 0 (top-left) and pixel 440 (bottom-right) of a 21 x 21 window
        o = lk._window_origin(xs[i], xs[i])
        out[2 * i] = lk._window_px(img, 0, 100, 80, o, 0, 21, 1.0 / 21.0)
        out[2 * i + 1] = lk._window_px(img, 0, 100, 80, o, 440, 21, 1.0 / 21.0)

    yy, xx = np.mgrid[0:80, 0:100]
    img = (xx + 1000.0 * yy).astype(np.float32)  # a pixel's value says where it is
    xs = np.array([10.25, -0.5, 3.0e9, 1.0e30, -1.0e30, np.inf, -np.inf, np.nan], np.float32)
    out = wp.zeros(2 * len(xs), dtype=float, device=DEVICE)
    wp.launch(probe, len(xs), [wp.array(img.ravel(), dtype=float, device=DEVICE),
                               wp.array(xs, dtype=float, device=DEVICE), out], device=DEVICE)
    got = out.numpy().reshape(-1, 2)
    assert np.allclose(got[0], [10.25 + 1000 * 10.25, 30.25 + 1000 * 30.25], atol=1e-2)  # inside: bilinear
    # half a pixel beyond the top-left corner: pixel -1 is pixel 1's mirror image
    assert np.allclose(got[1], [0.5 + 1000 * 0.5, 19.5 + 1000 * 19.5], atol=1e-2)
    far = got[2:5].ravel()  # far beyond: clamped into the image
    assert np.all((far >= 0) & (far <= img.max())), far
    # infinite or NaN: no usable fraction, so NaN (LK then reports the track lost), but no read beyond the image
    rest = got[5:]
    assert np.all(np.isnan(rest) | ((rest >= 0) & (rest <= img.max())))


def test_new_corners_take_their_slots_in_cell_order(wp):
    """Which of the cut bin's corners fit, and every new corner's slot, follow the cells' order, not the order the
    threads ran in (an atomic counter gave the slots before: the same frame put its tracks in different slots on
    CUDA, and the consensus draws its hypotheses by slot, so runs differed)."""
    from lapreco_hil.frontend.warp import corners

    n = 12
    best = 1.0
    # cells 0..11: selected (1) or not; scores in bins 0 (strong) and 1 (the cut bin)
    state = np.array([1, 0, 1, 1, 1, -1, 1, 1, 0, 1, 1, 1], np.int32)
    weak = best * 2.0 ** (-1.0 / corners.SCORE_BINS_PER_OCTAVE) * 0.999  # bin 1
    scores = np.where(np.arange(n) % 2 == 0, best, weak)
    cells = np.column_stack([np.arange(n) * 3.0 + 1, np.full(n, 2.0), scores]).astype(np.float32)
    occ = wp.zeros((8, 40), dtype=wp.int32, device=DEVICE)  # no track anywhere
    stamp = wp.array(np.array([7], np.int32), dtype=wp.int32, device=DEVICE)
    cut = wp.array(np.array([1, 2], np.int32), dtype=wp.int32, device=DEVICE)  # bin 1 is cut: 2 of it fit
    count = wp.array(np.array([3], np.int32), dtype=wp.int32, device=DEVICE)  # three live tracks
    next_id = wp.array(np.array([100], np.int32), dtype=wp.int32, device=DEVICE)
    taken = wp.zeros(2, dtype=wp.int32, device=DEVICE)
    pts = wp.zeros(20, dtype=wp.vec2, device=DEVICE)
    ids = wp.zeros(20, dtype=wp.int32, device=DEVICE)
    corners.take_corners(wp.array(cells, dtype=wp.vec3, device=DEVICE), wp.array(state, dtype=wp.int32, device=DEVICE),
                         wp.array(np.array([best], np.float32), dtype=float, device=DEVICE), cut, occ, stamp, count,
                         next_id, taken, pts, ids, corners.TakeScratch(n, DEVICE), DEVICE)
    # selected strong cells (even): 0, 2, 4, 6, 10; selected cut-bin cells (odd): 3, 7, 9, 11 -> the first two: 3, 7
    expect = [0, 2, 3, 4, 6, 7, 10]
    assert int(taken.numpy()[0]) == len(expect)
    got = pts.numpy()[3:3 + len(expect), 0]
    np.testing.assert_array_equal(got, np.array(expect) * 3.0 + 1)
    assert ids.numpy()[3:3 + len(expect)].tolist() == list(range(100, 100 + len(expect)))


def test_the_same_frames_give_the_same_tracks_on_every_run(wp):
    """Two front-ends on the same frames: the same track ids at the same positions, frame by frame (on CUDA too:
    LAPRECO_TEST_DEVICE=cuda:0)."""
    from lapreco_hil.frontend.warp import WarpFrontEnd

    rng = np.random.default_rng(5)
    base = texture_u8(rng, 240, 320)
    camera = CameraModel(320, 240, 300.0, 300.0, 160.0, 120.0, (0.0,) * 5)
    frames = [Frame(bgr(warped(base, 3.0 * k, 1.5 * k, angle=0.01 * k)[0]), k * 40_000_000, k) for k in range(6)]
    runs = []
    for _ in range(2):
        fe = WarpFrontEnd(camera, TrackerConfig(max_features=300, min_distance_px=6.0), DEVICE)
        runs.append([fe.process(f) for f in frames])
    for a, b in zip(*runs):
        assert len(a) > 50
        np.testing.assert_array_equal(a.track_ids, b.track_ids)
        np.testing.assert_array_equal(a.uv, b.uv)


@pytest.mark.parametrize("live, expect", [
    (0, (3, 1, 10)),   # 10 free slots: bins 0-2 hold 2 + 0 + 7 = 9, one more from bin 3
    (1, (3, 0, 9)),    # 9 free: bins 0-2 exactly; none from bin 3
    (8, (2, 0, 2)),    # 2 free: bin 0 fills them; the cut is bin 2, which gives none
    (-20, (512, 0, 12)),  # 30 free, 12 selected corners: all of them, no cut
])
def test_score_threshold_takes_the_strongest_that_fit(wp, live, expect):
    from lapreco_hil.frontend.warp import corners

    hist = np.zeros(corners.SCORE_BINS, np.int32)
    hist[[0, 2, 3, 40]] = [2, 7, 2, 1]
    count = wp.array(np.array([live], np.int32), dtype=wp.int32, device=DEVICE)
    cut = wp.zeros(2, dtype=wp.int32, device=DEVICE)
    taken = wp.array(np.array([5, 5], np.int32), dtype=wp.int32, device=DEVICE)
    corners.score_threshold(wp.array(hist, dtype=wp.int32, device=DEVICE), count, 10, cut, taken, DEVICE)
    assert taken.numpy().tolist() == [0, 0]  # take_corners' counters start from zero
    want = 10 - live
    c0, c1 = (int(v) for v in cut.numpy())
    offered = int(hist[:c0].sum()) + c1
    assert offered == min(want, int(hist.sum()))
    assert (c0, c1, offered) == expect


@pytest.mark.parametrize("impl", ["warp", "opencv"])
def test_lk_error_above_the_limit_loses_the_track(wp, rng, impl):
    """Where the scene changes under a track (here the right half: a new texture), LK still converges
    somewhere, but its window no longer matches: the mean absolute difference over the window is large, and
    both trackers drop such tracks (TrackerConfig.max_lk_error, in the 8-bit units of the tracked image)."""
    from lapreco_hil.frontend.opencv import OpenCVFrontEnd

    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    gray = texture_u8(rng)
    other = texture_u8(np.random.default_rng(7))
    changed, _ = warped(gray, 0.4, -0.3)
    changed[:, 160:] = other[:, 160:]
    kept_right = {}
    for limit in (8.0, 1e9):
        cfg = dict(max_features=200, drift_check=False, max_lk_error=limit)
        fe = frontend(cam, **cfg) if impl == "warp" else OpenCVFrontEnd(cam, TrackerConfig(**{**PLAIN, **cfg}))
        a = fe.process(Frame(bgr(gray), 0, 0))
        b = fe.process(Frame(bgr(changed), 40_000_000, 1))
        right = set(a.track_ids[a.uv[:, 0] > 175].tolist())
        left = set(a.track_ids[a.uv[:, 0] < 145].tolist())
        survivors = set(b.track_ids.tolist())
        kept_right[limit] = len(right & survivors) / len(right)
        assert len(left & survivors) / len(left) > 0.9  # unchanged texture: tracked on
    assert kept_right[1e9] > 0.3 and kept_right[8.0] < 0.1, kept_right


def test_tracks_carry_their_last_step_and_the_selection_avoids_where_they_go_next(wp, rng):
    """Compaction stores each track's motion in the frame; the selection's occupancy discs are drawn where the
    tracks will be if they keep moving so (position + step), so they leave little room between them and the
    discs that taking a corner checks, around where the tracks turn out to be."""
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    fe = frontend(cam, max_features=150, min_distance_px=8.0, quality_level=0.01)
    gray = texture_u8(rng)
    fe.process(Frame(bgr(gray), 0, 0))
    moved, _ = warped(gray, 3.0, -2.0)
    fe.process(Frame(bgr(moved), 40_000_000, 1))
    n = fe.n_tracks
    pts, steps = fe._pts[fe._cur].numpy()[:n], fe._steps[fe._cur].numpy()[:n]
    survivors = np.abs(steps).sum(axis=1) > 0  # the frame's new tracks have no step yet
    assert survivors.sum() > 50
    np.testing.assert_allclose(np.median(steps[survivors], axis=0), [3.0, -2.0], atol=0.05)

    # the next frame's selection stamps discs of radius 8 around position + step: exactly those pixels
    fe._cur = 1 - fe._cur  # as the next frame would: these tracks become the previous buffer
    fe._selection_start()
    got = fe._occ.numpy() == int(fe._stamp.numpy()[0])
    expected = np.zeros_like(got)
    yy, xx = np.mgrid[0:240, 0:320]
    for cx, cy in np.floor(pts + steps + 0.5).astype(int):  # rounded as the kernel rounds
        expected |= (xx - cx) ** 2 + (yy - cy) ** 2 <= 64
    assert np.array_equal(got, expected), np.count_nonzero(got != expected)


def test_new_corners_keep_their_distance_from_the_tracks_that_survive(wp, rng):
    """Re-detection fills the free slots away from live tracks. The corner selection keeps its distance from
    where the tracks were predicted to be (on CUDA it runs beside tracking); these tracks are new, so they
    have no step to predict with, and they move 4.3 px: the new corners keep their distance only if taking
    them checks again, against where the tracks are now."""
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    fe = frontend(cam, max_features=150, min_distance_px=8.0, quality_level=0.01)
    gray = texture_u8(rng)
    a = fe.process(Frame(bgr(gray), 0, 0))
    moved, _ = warped(gray, 3.6, -2.4)
    moved[:, :110] = 0  # the tracks on the left lose their texture; new corners take their slots elsewhere
    b = fe.process(Frame(bgr(moved), 40_000_000, 1))
    old = np.isin(b.track_ids, a.track_ids)
    assert b.n_new > 10 and old.sum() > 50
    gap = np.linalg.norm(b.uv[~old][:, None] - b.uv[old][None], axis=2).min()
    assert gap >= 8.0 - 1.0, gap  # the occupancy disc is drawn around the nearest pixel (as cv2.circle)
