"""Experiment design (inverse.design, `jaxmpm design`): the Fisher information against central
differences, unidentified directions, the greedy selection, the design file's checks, and a
run of the command. The scene is tests/scenes.BLOCK (an elastic block settling under its weight
between slip walls, 14 steps) with a second material no body uses: its parameters have no effect.
"""

import functools

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxmpm
from inverse.design import design, greedy_selection, information, planned_observations
from inverse.experiments import observation_data, residual_function
from inverse.parameters import ParameterSpace
from jaxmpm import SceneError
from jaxmpm.cli import main
from scenes import BLOCK

SPARE = """
[materials.spare]
model = "linear_elastic"
density = 2000.0
young = 2.0e6
poisson = 0.25
"""
TOP = {"top": {"every": 0.0025, "noise": 1e-6, "components": [1]}}
# E and g are told apart: the settlement goes as rho g / M, its oscillation's period as sqrt(rho / M)
GUESS = {"soil.young": 1.0e6, "scene.gravity[1]": -9.81}


@functools.cache
def block():
    return jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK + SPARE))


def test_the_fisher_matrix_is_that_of_central_differences():
    # F = J^T Sigma^-1 J with J from central differences (relative step 1e-6, float64) of the
    # calibration's own residual function.
    sim = block()
    observations = planned_observations(sim, TOP)
    result = design(inverse.Experiment(sim, observations, name="top"), GUESS)
    space = ParameterSpace(sim.params, {name: {"start": value} for name, value in GUESS.items()})
    residuals = residual_function(sim, observations, space.insert)
    data, base = observation_data(sim, observations), sim.cast(sim.params)
    point = space.start_values()
    columns = []
    for index in range(len(point)):
        step = 1e-6 * abs(point[index])
        up, down = point.copy(), point.copy()
        up[index] += step
        down[index] -= step
        difference = residuals(jnp.asarray(up), data, base) - residuals(jnp.asarray(down), data, base)
        columns.append(np.asarray(difference) / (2 * step))
    jacobian = np.stack(columns, axis=1)
    assert np.all(np.abs(jacobian) > 0).any()
    np.testing.assert_allclose(result.fisher(), jacobian.T @ jacobian, rtol=1e-5)
    info = result.information()
    assert info.identified.all() and np.isfinite(info.log_det)
    np.testing.assert_allclose(info.covariance, np.linalg.inv(result.fisher()), rtol=1e-6)


def test_a_parameter_without_effect_and_a_hidden_combination_are_reported_with_their_directions():
    sim = block()
    observations = planned_observations(sim, TOP)
    parameters = {"soil.young": 1.0e6, "soil.density": 1800.0, "spare.young": 2.0e6}
    result = design(inverse.Experiment(sim, observations, name="top"), parameters)
    info = result.information()
    assert np.all(np.isinf(info.stderr))      # every parameter takes part in an unseen direction
    assert info.log_det == -np.inf
    directions = [d.describe(result.names) for d in info.unidentified]
    # the spare material is used by no body; the block's motion depends on E / rho alone
    # (rho u'' = div sigma(E) + rho g), so raising both by the same fraction changes nothing
    assert directions == ["1.00·spare.young", "0.71·soil.young + 0.71·soil.density"]
    assert "0.71·soil.young + 0.71·soil.density is not identified" in result.summary()


def test_the_greedy_selection_picks_the_known_best_set():
    # Three parameters; a sees t0, b sees it twice as precisely; c sees t1 + t2, d t1 - t2,
    # e t2 weakly. Known best: c first (the largest single eigenvalue, 4.5), then b (4, a new
    # direction), then d, which completes them: F = diag(4) + [[3.25, 1.25], [1.25, 3.25]], det 4 * 9.
    def fisher(*rows):
        jacobian = np.array(rows, float)
        return np.broadcast_to(jacobian.T @ jacobian, (1, 3, 3))

    fishers = {"a": fisher([1, 0, 0]), "b": fisher([2, 0, 0]), "c": fisher([0, 1.5, 1.5]), "d": fisher([0, 1, -1]),
               "e": fisher([0, 0, 0.5])}
    names, guesses, scales = ("t0", "t1", "t2"), np.ones((1, 3)), np.ones((1, 3))
    steps = greedy_selection(fishers, 3, names, guesses, scales)
    assert [step.added for step in steps] == ["c", "b", "d"]
    assert [step.worst.rank_and_log_det[0] for step in steps] == [1, 2, 3]
    np.testing.assert_allclose(steps[-1].worst.log_det, np.log(4.0 * 9.0))
    np.testing.assert_allclose(steps[-1].worst.stderr, [0.5, np.sqrt(3.25 / 9), np.sqrt(3.25 / 9)])
    info = information(fishers["c"][0] + fishers["a"][0], names, [1.0, 1.0, 1.0])
    assert [d.describe(names) for d in info.unidentified] == ["0.71·t1 − 0.71·t2"]


def test_the_worst_case_over_guesses_and_the_selection_on_a_scene():
    sim = block()
    parameters = {"soil.young": {"guess": 1.0e6, "low": 0.6e6, "high": 1.6e6}, "scene.gravity[1]": -9.81}
    sparse = {"top": {"times": [0.01], "noise": 1e-6, "components": [1]}}
    candidates = [inverse.Experiment(sim, planned_observations(sim, TOP), name="dense"),
                  inverse.Experiment(sim, planned_observations(sim, sparse), name="last")]
    result = design(candidates, parameters, k=1, guesses="corners")
    assert result.guesses.shape == (3, 2)             # the guess and the two corners of E's range
    assert result.fishers.shape == (3, 2, 2, 2)
    assert [step.added for step in result.selection] == ["dense"]
    dense = result.worst_stderr("dense")
    assert np.all(np.isfinite(dense)) and np.all(dense >= result.information("dense").relative_stderr)
    assert np.all(np.isinf(result.worst_stderr("last")))     # one value cannot give two parameters


