"""Every example file loads, validates and runs: each scene a few steps with its own settings,
each calibration file read with its scene and observations, each design file with its
candidates."""

import pathlib

import jax
import numpy as np
import pytest

import jaxmpm

from tests.test_presets import SCENES as RUN_BY_EVERY_PRESET

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"
ALL_SCENES = sorted(path for path in EXAMPLES.glob("*.toml")
                    if not path.name.endswith((".calibration.toml", ".design.toml")))
# tests/test_presets.py runs three steps of these under every preset that compiles other code
SCENES = [path for path in ALL_SCENES if path not in RUN_BY_EVERY_PRESET]
CALIBRATIONS = sorted(EXAMPLES.glob("*.calibration.toml"))
DESIGNS = sorted(EXAMPLES.glob("*.design.toml"))


def test_the_examples_are_found():
    assert len(ALL_SCENES) >= 10 and len(CALIBRATIONS) >= 2 and len(DESIGNS) >= 1
    assert set(RUN_BY_EVERY_PRESET) <= set(ALL_SCENES)            # every example runs in one test or the other
    for path in ALL_SCENES:                                        # and every one reads and round-trips
        scene = jaxmpm.load_scene(path)
        assert jaxmpm.Scene.from_toml(scene.to_toml()) == scene, path.name


@pytest.mark.parametrize("path", SCENES, ids=[path.stem for path in SCENES])
def test_every_example_scene_runs_a_few_steps(path):
    """Three steps with the example's own numerics stay finite and inside the grid, and move
    something (gravity, a prescribed body or an initial velocity acts in every example)."""
    scene = jaxmpm.load_scene(path)
    assert jaxmpm.Scene.from_toml(scene.to_toml()) == scene
    sim = jaxmpm.Simulation(scene)
    step = jax.jit(sim.step)
    params = sim.cast(sim.params)
    start = sim.initial_state(params)
    state = start
    for _ in range(3):
        state, _ = step(params, state)
    particles = state.particles
    assert np.all(np.isfinite(np.asarray(particles.x))) and np.all(np.isfinite(np.asarray(particles.stress)))
    assert int(np.max(np.asarray(particles.flags))) == 0, "a point left the grid or went non-finite"
    assert np.max(np.abs(np.asarray(particles.v))) > 0.0


@pytest.mark.parametrize("path", CALIBRATIONS, ids=[path.stem for path in CALIBRATIONS])
def test_every_example_calibration_file_loads(path):
    from inverse.config import load_calibration

    config = load_calibration(path)
    assert config.fit and config.experiments
    for experiment in config.experiments:
        assert experiment.observations.channels, path.name
        probes = {probe.name for probe in experiment.scene.probes}
        assert set(experiment.observations.channels) <= probes, path.name


@pytest.mark.parametrize("path", DESIGNS, ids=[path.stem for path in DESIGNS])
def test_every_example_design_file_loads(path):
    from inverse.design_command import load_design

    config = load_design(path)
    assert config.parameters and len(config.candidates) >= 2
    for candidate in config.candidates:
        probes = {probe.name for probe in candidate.sim.scene.probes}
        assert candidate.observations.count > 0 and set(candidate.observations.channels) <= probes, path.name
    if config.options["k"] is not None:
        assert config.options["k"] <= len(config.candidates)
