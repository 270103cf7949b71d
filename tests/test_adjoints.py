"""The transfers' hand-paired transposes (jaxmpm/adjoints.py) against XLA's own transposes of
the plain formulation: same values and derivatives to round-off in reverse mode, forward mode,
forward over reverse, and under vmap (with batched point positions). Through the whole
checkpointed rollout, tests/test_gradients.py checks the gradients against finite differences."""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.grid import (
    GridLayout, add_over_stencil, add_to_nodes, add_to_nodes_batched, gather_from_nodes, read_at_stencils, scatter_to_nodes, sum_over_stencil,
)

def equations_binding(jaxpr, name):
    """The equations of `jaxpr` and of every jaxpr nested in it that bind primitive `name`."""
    found = []
    for equation in jaxpr.eqns:
        if equation.primitive.name == name:
            found.append(equation)
        for value in equation.params.values():
            for inner in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(inner, jax.extend.core.ClosedJaxpr):
                    found += equations_binding(inner.jaxpr, name)
                elif isinstance(inner, jax.extend.core.Jaxpr):
                    found += equations_binding(inner, name)
    return found


def count_primitive(jaxpr, name):
    """How many equations of `jaxpr` and of every jaxpr nested in it bind primitive `name`."""
    return len(equations_binding(jaxpr, name))


LAYOUT = GridLayout((0.0, 0.0), 0.1, (10, 8), "bspline2", 2)
FIELDS = 2


def points(seed, count=60):
    return jax.random.uniform(jax.random.PRNGKey(seed), (count, 2)) * jnp.array([1.0, 0.8])


FIELD = jnp.asarray(np.arange(60) % FIELDS, jnp.int32)     # each point's velocity field


def plain_transfers():
    return (lambda base, values: add_to_nodes(LAYOUT, base, values, FIELD, FIELDS),
            lambda base, nodes: read_at_stencils(LAYOUT, base, nodes, 3, FIELD),
            add_over_stencil)


def paired_transfers():
    return (lambda base, values: scatter_to_nodes(LAYOUT, base, values, FIELD, FIELDS),
            lambda base, nodes: gather_from_nodes(LAYOUT, base, nodes, 3, FIELD),
            sum_over_stencil)


def misfit(transfers):
    """A nonlinear scalar of positions and node values through a scatter, a gather and a
    stencil sum (the step's pattern: weights from positions, values to nodes and back)."""
    scatter, gather, total = transfers

    def loss(x, nodes):
        stencil = LAYOUT.stencil(x)
        values = stencil.weights[..., None] * jnp.sin(nodes[0, :3, :3, :][None] + x[:, None, None, :1])
        grid = scatter(stencil.base, values)
        back = gather(stencil.base, jnp.cos(grid) * nodes)
        return jnp.sum(total(stencil.weights[..., None] * back) ** 2) + jnp.sum(grid * nodes)

    return loss


NODES = jax.random.normal(jax.random.PRNGKey(7), (FIELDS,) + LAYOUT.nodes + (2,))


@pytest.mark.parametrize("transform", ["grad", "jvp", "vmap_grad", "jacfwd_of_grad"])
def test_paired_transposes_match_xla_transposes(transform):
    plain, paired = misfit(plain_transfers()), misfit(paired_transfers())
    x = points(0)
    if transform == "grad":
        results = [jax.jit(jax.grad(f, argnums=(0, 1)))(x, NODES) for f in (plain, paired)]
    elif transform == "jvp":
        results = [jax.jit(lambda x, n, f=f: jax.jvp(f, (x, n), (jnp.ones_like(x), n))[1])(x, NODES) for f in (plain, paired)]
    elif transform == "vmap_grad":       # positions batched: the integer residuals are batched too
        xs = jnp.stack([x, points(1)])
        results = [jax.jit(jax.vmap(jax.grad(f, argnums=(0, 1)), in_axes=(0, None)))(xs, NODES) for f in (plain, paired)]
    else:                                # forward over reverse (Hessian-vector products)
        results = [jax.jit(lambda x, n, f=f: jax.jvp(jax.grad(f, argnums=1), (x, n), (jnp.ones_like(x), n))[1])(x, NODES)
                   for f in (plain, paired)]
    np.testing.assert_allclose(jax.jit(paired)(x, NODES), jax.jit(plain)(x, NODES), rtol=1e-13)
    for a, b in zip(jax.tree.leaves(results[0]), jax.tree.leaves(results[1])):
        scale = float(jnp.max(jnp.abs(a)))
        assert scale > 0.0
        np.testing.assert_allclose(b, a, atol=1e-12 * scale)


