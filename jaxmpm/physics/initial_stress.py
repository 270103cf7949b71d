"""Initial stress of bodies: the geostatic state.

sigma_yy = g_y (rho d + sum_c rho_c t_c) (compression under gravity g_y < 0): the weight of the
body above the point, at depth d below the body's top, and of every other geostatic body c
stacked above it in the same column, of thickness t_c there (a backfill on a foundation);
sigma_xx = sigma_zz = K0 sigma_yy, no shear; K0 = 1 - sin(phi) (Jaky) or a given number.
The depth of a point is measured in its own lattice column, from the top of the body's points
in that column plus half a point spacing, so sloping surfaces are followed.
"""

import jax.numpy as jnp
import numpy as np


def lattice_cells(positions, spacing, origin):
    """(column, row) integer indices (n,), (n,) of each point's sub-cell: points sit at sub-cell
    centres origin + (i + 1/2) spacing, so floor gives i."""
    return np.floor((positions - np.asarray(origin)) / spacing).astype(np.int64).T


def depth_below_top(positions, spacing, origin):
    """(n,) depth [m] of each point below the top of its column of points (same x)."""
    columns, _ = lattice_cells(positions, spacing, origin)
    _, inverse = np.unique(columns, return_inverse=True)
    tops = np.full(inverse.max() + 1, -np.inf)
    np.maximum.at(tops, inverse, positions[:, 1])
    return tops[inverse] + 0.5 * spacing - positions[:, 1]


def thickness_above(positions, others, spacing, origin):
    """(n,) thickness [m] of the points `others` (m, 2) that lie above each point of `positions`
    (n, 2) in its lattice column: their count there times the point spacing."""
    column, row = lattice_cells(positions, spacing, origin)
    other_column, other_row = lattice_cells(others, spacing, origin)
    rows = max(row.max(initial=0), other_row.max(initial=0)) + 1
    keys = np.sort(other_column * rows + other_row)        # sorted by column, then row
    column_end = np.searchsorted(keys, (column + 1) * rows, side="left")
    return spacing * (column_end - np.searchsorted(keys, column * rows + row, side="right"))


def jaky_k0(friction_angle):
    """K0 = 1 - sin(phi), phi in degrees (Jaky 1944)."""
    return 1.0 - jnp.sin(jnp.deg2rad(friction_angle))


def geostatic_stress(overburden, vertical_gravity, k0):
    """(n, 4) stresses [sigma_xx, sigma_yy, sigma_zz, sigma_xy] (`Particles.stress_voigt`) under
    the mass per unit area `overburden` (n,) [kg/m^2] above each point: sigma_yy = g_y overburden,
    sigma_xx = sigma_zz = K0 sigma_yy, no shear."""
    vertical = vertical_gravity * overburden
    return jnp.stack([k0 * vertical, vertical, k0 * vertical, jnp.zeros_like(vertical)], axis=-1)
