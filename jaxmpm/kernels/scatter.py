"""The particle-to-grid scatter with its own batching rule, for forward-mode programs.

`jax.vmap` of a scatter-add (the P tangents of a Levenberg-Marquardt Jacobian, the members of
an ensemble) puts the batch axis first in the node array, so each point's (s, s, C) window
becomes B pieces far apart in memory. Here a batch of B scatters onto F velocity fields is
one scatter onto B F fields, whose rows are the batch's B N rows, each window contiguous.
A `custom_vmap` function has no reverse mode, so a step uses this only when its program is
never differentiated in reverse mode (`Structure.derivatives = "forward"`).
"""

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def batched_add_to_nodes(add_to_nodes, layout, base, values, field, fields):
    """add_to_nodes(layout, base, values, field, fields), whose vmap is one scatter. Linear in
    `values`: its tangent is the same scatter of the values' tangents, batched the same way
    (JAX's own jvp of a `custom_vmap` function would batch it again at every level)."""
    scatter = batched_scatter(add_to_nodes, layout, fields)

    @jax.custom_jvp
    def linear(base, values, field):
        return scatter(base, values, field)

    def tangent(primals, tangents):
        base, values, field = primals
        return linear(base, values, field), linear(base, tangents[1], field)

    linear.defjvp(tangent)
    return linear(base, values, field)


def batched_scatter(add_to_nodes, layout, fields):
    """add_to_nodes on `layout` with `fields` fields as a function of (base, values, field)."""

    @custom_vmap
    def scatter(base, values, field):
        return add_to_nodes(layout, base, values, field, fields)

    @scatter.def_vmap
    def _(axis_size, in_batched, base, values, field):
        def batched(array, on):
            return array if on else jnp.broadcast_to(array, (axis_size,) + array.shape)

        def rows(array):
            return array.reshape((-1,) + array.shape[2:])

        base, values, field = (batched(array, on) for array, on in zip((base, values, field), in_batched))
        field = field + fields * jnp.arange(axis_size, dtype=field.dtype)[:, None]   # member b: fields b F ...
        out = batched_scatter(add_to_nodes, layout, axis_size * fields)(rows(base), rows(values), rows(field))
        return out.reshape((axis_size, fields) + out.shape[1:]), True

    return scatter
