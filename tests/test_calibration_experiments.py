"""Calibration where MPM is needed: Levenberg–Marquardt, large deformation, several experiments.

Twins (data made by the scene itself from known parameters, docs/calibration.md):
- a small heap: a viscoplastic sand column slumping under gravity, its points crossing cells
  (a coarse version of examples/calibrate_heap_scene.toml);
- a footing pushed at two rates into viscoplastic sand (a coarse version of
  examples/calibrate_rates_scene.toml), the two experiments sharing one compiled simulation;
- a rigid retaining wall pushed over by its backfill (a coarse version of
  examples/calibrate_wall_scene.toml), observed through the wall top and the thrust.
"""

import functools
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxmpm
from inverse import levenberg_marquardt
from inverse.problem import cells_crossed, linear_shape_warning
from inverse.fit import gauss_newton
from inverse.experiments import (
    base_parameters, experiments_from, group_experiments, observation_data, problem_arguments, problem_residuals,
    residual_function, window_mean,
)
from jaxmpm import SceneError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
sys.path.insert(0, str(EXAMPLES))
import calibrate_heap as heap  # noqa: E402
import calibrate_rates as rates  # noqa: E402

sys.path.insert(0, str(EXAMPLES.parent / "benchmarks"))
from calibration_study import wall_observations  # noqa: E402


def small_heap_toml(shape="bspline2"):
    """The heap twin's scene at a third of its points: a 0.08 x 0.06 m column, 0.3 s, at
    twice the example's time step (cfl 0.8: half the steps of every Levenberg–Marquardt
    iteration; the twin's data are made at the same step)."""
    text = (EXAMPLES / "calibrate_heap_scene.toml").read_text()
    for old, new in (("size = [0.4, 0.1]", "size = [0.25, 0.08]"), ("cfl = 0.4", "cfl = 0.8"), ("[[0.0, 0.0], [0.16, 0.08]]", "[[0.0, 0.0], [0.08, 0.06]]"),
                     ("duration = 0.5", "duration = 0.3"), ("at = [0.16, 0.08]", "at = [0.08, 0.06]"),
                     ("at = [0.08, 0.08]", "at = [0.04, 0.06]"), ("at = [0.16, 0.0]", "at = [0.08, 0.0]"),
                     ('shape = "bspline2"', f'shape = "{shape}"')):
        assert old in text
        text = text.replace(old, new)
    return text


@functools.lru_cache
def small_heap(shape="bspline2"):
    return jaxmpm.Simulation(jaxmpm.Scene.from_toml(small_heap_toml(shape)))


@functools.lru_cache
def coarse_rates():
    text = (EXAMPLES / "calibrate_rates_scene.toml").read_text().replace("cell = 0.025", "cell = 0.05")
    return jaxmpm.Simulation(jaxmpm.Scene.from_toml(text))


def test_levenberg_marquardt_finds_the_minimum_of_rosenbrock_residuals():
    # r = (10 (y - x^2), 1 - x): the Rosenbrock valley, minimum r = 0 at (1, 1) (Moré, Garbow
    # & Hillstrom 1981, problem 1), from their standard start (-1.2, 1).
    # The iterates must not depend on the residuals' scale (a stated noise sigma scales them).
    def path(scale):
        def residuals(z):
            return scale * jnp.array([10.0 * (z[1] - z[0] ** 2), 1.0 - z[0]])

        state = levenberg_marquardt.init(residuals, jnp.array([-1.2, 1.0]))
        step = jax.jit(functools.partial(levenberg_marquardt.step, residuals))   # compiled, as calibrate runs it
        points = []
        for _ in range(60):
            state = step(state)
            points.append(np.asarray(state.z))
        return np.array(points)

    unit, large = path(1.0), path(1e4)
    np.testing.assert_allclose(unit[-1], [1.0, 1.0], atol=1e-10)
    np.testing.assert_allclose(large, unit, rtol=1e-9, atol=1e-12)
    residuals = lambda z: jnp.array([10.0 * (z[1] - z[0] ** 2), 1.0 - z[0]])  # noqa: E731
    r, jacobian = levenberg_marquardt.residuals_and_jacobian(residuals, jnp.array([0.5, 2.0]))
    np.testing.assert_allclose(jacobian, [[-10.0, 10.0], [-1.0, 0.0]])
    np.testing.assert_allclose(r, [17.5, 0.5])


def test_a_rejected_step_keeps_the_point_and_raises_the_damping():
    # A residual that is NaN away from the start: every trial step fails, nothing moves.
    def residuals(z):
        return jnp.where(jnp.abs(z - 3.0) < 1e-9, z - 2.0, jnp.nan)

    state = levenberg_marquardt.init(residuals, jnp.array([3.0]))
    after = levenberg_marquardt.step(residuals, state)
    assert float(after.z[0]) == 3.0 and not bool(after.accepted)
    assert float(after.damping) == pytest.approx(2.0 * float(state.damping))


