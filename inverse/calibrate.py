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

import copy
import dataclasses
import functools
import hashlib
import resource
import time as clock
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec

from inverse import levenberg_marquardt
from inverse.compile_clock import CompileClock
from inverse.experiments import (
    base_parameters, check_observations, experiment_bases, experiments_from, group_experiments, layout_of,
    members_over_devices, problem_arguments, problem_residuals,
)
from inverse.fit import ExperimentFit, Fit, gauss_newton
from inverse.numerical_error import REFINEMENTS, numerical_shifts, residuals_at
from inverse.parameters import ParameterSpace
from jaxmpm.running.ensembles import batch_mesh, is_spread, spread_over_devices
from jaxmpm.errors import SceneError, SimulationError
from jaxmpm.scene.parameters import resolve
from jaxmpm.files import atomic_path
from jaxmpm.running.runner import describe_failure
from jaxmpm.physics.time_step import exceeds
from jaxmpm.running.tracing import collector_paused
from jaxmpm.kernels.xla_options import jit_reverse_mode, jit_with_options

OPTIMIZERS = ("lm", "lbfgs", "adam")
LM_DAMPING_LIMIT = 1e16     # Levenberg–Marquardt damping beyond this: no step lowers the loss


def check_stable_over_bounds(experiment, space: ParameterSpace, index: int):
    """SceneError if the bounds let a fitted modulus, Poisson's ratio or density reach values for
    which the scene's fixed time step would be unstable (c_p grows with E and nu, falls with rho),
    from the experiment's own values (its `set` included)."""
    extremes = {"young": "high", "poisson": "high", "density": "low"}
    sim = experiment.sim
    base = base_parameters(experiment)
    materials = {name: {key: float(value) for key, value in values.items()}
                 for name, values in base["materials"].items()}
    for material_name in materials:
        values = dict(materials[material_name])
        for entry, location in space.fitted_in(index):
            if location[:2] != ("materials", material_name) or len(location) != 3 or location[2] not in extremes:
                continue
            key = location[2]
            bound = getattr(entry, extremes[key])
            if bound is None:
                raise SceneError(f"fit.{entry.path} needs a {extremes[key]} bound: the time step is fixed "
                                 "from the scene, and an unbounded value could make it unstable.")
            values[key] = bound
        extreme = {**base, "materials": {**materials, material_name: values}}
        limit = sim.material_time_steps(extreme).get(material_name, float("inf"))
        if exceeds(sim.dt, limit):
            raise SceneError(
                f"fit bounds allow material {material_name!r} values that need a time step below "
                f"{limit:.4g} s, but the scene's is {sim.dt:.4g} s: narrow the bounds or lower scene.cfl."
            )


@dataclasses.dataclass(frozen=True)
class CompiledProblem:
    """The jitted pieces of a calibration, reused by every calibration of the same
    simulations, fitted parameters, optimiser and observation layouts (data values and the
    experiments' fixed values may change freely).

    start(z (S, P), data, bases) -> state;  start_shape(z, data, bases) -> its shapes (nothing
    runs);  iterate(z, state, data, bases) -> (z, state, loss at the incoming z (S,),
    ||dL/dz||_inf there (S,))."""

    residuals: object      # residuals(values (P,), data, bases) -> (M,)
    linearization: object  # linearization(values (P,), data, bases) -> (r (M,), dr/dvalues (M, P)), forward mode
    start: object
    start_shape: object
    iterate: object
    losses: object         # losses(z (S, P), data, bases) -> (S,); None for "lm" (its state holds them)