@pytest.mark.parametrize("batched", ["values", "points", "both", "nested"])
def test_scatter_under_vmap_is_the_scatter_of_each_member(batched):
    """`add_to_nodes_batched` batches by hand (the batch becomes fields of one scatter); its
    vmap must equal add_to_nodes applied member by member, whichever inputs are batched."""
    values = jax.random.normal(jax.random.PRNGKey(3), (3, 60, 3, 3, 4))
    bases = jnp.stack([LAYOUT.stencil(points(seed)).base for seed in range(3)])
    fields = jnp.stack([jnp.roll(FIELD, seed) for seed in range(3)])
    scatter = lambda base, values, field: add_to_nodes_batched(LAYOUT, base, values, field, FIELDS)  # noqa: E731
    member = lambda base, values, field: add_to_nodes(LAYOUT, base, values, field, FIELDS)  # noqa: E731
    if batched == "values":
        mapped = jax.vmap(scatter, in_axes=(None, 0, None))(bases[0], values, fields[0])
        expected = [member(bases[0], values[b], fields[0]) for b in range(3)]
    elif batched == "points":
        mapped = jax.vmap(scatter, in_axes=(0, None, 0))(bases, values[0], fields)
        expected = [member(bases[b], values[0], fields[b]) for b in range(3)]
    elif batched == "both":
        mapped = jax.vmap(scatter)(bases, values, fields)
        expected = [member(bases[b], values[b], fields[b]) for b in range(3)]
    else:                                # a vmap of tangents inside a vmap of starts
        pairs = jnp.stack([values, -2.0 * values], axis=1)
        mapped = jax.vmap(jax.vmap(scatter, in_axes=(None, 0, None)))(bases, pairs, fields)
        expected = [jnp.stack([member(bases[b], pairs[b, k], fields[b]) for k in range(2)]) for b in range(3)]
    np.testing.assert_allclose(mapped, jnp.stack(expected), rtol=1e-13, atol=1e-13)


def test_scatter_under_vmap_keeps_each_window_contiguous():
    """The batched scatter is one scatter of B N rows into B F fields, not JAX's own batching
    (the batch axis first in the node array, each window split in B pieces: 40x slower)."""
    values = jax.random.normal(jax.random.PRNGKey(3), (3, 60, 3, 3, 4))
    base = LAYOUT.stencil(points(0)).base
    scatter = lambda values: add_to_nodes_batched(LAYOUT, base, values, FIELD, FIELDS)  # noqa: E731
    scatters = equations_binding(jax.make_jaxpr(jax.vmap(scatter))(values).jaxpr, "scatter-add")
    assert len(scatters) == 1
    operand, _, updates = (v.aval.shape for v in scatters[0].invars)
    assert updates == (3 * 60, 3, 3, 4) and operand[1:] == (3, 3, 4)


# --------------------------------------------------------------------------- stress updates
# Each law's hand-written reverse mode (`update_adjoint`, used by `points_update`) against
# JAX's own reverse mode of the same `update`: same cotangents for the parameters, the stress,
# the velocity gradient and the history, to round-off, with points in every branch of the
# return (elastic, cone, apex); forward mode, vmap and forward-over-reverse must still work.

from jaxmpm.materials import DruckerPrager, LinearElastic, material_parameters  # noqa: E402
from jaxmpm.materials.base import points_update  # noqa: E402
from jaxmpm.materials.linear_elastic import elastic_trial_voigt  # noqa: E402

LAWS = {
    "elastic": LinearElastic(density=2000.0, young=2e7, poisson=0.3),
    "drucker_prager": DruckerPrager(density=1800.0, young=1e6, poisson=0.3, friction_angle=30.0, dilation_angle=5.0),
    "perzyna": DruckerPrager(density=1800.0, young=1e6, poisson=0.25, friction_angle=35.0, dilation_angle=3.0,
                             fluidity=50.0, exponent=2.0),
}
STRESS_DT = 1e-3


def point_states(count=600, seed=3):
    """Compressed stresses with random deviators and random velocity gradients (the in-plane
    entries and the hoop rate, as in axisymmetry), large enough that points yield, return to
    the apex, or stay elastic."""
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    in_plane = jnp.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])    # no out-of-plane shear
    noise = in_plane * jax.random.normal(keys[0], (count, 3, 3))
    stress = -1e4 * (jnp.eye(3) + 0.25 * (noise + jnp.swapaxes(noise, 1, 2)))
    stress = stress.at[: count // 10].multiply(-1.0)      # some in tension: they return to the apex
    # singular points: a zero deviator under pressure, and a zero stress (p = q = 0), both at rest
    stress = stress.at[-2].set(-1e4 * jnp.eye(3)).at[-1].set(0.0)
    gradient = 2.0 * in_plane * jax.random.normal(keys[1], (count, 3, 3)).at[-2:].set(0.0)
    history = {"plastic_strain": 1e-3 * jax.random.uniform(keys[2], (count,))}
    return stress, gradient, history


def update_pair(name):
    material = LAWS[name]
    law = material.law
    params = jax.tree.map(jnp.asarray, material_parameters(material))

    def plain(params, stress, gradient, history):
        return jax.vmap(law.update, in_axes=(None, 0, 0, None, 0))(params, stress, gradient, STRESS_DT, history)

    return law, params, plain, points_update(law, STRESS_DT)


def assert_same_trees(ours, theirs, rtol=1e-12):
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(a, b, atol=rtol * scale + 1e-300)


@pytest.mark.parametrize("name", list(LAWS))
def test_hand_written_stress_adjoint_matches_jax_reverse_mode(name):
    law, params, plain, hand = update_pair(name)
    stress, gradient, history = point_states()
    if name != "elastic":      # every branch of the return occurs
        returned = jax.vmap(lambda s, L: law.return_state(law.constants(params), elastic_trial_voigt(
            law.constants(params), s, L, STRESS_DT), STRESS_DT))(stress, gradient)
        cone, apex = int(jnp.sum(returned["to_cone"])), int(jnp.sum(returned["to_apex"]))
        assert 0 < cone < len(stress) and apex > 0 and cone + apex < len(stress)
    primals = (params, stress, gradient, history)
    cotangent = (jnp.cos(jnp.arange(stress.size, dtype=float)).reshape(stress.shape),
                 {"plastic_strain": jnp.sin(jnp.arange(len(stress), dtype=float))})
    assert_same_trees(jax.jit(hand)(*primals), jax.jit(plain)(*primals), rtol=0.0)
    ours = jax.jit(lambda *p: jax.vjp(hand, *p)[1](cotangent))(*primals)
    theirs = jax.jit(lambda *p: jax.vjp(plain, *p)[1](cotangent))(*primals)
    assert float(jnp.max(jnp.abs(ours[0]["young"]))) > 0.0
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(ours))
    assert_same_trees(ours, theirs)


