"""Calibration: fit material parameters to observed probe histories.

    fit = inverse.calibrate(sim, observations, fit={"sand.friction_angle": (20, 45)})

Residuals r_j = (y_sim(t_j) - y_obs_j) / sigma_j, the simulated probes linearly interpolated
to the observation times; sigma is the stated noise, or the channel's RMS when none is given.
The optimiser minimises the mean half-square L(z) = sum_j r_j^2 / (2 M) in unconstrained
coordinates z (see `parameters`), for one or several starts at once (vmapped), with optax's
Adam or L-BFGS (zoom line search). Each start stops when ||dL/dz||_inf < gtol, or when
|L_prev - L| <= ftol max(|L|, tiny), or after max_iterations. Progress is saved to a
checkpoint every `checkpoint_every` iterations and on Ctrl-C; `resume=True` continues from it
and ends where an uninterrupted run would.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import time as clock
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from inverse.fit import Fit, gauss_newton
from inverse.observations import Observations, check_against, default_scale
from inverse.parameters import ParameterSpace
from jaxmpm.errors import SceneError, SimulationError
from jaxmpm.files import atomic_path
from jaxmpm.simulation import STEP_SLACK, describe_failure
from jaxmpm.xla_options import jit_reverse_mode

OPTIMIZERS = ("lbfgs", "adam")


def observation_data(sim, observations: Observations):
    """The observed values as jit arguments: one (times, values, scale) triple per channel."""
    return tuple(
        (
            jnp.asarray(channel.times, sim.dtype),
            jnp.asarray(channel.values, sim.dtype),
            jnp.asarray(channel.sigma if channel.sigma is not None else default_scale(channel), sim.dtype),
        )
        for channel in observations.channels.values()
    )


def check_observations(sim, observations: Observations):
    """SceneError unless every channel names a probe component of the scene inside its time."""
    probe_widths = {name: value.shape[0] for name, value in sim.observe_start(sim.initial_state()).items()}
    check_against(observations, probe_widths, (float(sim.time[0]), float(sim.time[-1])))
    for name, channel in observations.channels.items():
        for component in channel.components:
            if not 0 <= component < probe_widths[name]:
                raise SceneError(f"observations.{name} names component {component}; the probe has {probe_widths[name]}.")


def check_stable_over_bounds(sim, space: ParameterSpace):
    """SceneError if the bounds let a fitted modulus, Poisson's ratio or density reach values for
    which the scene's fixed time step would be unstable (c_p grows with E and nu, falls with rho)."""
    extremes = {"young": "high", "poisson": "high", "density": "low"}
    materials = sim.params["materials"]
    for material_name in materials:
        values = dict(materials[material_name])
        for entry, (namespace, owner, key) in zip(space.entries, space.locations):
            if namespace != "materials" or owner != material_name or key not in extremes:
                continue
            bound = getattr(entry, extremes[key])
            if bound is None:
                raise SceneError(f"fit.{entry.path} needs a {extremes[key]} bound: the time step is fixed "
                                 "from the scene, and an unbounded value could make it unstable.")
            values[key] = bound
        extreme = {**sim.params, "materials": {**materials, material_name: values}}
        limit = sim.material_time_steps(extreme).get(material_name, float("inf"))
        if sim.dt > limit * (1.0 + STEP_SLACK):
            raise SceneError(
                f"fit bounds allow material {material_name!r} values that need a time step below "
                f"{limit:.4g} s, but the scene's is {sim.dt:.4g} s: narrow the bounds or lower scene.cfl."
            )


def residual_function(sim, observations: Observations, space: ParameterSpace):
    """residuals(values, data, base) -> (M,) weighted residuals for physical parameter values
    (P,), with `data` from `observation_data` and `base` the parameter pytree the fitted values
    are inserted into (both arguments, so new data or fixed values never recompile)."""
    time = jnp.asarray(sim.time, sim.dtype)
    layout = [(name, channel.components) for name, channel in observations.channels.items()]

    def residuals(values, data, base):
        probes = sim.probes(space.insert(values, base))
        parts = []
        for (name, components), (times, observed, scale) in zip(layout, data):
            simulated = jnp.stack([jnp.interp(times, time, probes[name][:, k]) for k in components], axis=1)
            parts.append(((simulated - observed) / scale).ravel())
        return jnp.concatenate(parts)

    return residuals


@dataclasses.dataclass(frozen=True)
class CompiledProblem:
    """The jitted pieces of a calibration, reused by every calibration of the same simulation,
    fitted parameters, optimiser and observation layout (data values may change freely)."""

    residuals: object      # residuals(values, data, base)
    start: object          # start(z (S, P), state, data, base) -> (z, state, loss (S,), |grad|inf (S,))
    iterate: object        # the same, reusing the loss and gradient the L-BFGS line search stored
    losses: object         # losses(z (S, P), data, base) -> (S,)
    init: object           # init(z (S, P)) -> optimiser state


