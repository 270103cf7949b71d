"""The background grid: moving stencil values between points and nodes, and edge conditions.

Nodes form an (nx + 1, ny + 1) array, one per velocity field: node arrays are
(fields, nx + 1, ny + 1, channels), and each point talks to its own body's field only (a scene
without contact pairs has one field). Particle-to-grid is ONE scatter: each point adds a row
holding all its s x s nodes' values side by side, keyed by its base node; the rows are then
summed onto the nodes as s x s shifted slices (on XLA:CPU much faster than s^2 N separate
scatter rows).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.kernels.fusion import materialized
from jaxmpm.kernels.scatter import batched_add_to_nodes
from jaxmpm.kernels.transposes import (
    gather_with_scatter_transpose, scatter_with_gather_transpose, sum_with_broadcast_transpose,
)
from jaxmpm.physics.shapes import make_shape, stencil
from jaxmpm.tensors import stack_last


@dataclasses.dataclass(frozen=True)
class GridLayout:
    """Static grid facts. origin (2,) [m]; cell [m]; cells (nx, ny); the shape function's name
    and the points per cell it may depend on.

    Node arrays hold the (nx + 1) x (ny + 1) grid nodes plus `ghost` layers of nodes outside
    each edge for shape functions wider than a cell; node (i, j) of an array sits at
    origin + (i - ghost, j - ghost) h.
    """

    origin: tuple[float, float]
    cell: float
    cells: tuple[int, int]
    shape_name: str = "linear"
    ppc: int = 2

    @property
    def shape(self):
        return make_shape(self.shape_name, self.ppc)

    @property
    def ghost(self):
        return self.shape.ghost

    @property
    def nodes(self):
        """Node array size (ghost layers included)."""
        return (self.cells[0] + 1 + 2 * self.ghost, self.cells[1] + 1 + 2 * self.ghost)

    def local(self, positions):
        """Positions in cell units from the origin, (N, 2)."""
        return jnp.stack(self.local_along(positions), axis=1)

    def local_along(self, positions):
        """(x, y) of the positions (N, 2) in cell units from the origin, each (N,).

        Every grid constant in the step's stencil arithmetic is a Python scalar, never a small
        array: an array the step closes over becomes an operand of the loops around the step
        (lax.scan hoists it, and so does reverse mode), which XLA:CPU does not fold back into
        a constant inside nested loops (the segments of a checkpointed rollout), where the
        stencil's kernels then ran twice as slow."""
        along_x, along_y = (part[:, 0] for part in jnp.split(positions, 2, axis=1))
        return (along_x - self.origin[0]) / self.cell, (along_y - self.origin[1]) / self.cell

    def stencil(self, positions):
        local_x, local_y = self.local_along(positions)
        return stencil(self.shape, (local_x + self.ghost, local_y + self.ghost), self.nodes, self.cell)

    def node_offsets(self, base, positions, support):
        """x_I - x_p along x and along y for each point's s x s stencil nodes: two (N, s, s)
        arrays [m] (not one stacked array, see `shapes.Stencil`)."""
        along = []
        for axis, part in enumerate(jnp.split(positions, 2, axis=1)):
            corner = self.origin[axis] + (base[:, axis] - self.ghost).astype(positions.dtype) * self.cell - part[:, 0]
            along.append(stack_last([corner + node * self.cell for node in range(support)]))
        shape = (len(positions), support, support)
        return jnp.broadcast_to(along[0][:, :, None], shape), jnp.broadcast_to(along[1][:, None, :], shape)

    def outside(self, positions):
        """(N,) bool: the point has left the grid."""
        local_x, local_y = self.local_along(positions)
        return (local_x < 0.0) | (local_x > self.cells[0]) | (local_y < 0.0) | (local_y > self.cells[1])


def node_keys(base, nodes, field=None):
    """Row of each point's base node `base` (N, 2) in a flattened (fields, nx, ny) node array,
    nodes = (nx, ny): (N,) int32. `field` (N,) is each point's velocity field (None: field 0)."""
    nx, ny = nodes
    keys = base[:, 0] * ny + base[:, 1]
    return keys if field is None else keys + field * (nx * ny)