@pytest.mark.parametrize("transform", ["jvp", "vmap_jvp", "vmap_grad", "jvp_of_grad", "zero_history"])
def test_hand_written_stress_adjoint_under_other_transformations(transform):
    _, params, plain, hand = update_pair("perzyna")
    stress, gradient, history = point_states(200)

    def misfit(update):
        def loss(young, stress):
            new, state = update(dict(params, young=young), stress, gradient, history)
            return jnp.sum(jnp.sin(new / 1e4)) + jnp.sum(state["plastic_strain"] ** 2)
        return loss

    young = params["young"]
    results = []
    for update in (plain, hand):
        loss = misfit(update)
        if transform == "jvp":
            results.append(jax.jvp(loss, (young, stress), (1e4, stress))[1])
        elif transform == "vmap_jvp":    # Levenberg-Marquardt's pass: a batch of tangents, one primal
            push = lambda tangent, loss=loss: jax.jvp(loss, (young, stress), (tangent, stress * tangent / 1e4))  # noqa: E731
            results.append(jax.vmap(push, out_axes=(None, 0))(jnp.array([1e4, -2e4, 5e3]))[1])
        elif transform == "vmap_grad":
            results.append(jax.vmap(jax.grad(loss, argnums=(0, 1)), in_axes=(0, None))(young * jnp.array([0.5, 1.0, 2.0]), stress))
        elif transform == "jvp_of_grad":
            results.append(jax.jvp(jax.grad(loss, argnums=(0, 1)), (young, stress), (1e4, stress))[1])
        else:  # the history's tangent is a symbolic zero: only young carries a derivative
            results.append(jax.grad(lambda y, loss=loss: loss(y, stress))(young))
    assert float(jnp.max(jnp.abs(jax.tree.leaves(results[0])[0]))) > 0.0
    assert_same_trees(results[1], results[0], rtol=1e-10)


def test_forward_mode_computes_the_shared_values_once():
    # Forward mode differentiates the update with shared_once=True: the values every stress
    # entry's tangent reads (trial, p, q, dl, q'/q, p') pass through `materialized`, which is
    # a conditional XLA cannot fuse into; the plain forward pass has none of them.
    _, params, _, hand = update_pair("perzyna")
    stress, gradient, history = point_states(50)
    update = lambda young: hand(dict(params, young=young), stress, gradient, history)  # noqa: E731
    young = params["young"]
    forward = count_primitive(jax.make_jaxpr(update)(young).jaxpr, "cond")
    tangent = count_primitive(jax.make_jaxpr(lambda y: jax.jvp(update, (y,), (1e4,))[1])(young).jaxpr, "cond")
    assert forward == 0 and tangent >= 4


@pytest.mark.parametrize("transform", ["grad", "jvp"])
def test_perzyna_derivatives_read_the_remembered_root(transform):
    # The Newton solve of the Perzyna equation is a while loop. The forward pass solves it once;
    # the hand-written adjoint and the forward-mode tangent read its root instead of solving
    # again (the plain formulation's reverse mode holds the loop once too, through the root's
    # stop_gradient and the implicit-function expression).
    _, params, _, hand = update_pair("perzyna")
    stress, gradient, history = point_states(50)

    def loss(young):
        new, state = hand(dict(params, young=young), stress, gradient, history)
        return jnp.sum(new) + jnp.sum(state["plastic_strain"])

    young = params["young"]
    derivative = jax.grad(loss) if transform == "grad" else (lambda y: jax.jvp(loss, (y,), (1.0,)))
    assert count_primitive(jax.make_jaxpr(loss)(young).jaxpr, "while") == 1
    assert count_primitive(jax.make_jaxpr(derivative)(young).jaxpr, "while") == 1
