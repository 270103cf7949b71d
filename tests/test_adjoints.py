"""The transfers' hand-paired transposes (jaxmpm/adjoints.py) against XLA's own transposes of
the plain formulation: same values and derivatives to round-off in reverse mode, forward mode,
forward over reverse, and under vmap (with batched point positions). Through the whole
checkpointed rollout, tests/test_gradients.py checks the gradients against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.grid import (
    GridLayout, add_over_stencil, add_to_nodes, gather_from_nodes, read_at_stencils, scatter_to_nodes, sum_over_stencil,
)

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
