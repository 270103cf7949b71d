"""The calibration problem: experiments and the fitted parameters made into one residual
function of the parameters, compiled for the chosen optimiser.

    problem = build_problem(experiments, fit, optimizer, learning_rate)

checks what can be checked before anything runs (one dtype, no value both fixed and fitted,
observations inside the simulated span, bounds that keep the time step stable), groups the
experiments that run together (`inverse.experiments.group_experiments`), and compiles the
optimiser's start and iteration over the batch of starts (`CompiledProblem`, cached on the
first simulation so that later calibrations of the same layout compile nothing).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from inverse import levenberg_marquardt
from inverse.experiments import (
    base_parameters, check_observations, group_experiments, layout_of, problem_arguments, problem_residuals,
)
from inverse.parameters import ParameterSpace
from jaxmpm.errors import SceneError
from jaxmpm.kernels.xla_options import jit_reverse_mode, jit_with_options
from jaxmpm.physics.time_step import exceeds
from jaxmpm.scene.parameters import resolve

OPTIMIZERS = ("lm", "lbfgs", "adam")



@dataclasses.dataclass(frozen=True)
class Problem:
    """A calibration's problem: its experiments, the fitted parameters' space, the groups of
    experiments run together with their observation data and fixed values (`data`, `bases`,
    the arguments of every compiled program), and the compiled programs."""

    experiments: list
    space: ParameterSpace
    groups: list
    data: object
    bases: object
    programs: CompiledProblem
    optimizer: str
    learning_rate: float | None

    @property
    def dtype(self):
        return self.experiments[0].sim.dtype

    @property
    def count(self) -> int:
        """M, the number of residuals of all experiments together."""
        return sum(e.observations.count for e in self.experiments)


def build_problem(experiments, fit, optimizer, learning_rate) -> Problem:
    """The Problem of fitting `fit` ({path: bounds}) to `experiments`; SceneError naming the key
    for anything wrong that can be told before compiling."""
    dtypes = {e.sim.dtype for e in experiments}
    if len(dtypes) > 1:
        raise SceneError("experiments: every scene must have the same numerics.dtype "
                         f"(they have {', '.join(sorted(map(str, dtypes)))}).")
    space = ParameterSpace([e.sim.params for e in experiments], fit)
    for index, experiment in enumerate(experiments):
        check_fixed_not_fitted(experiment, space, index)
        check_observations(experiment)
        check_stable_over_bounds(experiment, space, index)
    groups = group_experiments(experiments, space)
    data, bases = problem_arguments(experiments, groups)
    programs = compiled_problem(experiments, groups, space, optimizer, learning_rate)
    return Problem(experiments, space, groups, data, bases, programs, optimizer, learning_rate)


def check_fixed_not_fitted(experiment, space: ParameterSpace, index: int):
    """SceneError if a value the experiment fixes (`set`) is also fitted."""
    fitted = {location: entry.path for entry, location in space.fitted_in(index)}
    for name in experiment.set:
        try:
            location = resolve(experiment.sim.params, name)
        except SceneError:
            continue                    # base_parameters names the bad key
        if location in fitted:
            raise SceneError(f"experiments.{experiment.name}.set.{name} is also fitted (as {fitted[location]!r}): "
                             "a value cannot be both fixed and fitted.")


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


def rough_misfit_warning(problem: Problem, start_values) -> str:
    """`linear_shape_warning` of every experiment at the first start, joined ("" if none)."""
    return "; ".join(filter(None, (linear_shape_warning(e, problem.space, start_values[0], i)
                                   for i, e in enumerate(problem.experiments))))
