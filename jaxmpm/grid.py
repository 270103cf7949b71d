"""The background grid: moving stencil values between points and nodes, and edge conditions.

Nodes form an (nx + 1, ny + 1) array. Particle-to-grid is ONE scatter: each point adds a row
holding all its s x s nodes' values side by side, keyed by its base node; the rows are then
spread to the nodes with s x s shifted adds. This was ~2.5x faster on CPU than s^2 N separate
scatter rows (../PERFORMANCE notes, measured again in benchmarks/).
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxmpm.shapes import SHAPES


@dataclasses.dataclass(frozen=True)
class GridLayout:
    """Static grid facts. origin (2,) [m]; cell [m]; cells (nx, ny)."""

    origin: tuple[float, float]
    cell: float
    cells: tuple[int, int]
    shape_name: str = "linear"

    @property
    def nodes(self):
        return (self.cells[0] + 1, self.cells[1] + 1)

    @property
    def shape(self):
        return SHAPES[self.shape_name]

    def local(self, positions):
        """Positions in cell units from the origin, (N, 2)."""
        return (positions - jnp.asarray(self.origin, positions.dtype)) / self.cell

    def stencil(self, positions):
        return self.shape.stencil(self.local(positions), self.cells, self.cell)

    def node_offsets(self, base, positions, support):
        """x_I - x_p for each point's s x s stencil nodes: (N, s, s, 2) [m]."""
        offsets = jnp.arange(support, dtype=positions.dtype)
        corner = jnp.asarray(self.origin, positions.dtype) + base.astype(positions.dtype) * self.cell - positions
        along_x = corner[:, None, 0] + offsets * self.cell
        along_y = corner[:, None, 1] + offsets * self.cell
        shape = (len(positions), support, support)
        return jnp.stack(
            [jnp.broadcast_to(along_x[:, :, None], shape), jnp.broadcast_to(along_y[:, None, :], shape)], axis=-1
        )

    def outside(self, positions):
        """(N,) bool: the point has left the grid."""
        local = self.local(positions)
        return jnp.any((local < 0.0) | (local > jnp.asarray(self.cells, local.dtype)), axis=1)


def scatter_to_nodes(layout, base, values):
    """Sum stencil values (N, s, s, C) into node arrays (nx + 1, ny + 1, C)."""
    count, support, _, channels = values.shape
    nx, ny = layout.nodes
    keys = base[:, 0] * ny + base[:, 1]
    rows = jnp.zeros((nx * ny, support * support * channels), values.dtype)
    rows = rows.at[keys].add(values.reshape(count, -1))
    rows = rows.reshape(nx, ny, support, support, channels)
    # A base node is at most nx - s, so the shifted copies never wrap around.
    return sum(
        jnp.roll(rows[:, :, a, b], (a, b), axis=(0, 1))
        for a in range(support)
        for b in range(support)
    )


def gather_from_nodes(base, nodes, support):
    """Node values (nx + 1, ny + 1, C) at each point's s x s stencil: (N, s, s, C).

    The mirror of `scatter_to_nodes`: every node first holds its s x s neighbours' values side
    by side (s^2 shifted copies of the small node array), then each point reads ONE contiguous
    row at its base node, instead of s^2 scattered reads.
    """
    nx, ny, channels = nodes.shape
    # A base node is at most nx - s, so the wrapped-around part of each shift is never read.
    neighbours = jnp.stack(
        [jnp.roll(nodes, (-a, -b), axis=(0, 1)) for a in range(support) for b in range(support)], axis=2
    )
    rows = neighbours.reshape(nx * ny, support * support * channels)
    return rows[base[:, 0] * ny + base[:, 1]].reshape(len(base), support, support, channels)


def sum_over_stencil(values):
    """Sum (N, s, s, ...) over the s x s stencil nodes, written as s^2 - 1 adds: XLA:CPU runs
    such short reductions (and einsums with a point batch axis) as slow library kernels."""
    support = values.shape[1]
    return sum(values[:, a, b] for a in range(support) for b in range(support))


def boundary_mask(layout, boundaries, dtype):
    """(nx + 1, ny + 1, 2) multiplier that zeroes the constrained velocity components.

    fixed: both components zero on the edge; slip: the normal component zero; free: none.
    """
    mask = np.ones(layout.nodes + (2,))
    edges = {"left": (0, 0), "right": (0, -1), "bottom": (1, 0), "top": (1, -1)}
    for edge, (axis, index) in edges.items():
        kind = getattr(boundaries, edge)
        if kind == "free":
            continue
        components = [0, 1] if kind == "fixed" else [axis]
        selector = [slice(None), slice(None)]
        selector[axis] = index
        for component in components:
            mask[tuple(selector) + (component,)] = 0.0
    return jnp.asarray(mask, dtype)
