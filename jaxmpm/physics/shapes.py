"""Shape functions on the regular grid: weights and gradients of the nodes around each point.

A shape function gives, for N points, a stencil of s x s nodes: the lower-left node index
`base` (N, 2), the weights N_I (N, s, s) and their gradients dN_I/dx_j [1/m], one (N, s, s)
array along x and one along y.
Every kind here is a tensor product of a 1-D function, so a kind only says what its 1-D
function is on the s nodes around a point (`along`). Kinds that reach beyond the node next
to a point need one ghost layer of nodes outside the grid (`ghost`), so points up to the grid
edge keep a full stencil.

    linear    tent functions of classic MPM (Sulsky et al. 1994; the paper's), s = 2
    gimp      uGIMP: the tent smoothed over the point's undeformed cell of half-width
              l = h / (2 ppc) (Bardenhagen & Kober 2004), s = 3
    bspline2  quadratic B-spline (Steffen et al. 2008), s = 3, C1 across cell edges

gimp and bspline2 remove the jump of grad N when a point crosses a cell edge, the source of
linear MPM's cell-crossing error.
"""

import dataclasses
from typing import ClassVar, NamedTuple

import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from jaxmpm.kernels.fusion import materialized
from jaxmpm.tensors import stack_last


class Stencil(NamedTuple):
    """The nodes a set of points talks to. base: (N, 2) int32; weights: (N, s, s);
    gradients: (d/dx, d/dy), two (N, s, s) arrays [1/m]. Two arrays, not one stacked array:
    reverse mode turns each read of a part of an array into a pad of the whole array."""

    base: jnp.ndarray
    weights: jnp.ndarray
    gradients: tuple[jnp.ndarray, jnp.ndarray]


@dataclasses.dataclass(frozen=True)
class Linear:
    """N(r) = 1 - |r| for |r| < 1 (r in cells)."""

    support: ClassVar[int] = 2
    ghost: ClassVar[int] = 0
    reach: ClassVar[float] = 0.0     # base node = floor(position - reach)
    # compute the 1-D factors once (`kernels.fusion.materialized`) rather than in every
    # kernel that reads the weights: faster with gimp and bspline2, not with linear
    factors_once: ClassVar[bool] = False

    def along(self, offset):
        """1-D values and slopes d/dr (per cell) at the stencil nodes, (N, s) each; `offset`
        (N,) is the position minus the base node along one axis, in cells."""
        return stack_last([1.0 - offset, offset]), stack_last([-jnp.ones_like(offset), jnp.ones_like(offset)])


@dataclasses.dataclass(frozen=True)
class QuadraticBSpline:
    """N(r) = 3/4 - r^2 for |r| < 1/2, (3/2 - |r|)^2 / 2 for 1/2 <= |r| < 3/2."""

    support: ClassVar[int] = 3
    ghost: ClassVar[int] = 1
    reach: ClassVar[float] = 0.5
    factors_once: ClassVar[bool] = True

    def along(self, offset):
        # offset in [1/2, 3/2): the nodes sit at r = offset, offset - 1, offset - 2
        first, middle, last = 1.5 - offset, offset - 1.0, offset - 0.5
        values = stack_last([0.5 * first * first, 0.75 - middle * middle, 0.5 * last * last])
        slopes = stack_last([-first, -2.0 * middle, last])
        return values, slopes


@dataclasses.dataclass(frozen=True)
class UniformGIMP:
    """uGIMP with a point half-width l (cells, l <= 1/2), r the point-to-node distance:
    N = 1 - (r^2 + l^2) / (2 l) for |r| < l; 1 - |r| for l <= |r| < 1 - l;
    (1 + l - |r|)^2 / (4 l) for 1 - l <= |r| < 1 + l; 0 beyond."""

    half_width: float
    support: ClassVar[int] = 3
    ghost: ClassVar[int] = 1
    reach: ClassVar[float] = 0.5
    factors_once: ClassVar[bool] = True

    def along(self, offset):
        width = self.half_width
        distance = stack_last([offset, offset - 1.0, offset - 2.0])
        size, sign = jnp.abs(distance), jnp.sign(distance)
        inner = size < width
        outer = size >= 1.0 - width
        tail = jnp.maximum(1.0 + width - size, 0.0)
        values = jnp.where(inner, 1.0 - (distance * distance + width * width) / (2.0 * width),
                           jnp.where(outer, tail * tail / (4.0 * width), 1.0 - size))
        slopes = jnp.where(inner, -distance / width, jnp.where(outer, -sign * tail / (2.0 * width), -sign))
        return values, slopes


def make_shape(name, ppc):
    """The shape function called `name` (numerics.shape) for ppc x ppc points per cell."""
    if name == "linear":
        return Linear()
    if name == "bspline2":
        return QuadraticBSpline()
    if name == "gimp":
        return UniformGIMP(half_width=0.5 / ppc)
    raise ValueError(f"unknown shape function {name!r}")


def stencil(shape, local, nodes, cell):
    """The stencil of points at `local` = (x, y), each (N,), positions in cells from node 0 of
    a grid with `nodes` (nx, ny) nodes (ghosts included); cell [m]. Computed per axis with
    the grid's sizes as Python scalars (see `GridLayout.local_along`)."""
    base, along, slope = [], [], []
    for axis in range(2):
        first = jnp.clip(jnp.floor(local[axis] - shape.reach).astype(jnp.int32), 0, nodes[axis] - shape.support)
        values, slopes = shape.along(local[axis] - first.astype(local[axis].dtype))     # (N, s) each
        base.append(first)
        along.append(values)
        slope.append(slopes / cell)
    if shape.factors_once:
        along, slope = materialized((along, slope))
    weights = along[0][:, :, None] * along[1][:, None, :]
    gradients = (slope[0][:, :, None] * along[1][:, None, :], along[0][:, :, None] * slope[1][:, None, :])
    base = stack_last(base)
    return Stencil(checkpoint_name(base, "stencil"), checkpoint_name(weights, "stencil"), checkpoint_name(gradients, "stencil"))
