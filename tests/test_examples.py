"""Every example file loads and validates: each scene reads and round-trips, each calibration
file is read with its scene and observations, each design file with its candidates. Each
scene's first steps run with its own settings in tests/test_example_references.py, and four
of them under each preset that compiles other code in tests/test_presets.py."""

import pathlib

import pytest

import jaxmpm

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"
ALL_SCENES = sorted(path for path in EXAMPLES.glob("*.toml")
                    if not path.name.endswith((".calibration.toml", ".design.toml")))
CALIBRATIONS = sorted(EXAMPLES.glob("*.calibration.toml"))
DESIGNS = sorted(EXAMPLES.glob("*.design.toml"))


def test_the_examples_are_found():
    assert len(ALL_SCENES) >= 10 and len(CALIBRATIONS) >= 2 and len(DESIGNS) >= 1
    for path in ALL_SCENES:                                        # every one reads and round-trips
        scene = jaxmpm.load_scene(path)
        assert jaxmpm.Scene.from_toml(scene.to_toml()) == scene, path.name


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