DESIGN = """
scene = "block.toml"
k = 1
guesses = "corners"

[parameters]
"soil.young" = { guess = 1.0e6, low = 0.6e6, high = 1.6e6 }
"scene.gravity[1]" = -9.81

[[candidates]]
name = "dense"
probes.top = { components = [1], every = 0.0025, noise = 1e-6 }

[[candidates]]
name = "moved"
probes.block_move = { every = 0.005, noise = [1e-6, 1e-6] }
"""


def write_design(folder, text=DESIGN):
    (folder / "block.toml").write_text(BLOCK + SPARE)
    path = folder / "design.toml"
    path.write_text(text)
    return path


def test_jaxmpm_design_prints_its_table_and_writes_its_files(tmp_path, capsys):
    import h5py

    path = write_design(tmp_path)
    outputs = [tmp_path / name for name in ("d.h5", "d.csv", "d.png")]
    assert main(["design", str(path)] + [f"-o{output}" for output in outputs]) == 0
    printed = capsys.readouterr().out
    assert "Greedy selection of 1" in printed and "dense" in printed
    with h5py.File(outputs[0]) as file:
        assert file["fishers"].shape == (3, 2, 2, 2)          # points, candidates, P, P
        assert [n.decode() for n in file["selection/order"][()]] == ["dense"]
        assert np.all(np.isfinite(file["designs/dense/stderr"][()]))
    rows = outputs[1].read_text().splitlines()
    assert rows[0].startswith("design,point,log_det,soil.young,soil.young_stderr")
    assert len(rows) == 1 + 3 * 3               # dense, moved, all candidates at 3 points
    assert outputs[2].stat().st_size > 0


@pytest.mark.parametrize("change, message", [
    ((", noise = 1e-6 }", " }"), "candidates[0].probes.top.noise is missing: it is required."),
    (("probes.top =", "probes.tip ="), "candidates[0].probes.tip is not a probe of the scene"),
    (("every = 0.0025", "every = 0.5"), "candidates[0].probes.top.every = 0.5 must be a time in (0, 0.01] s."),
    (("every = 0.0025", "times = [0.02]"), "candidates[0].probes.top.times has t = 0.02 s outside the simulated span"),
    (("every = 0.0025", "every = 0.0025, times = [0.01]"), "candidates[0].probes.top must give exactly one of times"),
    (("components = [1]", "components = [1.5]"), "candidates[0].probes.top.components[0] = 1.5 must be a whole number."),
    (("components = [1]", "components = [4]"), "names component 4; the probe has 2."),
    (("noise = [1e-6, 1e-6]", "noise = [1e-6, -1.0]"), "candidates[1].probes.block_move.noise[1] = -1.0 is out of range"),
    (("k = 1", "k = 3"), "k = 3 must be a whole number from 1 to the number of candidates (2)."),
    (('"scene.gravity[1]"', '"soil.yung"'), "parameters: 'soil.yung' is not a parameter of the scene (did you mean"),
    (("guess = 1.0e6,", "guess = 2.0e6,"), "parameters.soil.young: the initial value 2e+06 is not strictly inside"),
    (('name = "dense"', 'name = "dense"\nset = { "soil.young" = 2.0e6 }'),
     "candidates.dense.set.soil.young is also a design parameter"),
    (('name = "dense"', 'name = "dense"\ncolour = "red"'), "candidates[0].colour is not a known key."),
    (('guesses = "corners"', 'guesses = "all"'), "guesses = 'all' is not one of 'guess', 'corners', 'samples'."),
    (('scene = "block.toml"', 'scene = "missing.toml"'), "missing.toml"),
])
def test_jaxmpm_design_refuses_a_bad_design_file_in_one_sentence(tmp_path, capsys, change, message):
    old, new = change
    assert old in DESIGN
    path = write_design(tmp_path, DESIGN.replace(old, new, 1))
    assert main(["design", str(path), "-o", str(tmp_path / "d.h5")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("jaxmpm: error: ") and error.count("\n") == 1 and "Traceback" not in error
    assert message in error
    assert not (tmp_path / "d.h5").exists()


def test_jaxmpm_design_refuses_an_output_it_cannot_write(tmp_path, capsys):
    path = write_design(tmp_path)
    assert main(["design", str(path), "-o", str(tmp_path / "d.txt")]) == 2
    assert "the file type must be one of .h5" in capsys.readouterr().err


def test_a_candidate_without_noise_is_refused_before_compiling():
    sim = block()
    measured = inverse.Observations.from_arrays({"top": ([0.005, 0.01], [[0.0], [0.0]], [1])})
    with pytest.raises(SceneError, match=r"candidates.top.probes.top.noise is missing"):
        design(inverse.Experiment(sim, measured, name="top"), GUESS)


def test_the_design_file_keys_in_the_docs_are_current():
    # docs/experiment_design.md holds the keys generated from the schema; regenerate them after
    # changing it (python -m inverse.design_command).
    from pathlib import Path

    from inverse.design_command import REFERENCE_MARKERS, reference_markdown

    page = (Path(__file__).resolve().parents[1] / "docs" / "experiment_design.md").read_text()
    start, end = (page.index(marker) for marker in REFERENCE_MARKERS)
    assert page[start + len(REFERENCE_MARKERS[0]):end].strip() == reference_markdown().strip()
