"""Plain data that flows between stages. Every sample carries its capture time (int ns, one monotonic
clock) and a sequence number, stamped where it was captured, never after processing."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One video frame as the grabber delivered it (distorted, BGR uint8, H x W x 3)."""

    image: np.ndarray
    t_ns: int
    seq: int
    # when it was captured on this host's monotonic clock (time.monotonic_ns), where the grabber knows: the
    # V4L2 buffer time, a real-time replay's or simulation's due time. The live latency starts here, so time
    # a frame spent queued in the grabber counts. (t_ns is the capture time on the session's clock.)
    host_ns: int | None = None
    # the other cameras of a rig, captured at the same instant as ``image`` (camera 0): camera k's image is
    # views[k - 1] (a stereo scope: one). Each keeps its own size; nothing is resampled.
    views: tuple[np.ndarray, ...] = ()

    @property
    def n_cameras(self) -> int:
        return 1 + len(self.views)

    def image_of(self, camera: int) -> np.ndarray:
        return self.image if camera == 0 else self.views[camera - 1]


@dataclass(frozen=True)
class JointSample:
    """One reading of all joints: positions in SI units (rad, m) in the robot's joint order."""

    q: np.ndarray
    t_ns: int
    seq: int


@dataclass(frozen=True)
class MarkerSample:
    """One pose of a tracked tool (an optical or EM tracker's marker) in the tracker's frame: T_tracker_marker
    4x4 in METRES (the device reports millimetres; drivers convert), the capture time (int ns, the run's clock),
    a sequence number, the tool's name, its fit RMS error in mm as the device reports it, and whether the
    device flagged it inside its characterised volume (False: still a pose, not a trusted one)."""

    T_tracker_marker: np.ndarray
    t_ns: int
    seq: int
    tool: str
    rms_mm: float
    in_volume: bool


@dataclass(frozen=True)
class JointLimits:
    lower: np.ndarray
    upper: np.ndarray


@dataclass(frozen=True)
class RobotInfo:
    """What a robot driver says about itself."""

    name: str
    joint_names: tuple[str, ...]
    limits: JointLimits


@dataclass(frozen=True)
class PosePrior:
    """Camera pose from kinematics at a frame time with its covariance.

    ``cov`` is 6x6 in GTSAM's Pose3 tangent order (rotation, translation), expressed in the camera frame.
    """

    T_world_camera: np.ndarray
    cov: np.ndarray
    t_ns: int


@dataclass(frozen=True)
class Observations:
    """What the front-end saw in one frame: undistorted pixel positions (ideal pinhole with the camera's K)
    of live tracks, keyed by track id, with the colour (RGB uint8) under each."""

    frame_seq: int
    t_ns: int
    track_ids: np.ndarray  # (N,) int64
    uv: np.ndarray  # (N, 2) float64, undistorted pixels
    colors: np.ndarray  # (N, 3) uint8 RGB
    n_new: int = 0
    timings_s: dict[str, float] = field(default_factory=dict)
    # which camera of the rig these pixels belong to (0: the reference camera)
    camera: int = 0
    # the front-end's funnel for this frame: counts per stage (see FUNNEL_STAGES), summed over a run
    funnel: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])


@dataclass(frozen=True)
class RobotDescription:
    """What turns joint readings into camera poses: the URDF (a packaged name such as 'ecm' or a file path),
    the link that holds the scope, the hand-eye T_tip_camera, and where the robot base sits in the world."""

    urdf: str
    tip_frame: str
    T_tip_camera: np.ndarray
    T_world_base: np.ndarray = field(default_factory=lambda: np.eye(4))


# the tracking funnel, stage by stage: corners detected, tracks that LK followed, tracks left after the drift
# check; then the mapper's: tracks that became triangulation candidates, points triangulated, final inliers
FUNNEL_STAGES = ("corners", "after_lk", "after_drift_check", "candidates", "triangulated", "inliers")


@dataclass(frozen=True)
class FrameMotion:
    """What the pose source says about the camera's motion into a new frame, for the front-end to start each
    track where it should land rather than where it was (fast scope motion moves tissue 50-80 px a frame).

    ``T_cur_prev`` maps points from the previous frame's camera to the new one's (undistorted pinhole cameras).
    Tracks in ``track_ids`` have a known depth ``depth_m`` (z in the previous camera, metres: their landmark,
    or the map's depth nearby); the others are searched along their epipolar line over ``depth_range_m``
    (near, far), never started from the same pixel."""

    T_cur_prev: np.ndarray
    track_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    depth_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    depth_range_m: tuple[float, float] = (0.01, 0.3)
