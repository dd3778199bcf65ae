"""Ground truth a source may carry: the true surface and the true camera poses (simulator, session). A core
type: sessions and simulators produce it, evaluation and the outputs read it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GroundTruth:
    """``surface``: a pyvista PolyData in the world frame (metres) or None; ``camera_pose``: a callable
    t_ns -> true T_world_camera, or None."""

    surface: object | None = None
    camera_pose: object | None = None
