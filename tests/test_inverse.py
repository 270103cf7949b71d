"""Calibration on a small-deformation twin: loss gradients, recovery with each optimiser,
uncertainty, resume, bad input (tests/test_calibration_experiments.py: large deformation,
several experiments).

The twin is a coarse version of examples/calibrate_twin_scene.toml: a heavy footing dropped on
viscoplastic sand (truth: friction_angle 25, fluidity 5, exponent 2). Its settlement stays
below a cell, so the misfit is smooth in the parameters.
"""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxmpm
from inverse.experiments import observation_data, residual_function
from inverse.fit import gauss_newton
from inverse.parameters import ParameterSpace
from jaxmpm import SceneError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

TWIN = """
[scene]
name = "footing_twin"
duration = 0.2
output_every = 0.01
snapshot_fields = ["x"]

[grid]
size = [0.4, 0.25]
cell = 0.05
boundaries = { left = "slip", right = "slip", bottom = "fixed", top = "free" }

[numerics]
shape = "linear"
transfer = "apic"
ppc = 2

[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 2.0e6
poisson = 0.3
friction_angle = 25.0
cone = "plane_strain"
fluidity = 5.0
exponent = 2.0

[materials.block]
model = "linear_elastic"
density = 20000.0
young = 5.0e7
poisson = 0.2

[[bodies]]
name = "layer"
material = "sand"
region = { rectangle = [[0.0, 0.0], [0.4, 0.15]] }
initial_stress = { geostatic = { k0 = "jaky" } }

[[bodies]]
name = "footing"
material = "block"
region = { rectangle = [[0.15, 0.15], [0.25, 0.2]] }
velocity = [0.0, -0.1]

[[probes]]
name = "footing"
kind = "body_displacement"
body = "footing"

[[probes]]
name = "surface"
kind = "displacement"
at = [0.3, 0.15]
"""
TRUTH = {"sand.friction_angle": 25.0, "sand.fluidity": 5.0, "sand.exponent": 2.0}
FIT = {"sand.friction_angle": (15.0, 40.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
# at least 20 % away from the truth in every parameter
WRONG = {"sand.friction_angle": 30.0, "sand.fluidity": 3.5, "sand.exponent": 2.5}


# The optimisers' own mechanics (Adam's and L-BFGS's steps, starts vmapped together) are
# checked on the same footing over an elastic layer: a simpler step, compiled in reverse mode
# in a fraction of the viscoplastic one's time (the tests' largest cost); the viscoplastic
# twin keeps the tests of the misfit's gradient, recovery, uncertainty and resume.
ELASTIC_TWIN = "\n".join(
    line for line in TWIN.splitlines() if not line.startswith(("friction_angle", "cone", "fluidity", "exponent"))
).replace('"drucker_prager"', '"linear_elastic"').replace('k0 = "jaky"', "k0 = 0.43")
ELASTIC_FIT = {"sand.young": (0.5e6, 8.0e6), "sand.poisson": (0.1, 0.45)}
ELASTIC_WRONG = {"sand.young": 3.2e6, "sand.poisson": 0.38}      # 60 % and 27 % away
ELASTIC_OTHER = {"sand.young": 1.0e6, "sand.poisson": 0.2}


@functools.cache
def twin_simulation(text=TWIN):
    """One Simulation per twin for every test: its compiled rollout and calibration problems are shared."""
    return jaxmpm.Simulation(jaxmpm.Scene.from_toml(text))


def twin_observations(noise=0.0, seed=0, text=TWIN):
    """Footing settlement and a surface point every 0.01 s, plus N(0, noise^2) [m]."""
    sim = twin_simulation(text)
    probes = sim.probes()
    stride = int(round(0.01 / sim.dt))
    rng = np.random.default_rng(seed)
    data = {}
    for name, components in (("footing", [1]), ("surface", [0, 1])):
        values = np.asarray(probes[name])[::stride][:, components]
        data[name] = (sim.time[::stride], values + noise * rng.standard_normal(values.shape), components)
    sigma = {"footing": noise, "surface": noise} if noise > 0 else None
    return inverse.Observations.from_arrays(data, sigma=sigma)


@functools.cache
def twin_run():
    """The twin run forward (jaxmpm.simulate) once, for the tests that need a run's output
    file (which they write without changing the Result)."""
    return jaxmpm.simulate(jaxmpm.Scene.from_toml(TWIN), progress=False)


OTHER = {"sand.friction_angle": 20.0, "sand.fluidity": 8.0, "sand.exponent": 1.5}


@functools.cache
def levenberg_marquardt_fit(starts):
    """Three Levenberg–Marquardt iterations on the viscoplastic twin (noise 1e-5, seed 2) from
    the named starts (a tuple of "WRONG" and "OTHER"), run once for the tests that compare them."""
    named = {"WRONG": WRONG, "OTHER": OTHER}
    return inverse.calibrate(twin_simulation(), twin_observations(noise=1e-5, seed=2), FIT,
                             starts=[named[name] for name in starts], max_iterations=3, progress=False)


def test_loss_gradient_matches_central_differences():
    # docs/validation.md §8: central differences, relative step 1e-6, float64.
    sim = twin_simulation()
    observations = twin_observations(noise=1e-5)
    space = ParameterSpace(sim.params, FIT)
    residuals = residual_function(sim, observations, space.insert)
    data = observation_data(sim, observations)
    base = sim.cast(sim.params)

    def loss(values):
        r = residuals(values, data, base)
        return 0.5 * jnp.sum(r * r)

    point = jnp.array([WRONG[name] for name in FIT])
    gradient = np.asarray(jax.grad(loss)(point))
    for index in range(len(FIT)):
        step = 1e-6 * float(point[index])
        up, down = point.at[index].add(step), point.at[index].add(-step)
        reference = (float(loss(up)) - float(loss(down))) / (2.0 * step)
        assert abs(reference) > 0.0
        np.testing.assert_allclose(gradient[index], reference, rtol=1e-5)


def test_multistart_batch_matches_separate_runs():
    # Starts run together under jax.vmap must follow exactly the paths they follow alone:
    # each start of [wrong, other] as in a batch of copies of itself (one compiled batch size).
    sim = twin_simulation(ELASTIC_TWIN)
    observations = twin_observations(noise=1e-5, text=ELASTIC_TWIN)
    options = dict(optimizer="adam", learning_rate=0.05, max_iterations=3, progress=False)
    together = inverse.calibrate(sim, observations, ELASTIC_FIT, starts=[ELASTIC_WRONG, ELASTIC_OTHER], **options)
    for index, start in enumerate([ELASTIC_WRONG, ELASTIC_OTHER]):
        alone = inverse.calibrate(sim, observations, ELASTIC_FIT, starts=[start, start], **options)
        np.testing.assert_allclose(together.history["loss"][:, index], alone.history["loss"][:, 0], rtol=1e-10)
        np.testing.assert_allclose(together.final_values[index], alone.final_values[0], rtol=1e-10)
    assert not np.allclose(together.final_values[0], together.final_values[1])
    assert np.all(np.diff(together.history["loss"], axis=0) < 0.0)   # Adam descends from both


def test_a_single_start_runs_unbatched_and_follows_its_batched_path():
    # One start (the default) runs without vmap (a batch of one batches every gather and
    # scatter of the simulation: 11 % slower): its results must be those of vmap, and its
    # path the one it follows in a batch of copies of itself.
    from inverse.problem import over_starts

    seen = []

    def doubled(z, data):
        seen.append(z)
        return {"value": 2.0 * z + data, "count": jnp.sum(z)}

    z, data = jnp.arange(1.0, 4.0).reshape(1, 3), jnp.ones(3)
    for batch in (z, jnp.concatenate([z, -z])):
        ours, theirs = over_starts(doubled, in_axes=(0, None))(batch, data), jax.vmap(doubled, in_axes=(0, None))(batch, data)
        for key in theirs:
            np.testing.assert_array_equal(ours[key], theirs[key])
    assert not isinstance(seen[0], jax.core.Tracer)      # one start: called as it is, not under vmap
    assert isinstance(seen[2], jax.core.Tracer)          # two starts: vmapped

    # Levenberg–Marquardt on the viscoplastic twin: the programs of one start and of a batch
    # of two are those the other tests compile.
    alone = levenberg_marquardt_fit(("WRONG",))
    copies = levenberg_marquardt_fit(("WRONG", "WRONG"))
    np.testing.assert_allclose(alone.history["loss"][:, 0], copies.history["loss"][:, 0], rtol=1e-10)
    np.testing.assert_allclose(alone.final_values[0], copies.final_values[0], rtol=1e-10)


def test_levenberg_marquardt_starts_run_vmapped_exactly_as_alone():
    # A start's path must not depend on the other starts of its batch: each start of
    # [WRONG, other] follows, to round-off, its path in a batch of copies of itself (one compiled
    # batch size). (That LM and L-BFGS reach the same optimum from a far start is measured in
    # benchmarks/calibration_study.py, too slow for the tests.)
    together = levenberg_marquardt_fit(("WRONG", "OTHER"))
    for index, start in enumerate(("WRONG", "OTHER")):
        alone = levenberg_marquardt_fit((start, start))
        np.testing.assert_allclose(together.history["loss"][:, index], alone.history["loss"][:, 0], rtol=1e-10)
    assert np.all(together.history["loss"][-1] < together.history["loss"][0])


def test_lbfgs_descends_from_a_far_start():
    fit = inverse.calibrate(twin_simulation(ELASTIC_TWIN), twin_observations(noise=1e-5, seed=2, text=ELASTIC_TWIN),
                            ELASTIC_FIT, starts=[ELASTIC_WRONG], optimizer="lbfgs", max_iterations=2, progress=False)
    assert fit.optimizer == "lbfgs" and np.all(np.isfinite(fit.final_values))
    assert fit.loss < fit.history["loss"][0, 0]

def test_standard_errors_shrink_with_noise_and_bracket_the_truth():
    # Gauss-Newton: C = (J^T J)^-1 with residuals weighted by 1/sigma, so standard errors scale
    # with the noise; at a realistic noise the truth lies within 3 standard errors.
    sim = twin_simulation()
    truth_start = [dict(TRUTH)]
    errors = {}
    for noise in (4e-5, 1e-5):
        fit = inverse.calibrate(sim, twin_observations(noise, seed=1), FIT, starts=truth_start,
                                max_iterations=15, progress=False)
        errors[noise] = fit.stderr
        for name, value in TRUTH.items():
            assert abs(fit.params[name] - value) < 3.0 * fit.stderr[name], (noise, name, fit.params, fit.stderr)
    for name in TRUTH:
        assert errors[1e-5][name] < 0.5 * errors[4e-5][name]


def test_interrupted_calibration_resumes_where_it_would_have_ended(tmp_path):
    sim = twin_simulation()
    observations = twin_observations()
    options = dict(starts=[WRONG], max_iterations=6, progress=False, checkpoint_every=2)
    whole = inverse.calibrate(sim, observations, FIT, **options)

    def stop_after_three(iteration, progress):
        if iteration == 3:
            raise KeyboardInterrupt

    checkpoint = tmp_path / "fit.checkpoint.npz"
    with pytest.raises(KeyboardInterrupt):
        inverse.calibrate(sim, observations, FIT, checkpoint=checkpoint, callback=stop_after_three, **options)
    assert checkpoint.exists()
    resumed = inverse.calibrate(sim, observations, FIT, checkpoint=checkpoint, resume=True, **options)
    assert resumed.iterations == whole.iterations
    np.testing.assert_allclose(resumed.values, whole.values, rtol=1e-12)
    np.testing.assert_allclose(resumed.history["loss"], whole.history["loss"], rtol=1e-12)
    # the time counts the session before the resume: at least its three iterations
    assert resumed.cost["before_resume"] >= np.sum(resumed.history["seconds"][:3]) > 0.0
    assert resumed.wall_time > resumed.cost["before_resume"] + np.sum(resumed.history["seconds"][3:])
    assert "before the resume" in resumed.summary()


def test_a_calibration_interrupted_in_its_first_iteration_resumes(tmp_path, monkeypatch):
    # Ctrl-C while the first iteration compiles must leave a checkpoint that resumes.
    import dataclasses

    from inverse import problem as calibration
    sim = twin_simulation()
    observations = twin_observations()
    options = dict(starts=[WRONG], max_iterations=2, progress=False)
    whole = inverse.calibrate(sim, observations, FIT, **options)
    built = calibration.compiled_problem

    def interrupted(*arguments):
        def stop(*_):
            raise KeyboardInterrupt

        return dataclasses.replace(built(*arguments), iterate=stop)

    checkpoint = tmp_path / "fit.checkpoint.npz"
    monkeypatch.setattr(calibration, "compiled_problem", interrupted)
    with pytest.raises(KeyboardInterrupt):
        inverse.calibrate(sim, observations, FIT, checkpoint=checkpoint, **options)
    monkeypatch.setattr(calibration, "compiled_problem", built)
    resumed = inverse.calibrate(sim, observations, FIT, checkpoint=checkpoint, resume=True, **options)
    np.testing.assert_allclose(resumed.values, whole.values, rtol=1e-12)
    # the last step's point counts: after 2 iterations the answer is that point, not the one before
    assert whole.loss < whole.history["loss"][-1, 0]


def test_observation_files_round_trip(tmp_path):
    observations = twin_observations(noise=1e-5)
    observations.to_csv(tmp_path / "obs.csv")
    again = inverse.load_observations(tmp_path / "obs.csv")
    for name, channel in observations.channels.items():
        np.testing.assert_array_equal(again.channels[name].values, channel.values)
        assert again.channels[name].components == channel.components
    # a jaxmpm output file is an observation file too
    result = twin_run()
    loaded = inverse.load_observations(result.save(tmp_path / "run.h5"))
    np.testing.assert_array_equal(loaded.channels["footing"].values, result.probes["footing"])


@pytest.mark.parametrize("text, words", [
    ("time,footing[1]\n0.0,1.0\n0.1,2.0,3.0\n", ["line 3", "3 values", "names 2 columns"]),      # a ragged row
    ("time,footing[1]\n0.0,1.0\n0.1,n/a\n", ["line 3", "column 'footing[1]'", "'n/a' is not a number"]),
    ("time,footing[1]\n", ["a header but no rows"]),
])
def test_observation_csv_errors_name_line_and_column(tmp_path, text, words):
    path = tmp_path / "obs.csv"
    path.write_text(text)
    with pytest.raises(SceneError) as caught:
        inverse.load_observations(path)
    for word in words:
        assert word in str(caught.value)


def test_a_misspelt_column_is_suggested_where_the_noise_names_the_probe(tmp_path):
    path = tmp_path / "obs.csv"
    path.write_text("time,footng[1]\n0.0,1.0\n0.1,2.0\n")
    with pytest.raises(SceneError, match=r"sigma.footing names no observed probe .*'footng' a misspelling"):
        inverse.load_observations(path, sigma={"footing": 1e-5})


def test_bad_calibration_input_is_a_clear_error():
    sim = twin_simulation()
    observations = twin_observations()
    with pytest.raises(SceneError, match=r"'sand.friction_angl'.*did you mean 'materials.sand.friction_angle'"):
        inverse.calibrate(sim, observations, {"sand.friction_angl": (20, 40)}, progress=False)
    with pytest.raises(SceneError, match=r"sand.fluidity: the initial value 5 is not strictly inside"):
        inverse.calibrate(sim, observations, {"sand.fluidity": (10, 100)}, progress=False)
    times = np.array([0.0, 0.1, 0.2])
    with pytest.raises(SceneError, match=r"observations.footing.values has a non-finite value"):
        inverse.Observations.from_arrays({"footing": (times, [0.0, np.nan, 0.0], [1])})
    late = inverse.Observations.from_arrays({"footing": (np.array([0.0, 0.1, 0.5]), [0.0, 0.0, 0.0], [1])})
    with pytest.raises(SceneError, match=r"observations.footing.times has t = 0.5 s outside the simulated span"):
        inverse.calibrate(sim, late, FIT, progress=False)
    unknown = inverse.Observations.from_arrays({"wall": (times, [0.0, 0.0, 0.0])})
    with pytest.raises(SceneError, match=r"observations.wall is not a probe of the scene"):
        inverse.calibrate(sim, unknown, FIT, progress=False)


def test_calibrate_command(tmp_path, capsys):
    from jaxmpm.cli import main

    (tmp_path / "scene.toml").write_text(TWIN)
    twin_observations(noise=1e-5).to_csv(tmp_path / "obs.csv")
    config = tmp_path / "calibration.toml"
    config.write_text(
        'scene = "scene.toml"\nobservations = "obs.csv"\nnumerical_check = ["dt"]\n'
        '[fit]\n"sand.friction_angle" = [15.0, 40.0]\n'
        "[noise]\nfooting = 1e-5\nsurface = 1e-5\n"
        "[optimizer]\nmax_iterations = 8\n"
    )
    output = tmp_path / "fit.h5"
    assert main(["calibrate", str(config), "-o", str(output), "--quiet", "--keep-checkpoint"]) == 0
    printed = capsys.readouterr().out
    assert "sand.friction_angle" in printed
    assert "numerical error (time step halved): sand.friction_angle" in printed
    assert f"kept the checkpoint {output}.checkpoint.npz" in printed     # asked to keep it (removed by default:
    assert (tmp_path / "fit.h5.checkpoint.npz").exists()                  # tests/test_calibration_experiments.py)
    import h5py

    with h5py.File(output) as file:
        assert abs(file["params/sand.friction_angle"][()] - 25.0) < 0.5
        assert file["correlation"].shape == (1, 1)
        assert np.isfinite(file["numerical_shift/dt/sand.friction_angle"][()])
    config.write_text(config.read_text().replace("max_iterations", "max_iteration"))
    assert main(["calibrate", str(config), "-o", str(output), "--quiet"]) == 2
    assert "optimizer.max_iteration" in capsys.readouterr().err


def test_gauss_newton_reports_an_unconstrained_direction_as_infinite():
    # r depends on theta_0 + theta_1 only: the data cannot tell the two apart, so both standard
    # errors must be infinite (a pseudo-inverse would report 0), while a third, independent
    # parameter keeps its exact standard error sigma / |dr/dtheta_2| = 1 / 2.
    def residuals(theta):
        return jnp.array([theta[0] + theta[1], 3.0 * (theta[0] + theta[1]), 2.0 * theta[2]])

    covariance, _ = gauss_newton(residuals, np.array([1.0, 2.0, 3.0]), noise_known=True)
    assert np.isinf(covariance[0, 0]) and np.isinf(covariance[1, 1])
    np.testing.assert_allclose(np.sqrt(covariance[2, 2]), 0.5, rtol=1e-12)


def test_covariance_from_the_levenberg_marquardt_state_equals_a_fresh_jacobian():
    # Levenberg-Marquardt holds dr/dz in the unconstrained coordinates; the Fit's covariance is
    # built from it (no further simulation), which must equal the one from dr/dtheta taken by
    # forward mode at the same point, for every kind of bound; a value pinned at a bound
    # (dtheta/dz = 0 in floating point) falls back to the fresh Jacobian.
    from inverse.fit import physical_linearization
    from inverse.levenberg_marquardt import residuals_and_jacobian

    params = {"materials": {"sand": {"a": 2.0, "b": 3.0, "c": -1.0, "d": 0.5}}}
    space = ParameterSpace(params, {"sand.a": (1.0, 5.0), "sand.b": (0.0, None), "sand.c": (None, 0.0), "sand.d": (None, None)})

    def residuals(theta):
        return jnp.array([theta[0] * theta[1], jnp.sin(theta[2]) + theta[3], theta[0] ** 2 - theta[3], theta[1] + theta[2]])

    z = space.to_unconstrained(jnp.array([2.0, 3.0, -1.0, 0.5]))
    r, jacobian_z = residuals_and_jacobian(lambda z: residuals(space.to_physical(z)), z)
    linearization = physical_linearization(space, z, r, jacobian_z)
    values = space.to_physical(z)
    held, _ = gauss_newton(residuals, values, noise_known=False, linearization=linearization)
    fresh, _ = gauss_newton(residuals, values, noise_known=False)
    np.testing.assert_allclose(held, fresh, rtol=1e-10)
    pinned = z.at[0].set(60.0)            # sigmoid'(60) underflows to 0 relative to the range
    assert physical_linearization(space, pinned, r, jacobian_z) is None


def test_bounds_transforms_round_trip_and_stay_inside():
    params = {"materials": {"sand": {"a": 2.0, "b": 3.0, "c": -1.0, "d": 0.5}}}
    space = ParameterSpace(params, {"sand.a": (1.0, 5.0), "sand.b": (0.0, None), "sand.c": (None, 0.0), "sand.d": (None, None)})
    values = jnp.array([2.0, 3.0, -1.0, 0.5])
    np.testing.assert_allclose(space.to_physical(space.to_unconstrained(values)), values, rtol=1e-12)
    far = space.to_physical(jnp.array([40.0, -40.0, 40.0, 7.0]))
    assert 1.0 < far[0] <= 5.0 and far[1] >= 0.0 and far[2] <= 0.0 and far[3] == 7.0
    draws = space.random_values(50, seed=3)
    assert np.all((draws[:, 0] > 1.0) & (draws[:, 0] < 5.0) & (draws[:, 1] > 0.0) & (draws[:, 2] < 0.0))


def test_bounds_that_would_make_the_time_step_unstable_are_refused():
    sim = twin_simulation()
    with pytest.raises(SceneError, match=r"allow material .sand. values that need a time step below"):
        inverse.calibrate(sim, twin_observations(), {"sand.young": (1.0e5, 1.0e9)}, progress=False)
    with pytest.raises(SceneError, match=r"fit.sand.young needs a high bound"):
        inverse.calibrate(sim, twin_observations(), {"sand.young": (1.0e5, None)}, progress=False)


def test_a_fits_summary_names_every_refinement_it_checked():
    # A calibration with numerical_check = ("stress",) crashed in fit.summary() with a KeyError
    # until 2026-12-06: the summary knew the words for dt, cell and relaxation only. Every
    # refinement calibrate accepts must read as a line, with each shift in standard errors.
    from types import SimpleNamespace

    from inverse.fit import Fit
    from jaxmpm.running.refinement import REFINEMENT_LABELS, REFINEMENTS

    fit = SimpleNamespace(names=("sand.friction_angle", "sand.fluidity"), stderr={"sand.friction_angle": 0.5,
                                                                                  "sand.fluidity": 0.1},
                          params={"sand.friction_angle": 30.0, "sand.fluidity": 5.0},
                          numerical_shifts={refinement: np.array([1.0, 0.01]) for refinement in REFINEMENTS})
    lines = Fit.numerical_error_lines(fit)
    assert len(lines) == len(REFINEMENTS)
    for line, refinement in zip(lines, REFINEMENTS):
        assert f"numerical error ({REFINEMENT_LABELS[refinement]}): sand.friction_angle +1 (2 se)" in line
        assert line.endswith("the numerics dominate the noise")


def test_a_shift_beyond_one_gauss_newton_step_asks_for_a_fit_at_the_refined_numerics():
    # The wall twin fitted at its cell to data made at half of it (docs/calibration.md,
    # 2026-12-07): biased by -4.18 deg, -2.75 1/s and -0.53, where the one-step shift said
    # +34.2 deg, -53.6 1/s and -19.1, each over half its value. Such a shift must not be read
    # as the bias; a shift within half of every value (the time step's, -0.29 deg) reads alone.
    from types import SimpleNamespace

    from inverse.fit import Fit

    names = ("sand.friction_angle", "sand.fluidity", "sand.exponent")
    fitted = {"sand.friction_angle": 25.82, "sand.fluidity": 2.25, "sand.exponent": 1.474}
    stderr = {"sand.friction_angle": 0.548, "sand.fluidity": 1.77, "sand.exponent": 0.531}
    far = SimpleNamespace(names=names, params=fitted, stderr=stderr,
                          numerical_shifts={"cell": np.array([34.2, -53.6, -19.1])})
    line, = Fit.numerical_error_lines(far)
    assert line.endswith("the shift is over half the value of sand.friction_angle, sand.fluidity, sand.exponent, "
                         "beyond what one Gauss-Newton step can say: fit again at the refined numerics"), line
    near = SimpleNamespace(names=names, params={"sand.friction_angle": 30.30, "sand.fluidity": 6.58,
                                                "sand.exponent": 2.077},
                           stderr=stderr, numerical_shifts={"dt": np.array([-0.29, -1.85, -0.079])})
    line, = Fit.numerical_error_lines(near)
    assert line.endswith("; the numerics dominate the noise") and "one Gauss-Newton step" not in line, line


def test_the_numerical_check_predicts_the_bias_of_a_coarse_fit():
    # A twin made at half the time step, noise-free, fitted at the default step: the fitted
    # modulus is biased by the discretisation alone, and the check's predicted shift (the
    # Gauss-Newton step of the refined problem, inverse/numerical_error.py) must be minus that
    # bias. The bar (examples/vibrating_bar.toml, plain APIC, whose dissipation depends on dt).
    scene = (jaxmpm.load_scene(EXAMPLES / "vibrating_bar.toml").with_value("numerics.transfer", "apic")
             .with_value("scene.duration", 10.0))
    coarse = jaxmpm.Simulation(scene)
    fine = jaxmpm.Simulation(scene.with_value("scene.cfl", scene.cfl / 2.0))
    every = int(round(0.25 / fine.dt))
    measured = inverse.Observations.from_arrays(
        {"tip": (fine.time[::every], np.asarray(fine.probes()["tip"])[::every][:, [0]], [0])})
    fit = inverse.calibrate(coarse, measured, {"rod.young": (50.0, 200.0)}, starts=[{"rod.young": 90.0}],
                            progress=False, numerical_check="dt")
    bias = fit.params["rod.young"] - 100.0
    assert abs(bias) > 1e-3                          # the coarse step does bias the fit ...
    assert fit.numerical_shifts["dt"][0] == pytest.approx(-bias, rel=0.05)     # ... and the check sees it
    assert "numerical error (time step halved): rod.young" in fit.summary()
    assert "+- one standard error" in fit.summary() and "nan s" not in fit.summary()
    with pytest.raises(SceneError, match=r"numerical_check = 'dx': 'dx' is not one of 'dt', 'cell'"):
        inverse.calibrate(coarse, measured, {"rod.young": (50.0, 200.0)}, progress=False, numerical_check="dx")


def test_the_relaxation_check_predicts_the_bias_of_a_fit_made_at_another_relaxation():
    # The relaxation kappa is a numerical parameter that biases a fit of viscoplastic sand
    # (docs/convergence.md). A noise-free twin of the footing made at kappa = 20, fitted for
    # the friction angle at kappa = 10: the check's predicted shift (kappa doubled) must be
    # minus that bias (measured: bias -0.90 degrees, shift +0.88).
    scene = jaxmpm.Scene.from_toml(TWIN).with_value("numerics.relaxation", 10.0)
    fine = jaxmpm.Simulation(scene.with_value("numerics.relaxation", 20.0))
    stride = int(round(0.01 / fine.dt))
    probes = fine.probes()
    measured = inverse.Observations.from_arrays(
        {name: (fine.time[::stride], np.asarray(probes[name])[::stride][:, components], components)
         for name, components in (("footing", [1]), ("surface", [0, 1]))})
    fit = inverse.calibrate(jaxmpm.Simulation(scene), measured, {"sand.friction_angle": (15.0, 40.0)},
                            starts=[{"sand.friction_angle": 27.0}], progress=False, numerical_check=["relaxation"])
    bias = fit.params["sand.friction_angle"] - TRUTH["sand.friction_angle"]
    assert abs(bias) > 0.2                                     # kappa does bias the fit ...
    assert fit.numerical_shifts["relaxation"][0] == pytest.approx(-bias, rel=0.1)   # ... and the check sees it
    assert "numerical error (relaxation doubled): sand.friction_angle" in fit.summary()
    with pytest.raises(SceneError, match=r"numerical_check = 'relaxation': the scene 'footing_twin' has no relaxation"):
        inverse.calibrate(twin_simulation(), measured, {"sand.friction_angle": (15.0, 40.0)}, progress=False,
                          numerical_check="relaxation")


def test_a_levenberg_marquardt_fit_ending_pinned_at_a_bound_reports_its_covariance():
    # The truth (poisson 0.3) lies above the allowed range: the fit drives the ratio to its
    # bound, where dtheta/dz underflows, so the held Jacobian cannot be mapped back and the
    # covariance is taken from a fresh forward-mode Jacobian at the fitted values.
    sim = twin_simulation(ELASTIC_TWIN)
    fit = inverse.calibrate(sim, twin_observations(1e-5, text=ELASTIC_TWIN),
                            fit={"sand.young": {"low": 0.5e6, "high": 8.0e6, "start": 2.6e6},
                                 "sand.poisson": {"low": 0.1, "high": 0.2, "start": 0.12}},
                            max_iterations=60, progress=False)
    assert fit.params["sand.poisson"] == pytest.approx(0.2, abs=1e-9)
    assert np.isfinite(fit.stderr["sand.young"]) and fit.stderr["sand.young"] > 0


def test_a_fit_file_loads_back_to_the_fit_that_wrote_it_and_plots(tmp_path, capsys, monkeypatch):
    from jaxmpm.cli import main

    monkeypatch.chdir(tmp_path)            # the figure's default name is the file's, in the working folder
    fit = inverse.calibrate(twin_simulation(), twin_observations(1e-5), FIT, starts=[WRONG], max_iterations=2,
                            progress=False)
    path = fit.save(tmp_path / "fit.h5")
    loaded = inverse.Fit.load(path)
    for field in ("names", "values", "loss", "covariance", "jacobian", "start_values", "final_values", "final_losses",
                  "best_start", "reasons", "iterations", "evaluations", "wall_time", "optimizer", "scene_toml",
                  "compile_seconds", "iteration_compile_seconds", "earlier_seconds", *fit.history):
        expected = fit.history[field] if field in fit.history else getattr(fit, field)
        got = loaded.history[field] if field in fit.history else getattr(loaded, field)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected), err_msg=field)
    for run, again in zip(fit.experiments, loaded.experiments, strict=True):
        assert again.name == run.name and again.fixed == run.fixed
        for name, channel in run.observations.channels.items():
            for part in ("times", "values", "components", "sigma", "window"):
                np.testing.assert_array_equal(getattr(again.observations.channels[name], part), getattr(channel, part))
        for name, values in run.probes.items():
            np.testing.assert_array_equal(again.probes[name], values)
    assert loaded.summary() == fit.summary()
    # a correlated pair is named on both parameters' lines, the poorly identified one's too
    import dataclasses

    errors = np.abs(fit.values) * np.array([0.01, 0.5, 0.05])
    correlation = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.99], [0.0, 0.99, 1.0]])
    verdicts = dataclasses.replace(fit, covariance=correlation * np.outer(errors, errors)).identifiability()
    assert verdicts["sand.friction_angle"].startswith("identified") and "correlated" not in verdicts["sand.friction_angle"]
    assert verdicts["sand.fluidity"].startswith("poorly identified") and "correlated with sand.exponent" in verdicts["sand.fluidity"]
    assert verdicts["sand.exponent"].startswith("identified") and "correlated with sand.fluidity" in verdicts["sand.exponent"]
    assert fit.jacobian.shape == (sum(c.values.size for c in fit.observations.channels.values()), len(FIT))

    # the command draws it: the loss and parameter histories, 3 error ellipses, 3 observed
    # components and the residuals, which are those of the loss: sum r^2 / (2 M) is the loss
    assert main(["plot", str(path)]) == 0
    assert (tmp_path / "fit.png").stat().st_size > 10_000
    figure = fit.plot()
    assert sum(axis.get_visible() for axis in figure.axes) == 1 + 3 + 3 + 3 + 1
    drawn = np.concatenate([line.get_ydata() for line in figure.axes[10].get_lines() if len(line.get_ydata()) > 2])
    assert 0.5 * np.sum(drawn**2) / drawn.size == pytest.approx(fit.loss, rel=1e-6)
    for options, words in ((["--field", "p"], "--field draws the output of a run"),
                           (["-o", str(tmp_path / "fit.gif")], "the file type must be .png")):
        assert main(["plot", str(path), *options]) == 2
        assert words in capsys.readouterr().err
    assert main(["export", str(path)]) == 2
    assert "is a calibration result (`jaxmpm calibrate`), not a run: draw it with `jaxmpm plot`" in capsys.readouterr().err

    # a file cut short is called damaged; a run's output is not taken for a fit
    (tmp_path / "cut.h5").write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(SceneError, match="is damaged"):
        inverse.Fit.load(tmp_path / "cut.h5")
    run = twin_run().save(tmp_path / "run.h5")
    with pytest.raises(SceneError, match="is the output of a run"):
        inverse.Fit.load(run)


