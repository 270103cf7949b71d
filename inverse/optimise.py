"""The optimiser's loop over a Problem (inverse/problem.py): every start iterated together
until each stops, with the history, the checkpoint and the time kept as it goes.

    problem, z0 = on_devices(problem, start_values)
    run, state = optimise(problem, z0, max_iterations, gtol, ftol, ...)

`run` (a `Progress`) is also what a checkpoint holds: an interrupted calibration resumes from
it and ends where an uninterrupted one would.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import resource
import time as clock
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec

from inverse.compile_clock import CompileClock
from inverse.experiments import layout_of, members_over_devices
from inverse.parameters import ParameterSpace
from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.running.ensembles import batch_mesh, is_spread, spread_over_devices
from jaxmpm.running.tracing import collector_paused

LM_DAMPING_LIMIT = 1e16     # Levenberg–Marquardt damping beyond this: no step lowers the loss



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
    earlier_seconds: float = 0.0            # of elapsed_seconds, the sessions before the last resume
    earlier_compile_seconds: float = 0.0    # of compile_seconds, theirs


HISTORIES = ("history_loss", "history_values", "history_gradient", "history_seconds", "history_memory",
             "history_simulations")


TIMES = ("elapsed_seconds", "compile_seconds", "iteration_compile_seconds")


def optimise(problem, z0, start_values, max_iterations, gtol, ftol, checkpoint, checkpoint_every, resume,
             progress, callback, timing: CompileClock):
    """(Progress, optimiser state) after iterating the starts z0 (S, P) (`start_values` in
    physical units) of `problem` until
    each stops or `max_iterations`; `timing` (a CompileClock opened before anything ran)
    counts the time, that of the sessions before a resume included."""
    from jaxmpm.running.progress import progress_bar

    programs, data, bases, space = problem.programs, problem.data, problem.bases, problem.space
    count, optimizer = z0.shape[0], problem.optimizer
    mark = fingerprint(problem, start_values)
    with collector_paused():        # the first call of each program traces it (jaxmpm.running.tracing)
        treedef = jax.tree_util.tree_structure(programs.start_shape(z0, data, bases))
    if resume and checkpoint is not None and Path(checkpoint).exists():
        run = load_checkpoint(checkpoint, mark)
        state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(leaf) for leaf in run.opt_leaves])
    else:
        with collector_paused():
            state = jax.block_until_ready(programs.start(z0, data, bases))     # one sharded program in flight
        run = Progress(0, np.asarray(z0), np.full(count, np.inf), np.zeros(count, bool), [""] * count,
                       [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(state)], [], [], [], [], [], [],
                       count * len(problem.experiments) if optimizer in ("lm", "lbfgs") else 0, np.array(z0),
                       np.full(count, np.inf))
    run.earlier_seconds, run.earlier_compile_seconds = run.elapsed_seconds, run.compile_seconds  # 0 afresh
    z = over_devices(jnp.asarray(run.z, problem.dtype), replicate=is_spread((data, bases)))
    saved = copy.deepcopy(run)          # the last complete iteration: what an interrupt keeps
    bar = progress_bar(progress, total=max_iterations, initial=run.iteration, unit="it", desc="calibrate")
    try:
        while run.iteration < max_iterations and not run.done.all():
            tick, compiled = clock.monotonic(), timing.seconds
            moved = np.asarray(state.accepted) if optimizer == "lm" else np.ones(count, bool)
            with collector_paused():
                new_z, new_state, value, gradient_norm = programs.iterate(z, state, data, bases)
            value, gradient_norm = np.asarray(value), np.asarray(gradient_norm)
            running = ~run.done
            run.evaluations += (int(np.sum(running)) * len(problem.experiments)
                                * (1 + linesearch_steps(new_state, optimizer)))
            # the value and gradient were taken at z: record them, then decide whether to stop there
            run.history_loss.append(value)
            run.history_values.append(np.asarray(jax.vmap(space.to_physical)(z)))
            run.history_gradient.append(gradient_norm)
            for s in np.flatnonzero(running):
                run.reason[s] = stopping_reason(run, s, value[s], gradient_norm[s], moved[s], new_state, optimizer,
                                                gtol, ftol)
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
            clock_in(run, timing)
            run.history_memory.append(peak_memory_mb())
            run.history_simulations.append(run.evaluations)
            saved = copy.deepcopy(run)
            bar.update(1)
            bar.set_postfix(loss=f"{np.min(run.best_loss):.4g}", sims=run.evaluations,
                            s_per_it=f"{run.history_seconds[-1]:.1f}", mem=f"{run.history_memory[-1]:.0f}MB")
            if checkpoint is not None and run.iteration % checkpoint_every == 0:
                save_checkpoint(checkpoint, run, mark)
            if callback is not None:
                callback(run.iteration, run)
    except KeyboardInterrupt:
        if checkpoint is not None:
            save_checkpoint(checkpoint, clock_in(saved, timing), mark)   # the time spent counts
        raise
    finally:
        bar.close()
    if checkpoint is not None:
        save_checkpoint(checkpoint, clock_in(run, timing), mark)
    for s in range(count):
        if not run.reason[s]:
            run.reason[s] = f"max_iterations = {max_iterations} reached"
    return run, state


def stopping_reason(run, start, value, gradient_norm, moved, state, optimizer, gtol, ftol) -> str:
    """Why start `start` stops at the point whose loss is `value` ("" if it goes on)."""
    change = abs(run.loss[start] - value)
    if not (np.isfinite(value) and np.isfinite(gradient_norm)):
        return "loss or gradient became non-finite (kept the best finite point)"
    if gradient_norm < gtol:
        return f"gradient norm {gradient_norm:.3g} < gtol"
    if moved and np.isfinite(run.loss[start]) and change <= ftol * max(abs(value), 1e-300):
        return f"relative loss change {change / max(abs(value), 1e-300):.3g} <= ftol"
    if optimizer == "lm" and damping_exhausted(state, start):
        return "no step lowers the loss any more (Levenberg-Marquardt damping exhausted)"
    return ""


def on_devices(problem, start_values):
    """(problem, z0): the starts in unconstrained coordinates, and both laid out over the
    devices: the starts' axis when it divides evenly, else the experiments' of each group."""
    z0 = jnp.stack([problem.space.to_unconstrained(jnp.asarray(v, problem.dtype)) for v in start_values])
    if not is_spread(over_devices(z0)):
        data, bases = members_over_devices(problem.groups, problem.data, problem.bases)
        problem = dataclasses.replace(problem, data=data, bases=bases)
    return problem, over_devices(z0, replicate=is_spread((problem.data, problem.bases)))


def clock_in(run: Progress, timing: CompileClock) -> Progress:
    """`run` with its wall and compile time so far: this session's (`timing`) after the
    sessions' before the resume (`run.earlier_seconds`, `run.earlier_compile_seconds`)."""
    run.elapsed_seconds = run.earlier_seconds + timing.elapsed
    run.compile_seconds = run.earlier_compile_seconds + timing.seconds
    return run


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