def add_to_nodes(layout, base, values, field=None, fields=1):
    """Sum stencil values (N, s, s, C) into node arrays (fields, nx, ny, C), each point into
    its own velocity field `field` (N,) (None: one field).

    One scatter of N rows, each row keeping its (s, s, C) window as it is (flattening it to
    s^2 C values first cost a re-indexing copy 3x the scatter itself on XLA:CPU), keyed by the
    base node on an array with s - 1 extra node layers below each axis; node I then sums the
    window entries (a, b) of the rows keyed at I - (a, b), as s^2 slices of that array."""
    count, support, _, channels = values.shape
    nx, ny = layout.nodes
    extra = support - 1
    keys = node_keys(base + extra, (nx + extra, ny + extra), field)
    rows = jnp.zeros((fields * (nx + extra) * (ny + extra), support, support, channels), values.dtype)
    rows = rows.at[keys].add(values, mode="promise_in_bounds")
    rows = rows.reshape(fields, nx + extra, ny + extra, support, support, channels)
    return sum(
        rows[:, extra - a:extra - a + nx, extra - b:extra - b + ny, a, b] for a in range(support) for b in range(support)
    )


def read_at_stencils(layout, base, nodes, support, field=None):
    """Node values (fields, nx, ny, C) at each point's s x s stencil in its own field: (N, s, s, C).

    One windowed gather: each point reads the (s, s, C) block of its field's node array that
    starts at its base node (a base node is at most nx - s, so the block is always inside).
    (On XLA:CPU much faster than reading rows of an array of s^2 shifted node copies.)"""
    field = jnp.zeros(len(base), jnp.int32) if field is None else field
    starts = stack_last([field, base[:, 0], base[:, 1], jnp.zeros_like(field)])
    numbers = jax.lax.GatherDimensionNumbers(offset_dims=(1, 2, 3), collapsed_slice_dims=(0,), start_index_map=(0, 1, 2, 3))
    window = (1, support, support, nodes.shape[-1])
    return jax.lax.gather(nodes, starts, numbers, window, mode="promise_in_bounds")


def scatter_to_nodes(layout, base, values, field=None, fields=1, derivatives="any"):
    """Stencil values (N, s, s, C) added onto the node arrays (fields, nx, ny, C) of each
    point's own field (`add_to_nodes`). derivatives: "any" (plain JAX), "forward" (with the
    scatter's own batching rule, `jaxmpm.kernels.scatter`) or "reverse" (with `read_at_stencils`
    as its transpose, `jaxmpm.kernels.transposes`): see `solver.Structure`."""
    field = jnp.zeros(len(base), jnp.int32) if field is None else field
    if derivatives == "forward":
        return batched_add_to_nodes(add_to_nodes, layout, base, values, field, fields)
    if derivatives == "reverse":
        support = values.shape[1]
        return scatter_with_gather_transpose(
            lambda base, values, field: add_to_nodes(layout, base, values, field, fields),
            lambda base, nodes, field: read_at_stencils(layout, base, materialized(nodes), support, field),
            base, values, field)
    return add_to_nodes(layout, base, values, field, fields)


def gather_from_nodes(layout, base, nodes, support, field=None, derivatives="any"):
    """Node values (fields, nx, ny, C) read at each point's s x s stencil: (N, s, s, C)
    (`read_at_stencils`), the node values computed once before (`kernels.fusion`).
    derivatives: see `scatter_to_nodes`."""
    field = jnp.zeros(len(base), jnp.int32) if field is None else field
    nodes = materialized(nodes)
    if derivatives == "reverse":
        fields = nodes.shape[0]
        return gather_with_scatter_transpose(
            lambda base, nodes, field: read_at_stencils(layout, base, nodes, support, field),
            lambda base, values, field: add_to_nodes(layout, base, values, field, fields),
            base, nodes, field)
    return read_at_stencils(layout, base, nodes, support, field)


def add_over_stencil(values):
    """Sum (N, s, s, ...) over the s x s stencil nodes, written as s^2 - 1 adds: XLA:CPU runs
    such short reductions (and einsums with a point batch axis) as slow library kernels."""
    support = values.shape[1]
    return sum(values[:, a, b] for a in range(support) for b in range(support))


def sum_over_stencil(values, derivatives="any"):
    """`add_over_stencil`; derivatives: see `scatter_to_nodes`."""
    if derivatives == "reverse":
        return sum_with_broadcast_transpose(add_over_stencil, values)
    return add_over_stencil(values)


EDGES = {"left": (0, 0), "right": (0, -1), "bottom": (1, 0), "top": (1, -1)}   # (axis, side)


