"""The simulated world: scenes with ground truth, textures, and the Warp ray-casting renderer."""

from lapreco_hil.simulators.world.scenes import SCENES, Scene, build_scene
from lapreco_hil.simulators.world.world import SimSettings, SimWorld, default_camera, thirty_degree_optics

__all__ = ["SCENES", "Scene", "SimSettings", "SimWorld", "build_scene", "default_camera", "thirty_degree_optics"]
