"""numerics.preset: what each preset sets, that explicit keys override it, and that every preset
runs the example scenes."""

import dataclasses
import pathlib

import jax
import numpy as np
import pytest

import jaxmpm
from jaxmpm import Numerics, SceneError
from jaxmpm.scene import PRESETS
from tests.scenes import BLOCK

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"
# Between them, every feature of the example scenes: Drucker–Prager flow with a free surface,
# a rigid body and a prescribed one along a velocity table, each in contact with sand, and an
# axisymmetric viscoplastic scene with two contact pairs and an elastic body. Every preset on
# every example scene: benchmarks/presets_on_examples.py (36 compilations, ~4 minutes).
SCENES = [EXAMPLES / name for name in
          ("column_collapse.toml", "retaining_wall.toml", "retaining_wall_active.toml", "pile_driving.toml")]


def test_no_numerics_gives_the_balanced_preset():
    numerics = Numerics()
    assert numerics.preset == "balanced"
    assert (numerics.shape, numerics.transfer, numerics.ppc, numerics.dtype, numerics.update) == (
        "bspline2", "apic", 2, "float64", "musl")


def test_explicit_keys_override_the_preset_and_survive_a_change_of_preset():
    numerics = Numerics(preset="fast", ppc=3)
    assert (numerics.shape, numerics.dtype, numerics.ppc) == ("linear", "float32", 3)
    accurate = dataclasses.replace(numerics, preset="accurate")
    assert accurate.shape == PRESETS["accurate"]["shape"] and accurate.dtype == "float64"
    assert accurate.ppc == 3                                       # given, so kept
    assert dataclasses.replace(accurate, shape="gimp").shape == "gimp"


def test_a_scene_file_states_only_what_it_gave():
    scene = jaxmpm.Scene.from_toml(BLOCK)             # [numerics]: shape, transfer, ppc, damping
    written = scene.to_dict()["numerics"]
    assert written == {"preset": "balanced", "shape": "linear", "transfer": "flip", "ppc": 2, "damping": 0.0}
    assert jaxmpm.Scene.from_toml(scene.to_toml()) == scene
    fast = scene.with_value("numerics.preset", "fast")
    assert fast.numerics.dtype == "float32"                     # not given by the file: from the preset
    assert (fast.numerics.shape, fast.numerics.transfer) == ("linear", "flip")   # given: kept


def test_an_unknown_preset_is_one_clear_error():
    text = (EXAMPLES / "vibrating_bar.toml").read_text().replace("[numerics]", '[numerics]\npreset = "quick"')
    with pytest.raises(SceneError, match=r"numerics.preset = 'quick' is not one of 'fast', 'balanced', 'accurate'"):
        jaxmpm.Scene.from_toml(text)


# "accurate" is "balanced" with ppc 3: the same compiled code paths on more points, so the
# tests run the two presets that differ in code (benchmarks/presets_on_examples.py runs all
# three on every example). The step is compiled with LLVM's optimisations off: three steps
# run in well under a second either way, and compiling takes 2-2.5 times less (the same
# program, only its machine code less optimised).
QUICK_TO_COMPILE = {"xla_backend_optimization_level": 0}
@pytest.mark.parametrize("preset", ["fast", "balanced"])
def test_every_preset_runs_the_example_scenes(preset):
    """Each example with its [numerics] table replaced by the preset alone (its damping kept):
    three steps stay finite, inside the grid, and use the preset's shape function."""
    for path in SCENES:
        scene = jaxmpm.load_scene(path)
        scene = dataclasses.replace(scene, numerics=Numerics(preset=preset, damping=scene.numerics.damping))
        sim = jaxmpm.Simulation(scene)
        assert sim.structure.layout.shape_name == PRESETS[preset]["shape"]
        step = jax.jit(sim.step, compiler_options=QUICK_TO_COMPILE)
        params = sim.cast(sim.params)
        state = sim.initial_state(params)
        for _ in range(3):
            state, _ = step(params, state)
        particles = state.particles
        assert particles.x.dtype == np.dtype(PRESETS[preset]["dtype"]), path.name
        assert np.all(np.isfinite(np.asarray(particles.stress))), path.name
        assert int(np.max(np.asarray(particles.flags))) == 0, path.name
