"""The transfers' reverse mode written as each other: for programs differentiated in reverse
mode only.

Adding stencil values into the nodes (particle-to-grid) and reading node values at the
stencils (grid-to-particle) are each other's exact transpose, and so are a sum over a
point's stencil and a broadcast over it. JAX transposes each of them on its own, into a
slower pattern on XLA:CPU (the scatter's transpose becomes a gather with per-element index
arithmetic, the sum's a pad of every stencil slice). Here each one's reverse mode calls its
partner's forward implementation (`jax.custom_vjp`). A `custom_vjp` function has no forward
mode, so a step uses these only when its program is never differentiated in forward mode
(`Structure.derivatives = "reverse"`, `Simulation.reverse_only`).
"""

import jax
import jax.numpy as jnp


def paired(forward, transpose):
    """f(indices, linear) = forward(indices, linear), linear in `linear`, whose reverse mode is
    transpose(indices, cotangent); `indices` (integers) carry no derivative."""

    @jax.custom_vjp
    def linear_map(indices, linear):
        return forward(indices, linear)

    def remember(indices, linear):
        return forward(indices, linear), indices

    def back(indices, cotangent):
        zeros = jax.tree_util.tree_map(lambda index: None, indices)
        return zeros, transpose(indices, cotangent)

    linear_map.defvjp(remember, back)
    return linear_map


def scatter_with_gather_transpose(add, read, base, values, field):
    """add(base, values, field), whose reverse mode is read(base, cotangent, field)."""
    return paired(lambda indices, v: add(*indices[:1], v, indices[1]),
                  lambda indices, nodes: read(indices[0], nodes, indices[1]))((base, field), values)


def gather_with_scatter_transpose(read, add, base, nodes, field):
    """read(base, nodes, field), whose reverse mode is add(base, cotangent, field)."""
    return paired(lambda indices, n: read(indices[0], n, indices[1]),
                  lambda indices, values: add(indices[0], values, indices[1]))((base, field), nodes)


def sum_with_broadcast_transpose(total, values):
    """total(values) (a sum over axes 1 and 2 of (N, s, s, ...)), whose reverse mode is a
    broadcast of the cotangent over those axes."""
    shape = values.shape
    return paired(lambda _, v: total(v), lambda _, bar: jnp.broadcast_to(bar[:, None, None], shape))((), values)