def compiled_problem(sim, observations, space, optimizer_name, learning_rate) -> CompiledProblem:
    layout = tuple((name, c.components, len(c.times)) for name, c in observations.channels.items())
    # The problem is cached on the simulation it belongs to (it compiles that simulation).
    key = (space.fingerprint(), optimizer_name, learning_rate, layout)
    cache = sim.compiled_cache.setdefault("calibration", {})
    if key in cache:
        return cache[key]
    transform = make_optimizer(optimizer_name, learning_rate)
    residuals = residual_function(sim, observations, space)
    count = observations.count

    def loss_of_z(z, data, base):
        r = residuals(space.to_physical(z), data, base)
        return 0.5 * jnp.sum(r * r) / count

    def one_iteration(z, state, data, base, stored):
        """One optimiser step from z. With `stored` (L-BFGS after its first step) the loss and
        gradient at z are the ones its line search kept: reading them, rather than using
        optax.value_and_grad_from_state, avoids a lax.cond that vmap would turn into an
        always-evaluated second simulation."""
        loss = functools.partial(loss_of_z, data=data, base=base)
        if stored:
            value = optax.tree_utils.tree_get(state, "value")
            gradient = optax.tree_utils.tree_get(state, "grad")
        else:
            value, gradient = jax.value_and_grad(loss)(z)
        if optimizer_name == "lbfgs":
            updates, state = transform.update(gradient, state, z, value=value, grad=gradient, value_fn=loss)
        else:
            updates, state = transform.update(gradient, state, z)
        return optax.apply_updates(z, updates), state, value, jnp.max(jnp.abs(gradient))

    batched = functools.partial(jax.vmap, in_axes=(0, 0, None, None))
    problem = CompiledProblem(
        residuals=residuals,
        start=jit_reverse_mode(batched(functools.partial(one_iteration, stored=False))),
        iterate=jit_reverse_mode(batched(functools.partial(one_iteration, stored=optimizer_name == "lbfgs"))),
        losses=jax.jit(jax.vmap(loss_of_z, in_axes=(0, None, None))),
        init=jax.jit(jax.vmap(transform.init)),
    )
    cache[key] = problem
    return problem


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
    evaluations: int           # loss-and-gradient evaluations (forward + reverse simulations)
    best_z: np.ndarray         # (S, P) the finite point of lowest loss seen by each start
    best_loss: np.ndarray      # (S,) its loss (inf if none was finite)


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
            history_loss=np.array(progress.history_loss),
            history_values=np.array(progress.history_values),
            history_gradient=np.array(progress.history_gradient),
            evaluations=progress.evaluations,
            best_z=progress.best_z,
            best_loss=progress.best_loss,
            leaf_count=len(progress.opt_leaves),
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
            history_loss=list(data["history_loss"]),
            history_values=list(data["history_values"]),
            history_gradient=list(data["history_gradient"]),
            evaluations=int(data["evaluations"]),
            best_z=np.array(data["best_z"]),
            best_loss=np.array(data["best_loss"]),
        )


def calibrate(
    sim,
    observations: Observations,
    fit: dict,
    optimizer: str = "lbfgs",
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
) -> Fit:
    """Fit `fit` = {"material.parameter": (low, high) | {"low", "high", "start"}} to the
    observations, from `starts` start points (an int: the configured start plus random draws
    inside the bounds; or a list of {path: value} dicts). Returns a `Fit`.

    callback(iteration, progress) is called after every iteration (e.g. to log or to stop).
    """
    # optax's L-BFGS mixes int32 and int64 internally, which strict promotion would refuse.
    with jax.numpy_dtype_promotion("standard"):
        return _calibrate(sim, observations, fit, optimizer, starts, max_iterations, gtol, ftol,
                          learning_rate, seed, checkpoint, checkpoint_every, resume, progress, callback)


