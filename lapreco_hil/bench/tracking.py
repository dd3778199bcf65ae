"""``lapreco bench tracking``: the front-ends on real laparoscopic frames moved by known homographies.

Each real frame is the texture of a plane at ``PLANE_DEPTH_M`` in front of a pinhole camera (K from the frame's
own calibration where there is one, else f = 0.8 x width and the principal point at the centre; no distortion,
so the front-ends' undistorted pixels are the image's pixels). The camera then moves relative to the plane, in
segments of a few frames: translation across it, rotation about the optical axis, zoom (motion along the axis)
and tilt (the scope pivoting about its trocar, 10 cm behind the tip: the view of the plane tilts, adding
perspective to a shift), each out and back. Every
step is scaled so that the median displacement of the image points is the requested speed (px per frame). The
plane point seen at reference pixel x is seen by camera k at H_k x, with

    H_k = K (R_k + t_k n^T / d) K^-1,   X_k = R_k X_ref + t_k,   the plane {X_ref : n^T X_ref = d}, n = (0, 0, 1),

and frame k is ``cv2.warpPerspective`` of the texture by H_k. The plane's texture beyond the frame's edges is the
frame mirrored (OpenCV's BORDER_REFLECT_101), so every pixel of every frame is a true view of the plane: the
homographies hold everywhere. Per frame the intensities change as a scope's light and auto-exposure make them:
a gain (x0.8 .. x1.25), a bias, a saturated specular highlight that moves across the image (it does not move with
the tissue), and mild blur on some frames.

A track is compared, in every frame after the one it was born in, with where its birth point truly went: its
birth pixel mapped back to the reference image, then forward by that frame's homography.
"""

from __future__ import annotations

import inspect
import logging
import math
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import TrackerConfig
from lapreco_hil.errors import ConfigError
from lapreco_hil.types import Frame, FrameMotion

log = logging.getLogger(__name__)

PLANE_DEPTH_M = 0.08  # a laparoscope works 5-10 cm from the tissue
TROCAR_BEHIND_M = 0.10  # the scope's fulcrum (the trocar in the abdominal wall) behind its tip
FRAME_PERIOD_NS = 40_000_000  # 25 fps
MOTION_KINDS = ("translate", "rotate", "zoom", "tilt")
PREDICT_MODES = ("off", "depth", "epipolar")
DEFAULT_SPEEDS = (0.0, 10.0, 20.0, 40.0, 60.0, 80.0)
SURVIVAL_FRAMES = 10

# the real frames of tests/data: (name, image, calibration K file or None)
REAL_FRAMES = (
    ("liver", "real-frames/liver_frame_1920x1080.png", None),
    ("hamlyn-phantom", "hamlyn-phantom-stereo/f7_dynamic_deint_L_0100.png",
     "hamlyn-phantom-stereo/calib.left.intrinsic.txt"),
    ("laparoscope-chessboard", "laparoscope-chessboard-right/right-1095.png",
     "laparoscope-chessboard-right/calib.right.intrinsic.txt"),
    ("viking-dotgrid", "viking-tracked-dotgrid/calib.right.images.4.png",
     "viking-tracked-dotgrid/calib.right.intrinsics.txt"),
)


def default_data_dir() -> Path:
    """The repository's ``tests/data`` (the bench runs from a source checkout)."""
    return Path(__file__).resolve().parents[2] / "tests" / "data"


@dataclass(frozen=True)
class RealFrame:
    name: str
    image: np.ndarray  # BGR uint8
    K: np.ndarray
    calibrated: bool


