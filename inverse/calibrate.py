"""Calibration: fit parameters to observed histories of one or several experiments.

    fit = inverse.calibrate(sim, observations, fit={"sand.friction_angle": (20, 45)})
    fit = inverse.calibrate([inverse.Experiment(sim, slow), inverse.Experiment(sim, fast, set=...)],
                            fit={"sand.fluidity": (0.1, 100), "sand.exponent": (1, 5)})

Residuals r_j = (y_sim(t_j) - y_obs_j) / sigma_j of every experiment form one vector (see
`inverse.experiments`), the simulated probes linearly interpolated to the observation times;
sigma is the stated noise, or the channel's RMS when none is given. The loss is the mean
half-square L(z) = sum_j r_j^2 / (2 M) in unconstrained coordinates z (see `parameters`).

Optimisers, for one or several starts at once (vmapped; the starts are sharded over the
devices when their number divides evenly, see `over_devices`, and otherwise the experiments
of a group run together are, `inverse.experiments.members_over_devices`):
  "lm"     Levenberg–Marquardt on r with forward-mode Jacobians (the default: a few
           parameters cost a few forward passes, no reverse-mode memory; docs/calibration.md
           measures it against the others);
  "lbfgs"  optax's L-BFGS (zoom line search) on L with reverse-mode gradients;
  "adam"   optax's Adam.
Each start stops when ||dL/dz||_inf < gtol, or when a step changes L by at most
ftol max(|L|, tiny), or when Levenberg–Marquardt's damping grows past any use (no step
lowers L), or after max_iterations. Progress is saved to a checkpoint every
`checkpoint_every` iterations and on Ctrl-C; `resume=True` continues from it and ends where
an uninterrupted run would.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp

from inverse.compile_clock import CompileClock
from inverse.experiments import experiments_from
from inverse.fit import Fit, fit_from
from inverse.numerical_error import numerical_shifts, residuals_at
from inverse.optimise import clock_in, on_devices, optimise, start_values_of
from inverse.problem import OPTIMIZERS, build_problem, rough_misfit_warning
from jaxmpm.errors import SceneError
from jaxmpm.running.refinement import REFINEMENTS, refinement_refused
from jaxmpm.running.tracing import collector_paused


def calibrate(
    sim,
    observations=None,
    fit: dict | None = None,
    optimizer: str = "lm",
    starts=1,
    max_iterations: int = 50,
    gtol: float = 1e-8,
    ftol: float = 1e-10,
    learning_rate: float | None = None,
    seed: int = 0,
    checkpoint=None,
    checkpoint_every: int = 5,
    resume: bool = False,
    progress: bool = True,
    callback=None,
    numerical_check=(),
) -> Fit:
    """Fit `fit` = {"material.parameter": (low, high) | {"low", "high", "start"}} to the
    observations of one experiment (`sim`, `observations`) or of several (`sim` a list of
    `inverse.Experiment` or (sim, observations[, set]) tuples, `observations` None), from
    `starts` start points (an int: the configured start plus random draws inside the bounds;
    or a list of {path: value} dicts). Returns a `Fit`.

    Observations may be an `Observations`, a dict {probe: (times, values[, components])}, a
    jaxmpm Result, or the path of a CSV or HDF5 file. optimizer: "lm" (default), "lbfgs" or
    "adam" (see the module docstring). callback(iteration, progress) is called after every
    iteration (e.g. to log or to stop). numerical_check: refinements among "dt" (time step
    halved), "cell" (cell halved), "relaxation" (numerics.relaxation doubled) and "stress"
    (numerics.stress_substeps doubled: the Perzyna update's own step): for each,
    the fit reports how far its values would move at those numerics (`Fit.numerical_shifts`,
    inverse/numerical_error.py), one forward run of every experiment each.
    """
    if fit is None:
        raise SceneError("fit is missing: name the parameters to fit, e.g. fit={'sand.friction_angle': (20, 45)}.")
    check_options(optimizer, max_iterations, checkpoint_every, gtol, ftol)
    refinements = checked_refinements(numerical_check)
    experiments = experiments_from(sim, observations)
    check_refinements_apply(refinements, experiments)
    # optax's L-BFGS mixes int32 and int64 internally, which strict promotion would refuse.
    with jax.numpy_dtype_promotion("standard"), CompileClock() as timing:
        problem = build_problem(experiments, fit, optimizer, learning_rate)
        start_values = start_values_of(problem.space, starts, seed)
        warning = rough_misfit_warning(problem, start_values)
        if warning:
            warnings.warn(warning, stacklevel=2)
        problem, z0 = on_devices(problem, start_values)
        run, state = optimise(problem, z0, start_values, max_iterations, gtol, ftol, checkpoint, checkpoint_every,
                              resume, progress, callback, timing)
        fitted = fit_from(problem, run, state, start_values, warning)
        clock_in(run, timing)           # the covariance and best-fit runs count too
        fitted = dataclasses.replace(fitted, wall_time=run.elapsed_seconds, compile_seconds=run.compile_seconds,
                                     iteration_compile_seconds=run.iteration_compile_seconds,
                                     earlier_seconds=run.earlier_seconds)
        if refinements:
            with collector_paused():
                values = jnp.asarray(fitted.values, problem.dtype)
                fitted.numerical_shifts = numerical_shifts(
                    experiments, problem.space, values, residuals_at(experiments, problem.space, values),
                    fitted.jacobian, refinements)
    return fitted


def checked_refinements(numerical_check):
    """The refinements of `numerical_check` as a tuple, or SceneError naming the bad one."""
    refinements = (numerical_check,) if isinstance(numerical_check, str) else tuple(numerical_check or ())
    for refinement in refinements:
        if refinement not in REFINEMENTS:
            raise SceneError(f"numerical_check = {numerical_check!r}: {refinement!r} is not one of "
                             f"{', '.join(map(repr, REFINEMENTS))}.")
    return refinements


def check_refinements_apply(refinements, experiments):
    """SceneError, before compiling, when a refinement cannot be made on an experiment's scene."""
    for refinement in refinements:
        for experiment in experiments:
            reason = refinement_refused(experiment.sim.scene, refinement)
            if reason:
                raise SceneError(f"numerical_check = {refinement!r}: {reason}.")


def check_options(optimizer, max_iterations, checkpoint_every, gtol, ftol):
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"optimizer = {optimizer!r} is not one of {', '.join(map(repr, OPTIMIZERS))}.")
    for key, value, low in (("max_iterations", max_iterations, 1), ("checkpoint_every", checkpoint_every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise SceneError(f"{key} = {value!r} must be a positive integer.")
    for key, value in (("gtol", gtol), ("ftol", ftol)):
        if not (isinstance(value, (int, float)) and value >= 0):
            raise SceneError(f"{key} = {value!r} must be a number >= 0.")
