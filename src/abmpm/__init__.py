"""abmpm: Adaptive Boundary Material Point Method on NVIDIA Warp."""

from .errors import AbmpmError, MeshError, OutputError, SceneError, SimulationBlowUp
from .scene.loader import list_builtin_scenes, load_scene
from .scene.model import (
    BoxBody,
    BunnyBody,
    Elastic,
    EllipsoidBody,
    Fluid,
    MeshBody,
    Output,
    Sand,
    Scene,
    SimulationSettings,
    Snow,
    SphereBody,
    Viscoelastic,
    Walls,
)
from .simulation import Particles, Simulation

__version__ = "0.1.0"

__all__ = [
    "AbmpmError", "MeshError", "OutputError", "SceneError", "SimulationBlowUp",
    "BoxBody", "BunnyBody", "Elastic", "EllipsoidBody", "Fluid", "MeshBody", "Output", "Sand",
    "Scene", "SimulationSettings", "Snow", "SphereBody", "Viscoelastic", "Walls",
    "Particles", "Simulation", "load_scene", "list_builtin_scenes",
]