def load_real_frames(data_dir: Path | None = None, names: tuple[str, ...] | None = None) -> list[RealFrame]:
    data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
    known = [n for n, _, _ in REAL_FRAMES]
    if names is not None:
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ConfigError(f"unknown real frame '{unknown[0]}' (known: {', '.join(known)})")
    out = []
    for name, image_rel, calib_rel in REAL_FRAMES:
        if names is not None and name not in names:
            continue
        path = data_dir / image_rel
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise ConfigError(f"real frame {path} is missing or unreadable: the tracking bench runs from a source "
                              "checkout, which has tests/data")
        h, w = image.shape[:2]
        if calib_rel is None:
            K = np.array([[0.8 * w, 0.0, (w - 1) / 2], [0.0, 0.8 * w, (h - 1) / 2], [0.0, 0.0, 1.0]])
        else:
            K = np.loadtxt(data_dir / calib_rel).reshape(3, 3)
        out.append(RealFrame(name, image, K, calib_rel is not None))
    return out


def camera_of(frame: RealFrame) -> CameraModel:
    """The zero-distortion pinhole camera that sees the plane (undistorted pixels = image pixels)."""
    h, w = frame.image.shape[:2]
    K = frame.K
    return CameraModel(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


# ---------------------------------------------------------------------------------------------------------------
# the plane, its homographies and the camera motion


def _transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def plane_in(T_cam_ref: np.ndarray, depth_m: float = PLANE_DEPTH_M) -> tuple[np.ndarray, float]:
    """The plane {X : n^T X = d} in camera coordinates (it is z = depth_m in the reference camera)."""
    n = T_cam_ref[:3, :3] @ np.array([0.0, 0.0, 1.0])
    return n, float(depth_m + n @ T_cam_ref[:3, 3])


def plane_homography(K: np.ndarray, T_b_a: np.ndarray, n_a: np.ndarray, d_a: float) -> np.ndarray:
    """Pixels of camera a -> pixels of camera b for points on the plane n_a^T X_a = d_a (X_b = R X_a + t)."""
    H = K @ (T_b_a[:3, :3] + np.outer(T_b_a[:3, 3], n_a) / d_a) @ np.linalg.inv(K)
    return H / H[2, 2]


def apply_homography(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    p = np.hstack([uv, np.ones((len(uv), 1))]) @ H.T
    return p[:, :2] / p[:, 2:3]


def plane_depth(K: np.ndarray, T_cam_ref: np.ndarray, uv: np.ndarray, depth_m: float = PLANE_DEPTH_M) -> np.ndarray:
    """z in the camera of the plane points seen at pixels ``uv``."""
    n, d = plane_in(T_cam_ref, depth_m)
    rays = np.hstack([np.asarray(uv, np.float64).reshape(-1, 2), np.ones((len(uv), 1))]) @ np.linalg.inv(K).T
    return d / (rays @ n)


def _grid(w: int, h: int, n: int = 24) -> np.ndarray:
    xs = (np.arange(n) + 0.5) * w / n
    ys = (np.arange(n) + 0.5) * h / n
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def _unit_step(kind: str, sign: float, angle: float, a: float, K: np.ndarray, T_prev_ref: np.ndarray,
               depth_m: float) -> np.ndarray:
    """T_cur_prev for a step of size ``a`` (dimensionless) of one motion kind."""
    n, d = plane_in(T_prev_ref, depth_m)
    z_axis = d / n[2]  # depth of the plane point on the optical axis
    direction = np.array([math.cos(angle), math.sin(angle), 0.0])
    if kind == "translate":  # the camera slides across: points move the other way
        return _transform(np.eye(3), -sign * a * z_axis * direction)
    if kind == "rotate":
        return _transform(Rotation.from_rotvec([0.0, 0.0, sign * a]).as_matrix(), np.zeros(3))
    if kind == "zoom":  # toward the plane (sign > 0) or away, along the optical axis
        return _transform(np.eye(3), np.array([0.0, 0.0, -sign * a * z_axis]))
    if kind == "tilt":  # the scope pivots about its trocar, behind the camera on the optical axis
        pivot = np.array([0.0, 0.0, -TROCAR_BEHIND_M])
        R = Rotation.from_rotvec(sign * a * np.array([-direction[1], direction[0], 0.0])).as_matrix()
        return _transform(R, pivot - R @ pivot)
    raise ValueError(kind)


def median_displacement(K: np.ndarray, T_prev_ref: np.ndarray, T_cur_prev: np.ndarray, size: tuple[int, int],
                        depth_m: float = PLANE_DEPTH_M) -> float:
    grid = _grid(*size)
    n, d = plane_in(T_prev_ref, depth_m)
    moved = apply_homography(plane_homography(K, T_cur_prev, n, d), grid)
    return float(np.median(np.linalg.norm(moved - grid, axis=1)))


def step_for_speed(kind: str, sign: float, angle: float, speed_px: float, K: np.ndarray, T_prev_ref: np.ndarray,
                   size: tuple[int, int], depth_m: float = PLANE_DEPTH_M) -> np.ndarray:
    """The step of this kind whose median image displacement is ``speed_px`` (bisection on its size)."""
    if speed_px <= 0:
        return np.eye(4)

    def disp(a):
        return median_displacement(K, T_prev_ref, _unit_step(kind, sign, angle, a, K, T_prev_ref, depth_m), size,
                                   depth_m)

    # zooming in cannot go through the plane; zooming out moves points at most their distance from the centre
    hi = {"zoom": 0.9 if sign > 0 else 50.0}.get(kind, 1.0)
    lo = 0.0
    if disp(hi) < speed_px:
        log.warning("a %s step moves this %dx%d image by at most %.0f px; using that instead of %g px", kind,
                    *size, disp(hi), speed_px)
        return _unit_step(kind, sign, angle, hi, K, T_prev_ref, depth_m)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if disp(mid) < speed_px:
            lo = mid
        else:
            hi = mid
    return _unit_step(kind, sign, angle, 0.5 * (lo + hi), K, T_prev_ref, depth_m)


def motion_schedule(n_frames: int, segment_frames: int = 4) -> list[tuple[str, float, float]]:
    """(kind, sign, direction angle) of the step into each frame 1..n-1: each kind out then back, in turn."""
    steps = []
    for k in range(1, n_frames):
        segment = (k - 1) // segment_frames
        kind = MOTION_KINDS[(segment // 2) % len(MOTION_KINDS)]
        sign = 1.0 if segment % 2 == 0 else -1.0
        cycle = segment // (2 * len(MOTION_KINDS))
        steps.append((kind, sign, math.radians(30.0 + 90.0 * cycle)))
    return steps


@dataclass(frozen=True)
class Photometric:
    gain: float
    bias: float
    highlight_xy: tuple[float, float]
    highlight_sigma_px: float
    blur_sigma_px: float  # 0: sharp


def photometric_schedule(n_frames: int, size: tuple[int, int], seed: int = 0) -> list[Photometric]:
    """Per frame: auto-exposure gain and bias, a specular highlight moving on a slow loop, blur on every 5th."""
    rng = np.random.default_rng(seed)
    w, h = size
    out = []
    for k in range(n_frames):
        phase = 2 * math.pi * k / 40.0
        xy = (w * (0.5 + 0.3 * math.cos(phase)), h * (0.5 + 0.3 * math.sin(2 * phase)))
        out.append(Photometric(gain=float(math.exp(rng.uniform(math.log(0.8), math.log(1.25)))),
                               bias=float(rng.uniform(-12.0, 12.0)), highlight_xy=xy,
                               highlight_sigma_px=0.03 * w, blur_sigma_px=0.8 if k % 5 == 3 else 0.0))
    return out


def apply_photometric(image: np.ndarray, p: Photometric) -> np.ndarray:
    h, w = image.shape[:2]
    x = np.arange(w, dtype=np.float32) - p.highlight_xy[0]
    y = np.arange(h, dtype=np.float32) - p.highlight_xy[1]
    blob = np.exp(-(y[:, None] ** 2 + x[None, :] ** 2) / (2 * p.highlight_sigma_px**2)).astype(np.float32)
    out = image.astype(np.float32) * p.gain + p.bias + (1.5 * 255.0) * blob[:, :, None]  # saturated core
    out = np.clip(out, 0, 255).astype(np.uint8)
    if p.blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), p.blur_sigma_px)
    return out


@dataclass
class PlaneSequence:
    """Frames of one real texture under one camera path, with the truth: T_k_ref and H_k (reference -> k)."""

    name: str
    camera: CameraModel
    speed_px: float
    T_cam_ref: list[np.ndarray]
    H: list[np.ndarray]
    images: list[np.ndarray]
    depth_m: float = PLANE_DEPTH_M
    kinds: list[str] = field(default_factory=list)

    @property
    def size(self) -> tuple[int, int]:
        return self.camera.width, self.camera.height

    def truth(self, k: int, uv_ref: np.ndarray) -> np.ndarray:
        """Where the plane points at reference pixels ``uv_ref`` are seen in frame k."""
        return apply_homography(self.H[k], uv_ref)

    def to_reference(self, k: int, uv: np.ndarray) -> np.ndarray:
        return apply_homography(np.linalg.inv(self.H[k]), uv)

    def motion(self, k: int, track_ids: np.ndarray, uv_ref: np.ndarray, mode: str) -> FrameMotion:
        """What a perfect pose source says about the step into frame k: each live track's true depth in
        frame k-1 (``depth``) or only the range of depths (``epipolar``)."""
        K = self.camera.K
        T_cur_prev = self.T_cam_ref[k] @ np.linalg.inv(self.T_cam_ref[k - 1])
        corners = np.array([[0, 0], [self.size[0], 0], [0, self.size[1]], self.size], np.float64)
        z = plane_depth(K, self.T_cam_ref[k - 1], np.vstack([corners, _grid(*self.size, 4)]), self.depth_m)
        z_range = (0.5 * float(z.min()), 2.0 * float(z.max()))
        if mode == "depth":
            z_tracks = plane_depth(K, self.T_cam_ref[k - 1], self.truth(k - 1, uv_ref), self.depth_m)
            return FrameMotion(T_cur_prev, np.asarray(track_ids, np.int64), z_tracks, z_range)
        if mode == "epipolar":
            return FrameMotion(T_cur_prev, depth_range_m=z_range)
        raise ValueError(mode)


def make_sequence(frame: RealFrame, speed_px: float, n_frames: int, seed: int = 0, photometric: bool = True,
                  segment_frames: int = 4, depth_m: float = PLANE_DEPTH_M) -> PlaneSequence:
    camera = camera_of(frame)
    K, size = camera.K, (camera.width, camera.height)
    poses = [np.eye(4)]
    kinds = ["start"]
    for kind, sign, angle in motion_schedule(n_frames, segment_frames):
        poses.append(step_for_speed(kind, sign, angle, speed_px, K, poses[-1], size, depth_m) @ poses[-1])
        kinds.append(kind)
    n0 = np.array([0.0, 0.0, 1.0])
    H = [plane_homography(K, T, n0, depth_m) for T in poses]
    light = photometric_schedule(n_frames, size, seed)
    images = []
    for k in range(n_frames):
        img = cv2.warpPerspective(frame.image, H[k], size, flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT_101)
        images.append(apply_photometric(img, light[k]) if photometric else img)
    return PlaneSequence(frame.name, camera, speed_px, poses, H, images, depth_m, kinds)


# ---------------------------------------------------------------------------------------------------------------
# running a front-end and scoring its tracks


def accepts_motion(frontend) -> bool:
    try:
        return "motion" in inspect.signature(frontend.process).parameters
    except (TypeError, ValueError):
        return False


def track_sequence(frontend, seq: PlaneSequence, predict: str = "off") -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
    """Runs the front-end over the frames; returns each frame's (track ids, uv) and the mean time per frame.
    ``motion`` is passed only when predicting, so front-ends without it run with ``predict='off'``."""
    if predict not in PREDICT_MODES:
        raise ConfigError(f"unknown prediction mode '{predict}' (known: {', '.join(PREDICT_MODES)})")
    if predict != "off" and not accepts_motion(frontend):
        raise ConfigError(f"{type(frontend).__name__}.process takes no camera motion in this build: run the "
                          "tracking bench with --predict off")
    out = []
    birth_ref: dict[int, np.ndarray] = {}
    elapsed = 0.0
    for k, image in enumerate(seq.images):
        frame = Frame(image, k * FRAME_PERIOD_NS, k)
        t0 = time.perf_counter()
        if predict == "off" or k == 0:
            obs = frontend.process(frame)
        else:
            ids_prev = out[-1][0]
            uv_ref = np.array([birth_ref[int(i)] for i in ids_prev]).reshape(-1, 2)
            obs = frontend.process(frame, motion=seq.motion(k, ids_prev, uv_ref, predict))
        elapsed += time.perf_counter() - t0
        ids = np.asarray(obs.track_ids, np.int64).copy()
        uv = np.asarray(obs.uv, np.float64).reshape(-1, 2).copy()
        new = [j for j, i in enumerate(ids) if int(i) not in birth_ref]
        if new:
            for j, p in zip(new, seq.to_reference(k, uv[new])):
                birth_ref[int(ids[j])] = p
        out.append((ids, uv))
    return out, elapsed / max(len(seq.images), 1)


@dataclass
class TrackErrors:
    """Per observation of a track after its birth frame: its error (px) and age (frames)."""

    errors: np.ndarray
    ages: np.ndarray
    survival_alive: int
    survival_eligible: int
    tracks_per_frame: list[int]


def score_tracks(observations: list[tuple[np.ndarray, np.ndarray]], H: list[np.ndarray], size: tuple[int, int],
                 survival_frames: int = SURVIVAL_FRAMES, margin_px: float = 10.0) -> TrackErrors:
    """Compares each reported track position with where its birth point truly is (``H[k]``: reference pixels
    -> frame k). Survival: of the tracks born at frame j whose true point stays at least ``margin_px`` inside
    the image through frame j + survival_frames, the share still reported there (without a gap)."""
    w, h = size
    birth: dict[int, tuple[int, np.ndarray]] = {}
    last_seen: dict[int, int] = {}
    gap: set[int] = set()
    errors, ages, per_frame = [], [], []
    for k, (ids, uv) in enumerate(observations):
        per_frame.append(len(ids))
        Hk_inv = np.linalg.inv(H[k])
        for i, p in zip(ids, uv):
            i = int(i)
            if i not in birth:
                birth[i] = (k, apply_homography(Hk_inv, p)[0])
            else:
                if last_seen[i] != k - 1:
                    gap.add(i)
                j, p_ref = birth[i]
                errors.append(float(np.linalg.norm(p - apply_homography(H[k], p_ref)[0])))
                ages.append(k - j)
            last_seen[i] = k
    alive = eligible = 0
    for i, (j, p_ref) in birth.items():
        end = j + survival_frames
        if end >= len(observations):
            continue
        path = np.array([apply_homography(H[k], p_ref)[0] for k in range(j, end + 1)])
        inside = ((path[:, 0] >= margin_px) & (path[:, 0] < w - margin_px) & (path[:, 1] >= margin_px)
                  & (path[:, 1] < h - margin_px)).all()
        if not inside:
            continue
        eligible += 1
        alive += int(last_seen[i] >= end and i not in gap)
    return TrackErrors(np.asarray(errors), np.asarray(ages, np.int64), alive, eligible, per_frame)


def summarize(scores: list[TrackErrors]) -> dict:
    errors = np.concatenate([s.errors for s in scores]) if scores else np.zeros(0)
    eligible = sum(s.survival_eligible for s in scores)
    tracks = [n for s in scores for n in s.tracks_per_frame[1:]]
    return {
        "observations": int(len(errors)),
        "median_error_px": float(np.median(errors)) if len(errors) else None,
        "p90_error_px": float(np.percentile(errors, 90)) if len(errors) else None,
        "within_1px": float(np.mean(errors <= 1.0)) if len(errors) else None,
        "within_3px": float(np.mean(errors <= 3.0)) if len(errors) else None,
        "survival": sum(s.survival_alive for s in scores) / eligible if eligible else None,
        "survival_eligible": int(eligible),
        "tracks_per_frame": float(np.mean(tracks)) if tracks else 0.0,
    }


# ---------------------------------------------------------------------------------------------------------------
# the benchmark


def _make(tracker: str, camera: CameraModel, config: TrackerConfig, device: str):
    from lapreco_hil.frontend import make_frontend

    return make_frontend(tracker, camera, config, device if tracker == "warp" else None)


def run(trackers: list[str], devices: list[str], speeds: list[float], predict_modes: list[str], frames: int = 32,
        frame_names: tuple[str, ...] | None = None, config: TrackerConfig | None = None, seed: int = 0,
        survival_frames: int = SURVIVAL_FRAMES, data_dir: Path | None = None) -> dict:
    """Every (tracker, device, prediction mode) on every real frame at every speed. The OpenCV tracker runs on
    the CPU whatever the device list says. Rows pool the frames; ``per_frame`` keeps each real frame's figures."""
    config = config or TrackerConfig()
    if frames < 2:
        raise ConfigError("the tracking bench needs at least 2 frames (--frames)")
    real = load_real_frames(data_dir, frame_names)
    combos = []
    for tracker in trackers:
        for device in (devices if tracker == "warp" else ["cpu"]):
            for mode in predict_modes:
                if (tracker, device, mode) not in combos:
                    combos.append((tracker, device, mode))
    scores: dict[tuple, list] = {}
    for frame in real:
        for speed in speeds:
            seq = make_sequence(frame, speed, frames, seed=seed)
            for tracker, device, mode in combos:
                frontend = _make(tracker, seq.camera, config, device)
                obs, per_frame_s = track_sequence(frontend, seq, mode)
                s = score_tracks(obs, seq.H, seq.size, survival_frames)
                scores.setdefault((tracker, device, mode, speed), []).append((frame.name, s, per_frame_s))
                log.info("%s %s %s %s %.0f px: %s", frame.name, tracker, device, mode, speed, summarize([s]))
    rows = []
    for (tracker, device, mode, speed), items in scores.items():
        row = {"tracker": tracker, "device": device, "predict": mode, "speed_px": speed,
               **summarize([s for _, s, _ in items]),
               "ms_per_frame": 1e3 * float(np.mean([t for _, _, t in items])),
               "per_frame": {name: {**summarize([s]), "ms_per_frame": 1e3 * t} for name, s, t in items}}
        rows.append(row)
    return {"benchmark": "tracking", "frames": frames, "speeds_px": list(speeds), "survival_frames": survival_frames,
            "plane_depth_m": PLANE_DEPTH_M, "seed": seed,
            "real_frames": [{"name": f.name, "size": list(f.image.shape[1::-1]), "calibrated": f.calibrated,
                             "K": f.K.tolist()} for f in real],
            "tracker_config": {k: getattr(config, k) for k in config.__dataclass_fields__},
            "cpu_threads": os.cpu_count(), "machine": platform.node(), "processor": platform.processor(),
            "rows": rows}


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def _pct(v) -> str:
    return "     -" if v is None else f"{100 * v:5.1f}%"


def format_table(result: dict) -> str:
    names = ", ".join(f["name"] for f in result["real_frames"])
    lines = [f"tracking on real frames ({names}), {result['frames']} frames per speed; errors against the "
             f"homography truth; survival over {result['survival_frames']} frames",
             f"{'tracker':>7s} {'device':>7s} {'predict':>8s} {'speed':>5s} | {'tracks':>6s} {'median px':>9s} "
             f"{'<=1px':>6s} {'<=3px':>6s} {'survival':>8s} | {'ms/frame':>8s}"]
    for r in result["rows"]:
        lines.append(f"{r['tracker']:>7s} {r['device']:>7s} {r['predict']:>8s} {r['speed_px']:5.0f} | "
                     f"{r['tracks_per_frame']:6.0f} {_fmt(r['median_error_px'], '9.2f')} "
                     f"{_pct(r['within_1px'])} {_pct(r['within_3px'])} {_pct(r['survival']):>8s} | "
                     f"{r['ms_per_frame']:8.1f}")
    return "\n".join(lines)
