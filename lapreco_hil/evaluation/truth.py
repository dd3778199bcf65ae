"""Ground truth a source may carry: the true surface and the true camera poses (simulator, session)."""

from __future__ import annotations

from dataclasses import dataclass

from ..geometry import SampledPoses

__all__ = ["GroundTruth", "SampledPoses"]


@dataclass(frozen=True)
class GroundTruth:
    """``surface``: a pyvista PolyData in the world frame (metres) or None; ``camera_pose``: a callable
    t_ns -> true T_world_camera, or None."""

    surface: object | None = None
    camera_pose: object | None = None
