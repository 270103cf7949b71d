"""Shape functions on the regular grid: weights and gradients of the nodes around each point.

A shape function gives, for N points, a stencil of s x s nodes: the lower-left node index
`base` (N, 2), the weights N_I (N, s, s) and their gradients dN_I/dx (N, s, s, 2) [1/m].
Each kind is a small frozen class; the solver picks one at trace time from `numerics.shape`.
"""

import dataclasses
from typing import ClassVar, NamedTuple

import jax.numpy as jnp


class Stencil(NamedTuple):
    """The nodes a set of points talks to. base: (N, 2) int32; weights: (N, s, s);
    gradients: (N, s, s, 2) [1/m]."""

    base: jnp.ndarray
    weights: jnp.ndarray
    gradients: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class Linear:
    """Bilinear (tent) functions of classic MPM (Sulsky et al. 1994; the paper's choice)."""

    support: ClassVar[int] = 2

    def stencil(self, local, cells, cell):
        """local: (N, 2) positions in cell units from the grid origin; cells: (nx, ny)."""
        upper = jnp.asarray(cells, jnp.int32) - 1
        base = jnp.clip(jnp.floor(local).astype(jnp.int32), 0, upper)
        fraction = local - base.astype(local.dtype)               # in [0, 1] inside the grid
        along = jnp.stack([1.0 - fraction, fraction], axis=1)    # (N, 2 nodes, 2 axes)
        slope = jnp.stack([-jnp.ones_like(fraction), jnp.ones_like(fraction)], axis=1) / cell
        weights = along[:, :, None, 0] * along[:, None, :, 1]
        gradients = jnp.stack(
            [slope[:, :, None, 0] * along[:, None, :, 1], along[:, :, None, 0] * slope[:, None, :, 1]],
            axis=-1,
        )
        return Stencil(base, weights, gradients)


SHAPES = {"linear": Linear()}