def _calibrate(sim, observations, fit, optimizer, starts, max_iterations, gtol, ftol, learning_rate,
               seed, checkpoint, checkpoint_every, resume, progress, callback):
    from tqdm.auto import tqdm

    space = ParameterSpace(sim.params, fit)
    for key, value, low in (("max_iterations", max_iterations, 1), ("checkpoint_every", checkpoint_every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise SceneError(f"{key} = {value!r} must be a positive integer.")
    for key, value in (("gtol", gtol), ("ftol", ftol)):
        if not (isinstance(value, (int, float)) and value >= 0):
            raise SceneError(f"{key} = {value!r} must be a number >= 0.")
    check_observations(sim, observations)
    check_stable_over_bounds(sim, space)
    optimizer_name = optimizer
    problem = compiled_problem(sim, observations, space, optimizer_name, learning_rate)
    data = observation_data(sim, observations)
    base = sim.cast(sim.params)
    start_values = _start_values(space, starts, seed)
    z0 = jnp.stack([space.to_unconstrained(jnp.asarray(v, sim.dtype)) for v in start_values])
    state = problem.init(z0)
    treedef = jax.tree_util.tree_structure(state)
    fingerprint = _fingerprint(sim, space, optimizer_name, learning_rate, start_values, data)
    count = len(start_values)

    if resume and checkpoint is not None and Path(checkpoint).exists():
        run = load_checkpoint(checkpoint, fingerprint)
        state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(leaf) for leaf in run.opt_leaves])
    else:
        run = Progress(0, np.asarray(z0), np.full(count, np.inf), np.zeros(count, bool), [""] * count,
                       [], [], [], [], 0, np.array(z0), np.full(count, np.inf))
    z = jnp.asarray(run.z, sim.dtype)
    started = clock.monotonic()
    saved = copy.deepcopy(run)          # the last complete iteration: what an interrupt keeps
    bar = tqdm(total=max_iterations, initial=run.iteration, unit="it", disable=not progress, desc="calibrate")
    try:
        while run.iteration < max_iterations and not run.done.all():
            step = problem.iterate if run.iteration > 0 else problem.start
            new_z, new_state, value, gradient_norm = step(z, state, data, base)
            value, gradient_norm = np.asarray(value), np.asarray(gradient_norm)
            running = ~run.done
            run.evaluations += int(np.sum(running)) * (1 + _linesearch_steps(new_state, optimizer_name))
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
                elif np.isfinite(run.loss[s]) and change <= ftol * max(abs(value[s]), 1e-300):
                    run.reason[s] = f"relative loss change {change / max(abs(value[s]), 1e-300):.3g} <= ftol"
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
            saved = copy.deepcopy(run)
            bar.update(1)
            bar.set_postfix(loss=f"{np.min(run.best_loss):.4g}")
            if checkpoint is not None and run.iteration % checkpoint_every == 0:
                save_checkpoint(checkpoint, run, fingerprint)
            if callback is not None:
                callback(run.iteration, run)
    except KeyboardInterrupt:
        if checkpoint is not None:
            save_checkpoint(checkpoint, saved, fingerprint)
        raise
    finally:
        bar.close()
    if checkpoint is not None:
        save_checkpoint(checkpoint, run, fingerprint)
    for s in range(count):
        if not run.reason[s]:
            run.reason[s] = f"max_iterations = {max_iterations} reached"

    # Each start's answer is its best finite point (the final one unless it went astray).
    final_z = jnp.asarray(run.best_z, sim.dtype)
    final_losses = np.asarray(problem.losses(final_z, data, base))
    if not np.any(np.isfinite(final_losses)):
        raise SimulationError("every start of the calibration went non-finite; narrow the bounds or change the starts.")
    best = int(np.nanargmin(np.where(np.isfinite(final_losses), final_losses, np.nan)))
    values = np.asarray(space.to_physical(final_z[best]))
    covariance, jacobian = gauss_newton(
        functools.partial(problem.residuals, data=data, base=base), values, noise_known=observations.noise_known
    )
    probes, final_state = sim._probes(space.insert(jnp.asarray(values, sim.dtype), base), sim.initial_state(base))
    warning = ""
    if int(final_state.error_step) >= 0:
        warning = "best-fit run: " + describe_failure(sim, final_state)
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
        iterations=run.iteration,
        # + one loss of every start, the Jacobian (P forward-mode passes ~ P simulations), the probes
        evaluations=run.evaluations + count + space.size + 1,
        wall_time=clock.monotonic() - started,
        optimizer=optimizer_name,
        observations=observations,
        time=np.asarray(sim.time),
        probes={name: np.asarray(v) for name, v in probes.items()},
        scene_toml=sim.scene.to_toml(),
        warning=warning,
    )


def _fingerprint(sim, space, optimizer_name, learning_rate, start_values, data):
    """What must match for a checkpoint to be resumed: problem, optimiser, starts and data."""
    digest = hashlib.sha256()
    digest.update(sim.scene.to_toml().encode())
    for times, values, scale in data:
        for array in (times, values, scale):
            digest.update(np.asarray(array).tobytes())
    digest.update(np.asarray(start_values).tobytes())
    return f"{space.fingerprint()} {optimizer_name} {learning_rate} {digest.hexdigest()}"


def _start_values(space: ParameterSpace, starts, seed):
    if isinstance(starts, int):
        if starts < 1:
            raise SceneError(f"starts = {starts!r} must be at least 1.")
        return space.random_values(starts, seed)
    rows = []
    for index, start in enumerate(starts):
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
    """Extra loss evaluations the L-BFGS line search made in this iteration (0 for Adam)."""
    if optimizer_name != "lbfgs":
        return 0
    steps = optax.tree_utils.tree_get(state, "num_linesearch_steps")
    return 0 if steps is None else int(np.max(np.asarray(steps)))