def damping_exhausted(state, start) -> bool:
    """Levenberg–Marquardt's damping has grown past any use: no step lowers the loss."""
    return float(state.damping[start]) > LM_DAMPING_LIMIT


def fingerprint(problem, start_values):
    """What must match for a checkpoint to be resumed: problem, optimiser, starts and data."""
    digest = hashlib.sha256()
    for experiment in problem.experiments:
        digest.update(experiment.sim.scene.to_toml().encode())
        digest.update(repr(layout_of(experiment.observations)).encode())
        digest.update(repr(sorted((k, np.asarray(v).tolist()) for k, v in experiment.set.items())).encode())
    for leaf in jax.tree_util.tree_leaves(problem.data):
        digest.update(np.asarray(leaf).tobytes())
    digest.update(np.asarray(start_values).tobytes())
    return f"{problem.space.fingerprint()} {problem.optimizer} {problem.learning_rate} {digest.hexdigest()}"


def over_devices(z, replicate=False):
    """The starts (S, P) sharded over every device along S when S divides evenly (the
    compiled iteration then runs its starts where they are, jaxmpm/running/ensembles.py); otherwise
    as they are, or a copy on every device with `replicate` (the experiments are spread: each
    iteration then sees its inputs laid out alike and compiles once)."""
    if replicate:
        return jax.device_put(z, NamedSharding(batch_mesh(), PartitionSpec()))
    return spread_over_devices(z)


def start_values_of(space: ParameterSpace, starts, seed):
    """The (S, P) start values: `starts` random draws inside the bounds (the first is the
    configured start), or the given {path: value} dicts; SceneError naming a bad one."""
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


def linesearch_steps(state, optimizer_name):
    """Extra loss evaluations the L-BFGS line search made in this iteration (0 otherwise)."""
    if optimizer_name != "lbfgs":
        return 0
    steps = optax.tree_utils.tree_get(state, "num_linesearch_steps")
    return 0 if steps is None else int(np.max(np.asarray(steps)))