def compiled_problem(experiments, groups, space, optimizer_name, learning_rate) -> CompiledProblem:
    layout = tuple((id(e.sim), layout_of(e.observations)) for e in experiments)
    # The problem is cached on the first simulation (it compiles that simulation).
    key = (space.fingerprint(), optimizer_name, learning_rate, layout)
    cache = experiments[0].sim.compiled_cache.setdefault("calibration", {})
    if key in cache:
        return cache[key]
    residuals = problem_residuals(groups)
    forward_residuals = problem_residuals(groups, derivatives="forward")
    reverse_residuals = problem_residuals(groups, derivatives="reverse")
    count = sum(e.observations.count for e in experiments)

    def forward_residuals_of_z(z, data, bases):
        return forward_residuals(space.to_physical(z), data, bases)

    def loss_of_z(z, data, bases):
        r = reverse_residuals(space.to_physical(z), data, bases)
        return 0.5 * jnp.sum(r * r) / count

    batched = functools.partial(over_starts, in_axes=(0, 0, None, None))
    several_fields = any(e.sim.several_fields for e in experiments)
    jit = functools.partial(jit_with_options, several_fields=several_fields)
    if optimizer_name == "lm":
        iterate = jit(batched(levenberg_marquardt_iteration(forward_residuals_of_z, count)))

        def unevaluated(z, data, bases):
            size = jax.eval_shape(forward_residuals_of_z, z[0], data, bases).shape[0]
            return jax.vmap(lambda point: levenberg_marquardt.unevaluated(point, size))(z)

        def start(z, data, bases):
            """The first iteration's program evaluates the starts (no second compilation)."""
            return iterate(z, unevaluated(z, data, bases), data, bases)[1]

        def start_shape(z, data, bases):
            # `iterate` traced at the top (JAX refuses a jit with compiler options inside another trace)
            return jax.eval_shape(iterate, z, jax.eval_shape(unevaluated, z, data, bases), data, bases)[1]
    else:
        first, step = optax_iteration(loss_of_z, optimizer_name, learning_rate)
        start = jit_reverse_mode(over_starts(first, in_axes=(0, None, None)), several_fields)
        start_shape = functools.partial(jax.eval_shape, start)
        iterate = jit_reverse_mode(batched(step), several_fields)
    problem = CompiledProblem(
        residuals=residuals,
        linearization=jit(lambda values, data, bases: levenberg_marquardt.residuals_and_jacobian(
            functools.partial(forward_residuals, data=data, bases=bases), values)),
        start=start,
        start_shape=start_shape,
        iterate=iterate,
        losses=None if optimizer_name == "lm" else jit(over_starts(loss_of_z, in_axes=(0, None, None))),
    )
    cache[key] = problem
    return problem


def over_starts(function, in_axes):
    """jax.vmap(function, in_axes) over the calibration's starts, but a single start (the
    default) runs unbatched, its outputs given the batch axis after: a batch of one still
    batches every gather, scatter and loop of the simulation, which runs slower."""
    mapped = jax.vmap(function, in_axes=in_axes)

    def call(*args):
        sizes = {jax.tree_util.tree_leaves(arg)[0].shape[0] for arg, axis in zip(args, in_axes) if axis == 0}
        if sizes != {1}:
            return mapped(*args)
        single = [jax.tree_util.tree_map(lambda leaf: leaf[0], arg) if axis == 0 else arg for arg, axis in zip(args, in_axes)]
        return jax.tree_util.tree_map(lambda leaf: jnp.expand_dims(leaf, 0), function(*single))

    return call


def levenberg_marquardt_iteration(residuals_of_z, count):
    """iterate(z, state, data, bases) of Levenberg–Marquardt with forward-mode Jacobians (see
    `inverse.levenberg_marquardt`); losses and gradients reported as L = r.r / (2 M), those of
    the state it starts from (zeros for an unevaluated one)."""

    def iterate(z, state, data, bases):
        del z                       # the state holds z with its residuals and Jacobian
        value = 0.5 * jnp.sum(state.residuals**2) / count
        gradient = state.jacobian.T @ state.residuals / count
        new_state = levenberg_marquardt.step(functools.partial(residuals_of_z, data=data, bases=bases), state)
        return new_state.z, new_state, value, jnp.max(jnp.abs(gradient))

    return iterate


