"""Initial stress of bodies: the geostatic state.

sigma_yy = g_y sum_c rho_c t_c (compression under gravity g_y < 0): the weight of the points
above each point in its lattice column, of its own body and of every other geostatic body
stacked on it (a backfill on its foundation), t_c the thickness of body c's points there
(their count times the point spacing; the point's own body counts half a spacing more, the
upper half of its own sub-cell), so sloping surfaces are followed and a gap weighs nothing;
sigma_xx = sigma_zz = K0 sigma_yy, no shear; K0 = 1 - sin(phi) (Jaky) or a given number.
"""

import jax.numpy as jnp
import numpy as np


def lattice_cells(positions, spacing, origin):
    """(column, row) integer indices (n,), (n,) of each point's sub-cell: points sit at sub-cell
    centres origin + (i + 1/2) spacing, so floor gives i."""
    return np.floor((positions - np.asarray(origin)) / spacing).astype(np.int64).T


def thickness_above(positions, others, spacing, origin):
    """(n,) thickness [m] of the points `others` (m, 2) that lie above each point of `positions`
    (n, 2) in its lattice column: the number of their sub-cells there times the point spacing
    (a sub-cell counted once: a multi-device run pads a body with copies of its last point)."""
    column, row = lattice_cells(positions, spacing, origin)
    other_column, other_row = lattice_cells(others, spacing, origin)
    rows = max(row.max(initial=0), other_row.max(initial=0)) + 1
    keys = np.unique(other_column * rows + other_row)        # sorted by column, then row
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
