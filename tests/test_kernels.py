"""The speed kernels (jaxmpm/kernels) against the plain code they replace: the same values and
derivatives to round-off, under every transformation they are used with."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.physics.grid import GridLayout, add_to_nodes
from jaxmpm.kernels.fusion import materialized
from jaxmpm.kernels.scatter import batched_add_to_nodes
from jaxmpm.scene import Scene
from jaxmpm.running.simulation import Simulation
from tests.scenes import BLOCK, jaxpr_equations

LAYOUT = GridLayout((0.0, 0.0), 0.1, (10, 8), "bspline2", 2)
FIELDS = 2
COUNT = 60
FIELD = jnp.asarray(np.arange(COUNT) % FIELDS, jnp.int32)     # each point's velocity field


# Random test data from NumPy: jax.random compiles a program for every shape it draws, about
# 4 s for the largest here (half the scatter tests' time), for data of no consequence.
def normal(seed, shape):
    return jnp.asarray(np.random.default_rng(seed).standard_normal(shape))


def bases(members):
    """The stencil base nodes of `members` random point clouds, (members, N, 2)."""
    x = [jnp.asarray(np.random.default_rng(seed).uniform(size=(COUNT, 2))) * jnp.array([1.0, 0.8]) for seed in range(members)]
    return jnp.stack([LAYOUT.stencil(points).base for points in x])


def kernel(base, values, field):
    return batched_add_to_nodes(add_to_nodes, LAYOUT, base, values, field, FIELDS)


def plain(base, values, field):
    return add_to_nodes(LAYOUT, base, values, field, FIELDS)


@pytest.mark.parametrize("batched", ["values", "points", "both", "nested"])
def test_batched_scatter_under_vmap_is_the_scatter_of_each_member(batched):
    values = normal(3, (3, COUNT, 3, 3, 4))
    base = bases(3)
    fields = jnp.stack([jnp.roll(FIELD, seed) for seed in range(3)])
    if batched == "values":
        mapped = jax.vmap(kernel, in_axes=(None, 0, None))(base[0], values, fields[0])
        expected = [plain(base[0], values[b], fields[0]) for b in range(3)]
    elif batched == "points":
        mapped = jax.vmap(kernel, in_axes=(0, None, 0))(base, values[0], fields)
        expected = [plain(base[b], values[0], fields[b]) for b in range(3)]
    elif batched == "both":
        mapped = jax.vmap(kernel)(base, values, fields)
        expected = [plain(base[b], values[b], fields[b]) for b in range(3)]
    else:                                # a vmap of tangents inside a vmap of ensemble members
        pairs = jnp.stack([values, -2.0 * values], axis=1)
        mapped = jax.vmap(jax.vmap(kernel, in_axes=(None, 0, None)))(base, pairs, fields)
        expected = [jnp.stack([plain(base[b], pairs[b, k], fields[b]) for k in range(2)]) for b in range(3)]
    np.testing.assert_allclose(mapped, jnp.stack(expected), rtol=1e-13, atol=1e-13)


def test_batched_scatter_keeps_each_window_contiguous():
    """Under vmap it stays one scatter of B N rows of whole (s, s, C) windows (JAX's own batching
    puts the batch axis first in the node array and splits each window in B pieces)."""
    values = normal(3, (3, COUNT, 3, 3, 4))
    base = bases(1)[0]
    jaxpr = jax.make_jaxpr(jax.vmap(lambda values: kernel(base, values, FIELD)))(values)
    shapes = [tuple(v.aval.shape for v in eqn.invars) for eqn in jaxpr_equations(jaxpr.jaxpr)
              if eqn.primitive.name == "scatter-add"]
    assert len(shapes) == 1
    operand, _, updates = shapes[0]
    assert updates == (3 * COUNT, 3, 3, 4) and operand[1:] == (3, 3, 4)


def test_batched_scatter_tangents_are_the_plain_tangents():
    """The Levenberg-Marquardt pattern: P tangents of one primal pass (vmap of jvp)."""
    base = bases(1)[0]
    values = normal(4, (COUNT, 3, 3, 4))
    directions = normal(5, (3, COUNT, 3, 3, 4))

    def pushed(scatter):
        nonlinear = lambda v: jnp.sin(scatter(base, v * v, FIELD))  # noqa: E731
        return jax.vmap(lambda t: jax.jvp(nonlinear, (values,), (t,)), out_axes=(None, 0))(directions)

    (value, tangents), (plain_value, plain_tangents) = pushed(kernel), pushed(plain)
    np.testing.assert_allclose(value, plain_value, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(tangents, plain_tangents, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("entry", [1.5, np.nan, np.inf])
def test_materialized_is_the_identity_in_value_and_derivatives(entry):
    # materialized passes values through a conditional (so that XLA computes them once); the
    # gathers and the stencil rely on it being exactly the identity, whatever the entry its
    # predicate reads (NaN and inf included), under jit, jvp, grad and vmap (where the
    # conditional becomes a select).
    values = normal(5, (4, 3, 2)).at[0, 0, 0].set(entry)
    other = normal(6, (4,))
    weights = normal(7, (4, 3, 2))

    def through(values, other):
        kept, also = materialized((values, other))
        return jnp.sum(weights * jnp.sin(kept)) + jnp.sum(also * also)

    def plain(values, other):
        return jnp.sum(weights * jnp.sin(values)) + jnp.sum(other * other)

    np.testing.assert_array_equal(jax.jit(materialized)((values, other))[0], values)
    np.testing.assert_array_equal(jax.jit(materialized)(values), values)
    tangents = (jnp.ones_like(values), 2.0 * other)
    np.testing.assert_array_equal(jax.jvp(through, (values, other), tangents)[1], jax.jvp(plain, (values, other), tangents)[1])
    finite = values.at[0, 0, 0].set(0.5)   # derivatives at a finite point (sin(NaN) has none to compare)
    for ours, theirs in zip(jax.jit(jax.grad(through, argnums=(0, 1)))(finite, other), jax.grad(plain, argnums=(0, 1))(finite, other)):
        np.testing.assert_array_equal(ours, theirs)
    batch = jnp.stack([values, 2.0 * values])
    np.testing.assert_array_equal(jax.vmap(materialized)(batch), batch)
    np.testing.assert_array_equal(jax.vmap(jax.grad(through), in_axes=(0, None))(jnp.stack([finite, -finite]), other),
                                  jax.vmap(jax.grad(plain), in_axes=(0, None))(jnp.stack([finite, -finite]), other))


CONTACT_BLOCKS = BLOCK.replace('''[[probes]]
name = "top"''', '''[[bodies]]
name = "slider"
material = "soil"
region = { rectangle = [[0.1, 0.2], [0.3, 0.25]] }
velocity = [0.3, 0.0]

[[contacts]]
pair = ["block", "slider"]
friction = 0.4

[[probes]]
name = "top"''')


def test_forward_only_simulation_gives_the_plain_jacobian():
    """`Simulation.forward_only` (the batched scatter in the step) against the plain simulation:
    the Levenberg-Marquardt Jacobian of the probes over E, nu and the contact friction, on a
    scene with two velocity fields."""
    sim = Simulation(Scene.from_toml(CONTACT_BLOCKS))
    fast = sim.forward_only()
    assert fast.structure.derivatives == "forward" and sim.structure.derivatives == "any" and sim.forward_only() is fast
    params = sim.cast(sim.params)

    def residuals(simulation, z):
        p = jax.tree_util.tree_map(lambda v: v, params)
        p["materials"]["soil"]["young"] = params["materials"]["soil"]["young"] * (1.0 + z[0])
        p["materials"]["soil"]["poisson"] = params["materials"]["soil"]["poisson"] * (1.0 + z[1])
        p["contacts"]["block/slider"]["friction"] = params["contacts"]["block/slider"]["friction"] * (1.0 + z[2])
        return jnp.concatenate([v.ravel() for v in jax.tree_util.tree_leaves(simulation.probes(p))])

    def jacobian(simulation):
        z = jnp.zeros(3, sim.dtype)
        push = lambda t: jax.jvp(lambda z: residuals(simulation, z), (z,), (t,))  # noqa: E731
        return jax.jit(jax.vmap(push, out_axes=(None, 0)))(jnp.eye(3, dtype=sim.dtype))

    (r, columns), (plain_r, plain_columns) = jacobian(fast), jacobian(sim)
    assert float(jnp.max(jnp.abs(plain_columns))) > 0.0
    np.testing.assert_allclose(r, plain_r, rtol=1e-12, atol=1e-15)
    scale = float(jnp.max(jnp.abs(plain_columns)))
    np.testing.assert_allclose(columns, plain_columns, rtol=1e-9, atol=1e-12 * scale)


def test_reverse_only_simulation_gives_the_plain_gradient():
    """`Simulation.reverse_only` (the transfers transposed into each other) against the plain
    simulation: value and gradient of a probe misfit over every parameter, on a scene with
    two velocity fields, a contact pair and 3 x 3 stencils."""
    sim = Simulation(Scene.from_toml(CONTACT_BLOCKS.replace('shape = "linear"', 'shape = "bspline2"')))
    fast = sim.reverse_only()
    assert fast.structure.derivatives == "reverse" and sim.reverse_only() is fast
    params = sim.cast(sim.params)

    def misfit(simulation):
        def loss(p):
            probes = simulation.probes(p)
            return sum(jnp.sum(jnp.sin(10.0 * history)) for history in probes.values())
        return jax.jit(jax.value_and_grad(loss))(params)

    (value, gradient), (plain_value, plain_gradient) = misfit(fast), misfit(sim)
    np.testing.assert_allclose(value, plain_value, rtol=1e-12)
    for ours, theirs in zip(jax.tree_util.tree_leaves(gradient), jax.tree_util.tree_leaves(plain_gradient)):
        assert float(jnp.max(jnp.abs(theirs))) > 0.0
        np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(theirs))))


@pytest.mark.parametrize("variant", ["forward_only", "reverse_only"])
def test_a_variant_refuses_the_other_mode(variant):
    sim = getattr(Simulation(Scene.from_toml(BLOCK)), variant)()
    loss = lambda young: jnp.sum(sim.probes(jaxmpm_with_young(sim, young))["top"])  # noqa: E731
    # under jit, as a calibration takes its derivatives: refused while tracing (taken op by op,
    # the forward-only variant compiled its linearized rollout before the transpose refused)
    other = ((lambda: jax.jit(jax.grad(loss))(1.0e6)) if variant == "forward_only"
             else (lambda: jax.jit(lambda young: jax.jvp(loss, (young,), (1.0,)))(1.0e6)))
    with pytest.raises((TypeError, NotImplementedError)):
        other()


def jaxmpm_with_young(sim, young):
    from jaxmpm import with_values
    return with_values(sim.params, {"soil.young": young})