def optax_iteration(loss_of_z, optimizer_name, learning_rate):
    """(start, iterate) of an optax optimiser on the loss (reverse-mode gradients)."""
    transform = make_optimizer(optimizer_name, learning_rate)
    stored = optimizer_name == "lbfgs"

    def start(z, data, bases):
        """The optimiser's state at z. L-BFGS keeps the loss and gradient at its current point
        in its state (its line search computes them at the next one), so the start computes
        them once here: every iteration then reads them, and one program serves all
        iterations (a separate first iteration compiled a second copy of the line search,
        about 40 s for the 100-point test twin)."""
        state = transform.init(z)
        if stored:
            value, gradient = jax.value_and_grad(functools.partial(loss_of_z, data=data, bases=bases))(z)
            state = optax.tree_utils.tree_set(state, value=value, grad=gradient)
        # optax's init leaves some scalars weakly typed, its update returns them strongly typed:
        # matching the types here keeps the second iteration from compiling `iterate` again
        return jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype=leaf.dtype), state)

    def iterate(z, state, data, bases):
        """One optimiser step from z. L-BFGS reads the loss and gradient at z from its state
        (rather than optax.value_and_grad_from_state, whose lax.cond vmap would turn into an
        always-evaluated second simulation)."""
        loss = functools.partial(loss_of_z, data=data, bases=bases)
        if stored:
            value = optax.tree_utils.tree_get(state, "value")
            gradient = optax.tree_utils.tree_get(state, "grad")
            updates, state = transform.update(gradient, state, z, value=value, grad=gradient, value_fn=loss)
        else:
            value, gradient = jax.value_and_grad(loss)(z)
            updates, state = transform.update(gradient, state, z)
        return optax.apply_updates(z, updates), state, value, jnp.max(jnp.abs(gradient))

    return start, iterate


def make_optimizer(name, learning_rate):
    if name == "adam":
        return optax.adam(0.05 if learning_rate is None else learning_rate)
    if name == "lbfgs":
        return optax.lbfgs(learning_rate=learning_rate)
    raise SceneError(f"optimizer = {name!r} is not one of {', '.join(map(repr, OPTIMIZERS))}.")


@dataclasses.dataclass
class Progress:
    """Everything needed to continue a calibration: the batch of starts and its history."""

    iteration: int
    z: np.ndarray              # (S, P) unconstrained values
    loss: np.ndarray           # (S,) loss at z
    done: np.ndarray           # (S,) bool
    reason: list               # (S,) why each start stopped ("" while running)
    opt_leaves: list           # optimiser state leaves
    history_loss: list         # per iteration: (S,)
    history_values: list       # per iteration: (S, P) physical values
    history_gradient: list     # per iteration: (S,) ||dL/dz||_inf
    history_seconds: list      # per iteration: wall time [s] (with any compiling in it)
    history_memory: list       # per iteration: the process's peak resident memory so far [MB]
    history_simulations: list  # per iteration: simulations so far (see `Fit.evaluations`)
    evaluations: int           # simulations so far
    best_z: np.ndarray         # (S, P) the finite point of lowest loss seen by each start
    best_loss: np.ndarray      # (S,) its loss (inf if none was finite)
    elapsed_seconds: float = 0.0            # wall time so far, the sessions before a resume included
    compile_seconds: float = 0.0            # of it compiling (`CompileClock`)
    iteration_compile_seconds: float = 0.0  # of that, inside the iterations of `history_seconds`


HISTORIES = ("history_loss", "history_values", "history_gradient", "history_seconds", "history_memory",
             "history_simulations")
TIMES = ("elapsed_seconds", "compile_seconds", "iteration_compile_seconds")


def save_checkpoint(path, progress: Progress, fingerprint):
    arrays = {f"opt_{i}": np.asarray(leaf) for i, leaf in enumerate(progress.opt_leaves)}
    with atomic_path(path) as temporary, open(temporary, "wb") as stream:
        np.savez(
            stream,
            fingerprint=np.array(fingerprint),
            iteration=progress.iteration,
            z=progress.z,
            loss=progress.loss,
            done=progress.done,
            reason=np.array(progress.reason),
            evaluations=progress.evaluations,
            best_z=progress.best_z,
            best_loss=progress.best_loss,
            leaf_count=len(progress.opt_leaves),
            **{name: np.array(getattr(progress, name)) for name in HISTORIES},
            **{name: getattr(progress, name) for name in TIMES},
            **arrays,
        )


