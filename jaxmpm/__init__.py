"""jaxmpm: a differentiable Material Point Method for soil mechanics, in JAX.

Public names: load_scene, Scene (and its parts), simulate, Simulation, Result, drive,
Checkpointing, ensemble, with_values, use_compilation_cache, SceneError, SimulationError, and the
material classes.
"""

__version__ = "0.1.0"

from jaxmpm.compilation_cache import use_compilation_cache
from jaxmpm.driver import drive
from jaxmpm.ensembles import ensemble
from jaxmpm.errors import SceneError, SimulationError
from jaxmpm.materials import DruckerPrager, LinearElastic
from jaxmpm.results import Result
from jaxmpm.parameters import with_values
from jaxmpm.rollout import Checkpointing
from jaxmpm.scene import (
    Body, Boundaries, Contact, Geostatic, Grid, Kinematics, Numerics, Polygon, Probe, Rectangle, Scene, load_scene,
)
from jaxmpm.simulation import Simulation, simulate

__all__ = [
    "Body",
    "Boundaries",
    "Checkpointing",
    "Contact",
    "DruckerPrager",
    "Geostatic",
    "Grid",
    "Kinematics",
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
    "ensemble",
    "load_scene",
    "simulate",
    "use_compilation_cache",
    "with_values",
]