def boundary_mask(layout, boundaries, dtype):
    """(nodes_x, nodes_y, 2) multiplier that zeroes the constrained velocity components of the
    edge nodes. fixed: both components; slip: the normal component; free: none."""
    mask = np.ones(layout.nodes + (2,))
    for edge, (axis, side) in EDGES.items():
        kind = getattr(boundaries, edge)
        if kind == "free":
            continue
        selector = [slice(None), slice(None)]
        selector[axis] = layout.ghost if side == 0 else -1 - layout.ghost
        for component in ([0, 1] if kind == "fixed" else [axis]):
            mask[tuple(selector) + (component,)] = 0.0
    return jnp.asarray(mask, dtype)


def ghost_mirror_pairs(layout, boundaries):
    """(kind, axis, ghost, mirror) for every ghost node layer beyond a fixed or slip edge:
    ghost and mirror are indices along grid `axis` (0: x, 1: y) of the node arrays, at equal
    distances outside and inside the edge node."""
    for edge, (axis, side) in EDGES.items():
        kind = getattr(boundaries, edge)
        if kind == "free":
            continue
        edge_node = layout.ghost if side == 0 else layout.nodes[axis] - 1 - layout.ghost
        outwards = -1 if side == 0 else 1
        for layer in range(1, layout.ghost + 1):
            yield kind, axis, edge_node + outwards * layer, edge_node - outwards * layer


def mirror_signs(kind, axis):
    """Sign of each velocity component in the mirror image across an edge: -1 held, +1 free."""
    return [-1.0 if kind == "fixed" or component == axis else 1.0 for component in (0, 1)]


def fold_ghosts(nodes, layout, boundaries, scalars=1):
    """Add what the points gave to ghost nodes beyond a fixed or slip edge onto the mirror
    nodes inside, as if every point had a mirror image across the wall (mass with +, momentum
    and force components with the mirror signs).

    nodes: (fields, nodes_x, nodes_y, scalars + 2 k): `scalars` scalar channels (mass), then k
    (x, y) pairs (momentum, force). Without this, the lumped projection of a field is biased
    next to the wall, where the support of the nodes is only partly filled with material.
    """
    if not layout.ghost:
        return nodes
    for kind, axis, ghost, mirror in ghost_mirror_pairs(layout, boundaries):
        signs = [1.0] * scalars + mirror_signs(kind, axis) * ((nodes.shape[-1] - scalars) // 2)
        nodes = nodes.at[node_selector(axis, mirror)].add(
            jnp.asarray(signs, nodes.dtype) * jnp.take(nodes, ghost, axis=axis - 3)
        )
    return nodes


def node_selector(axis, index, component=slice(None)):
    """Index of the node layer `index` along grid `axis` (0: x, 1: y) of (..., nx, ny, C) arrays."""
    selector = [slice(None), slice(None), component]
    selector[axis] = index
    return (Ellipsis, *selector)


def apply_edge_conditions(velocity, mask, layout, boundaries):
    """Nodal velocities (..., nodes_x, nodes_y, 2) with the edge conditions applied.

    Edge nodes: the constrained components are zeroed (`boundary_mask`). Ghost nodes beyond a
    fixed or slip edge mirror the nodes inside: odd for a held component (so the field through
    the wall is zero at the wall but keeps its slope there) and even for the free tangential
    component of a slip edge. Zeroing the ghosts instead would also force a zero slope, which
    stiffens the material next to the wall and costs an O(h) error with quadratic B-splines.
    Beyond a free edge, ghost nodes are ordinary nodes.
    """
    velocity = velocity * mask
    for kind, axis, ghost, mirror in ghost_mirror_pairs(layout, boundaries):     # both components in one write
        signs = jnp.asarray(mirror_signs(kind, axis), velocity.dtype)
        velocity = velocity.at[node_selector(axis, ghost)].set(signs * jnp.take(velocity, mirror, axis=axis - 3))
    return velocity


def per_unit_mass(values, mass, floor):
    """values / m_I on nodes with mass (..., 2), 0 on empty nodes: a node velocity from its
    momentum, or an acceleration from a force; finite value and gradient (double where)."""
    occupied = (mass > floor)[..., None]
    return jnp.where(occupied, values / jnp.where(occupied, mass[..., None], 1.0), 0.0)