def load_checkpoint(path, fingerprint) -> Progress:
    with np.load(path) as data:
        if str(data["fingerprint"]) != fingerprint:
            raise SceneError(f"checkpoint {str(path)!r} belongs to a different calibration; remove it or set resume=False.")
        count = int(data["leaf_count"])
        return Progress(
            iteration=int(data["iteration"]),
            z=data["z"],
            loss=data["loss"],
            done=data["done"],
            reason=[str(r) for r in data["reason"]],
            opt_leaves=[data[f"opt_{i}"] for i in range(count)],
            evaluations=int(data["evaluations"]),
            best_z=np.array(data["best_z"]),
            best_loss=np.array(data["best_loss"]),
            **{name: list(data[name]) for name in HISTORIES},
            **{name: float(data[name]) for name in TIMES if name in data.files},   # older checkpoints: 0
        )


def peak_memory_mb() -> float:
    """The process's peak resident memory so far [MB] (Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0**2 if peak > 1 << 32 else peak / 1024.0


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
    halved) and "cell" (cell halved): for each, the fit reports how far its values would move
    at those numerics (`Fit.numerical_shifts`, inverse/numerical_error.py), one forward run
    of every experiment each.
    """
    if fit is None:
        raise SceneError("fit is missing: name the parameters to fit, e.g. fit={'sand.friction_angle': (20, 45)}.")
    # optax's L-BFGS mixes int32 and int64 internally, which strict promotion would refuse.
    with jax.numpy_dtype_promotion("standard"), CompileClock() as timing:
        fitted = _calibrate(experiments_from(sim, observations), fit, optimizer, starts, max_iterations, gtol, ftol,
                            learning_rate, seed, checkpoint, checkpoint_every, resume, progress, callback,
                            _checked_refinements(numerical_check), timing)
    return fitted


def _checked_refinements(numerical_check):
    """The refinements of `numerical_check` as a tuple, or SceneError naming the bad one."""
    refinements = (numerical_check,) if isinstance(numerical_check, str) else tuple(numerical_check or ())
    for refinement in refinements:
        if refinement not in REFINEMENTS:
            raise SceneError(f"numerical_check = {numerical_check!r}: {refinement!r} is not one of "
                             f"{', '.join(map(repr, REFINEMENTS))}.")
    return refinements


