"""A value computed once, where XLA:CPU would recompute it in every kernel that reads it."""

import jax
import jax.numpy as jnp


def materialized(values):
    """`values` (an array or a pytree of arrays), exactly, in value and derivatives; computed
    into memory before anything reads them.

    XLA:CPU fuses a cheap producer into each of its consumers, so a value read by several
    kernels, or at every stencil entry by a gather, is recomputed each time it is read, and
    optimisation barriers are removed before fusion. A fusion cannot reach into a
    conditional: the values pass through a `lax.cond` whose predicate, c == c or c != c for an
    entry c of them, is true for every c (NaN included) yet is not folded by XLA, so the
    other branch never runs. Under `vmap` JAX turns the cond into a select, the same values."""
    entry = jax.tree_util.tree_leaves(values)[0].reshape(-1)[0]
    always = (entry == entry) | (entry != entry)
    return jax.lax.cond(always, lambda kept: kept, lambda kept: jax.tree_util.tree_map(
        lambda value: jnp.full_like(value, jnp.nan), kept), values)
