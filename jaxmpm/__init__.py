"""jaxmpm: a differentiable Material Point Method for soil mechanics, in JAX.

Public names (SPEC section 4): load_scene, Scene, simulate, Simulation, Result, drive,
Checkpointing, SceneError, SimulationError, and the material classes.
"""

__version__ = "0.1.0"

from jaxmpm.driver import drive
from jaxmpm.errors import SceneError, SimulationError
from jaxmpm.materials import DruckerPrager, LinearElastic
from jaxmpm.results import Result
from jaxmpm.rollout import Checkpointing
from jaxmpm.scene import Body, Boundaries, Geostatic, Grid, Numerics, Polygon, Probe, Rectangle, Scene, load_scene
from jaxmpm.simulation import Simulation, simulate

__all__ = [
    "Body",
    "Boundaries",
    "Checkpointing",
    "DruckerPrager",
    "Geostatic",
    "Grid",
    "LinearElastic",
    "Numerics",
    "Polygon",
    "Probe",
    "Rectangle",
    "Result",
    "Scene",
    "SceneError",
    "Simulation",
    "SimulationError",
    "drive",
    "load_scene",
    "simulate",
]
