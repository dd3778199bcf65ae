"""What the mapper keeps per frame and per keyframe, and the choice of keyframes: robot motion, track loss, and
parallax with the camera rotation removed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lapreco_hil.config import MapperConfig
from lapreco_hil.geometry import rotation_angle
from lapreco_hil.types import Observations, PosePrior


@dataclass
class Keyframe:
    id: int
    frame_seq: int
    t_ns: int
    prior: PosePrior
    T_world_camera: np.ndarray
    track_ids: np.ndarray
    uv: np.ndarray
    colors: np.ndarray
    refined: bool = False
    # a stereo partner's view: the id of its rig's reference keyframe (camera 0, taken at the same instant),
    # the rig camera it is, and T_cam0_cam (its pixels are re-expressed with camera 0's K: one pinhole model
    # for every view in triangulation and BA). None for a reference (camera 0) keyframe.
    reference: int | None = None
    camera: int = 0
    T_cam0_cam: np.ndarray | None = None


@dataclass(slots=True)
class FrameRecord:
    seq: int
    t_ns: int
    T_prior: np.ndarray
    cov: np.ndarray | None
    keyframe: int | None
    track_ids: np.ndarray | None  # None once the frame's pose is final (its keyframes were retired)
    uv: np.ndarray | None
    T_refined: np.ndarray | None = None


@dataclass(slots=True)
class PendingStructure:
    """A keyframe whose new points are still to be made (and its local BA asked for after them)."""

    kf_id: int
    local_ba: bool
    tracks: list[int] | None = None  # the candidate tracks still to triangulate (None: not chosen yet)
    colors: dict[int, np.ndarray] | None = None  # their colours in the keyframe


def is_keyframe(last: Keyframe | None, obs: Observations, prior: PosePrior, K: np.ndarray,
                config: MapperConfig) -> bool:
    """Whether a frame becomes a keyframe after ``last`` (the first one with any track does)."""
    if last is None:
        return len(obs) > 0
    T0, T1 = last.prior.T_world_camera, prior.T_world_camera
    if np.linalg.norm(T1[:3, 3] - T0[:3, 3]) > config.keyframe_translation_m:
        return True
    if rotation_angle(T0[:3, :3].T @ T1[:3, :3]) > config.keyframe_rotation_rad:
        return True
    # the tracks both hold, found once for the count and the parallax (a frame's track ids are distinct)
    common = np.intersect1d(last.track_ids, obs.track_ids, assume_unique=True, return_indices=True)[1:]
    if len(common[0]) < config.keyframe_track_ratio * max(len(last.track_ids), 1):
        return True
    return median_parallax_deg(last, obs, prior, K, common) > config.keyframe_parallax_deg


def median_parallax_deg(last: Keyframe, obs: Observations, prior: PosePrior, K: np.ndarray,
                        common: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Median angle between each common track's ray in the last keyframe and in this frame, with the
    camera rotation between them removed: what a triangulation from the two would get. ``common``: the
    common tracks' indices in each (ia, ib), if known."""
    ia, ib = common if common is not None else \
        np.intersect1d(last.track_ids, obs.track_ids, return_indices=True)[1:]
    if len(ia) == 0:
        return 0.0
    Kinv = np.linalg.inv(K)

    def rays(uv):
        r = np.column_stack([uv, np.ones(len(uv))]) @ Kinv.T
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    R_rel = last.prior.T_world_camera[:3, :3].T @ prior.T_world_camera[:3, :3]
    a, b = rays(last.uv[ia]), rays(obs.uv[ib]) @ R_rel.T
    return float(np.degrees(np.median(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))))