def test_a_fit_file_written_before_observations_and_jacobian_were_stored_still_loads(tmp_path):
    import h5py

    fit = inverse.calibrate(twin_simulation(), twin_observations(), {"sand.friction_angle": (15.0, 40.0)},
                            max_iterations=1, progress=False)
    path = fit.save(tmp_path / "old.h5")
    with h5py.File(path, "r+") as file:          # what a file of the earlier layout lacks
        for attribute in ("file_kind", "compile_seconds", "iteration_compile_seconds", "earlier_seconds"):
            del file.attrs[attribute]
        for key in ("values", "jacobian", "starts/stopped", *(f"experiments/{run.name}/observations"
                                                               for run in fit.experiments)):
            del file[key]
    loaded = inverse.Fit.load(path)
    np.testing.assert_array_equal(loaded.values, fit.values)
    assert loaded.jacobian is None and loaded.observations is None
    assert loaded.reasons[loaded.best_start] == fit.reasons[fit.best_start]
    assert "first iteration" in loaded.summary() and "nan s" not in loaded.summary()
    loaded.plot()                                 # no observations: the histories and no data panels


def test_the_compile_clock_counts_compiling_only():
    from inverse.compile_clock import CompileClock

    @jax.jit
    def fresh(x):
        return jnp.sin(x) * 1.2345678    # a constant no other test compiles

    with CompileClock() as first:
        fresh(jnp.arange(7.0)).block_until_ready()
    with CompileClock() as again:             # compiled already: nothing to count
        fresh(jnp.arange(7.0)).block_until_ready()
    assert 0.0 < first.seconds <= first.elapsed
    assert again.seconds == 0.0