def test_window_mean_is_the_centred_running_mean():
    history = jnp.asarray(np.random.default_rng(0).normal(size=(40, 2)))
    averaged = np.asarray(window_mean(history, 5))
    reference = np.stack([np.convolve(np.pad(history[:, k], 2, mode="edge"), np.ones(5) / 5, mode="valid")
                          for k in range(2)], axis=1)
    np.testing.assert_allclose(averaged, reference, rtol=1e-12)
    np.testing.assert_array_equal(window_mean(history, 1), history)


def test_heap_twin_recovers_the_truth_after_large_deformation(tmp_path):
    # The small heap's crest travels over a cell and most points change cell: the case linear
    # shape functions make rough. With quadratic B-splines Levenberg–Marquardt recovers the
    # truth from a start 30 % away (issue target: phi within 0.2 deg, fluidity and exponent 5 %).
    sim = small_heap()
    initial = sim.initial_state()
    assert cells_crossed(sim, sim.final_state(), initial) > sim.point_count // 4
    observations = heap.twin_observations(sim, 0.0)
    fit = inverse.calibrate(sim, observations, heap.FIT, starts=[heap.START], progress=False)
    assert abs(fit.params["sand.friction_angle"] - 20.0) < 0.2
    assert fit.params["sand.fluidity"] == pytest.approx(5.0, rel=0.05)
    assert fit.params["sand.exponent"] == pytest.approx(2.0, rel=0.05)
    assert fit.optimizer == "lm" and fit.warning == ""
    cost = fit.cost
    assert cost["simulations"] > fit.iterations and cost["peak_memory_mb"] > 0
    assert len(fit.history["seconds"]) == fit.iterations
    assert fit.evaluations >= fit.iterations
    figure = fit.plot(tmp_path / "fit.png")
    assert len(figure.axes) >= 2 and (tmp_path / "fit.png").stat().st_size > 0


def test_heap_twin_with_noise_brackets_the_truth_in_two_standard_errors():
    # 2 % noise (of each component's peak), stated as sigma: the Gauss–Newton standard errors
    # must cover the truth at about 95 % per parameter; 2 seeds x 3 parameters, at most one miss
    # (the study, benchmarks/calibration_study.py, runs 10 seeds on the full heap).
    sim = small_heap()
    inside = []
    for seed in (0, 1):
        fit = inverse.calibrate(sim, heap.twin_observations(sim, 0.02, seed=seed), heap.FIT,
                                starts=[heap.TRUTH], max_iterations=8, progress=False)
        inside += [abs(fit.params[n] - heap.TRUTH[n]) < 2.0 * fit.stderr[n] for n in fit.names]
        assert all(np.isfinite(fit.stderr[n]) and fit.stderr[n] > 0 for n in fit.names)
    assert sum(inside) >= 5, inside


def test_wall_twin_recovers_friction_angle_and_wall_friction_from_thrust():
    # Targets beyond point displacements: the thrust (contact force, averaged over 0.01 s) and
    # the wall top. The wall gives about a millimetre as the backfill settles against it and
    # then holds; both the soil's friction angle and the interface friction come back from a
    # start 20-25 % away.
    text = (EXAMPLES / "calibrate_wall_scene.toml").read_text()
    text = text.replace("cell = 0.025", "cell = 0.05").replace("duration = 0.5", "duration = 0.12")
    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(text))
    observations = wall_observations(sim, 0.0)
    assert observations.channels["thrust"].window == 0.01
    fit = inverse.calibrate(sim, observations, {"sand.friction_angle": (15.0, 45.0),
                                                "contacts.backfill/wall.friction": (0.05, 0.9)},
                            starts=[{"sand.friction_angle": 36.0, "contacts.backfill/wall.friction": 0.3}],
                            progress=False)
    assert abs(fit.params["sand.friction_angle"] - 30.0) < 0.2
    assert fit.params["contacts.backfill/wall.friction"] == pytest.approx(0.4, rel=0.05)


def test_linear_shapes_with_points_crossing_cells_warn():
    sim = small_heap("linear")
    experiment = experiments_from(sim, heap.twin_observations(sim, 0.0))[0]
    space = inverse.ParameterSpace(sim.params, heap.FIT)
    start = np.array([heap.START[name] for name in heap.FIT])
    message = linear_shape_warning(experiment, space, start, 0)
    assert "points cross a cell with linear shape functions" in message and "bspline2" in message
    smooth = small_heap()
    assert linear_shape_warning(experiments_from(smooth, heap.twin_observations(smooth, 0.0))[0],
                                space, start, 0) == ""