def _check_options(optimizer, max_iterations, checkpoint_every, gtol, ftol):
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"optimizer = {optimizer!r} is not one of {', '.join(map(repr, OPTIMIZERS))}.")
    for key, value, low in (("max_iterations", max_iterations, 1), ("checkpoint_every", checkpoint_every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise SceneError(f"{key} = {value!r} must be a positive integer.")
    for key, value in (("gtol", gtol), ("ftol", ftol)):
        if not (isinstance(value, (int, float)) and value >= 0):
            raise SceneError(f"{key} = {value!r} must be a number >= 0.")


def _calibrate(experiments, fit, optimizer, starts, max_iterations, gtol, ftol, learning_rate,
               seed, checkpoint, checkpoint_every, resume, progress, callback, refinements, timing):
    """The calibration; `timing` (a `CompileClock` opened before anything ran) times it."""
    from jaxmpm.running.progress import progress_bar

    _check_options(optimizer, max_iterations, checkpoint_every, gtol, ftol)
    dtypes = {e.sim.dtype for e in experiments}
    if len(dtypes) > 1:
        raise SceneError("experiments: every scene must have the same numerics.dtype "
                         f"(they have {', '.join(sorted(map(str, dtypes)))}).")
    dtype = dtypes.pop()
    space = ParameterSpace([e.sim.params for e in experiments], fit)
    for index, experiment in enumerate(experiments):
        fitted = {location: entry.path for entry, location in space.fitted_in(index)}
        for name in experiment.set:
            try:
                location = resolve(experiment.sim.params, name)
            except SceneError:
                continue                    # base_parameters names the bad key
            if location in fitted:
                raise SceneError(f"experiments.{experiment.name}.set.{name} is also fitted (as {fitted[location]!r}): "
                                 "a value cannot be both fixed and fitted.")
        check_observations(experiment)
        check_stable_over_bounds(experiment, space, index)
    groups = group_experiments(experiments, space)
    data, bases = problem_arguments(experiments, groups)
    problem = compiled_problem(experiments, groups, space, optimizer, learning_rate)
    start_values = _start_values(space, starts, seed)
    count = len(start_values)
    warning = "; ".join(filter(None, (linear_shape_warning(e, space, start_values[0], i)
                                      for i, e in enumerate(experiments))))
    if warning:
        warnings.warn(warning, stacklevel=3)
    z0 = jnp.stack([space.to_unconstrained(jnp.asarray(v, dtype)) for v in start_values])
    # One device axis: the starts' when they divide evenly, else the experiments'.
    if not is_spread(over_devices(z0)):
        data, bases = members_over_devices(groups, data, bases)
    place = functools.partial(over_devices, replicate=is_spread((data, bases)))
    z0 = place(z0)
    fingerprint = _fingerprint(experiments, space, optimizer, learning_rate, start_values, data)
    with collector_paused():        # the first call of each program traces it (jaxmpm.running.tracing)
        state_shape = problem.start_shape(z0, data, bases)
    treedef = jax.tree_util.tree_structure(state_shape)
    if resume and checkpoint is not None and Path(checkpoint).exists():
        run = load_checkpoint(checkpoint, fingerprint)
        state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(leaf) for leaf in run.opt_leaves])
    else:
        with collector_paused():
            state = jax.block_until_ready(problem.start(z0, data, bases))     # one sharded program in flight
        run = Progress(0, np.asarray(z0), np.full(count, np.inf), np.zeros(count, bool), [""] * count,
                       [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(state)], [], [], [], [], [], [],
                       count * len(experiments) if optimizer in ("lm", "lbfgs") else 0, np.array(z0), np.full(count, np.inf))
    earlier = (run.elapsed_seconds, run.compile_seconds)      # of the sessions before a resume (0 afresh)
    z = place(jnp.asarray(run.z, dtype))
    saved = copy.deepcopy(run)          # the last complete iteration: what an interrupt keeps
    bar = progress_bar(progress, total=max_iterations, initial=run.iteration, unit="it", desc="calibrate")
    try:
        while run.iteration < max_iterations and not run.done.all():
            tick, compiled = clock.monotonic(), timing.seconds
            moved = np.asarray(state.accepted) if optimizer == "lm" else np.ones(count, bool)
            with collector_paused():
                new_z, new_state, value, gradient_norm = problem.iterate(z, state, data, bases)
            value, gradient_norm = np.asarray(value), np.asarray(gradient_norm)
            running = ~run.done
            run.evaluations += int(np.sum(running)) * len(experiments) * (1 + _linesearch_steps(new_state, optimizer))
            # the value and gradient were taken at z: record them, then decide whether to stop there
            run.history_loss.append(value)
            run.history_values.append(np.asarray(jax.vmap(space.to_physical)(z)))
            run.history_gradient.append(gradient_norm)
            for s in np.flatnonzero(running):
                change = abs(run.loss[s] - value[s])
                if not (np.isfinite(value[s]) and np.isfinite(gradient_norm[s])):
                    run.reason[s] = "loss or gradient became non-finite (kept the best finite point)"
                elif gradient_norm[s] < gtol:
                    run.reason[s] = f"gradient norm {gradient_norm[s]:.3g} < gtol"
                elif moved[s] and np.isfinite(run.loss[s]) and change <= ftol * max(abs(value[s]), 1e-300):
                    run.reason[s] = f"relative loss change {change / max(abs(value[s]), 1e-300):.3g} <= ftol"
                elif optimizer == "lm" and _damping_exhausted(new_state, s):
                    run.reason[s] = "no step lowers the loss any more (Levenberg-Marquardt damping exhausted)"
                if np.isfinite(value[s]) and value[s] < run.best_loss[s]:
                    run.best_loss[s], run.best_z[s] = value[s], np.asarray(z[s])
            run.loss = np.where(running, value, run.loss)
            run.done = np.array([bool(r) for r in run.reason])
            moving = jnp.asarray(~run.done)
            z = jnp.where(moving[:, None], new_z, z)
            state = jax.tree_util.tree_map(
                lambda new, old: jnp.where(moving.reshape((-1,) + (1,) * (new.ndim - 1)), new, old), new_state, state
            )
            run.z = np.asarray(z)
            run.iteration += 1
            run.opt_leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(state)]
            run.history_seconds.append(clock.monotonic() - tick)
            run.iteration_compile_seconds += timing.seconds - compiled
            clock_in(run, timing, earlier)
            run.history_memory.append(peak_memory_mb())
            run.history_simulations.append(run.evaluations)
            saved = copy.deepcopy(run)
            bar.update(1)
            bar.set_postfix(loss=f"{np.min(run.best_loss):.4g}", sims=run.evaluations,
                            s_per_it=f"{run.history_seconds[-1]:.1f}", mem=f"{run.history_memory[-1]:.0f}MB")
            if checkpoint is not None and run.iteration % checkpoint_every == 0:
                save_checkpoint(checkpoint, run, fingerprint)
            if callback is not None:
                callback(run.iteration, run)
    except KeyboardInterrupt:
        if checkpoint is not None:
            save_checkpoint(checkpoint, clock_in(saved, timing, earlier), fingerprint)   # the time spent counts
        raise
    finally:
        bar.close()
    if checkpoint is not None:
        save_checkpoint(checkpoint, clock_in(run, timing, earlier), fingerprint)
    for s in range(count):
        if not run.reason[s]:
            run.reason[s] = f"max_iterations = {max_iterations} reached"
    fitted = _finish(experiments, groups, space, problem, data, bases, run, state, start_values, optimizer, warning)
    clock_in(run, timing, earlier)          # the covariance and best-fit runs count too
    fitted.wall_time, fitted.compile_seconds = run.elapsed_seconds, run.compile_seconds
    fitted.iteration_compile_seconds, fitted.earlier_seconds = run.iteration_compile_seconds, earlier[0]
    if refinements:
        with collector_paused():
            values = jnp.asarray(fitted.values, dtype)
            fitted.numerical_shifts = numerical_shifts(
                experiments, space, values, residuals_at(experiments, space, values), fitted.jacobian, refinements)
    return fitted


