"""Experiments: what a calibration fits at once.

An `Experiment` is one simulation with what was measured in it, and the parameter values
that set it apart from the others (a loading rate, a surcharge):

    slow = inverse.Experiment(sim, measured_slow, set={"bodies.footing.velocity": [0.0, -0.02]})
    fast = inverse.Experiment(sim, measured_fast, set={"bodies.footing.velocity": [0.0, -0.08]})
    fit = inverse.calibrate([slow, fast], fit={"sand.fluidity": (0.1, 100), ...})

The fitted parameters are shared by name: each applies to every experiment whose scene has
it (at least one must). The residuals of all experiments form one vector, so one optimiser
and one covariance see every measurement. Experiments of the same `Simulation` whose
observations have the same layout run together under `jax.vmap` (one compiled pass for the
group).

Observations may be handed over as an `Observations`, a dict {probe: (times, values)} or
{probe: (times, values, components)}, a jaxmpm `Result`, or the path of a CSV or HDF5 file.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from inverse.observations import Observations, check_against, default_scale, load_observations
from jaxmpm.running.ensembles import spread_over_devices
from jaxmpm.errors import SceneError
from jaxmpm.scene.parameters import resolve, value_at, with_values


def as_observations(source, sigma: dict | None = None, label: str = "observations") -> Observations:
    """Observations from whatever a user holds (see the module docstring)."""
    from jaxmpm.running.results import Result

    if isinstance(source, Observations):
        if sigma:
            raise SceneError(f"{label}: give the noise sigma when building the Observations, not beside them.")
        return source
    if isinstance(source, (str, Path)):
        return load_observations(source, sigma)
    if isinstance(source, Result):
        return Observations.from_arrays({name: (source.time, values) for name, values in source.probes.items()}, sigma)
    if isinstance(source, dict):
        for name, entry in source.items():
            if not isinstance(entry, (tuple, list)) or len(entry) not in (2, 3):
                raise SceneError(
                    f"{label}[{name!r}] must be (times, values) or (times, values, components), "
                    f"not {type(entry).__name__}."
                )
        return Observations.from_arrays(source, sigma)
    raise SceneError(
        f"{label} is a {type(source).__name__}: give an inverse.Observations, a dict "
        "{probe: (times, values)}, a jaxmpm Result, or the path of a .csv or .h5 file."
    )


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One simulation and its measurements. `set` {dotted name: value} fixes parameter values
    of this experiment (not fitted); `name` labels it in results (default "experiment_k")."""

    sim: object
    observations: object
    set: dict = dataclasses.field(default_factory=dict)
    name: str | None = None
    sigma: dict | None = None


def experiments_from(sim_or_experiments, observations) -> list[Experiment]:
    """A checked list of Experiments from calibrate's first two arguments: (sim, observations),
    an Experiment, or a list of Experiments or (sim, observations[, set]) tuples."""
    if isinstance(sim_or_experiments, (list, tuple)):
        if observations is not None:
            raise SceneError("observations: give them inside each experiment when calibrating several.")
        items = list(sim_or_experiments)
    elif isinstance(sim_or_experiments, Experiment):
        items = [sim_or_experiments] if observations is None else [
            dataclasses.replace(sim_or_experiments, observations=observations)]
    else:
        if observations is None:
            raise SceneError("observations are missing: calibrate(sim, observations, fit=...).")
        items = [Experiment(sim_or_experiments, observations)]
    if not items:
        raise SceneError("experiments is empty: give at least one (simulation, observations).")
    experiments = []
    for index, item in enumerate(items):
        if isinstance(item, (tuple, list)):
            if len(item) not in (2, 3):
                raise SceneError(f"experiments[{index}] must be (sim, observations) or (sim, observations, set).")
            item = Experiment(*item)
        if not isinstance(item, Experiment):
            raise SceneError(f"experiments[{index}] is a {type(item).__name__}, not an inverse.Experiment.")
        if not isinstance(item.set, dict):
            raise SceneError(f"experiments[{index}].set = {item.set!r} must be a dict {{dotted name: value}}.")
        if not hasattr(item.sim, "probes") or not hasattr(item.sim, "structure"):
            raise SceneError(f"experiments[{index}].sim is a {type(item.sim).__name__}, not a jaxmpm.Simulation.")
        name = item.name or (f"experiment_{index}" if len(items) > 1 else item.sim.scene.name)
        label = "observations" if len(items) == 1 else f"experiments.{name}.observations"
        experiments.append(dataclasses.replace(
            item, name=name, observations=as_observations(item.observations, item.sigma, label), sigma=None))
    names = [e.name for e in experiments]
    for name in names:
        if not isinstance(name, str) or not name or "/" in name:
            raise SceneError(f"experiments: the name {name!r} must be a non-empty string without '/' "
                             "(it names a group of the fit's HDF5 file).")
    duplicate = next((n for n in names if names.count(n) > 1), None)
    if duplicate is not None:
        raise SceneError(f"experiments: the name {duplicate!r} is used twice.")
    return experiments


