"""jaxmpm: a differentiable Material Point Method for soil mechanics, in JAX.

Public names: load_scene, Scene (and its parts), simulate, Simulation, Result, drive,
Checkpointing, ensemble, with_values, use_compilation_cache, refined_scene, compare_results,
SceneError, SimulationError, and the material classes.
"""

__version__ = "0.1.0"

import importlib

# Where each public name lives. They are imported when first used (PEP 562), so that
# `import jaxmpm.cli` starts in milliseconds and the `jaxmpm` command can take Ctrl-C quietly
# while JAX itself is still importing (`jaxmpm.cli.interrupts_end_quietly`).
_PUBLIC = {
    "use_compilation_cache": "jaxmpm.running.compilation_cache",
    "drive": "jaxmpm.running.driver",
    "ensemble": "jaxmpm.running.ensembles",
    "SceneError": "jaxmpm.errors",
    "SimulationError": "jaxmpm.errors",
    "DruckerPrager": "jaxmpm.materials",
    "LinearElastic": "jaxmpm.materials",
    "Result": "jaxmpm.running.results",
    "with_values": "jaxmpm.scene.parameters",
    "Checkpointing": "jaxmpm.running.rollout",
    **{name: "jaxmpm.scene" for name in (
        "Body", "Boundaries", "Contact", "Geostatic", "Grid", "Kinematics", "Numerics", "Polygon", "Probe",
        "Rectangle", "Scene", "load_scene")},
    "Simulation": "jaxmpm.running.simulation",
    "refined_scene": "jaxmpm.running.refinement",
    "compare_results": "jaxmpm.running.refinement",
    "simulate": "jaxmpm.running.simulation",
}


def __getattr__(name):
    """A public name (`_PUBLIC`) or a submodule (jaxmpm.scene.parameters, ...), imported on first use."""
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
    else:
        try:
            value = importlib.import_module(f"jaxmpm.{name}")
        except ModuleNotFoundError as error:
            if error.name != f"jaxmpm.{name}":      # a dependency missing inside a real submodule
                raise
            raise AttributeError(f"module 'jaxmpm' has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))


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
    "compare_results",
    "drive",
    "ensemble",
    "load_scene",
    "refined_scene",
    "simulate",
    "use_compilation_cache",
    "with_values",
]