def test_a_fits_numerical_error_gives_its_verdict_to_a_program():
    # Fit.numerical_error() carries what the summary line says, for a program to act on, on the
    # wall twin's numbers (docs/calibration.md, 2026-12-07): the cell's shift is beyond one step
    # and not to be trusted; the time step's is, and dominates the noise in fluidity (1.85 /
    # 1.77 = 1.05 standard errors); a shift under every standard error leaves the noise
    # dominant, and no finite standard error leaves no verdict.
    from types import SimpleNamespace

    from inverse.fit import Fit

    names = ("sand.friction_angle", "sand.fluidity", "sand.exponent")
    stderr = {"sand.friction_angle": 0.548, "sand.fluidity": 1.77, "sand.exponent": 0.531}
    far = SimpleNamespace(names=names, stderr=stderr,
                          params={"sand.friction_angle": 25.82, "sand.fluidity": 2.25, "sand.exponent": 1.474},
                          numerical_shifts={"cell": np.array([34.2, -53.6, -19.1])})
    cell = Fit.numerical_error(far)["cell"]
    assert cell.beyond_one_step == names and not cell.trusted and cell.dominant == "numerics"
    assert cell.shift["sand.friction_angle"] == 34.2
    assert cell.in_standard_errors["sand.friction_angle"] == pytest.approx(34.2 / 0.548)
    near = SimpleNamespace(names=names, stderr=stderr,
                           params={"sand.friction_angle": 30.30, "sand.fluidity": 6.58, "sand.exponent": 2.077},
                           numerical_shifts={"dt": np.array([-0.29, -1.85, -0.079]), "stress": np.array([0.1, 0.2, 0.05])})
    dt, stress = Fit.numerical_error(near)["dt"], Fit.numerical_error(near)["stress"]
    assert dt.trusted and dt.dominant == "numerics"
    assert dt.in_standard_errors["sand.fluidity"] == pytest.approx(1.85 / 1.77)
    assert stress.trusted and stress.dominant == "noise"
    unknown = SimpleNamespace(names=names, params=near.params, stderr=dict.fromkeys(names, np.inf),
                              numerical_shifts={"dt": np.array([-0.29, -1.85, -0.079])})
    verdict = Fit.numerical_error(unknown)["dt"]
    assert verdict.dominant is None and np.isnan(verdict.in_standard_errors["sand.exponent"])
