"""The constant offset between video and kinematics timestamps (kinematics time = video time + offset).

Features are tracked through the session; for a candidate offset, the camera poses at the frame times come
from the joint readings at the shifted times, and every pair of frames some distance apart gets its
epipolar geometry from those poses. The Sampson distance of the tracked correspondences to it is smallest
when the offset is right. The cost over a grid of offsets (coarse, then fine around the best) is minimised
with a parabola through the three best points; the uncertainty is the spread of that minimum when the frame
pairs are resampled (bootstrap).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lapreco_hil.config import PipelineConfig
from lapreco_hil.errors import CalibrationError
from lapreco_hil.frontend import make_frontend
from lapreco_hil.geometry import SampledPoses, inv_T
from lapreco_hil.kinematics import CameraKinematics
from lapreco_hil.robot_models import urdf_path

log = logging.getLogger(__name__)


@dataclass
class OffsetEstimate:
    offset_ns: int
    sigma_ns: int
    cost_at_zero_px: float
    cost_at_offset_px: float
    pairs: int
    grid_s: np.ndarray
    cost_px: np.ndarray

    def summary(self) -> dict:
        return {"offset_ms": self.offset_ns * 1e-6, "sigma_ms": self.sigma_ns * 1e-6, "pairs": self.pairs,
                "median_sampson_px_at_zero": self.cost_at_zero_px,
                "median_sampson_px_at_offset": self.cost_at_offset_px}


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def sampson_px(E: np.ndarray, x1: np.ndarray, x2: np.ndarray, f: float) -> np.ndarray:
    """Sampson distances (pixels, for focal length f) of normalised correspondences to essential matrix E."""
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.sum(h2 * Ex1, axis=1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return f * np.sqrt(num / np.maximum(den, 1e-18))


def track_session(session, config: PipelineConfig, device: str = "cpu", tracker: str = "opencv"):
    """Observations of every frame (undistorted pixels keyed by track id)."""
    frontend = make_frontend(tracker, session.meta.camera, config.tracker, device)
    return [frontend.process(session.frame(i)) for i in range(len(session))]


def estimate_time_offset(session, config: PipelineConfig | None = None, search_s: float = 1.0,
                         pair_gaps: tuple[int, ...] = (5, 10, 20, 40),
                         min_common: int = 15, bootstrap: int = 200, device: str = "cpu",
                         seed: int = 0) -> OffsetEstimate:
    if session.meta.pose_source != "joints":
        raise CalibrationError(f"session '{session.folder}' has camera poses, not joint readings: there is no "
                               f"kinematics clock to align")
    config = config or PipelineConfig()
    robot = session.robot
    kin = CameraKinematics(str(urdf_path(robot.urdf)), robot.tip_frame, robot.T_tip_camera, robot.T_world_base)
    # camera poses at the readings, interpolated on SE(3) between them (as the pipeline's priors are)
    poses_at = SampledPoses(np.array([j.t_ns for j in session.joint_samples], np.int64),
                            np.array([kin.camera_pose(j.q) for j in session.joint_samples]))
    obs = track_session(session, config, device)
    K = session.meta.camera.K
    Kinv = np.linalg.inv(K)
    f = float(K[0, 0])
    # a time shift moves both poses of a pair alike, so it shows only where the velocity differs between
    # them: pairs far apart in time (where tracks survive) carry most of the signal
    pairs = []
    for gap in pair_gaps:
        for i in range(0, len(obs) - gap):
            a, b = obs[i], obs[i + gap]
            common, ia, ib = np.intersect1d(a.track_ids, b.track_ids, return_indices=True)
            if len(common) >= min_common:
                x1 = np.column_stack([a.uv[ia], np.ones(len(ia))]) @ Kinv.T
                x2 = np.column_stack([b.uv[ib], np.ones(len(ib))]) @ Kinv.T
                pairs.append((a.t_ns, b.t_ns, x1[:, :2], x2[:, :2]))
    if len(pairs) < 5:
        raise CalibrationError(f"session '{session.folder}': only {len(pairs)} frame pairs share {min_common}+ "
                               f"tracks; the time offset needs a moving camera over a textured scene")

    def costs(offset_s: float) -> np.ndarray:
        off = int(round(offset_s * 1e9))
        out = np.empty(len(pairs))
        for n, (ta, tb, x1, x2) in enumerate(pairs):
            T_ab = inv_T(poses_at(ta + off)) @ poses_at(tb + off)  # camera b in camera a
            R, t = T_ab[:3, :3], T_ab[:3, 3]
            # x_a ~ R x_b + t  =>  x_a^T [t]x R x_b = 0
            E = _skew(t) @ R
            out[n] = np.median(sampson_px(E.T, x1, x2, f)) if np.linalg.norm(t) > 1e-6 else np.nan
        return out

    period_s = session.frame_period_ns * 1e-9
    coarse = np.arange(-search_s, search_s + 1e-12, period_s / 2)
    table = np.array([costs(o) for o in coarse])  # (offsets, pairs)
    valid = ~np.any(np.isnan(table), axis=0)
    table = table[:, valid]
    best = coarse[int(np.argmin(table.mean(axis=1)))]
    fine = np.arange(best - period_s, best + period_s + 1e-12, period_s / 20)
    fine_table = np.array([costs(o) for o in fine])[:, valid]
    grid = np.concatenate([coarse, fine])
    order = np.argsort(grid)
    grid, all_costs = grid[order], np.concatenate([table, fine_table])[order]

    fine_mask = (grid >= fine[0] - 1e-12) & (grid <= fine[-1] + 1e-12)
    grid_f, costs_f = grid[fine_mask], all_costs[fine_mask]

    def estimate(cols: np.ndarray) -> float:
        curve = costs_f[:, cols].mean(axis=1)
        k = int(np.clip(np.argmin(curve), 1, len(curve) - 2))
        a, b, _ = np.polyfit(grid_f[k - 1:k + 2] - grid_f[k], curve[k - 1:k + 2], 2)
        return float(grid_f[k] - b / (2 * a)) if a > 0 else float(grid_f[k])

    n = costs_f.shape[1]
    offset = estimate(np.arange(n))
    rng = np.random.default_rng(seed)
    boots = [estimate(rng.integers(0, n, n)) for _ in range(bootstrap)]
    zero = costs(0.0)[valid]
    at = costs(offset)[valid]
    log.info("time offset %.1f ms +- %.1f ms from %d frame pairs", offset * 1e3, np.std(boots) * 1e3, n)
    return OffsetEstimate(int(round(offset * 1e9)), int(round(np.std(boots) * 1e9)), float(np.median(zero)),
                          float(np.median(at)), n, grid, all_costs.mean(axis=1))