def base_parameters(experiment: Experiment):
    """The experiment's parameter pytree: the scene's values with its `set` values (checked
    against the fixed time step), as arrays of the scene's dtype."""
    sim = experiment.sim
    fixed = {}
    for name, value in experiment.set.items():
        try:
            fixed[name] = np.asarray(value, float)      # a list is one value, not a pytree of scalars
        except (TypeError, ValueError):
            raise SceneError(f"experiments.{experiment.name}.set.{name} = {value!r} must be a number or an array.") from None
        if not np.all(np.isfinite(fixed[name])):
            raise SceneError(f"experiments.{experiment.name}.set.{name} = {value!r} must be finite.")
    try:
        params = with_values(sim.params, fixed)
    except SceneError as error:
        raise SceneError(f"experiments.{experiment.name}.set: {error}") from None
    params = sim.cast(params)
    for name, value in fixed.items():
        expected = np.shape(value_at(sim.params, resolve(sim.params, name)))
        if value.shape != expected:
            raise SceneError(f"experiments.{experiment.name}.set.{name} has shape {value.shape}; the parameter has {expected}.")
    sim.check_time_step(params)
    return params


def check_observations(experiment: Experiment):
    """SceneError unless every channel names a probe component of the scene inside its time."""
    sim, observations = experiment.sim, experiment.observations
    probe_widths = {name: value.shape[0] for name, value in sim.observe_start(sim.initial_state()).items()}
    check_against(observations, probe_widths, (float(sim.time[0]), float(sim.time[-1])))
    for name, channel in observations.channels.items():
        for component in channel.components:
            if not 0 <= component < probe_widths[name]:
                raise SceneError(f"observations.{name} names component {component}; the probe has {probe_widths[name]}.")


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


def layout_of(observations: Observations):
    """What decides the shapes of an experiment's residuals (and so what it compiles)."""
    return tuple((name, c.components, len(c.times), c.window) for name, c in observations.channels.items())


def window_steps(window, dt) -> int:
    """The odd number of steps that spans an averaging window of `window` seconds (1: none)."""
    return 2 * int(round(0.5 * window / dt)) + 1


def window_mean(history, width: int):
    """(T, k) running mean of a probe history over `width` (odd) steps centred on each step;
    the ends repeat the first and last values."""
    if width == 1:
        return history
    half = width // 2
    padded = jnp.concatenate([jnp.repeat(history[:1], half, axis=0), history, jnp.repeat(history[-1:], half, axis=0)])
    total = jnp.concatenate([jnp.zeros_like(history[:1]), jnp.cumsum(padded, axis=0)])
    return (total[width:] - total[:-width]) / width