def test_experiments_of_one_simulation_run_vmapped_and_equal_separate_runs():
    sim = coarse_rates()
    experiments = experiments_from(rates.experiments(sim, 0.0), None)
    space = inverse.ParameterSpace([e.sim.params for e in experiments], rates.FIT)
    groups = group_experiments(experiments, space)
    assert [g.members for g in groups] == [(0, 1)]          # one vmapped group
    data, bases = problem_arguments(experiments, groups)
    values = jnp.array([rates.START[name] for name in rates.FIT])
    together = np.asarray(problem_residuals(groups)(values, data, bases))
    separate = []
    for index, experiment in enumerate(experiments):
        insert = functools.partial(space.insert, experiment=index)
        alone = residual_function(sim, experiment.observations, insert)
        separate.append(np.asarray(alone(values, observation_data(sim, experiment.observations),
                                         base_parameters(experiment))))
    np.testing.assert_allclose(together, np.concatenate(separate), rtol=1e-12, atol=1e-12)
    assert np.abs(separate[0] - separate[1]).max() > 0.01     # the two rates differ


def test_two_rates_separate_fluidity_from_exponent():
    # Perzyna: a steady flow at strain rate e fixes only (e / fluidity)^(1 / exponent); a second
    # rate must shrink the correlation of the two and their standard errors. The covariance is
    # the Gauss–Newton one at the truth (noise 2 % of the peak force, stated).
    sim = coarse_rates()
    fit = {"sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
    truth = jnp.array([5.0, 2.0])
    # The weighted residuals of both rates, [slow; fast], and their Jacobian come from one
    # forward-mode run of the two experiments together (the residuals are its primal: no
    # second program compiled for them); the fast rate alone is its rows.
    experiments = experiments_from(rates.experiments(sim, 0.02), None)
    space = inverse.ParameterSpace([e.sim.params for e in experiments], fit)
    groups = group_experiments(experiments, space)
    data, bases = problem_arguments(experiments, groups)
    residuals = functools.partial(problem_residuals(groups), data=data, bases=bases)
    both = levenberg_marquardt.residuals_and_jacobian(residuals, truth)
    fast = slice(experiments[0].observations.count, None)
    correlations, errors = [], []
    for r, jacobian in ((both[0][fast], both[1][fast]), both):
        covariance, _ = gauss_newton(residuals, truth, noise_known=True, linearization=(r, jacobian))
        errors.append(np.sqrt(np.diag(covariance)))
        correlations.append(covariance[0, 1] / (errors[-1][0] * errors[-1][1]))
    one, two = correlations
    assert abs(one) > 0.9 and abs(two) < abs(one)
    assert errors[1][1] < 0.5 * errors[0][1]


def test_observations_come_from_dicts_results_files_and_nothing_else(tmp_path):
    sim = coarse_rates()
    result = sim.run(progress=False)
    times = result.time[::10]
    from_dict = inverse.as_observations({"force": (times, result.probes["force"][::10])})
    from_result = inverse.as_observations(result)
    path = result.save(tmp_path / "run.h5")
    from_file = inverse.as_observations(str(path))
    for observations in (from_result, from_file):
        np.testing.assert_array_equal(observations.channels["force"].values, result.probes["force"])
    assert from_dict.channels["force"].values.shape == (len(times), 2)
    assert inverse.as_observations(from_dict) is from_dict
    with pytest.raises(SceneError, match=r"observations is a list: give an inverse.Observations, a dict"):
        inverse.calibrate(sim, [1, 2], {"sand.fluidity": (0.1, 100.0)}, progress=False)
    with pytest.raises(SceneError, match=r"observations\['force'\] must be \(times, values\)"):
        inverse.calibrate(sim, {"force": np.zeros(3)}, {"sand.fluidity": (0.1, 100.0)}, progress=False)
    with pytest.raises(SceneError, match=r"window.forse names no observed probe"):
        inverse.Observations.from_arrays({"force": (times, times)}, window={"forse": 0.01})


def test_bad_experiments_are_clear_errors():
    sim = coarse_rates()
    observations = rates.rate_observations(sim, [0.0, -0.05], 0.0)
    fit = {"sand.fluidity": (0.1, 100.0)}
    with pytest.raises(SceneError, match=r"experiments.fast.set: 'bodies.footing.velocit' is not a parameter"):
        inverse.calibrate([inverse.Experiment(sim, observations, set={"bodies.footing.velocit": [0, -1]}, name="fast")],
                          fit=fit, progress=False)
    with pytest.raises(SceneError, match=r"params\['bodies'\]\['footing'\]\['velocity'\] reaches 1000 m/s"):
        inverse.calibrate([inverse.Experiment(sim, observations, set={"bodies.footing.velocity": [0.0, -1000.0]})],
                          fit=fit, progress=False)
    with pytest.raises(SceneError, match=r"experiments.a.set.materials.sand.fluidity is also fitted"):
        inverse.calibrate([inverse.Experiment(sim, observations, set={"materials.sand.fluidity": 3.0}, name="a")],
                          fit=fit, progress=False)
    with pytest.raises(SceneError, match=r"experiments\[0\].set = \[1, 2\] must be a dict"):
        inverse.calibrate([inverse.Experiment(sim, observations, set=[1, 2])], fit=fit, progress=False)
    with pytest.raises(SceneError, match=r"allow material 'sand' values that need a time step below"):
        inverse.calibrate([inverse.Experiment(sim, observations, set={"sand.young": 6.0e6})],
                          fit={"sand.poisson": (0.1, 0.45)}, progress=False)
    with pytest.raises(SceneError, match=r"the name 'a' is used twice"):
        inverse.calibrate([inverse.Experiment(sim, observations, name="a")] * 2, fit=fit, progress=False)
    with pytest.raises(SceneError, match=r"fit: in every experiment, 'sand.friction_angl' is not a parameter"):
        inverse.calibrate([(sim, observations), (sim, observations)], fit={"sand.friction_angl": (10, 40)},
                          progress=False)
    with pytest.raises(SceneError, match=r"optimizer = 'gauss' is not one of 'lm', 'lbfgs', 'adam'"):
        inverse.calibrate(sim, observations, fit, optimizer="gauss", progress=False)


def test_calibrate_command_with_two_experiments(tmp_path, capsys):
    from jaxmpm.cli import main

    sim = jaxmpm.Simulation(coarse_rates().scene.with_value("scene.duration", 0.15))
    (tmp_path / "scene.toml").write_text(sim.scene.to_toml())
    for name, velocity in rates.RATES.items():
        rates.rate_observations(sim, velocity, 0.0).to_csv(tmp_path / f"{name}.csv")
    blocks = "".join(
        f'[[experiments]]\nname = "{name}"\nscene = "scene.toml"\nobservations = "{name}.csv"\n'
        f'set = {{ "bodies.footing.velocity" = [{velocity[0]}, {velocity[1]}] }}\n'
        for name, velocity in rates.RATES.items()
    )
    config = tmp_path / "calibration.toml"
    config.write_text(blocks + '[fit]\n"sand.exponent" = { low = 1.0, high = 5.0, start = 2.4 }\n'
                               "[optimizer]\nmax_iterations = 12\n")
    output = tmp_path / "fit.h5"
    assert main(["calibrate", str(config), "-o", str(output), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "experiments: slow, fast" in printed
    assert not (tmp_path / "fit.h5.checkpoint.npz").exists()        # removed once the fit is written
    import h5py

    with h5py.File(output) as file:
        assert file["params/sand.exponent"][()] == pytest.approx(2.0, rel=1e-3)
        assert set(file["experiments"]) == {"slow", "fast"}
        assert file.attrs["optimizer"] == "lm"
    config.write_text(config.read_text().replace('name = "slow"', 'nmae = "slow"'))
    assert main(["calibrate", str(config), "-o", str(output), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert "experiments[0].nmae is not a known key (did you mean 'name'?)" in error
    assert error.count("\n") == 1


def test_rollouts_run_together_share_the_reverse_mode_memory_budget(tmp_path):
    # jaxmpm calibrate runs the experiments of one scene file and every start under one vmap,
    # and each rollout keeps its own states for reverse mode: the budget is divided among them.
    from inverse.config import load_calibration
    from jaxmpm.running.rollout import STORE_BUDGET_BYTES

    experiment = f'scene = "{EXAMPLES / "calibrate_twin_scene.toml"}"\nobservations = "{EXAMPLES / "calibrate_twin_observations.csv"}"\n'
    fit = '[fit]\n"sand.friction_angle" = { low = 15.0, high = 40.0, start = 30.0 }\n'
    cases = (("lbfgs", 1, 1, 1), ("lbfgs", 1, 3, 3), ("adam", 2, 3, 6), ("lm", 2, 3, 1))   # lm: forward mode, keeps none
    for optimizer, experiments, starts, share in cases:
        path = tmp_path / f"{optimizer}{experiments}{starts}.calibration.toml"
        text = experiment if experiments == 1 else "".join(f"[[experiments]]\n{experiment}" for _ in range(experiments))
        path.write_text(text + fit + f"[optimizer]\nname = \"{optimizer}\"\nstarts = {starts}\n")
        sims = {id(e.sim): e.sim for e in load_calibration(path).simulations()}
        assert len(sims) == 1
        assert next(iter(sims.values())).checkpointing.budget == STORE_BUDGET_BYTES // share