def clock_in(run: Progress, timing: CompileClock, earlier) -> Progress:
    """`run` with its wall and compile time so far: this session's (`timing`) after the
    earlier sessions' (elapsed, compile) seconds."""
    run.elapsed_seconds = earlier[0] + timing.elapsed
    run.compile_seconds = earlier[1] + timing.seconds
    return run


def _finish(experiments, groups, space, problem, data, bases, run, state, start_values, optimizer, warning):
    """The Fit: each start's answer is the better of its last point and the best finite point
    it passed through (the last one unless it went astray); the best start's covariance and
    every experiment's best-fit probes. Levenberg–Marquardt's state holds the residuals and
    Jacobian of its last point, and its history the loss of every point it passed through, so
    nothing is simulated again for them (each costs a compilation of the whole problem)."""
    dtype = experiments[0].sim.dtype
    last_z, best_z = jnp.asarray(run.z, dtype), jnp.asarray(run.best_z, dtype)
    if optimizer == "lm":
        count = sum(e.observations.count for e in experiments)
        last_losses = 0.5 * np.sum(np.asarray(state.residuals) ** 2, axis=1) / count
        passed_losses = np.asarray(run.best_loss)
    else:
        with collector_paused():
            last_losses = np.asarray(problem.losses(last_z, data, bases))
            passed_losses = np.asarray(problem.losses(best_z, data, bases))
    at_best = np.all(np.asarray(run.best_z) == np.asarray(run.z), axis=1)    # the same point: no rounding decides
    take_last = np.isfinite(last_losses) & (at_best | ~(passed_losses < last_losses))
    final_z = jnp.where(jnp.asarray(take_last)[:, None], last_z, best_z)
    final_losses = np.where(take_last, last_losses, passed_losses)
    if not np.any(np.isfinite(final_losses)):
        raise SimulationError("every start of the calibration went non-finite; narrow the bounds or change the starts.")
    best = int(np.nanargmin(np.where(np.isfinite(final_losses), final_losses, np.nan)))
    values = np.asarray(space.to_physical(final_z[best]))
    linearization = None
    if optimizer == "lm" and take_last[best]:
        linearization = physical_linearization(space, final_z[best], state.residuals[best], state.jacobian[best])
    if linearization is None:             # another optimiser, a passed point, or a value pinned at a bound
        with collector_paused():
            linearization = problem.linearization(jnp.asarray(values, dtype), data, bases)
    covariance, jacobian = gauss_newton(
        problem.residuals, values, noise_known=all(e.observations.noise_known for e in experiments),
        linearization=linearization,
    )
    runs, warnings_found = [], [warning] if warning else []
    for index, (experiment, base) in enumerate(zip(experiments, experiment_bases(groups, bases, len(experiments)))):
        sim = experiment.sim
        params = space.insert(jnp.asarray(values, dtype), base, experiment=index)
        probes, final_state = sim.probes_and_final_state(params)
        if int(final_state.error_step) >= 0:
            warnings_found.append(f"best-fit run of {experiment.name}: " + describe_failure(sim, final_state))
        runs.append(ExperimentFit(experiment.name, experiment.observations, np.asarray(sim.time),
                                  {name: np.asarray(v) for name, v in probes.items()}, dict(experiment.set)))
    # + two losses of every start, the covariance's Jacobian and the best-fit probes, per experiment
    evaluations = run.evaluations + (2 * len(start_values) + 2) * len(experiments)
    return Fit(
        names=space.names,
        values=values,
        loss=float(final_losses[best]),
        covariance=covariance,
        jacobian=jacobian,
        start_values=np.asarray(start_values),
        final_values=np.asarray(jax.vmap(space.to_physical)(final_z)),
        final_losses=final_losses,
        best_start=best,
        reasons=list(run.reason),
        history_loss=np.array(run.history_loss),
        history_values=np.array(run.history_values),
        history_gradient=np.array(run.history_gradient),
        history_seconds=np.array(run.history_seconds),
        history_memory=np.array(run.history_memory),
        history_simulations=np.array(run.history_simulations),
        iterations=run.iteration,
        evaluations=evaluations,
        wall_time=float("nan"),           # set by the caller (`clock_in`)
        optimizer=optimizer,
        experiments=runs,
        scene_toml=experiments[0].sim.scene.to_toml(),
        warning="; ".join(warnings_found),
    )