def residual_function(sim, observations: Observations, insert):
    """residuals(values, data, base) -> (M,) weighted residuals r_j = (y_sim(t_j) - y_j) / s_j
    of one experiment, the simulated probes (averaged over each channel's window) linearly
    interpolated to the observation times;
    `insert(values, base)` puts the fitted values (P,) into the parameter pytree `base`.
    derivatives: which derivatives the residuals are taken with, "any", "forward" (the
    Levenberg-Marquardt Jacobians) or "reverse" (gradients of a loss): the simulation's variant
    with the kernels for it (`Simulation.for_derivatives`), the same values."""
    time = jnp.asarray(sim.time, sim.dtype)
    layout = [(name, channel.components, window_steps(channel.window, sim.dt))
              for name, channel in observations.channels.items()]

    variants = {kind: sim.for_derivatives(kind) for kind in ("any", "forward", "reverse")}   # built once, not while tracing

    def residuals(values, data, base, derivatives="any"):
        probes = variants[derivatives].probes(insert(values, base))
        parts = []
        for (name, components, width), (times, observed, scale) in zip(layout, data):
            history = window_mean(probes[name], width)
            simulated = jnp.stack([jnp.interp(times, time, history[:, k]) for k in components], axis=1)
            parts.append(((simulated - observed) / scale).ravel())
        return jnp.concatenate(parts)

    return residuals


@dataclasses.dataclass(frozen=True)
class Group:
    """Experiments run together: same Simulation, same observation layout."""

    members: tuple[int, ...]        # indices into the experiment list
    residuals: object               # residuals(values, data, base) of one member


def group_experiments(experiments, space) -> list[Group]:
    """Experiments grouped by (Simulation, observation layout), in order of first appearance."""
    keys, groups = [], []
    for index, experiment in enumerate(experiments):
        key = (id(experiment.sim), layout_of(experiment.observations))
        if key in keys:
            position = keys.index(key)
            groups[position] = (groups[position][0] + (index,), groups[position][1])
        else:
            keys.append(key)
            insert = lambda values, base, index=index: space.insert(values, base, experiment=index)  # noqa: E731
            groups.append(((index,), residual_function(experiment.sim, experiment.observations, insert)))
    return [Group(members, residuals) for members, residuals in groups]


def problem_arguments(experiments, groups):
    """(data, bases) per group, stacked along a leading axis where a group has several members."""
    data, bases = [], []
    for group in groups:
        members = [experiments[i] for i in group.members]
        group_data = [observation_data(m.sim, m.observations) for m in members]
        group_bases = [base_parameters(m) for m in members]
        if len(members) == 1:
            data.append(group_data[0])
            bases.append(group_bases[0])
        else:
            data.append(jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *group_data))
            bases.append(jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *group_bases))
    return tuple(data), tuple(bases)


def members_over_devices(groups, data, bases):
    """(data, bases) with the member axis of each group of several experiments sharded over
    the devices when the members divide evenly between them (jaxmpm/running/ensembles.py): each
    device then runs its members' simulations, and only their residuals are gathered."""
    spread = [spread_over_devices((d, b)) if len(group.members) > 1 else (d, b)
              for group, d, b in zip(groups, data, bases)]
    return tuple(d for d, _ in spread), tuple(b for _, b in spread)


def experiment_bases(groups, bases, count):
    """The parameter pytree of each of `count` experiments, unstacked from its group's."""
    unstacked = [None] * count
    for group, base in zip(groups, bases):
        for position, index in enumerate(group.members):
            unstacked[index] = base if len(group.members) == 1 else jax.tree_util.tree_map(
                lambda leaf, position=position: leaf[position], base)
    return unstacked


def problem_residuals(groups, derivatives="any"):
    """residuals(values, data, bases) -> (M,): every experiment's residuals, in group order
    (a group of several members is vmapped); derivatives: see `residual_function`."""

    def residuals(values, data, bases):
        parts = []
        for group, group_data, group_base in zip(groups, data, bases):
            of_member = functools.partial(group.residuals, derivatives=derivatives)
            if len(group.members) == 1:
                parts.append(of_member(values, group_data, group_base))
            else:
                batched = jax.vmap(of_member, in_axes=(None, 0, 0))(values, group_data, group_base)
                parts.append(batched.ravel())
        return jnp.concatenate(parts)

    return residuals
