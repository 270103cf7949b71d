"""Calibration: fit material parameters to observed probe histories (SPEC section 5).

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

import dataclasses
import functools
import os
import time as clock
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from inverse.fit import Fit, gauss_newton
from inverse.observations import Observations, check_against, default_scale
from inverse.parameters import ParameterSpace
from jaxmpm.errors import SceneError

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


def residual_function(sim, observations: Observations, space: ParameterSpace):
    """residuals(values, data) -> (M,) weighted residuals for physical parameter values (P,),
    with `data` from `observation_data` (so new data of the same layout never recompile)."""
    initial = sim.initial_state()
    probe_widths = {name: value.shape[0] for name, value in sim.observe(initial, initial.x).items()}
    check_against(observations, probe_widths, (float(sim.time[0]), float(sim.time[-1])))
    for name, channel in observations.channels.items():
        for component in channel.components:
            if not 0 <= component < probe_widths[name]:
                raise SceneError(f"observations.{name} names component {component}; the probe has {probe_widths[name]}.")
    time = jnp.asarray(sim.time, sim.dtype)
    layout = [(name, channel.components) for name, channel in observations.channels.items()]

    def residuals(values, data):
        probes = sim.probes(space.insert(values, sim.cast(sim.params)))
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

    residuals: object      # residuals(values, data)
    iterate: object        # iterate(z (S, P), state, data) -> (z, state, loss (S,), |grad|inf (S,))
    losses: object         # losses(z (S, P), data) -> (S,)
    init: object           # init(z (S, P)) -> optimiser state


def compiled_problem(sim, observations, space, optimizer_name, learning_rate) -> CompiledProblem:
    layout = tuple((name, c.components, len(c.times)) for name, c in observations.channels.items())
    key = (space.fingerprint(), optimizer_name, learning_rate, layout)
    cache = sim.__dict__.setdefault("_calibration_problems", {})
    if key in cache:
        return cache[key]
    transform = make_optimizer(optimizer_name, learning_rate)
    residuals = residual_function(sim, observations, space)
    count = observations.count

    def loss_of_z(z, data):
        r = residuals(space.to_physical(z), data)
        return 0.5 * jnp.sum(r * r) / count

    def one_iteration(z, state, data):
        loss = functools.partial(loss_of_z, data=data)
        if optimizer_name == "lbfgs":
            value, gradient = optax.value_and_grad_from_state(loss)(z, state=state)
            updates, state = transform.update(gradient, state, z, value=value, grad=gradient, value_fn=loss)
        else:
            value, gradient = jax.value_and_grad(loss)(z)
            updates, state = transform.update(gradient, state, z)
        return optax.apply_updates(z, updates), state, value, jnp.max(jnp.abs(gradient))

    problem = CompiledProblem(
        residuals=residuals,
        iterate=jax.jit(jax.vmap(one_iteration, in_axes=(0, 0, None))),
        losses=jax.jit(jax.vmap(loss_of_z, in_axes=(0, None))),
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


def save_checkpoint(path, progress: Progress, fingerprint):
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    arrays = {f"opt_{i}": np.asarray(leaf) for i, leaf in enumerate(progress.opt_leaves)}
    with open(temporary, "wb") as stream:
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
            leaf_count=len(progress.opt_leaves),
            **arrays,
        )
    os.replace(temporary, path)


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
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise SceneError(f"max_iterations = {max_iterations!r} must be a positive integer.")
    optimizer_name = optimizer
    problem = compiled_problem(sim, observations, space, optimizer_name, learning_rate)
    data = observation_data(sim, observations)
    start_values = _start_values(space, starts, seed)
    z0 = jnp.stack([space.to_unconstrained(jnp.asarray(v, sim.dtype)) for v in start_values])
    state = problem.init(z0)
    treedef = jax.tree_util.tree_structure(state)
    fingerprint = f"{space.fingerprint()} {optimizer_name} {learning_rate} {len(start_values)}"

    if resume and checkpoint is not None and Path(checkpoint).exists():
        saved = load_checkpoint(checkpoint, fingerprint)
        state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(leaf) for leaf in saved.opt_leaves])
        run = saved
    else:
        run = Progress(0, np.asarray(z0), np.full(len(start_values), np.inf), np.zeros(len(start_values), bool),
                       [""] * len(start_values), [], [], [], [], 0)
    z = jnp.asarray(run.z, sim.dtype)
    started = clock.monotonic()
    bar = tqdm(total=max_iterations, initial=run.iteration, unit="it", disable=not progress, desc="calibrate")
    try:
        while run.iteration < max_iterations and not run.done.all():
            new_z, new_state, value, gradient_norm = problem.iterate(z, state, data)
            value, gradient_norm = np.asarray(value), np.asarray(gradient_norm)
            run.evaluations += int(np.sum(~run.done)) * (1 + _linesearch_steps(new_state, optimizer_name))
            running = ~run.done
            # the value and gradient were taken at z: record them, then decide whether to stop there
            run.history_loss.append(value)
            run.history_values.append(np.asarray(jax.vmap(space.to_physical)(z)))
            run.history_gradient.append(gradient_norm)
            for s in np.flatnonzero(running):
                change = abs(run.loss[s] - value[s])
                if gradient_norm[s] < gtol:
                    run.reason[s] = f"gradient norm {gradient_norm[s]:.3g} < gtol"
                elif np.isfinite(run.loss[s]) and change <= ftol * max(abs(value[s]), 1e-300):
                    run.reason[s] = f"relative loss change {change / max(abs(value[s]), 1e-300):.3g} <= ftol"
                elif not np.isfinite(value[s]):
                    run.reason[s] = "loss became non-finite"
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
            bar.update(1)
            bar.set_postfix(loss=f"{np.min(run.loss):.4g}")
            if checkpoint is not None and run.iteration % checkpoint_every == 0:
                save_checkpoint(checkpoint, run, fingerprint)
            if callback is not None:
                callback(run.iteration, run)
    except KeyboardInterrupt:
        if checkpoint is not None:
            save_checkpoint(checkpoint, run, fingerprint)
        raise
    finally:
        bar.close()
    if checkpoint is not None:
        save_checkpoint(checkpoint, run, fingerprint)
    for s in range(len(run.reason)):
        if not run.reason[s]:
            run.reason[s] = f"max_iterations = {max_iterations} reached"

    final_losses = np.asarray(problem.losses(z, data))
    best = int(np.nanargmin(final_losses))
    values = np.asarray(space.to_physical(z[best]))
    covariance, jacobian = gauss_newton(
        functools.partial(problem.residuals, data=data), values, noise_known=observations.noise_known
    )
    probes = {name: np.asarray(v) for name, v in sim.probes(space.insert(jnp.asarray(values, sim.dtype), sim.cast(sim.params))).items()}
    return Fit(
        names=space.names,
        values=values,
        loss=float(final_losses[best]),
        covariance=covariance,
        jacobian=jacobian,
        start_values=np.asarray(start_values),
        final_values=np.asarray(jax.vmap(space.to_physical)(z)),
        final_losses=final_losses,
        best_start=best,
        reasons=list(run.reason),
        history_loss=np.array(run.history_loss),
        history_values=np.array(run.history_values),
        history_gradient=np.array(run.history_gradient),
        iterations=run.iteration,
        evaluations=run.evaluations + 1 + space.size,
        wall_time=clock.monotonic() - started,
        optimizer=optimizer_name,
        observations=observations,
        time=np.asarray(sim.time),
        probes=probes,
        scene_toml=sim.scene.to_toml(),
    )


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