def physical_linearization(space, z, residuals, jacobian):
    """(r, dr/dtheta) from Levenberg–Marquardt's (r, dr/dz) at z: the bounds' transforms act
    on each parameter alone, so dr/dtheta_k = (dr/dz_k) / (dtheta_k/dz_k); None where that
    derivative vanishes (a value pinned at a bound), and the Jacobian is then taken afresh."""
    slopes = np.diag(np.asarray(jax.jacfwd(space.to_physical)(z)))
    if not np.all(np.isfinite(slopes) & (np.abs(slopes) > np.finfo(slopes.dtype).tiny)):   # no subnormal divisor
        return None
    return np.asarray(residuals), np.asarray(jacobian) / slopes[None, :]


def cells_crossed(sim, final_state, initial_state) -> int:
    """How many points end in another grid cell than they started in."""
    origin, cell = np.asarray(sim.scene.grid.origin), sim.scene.grid.cell
    start = np.floor((np.asarray(initial_state.particles.x) - origin) / cell)
    end = np.floor((np.asarray(final_state.particles.x) - origin) / cell)
    return int(np.sum(np.any(start != end, axis=1)))


def linear_shape_warning(experiment, space, start_values, index) -> str:
    """A warning if the experiment uses linear shape functions and points cross cells at the
    start values: its misfit is then rough in the parameters (docs/calibration.md: the
    gradient and the secant slope differ by tens of per cent on the heap twin)."""
    sim = experiment.sim
    if sim.scene.numerics.shape != "linear":
        return ""
    params = space.insert(jnp.asarray(start_values, sim.dtype), base_parameters(experiment), experiment=index)
    initial = sim.initial_state(params)
    _, final = sim.probes_and_final_state(params, initial)
    crossed = cells_crossed(sim, final, initial)
    if crossed == 0:
        return ""
    return (f"{experiment.name}: {crossed} of {sim.point_count} points cross a cell with linear shape "
            "functions, which makes the misfit rough in the parameters (gradients then mislead the "
            "optimiser); set numerics.shape = 'bspline2' (or 'gimp') for calibration")


def _damping_exhausted(state, start) -> bool:
    """Levenberg–Marquardt's damping has grown past any use: no step lowers the loss."""
    return float(state.damping[start]) > LM_DAMPING_LIMIT


def _fingerprint(experiments, space, optimizer_name, learning_rate, start_values, data):
    """What must match for a checkpoint to be resumed: problem, optimiser, starts and data."""
    digest = hashlib.sha256()
    for experiment in experiments:
        digest.update(experiment.sim.scene.to_toml().encode())
        digest.update(repr(layout_of(experiment.observations)).encode())
        digest.update(repr(sorted((k, np.asarray(v).tolist()) for k, v in experiment.set.items())).encode())
    for leaf in jax.tree_util.tree_leaves(data):
        digest.update(np.asarray(leaf).tobytes())
    digest.update(np.asarray(start_values).tobytes())
    return f"{space.fingerprint()} {optimizer_name} {learning_rate} {digest.hexdigest()}"


def over_devices(z, replicate=False):
    """The starts (S, P) sharded over every device along S when S divides evenly (the
    compiled iteration then runs its starts where they are, jaxmpm/running/ensembles.py); otherwise
    as they are, or a copy on every device with `replicate` (the experiments are spread: each
    iteration then sees its inputs laid out alike and compiles once)."""
    if replicate:
        return jax.device_put(z, NamedSharding(batch_mesh(), PartitionSpec()))
    return spread_over_devices(z)


def _start_values(space: ParameterSpace, starts, seed):
    if isinstance(starts, bool) or not isinstance(starts, (int, list, tuple)):
        raise SceneError(f"starts = {starts!r} must be a number of starts or a list of {{name: value}} dicts.")
    if isinstance(starts, int):
        if starts < 1:
            raise SceneError(f"starts = {starts!r} must be at least 1.")
        return space.random_values(starts, seed)
    rows = []
    for index, start in enumerate(starts):
        if not isinstance(start, dict):
            raise SceneError(f"starts[{index}] = {start!r} must be a {{name: value}} dict.")
        unknown = set(start) - set(space.names)
        if unknown:
            raise SceneError(f"starts[{index}] names {sorted(unknown)[0]!r}, which is not fitted.")
        row = [float(start.get(e.path, e.start)) for e in space.entries]
        for entry, value in zip(space.entries, row):
            if (entry.low is not None and value <= entry.low) or (entry.high is not None and value >= entry.high):
                raise SceneError(f"starts[{index}].{entry.path} = {value:g} is outside the bounds ({entry.low}, {entry.high}).")
        rows.append(row)
    if not rows:
        raise SceneError("starts is empty.")
    return np.array(rows)


def _linesearch_steps(state, optimizer_name):
    """Extra loss evaluations the L-BFGS line search made in this iteration (0 otherwise)."""
    if optimizer_name != "lbfgs":
        return 0
    steps = optax.tree_utils.tree_get(state, "num_linesearch_steps")
    return 0 if steps is None else int(np.max(np.asarray(steps)))
