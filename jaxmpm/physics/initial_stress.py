"""Initial stress of bodies: the geostatic state.

sigma_yy = rho g_y d (compression under gravity g_y < 0) at depth d below the body's top,
sigma_xx = sigma_zz = K0 sigma_yy, no shear; K0 = 1 - sin(phi) (Jaky) or a given number.
The depth of a point is measured in its own lattice column, from the top of the body's points
in that column plus half a point spacing, so sloping surfaces are followed.
"""

import jax.numpy as jnp
import numpy as np


def depth_below_top(positions, spacing, origin_x):
    """(n,) depth [m] of each point below the top of its column of points (same x).
    Points sit at sub-cell centres origin + (i + 1/2) spacing, so floor gives the column i."""
    columns = np.floor((positions[:, 0] - origin_x) / spacing).astype(np.int64)
    _, inverse = np.unique(columns, return_inverse=True)
    tops = np.full(inverse.max() + 1, -np.inf)
    np.maximum.at(tops, inverse, positions[:, 1])
    return tops[inverse] + 0.5 * spacing - positions[:, 1]


def jaky_k0(friction_angle):
    """K0 = 1 - sin(phi), phi in degrees (Jaky 1944)."""
    return 1.0 - jnp.sin(jnp.deg2rad(friction_angle))


def geostatic_stress(depth, density, vertical_gravity, k0):
    """(n, 4) stresses [sigma_xx, sigma_yy, sigma_zz, sigma_xy] (`Particles.stress_voigt`):
    sigma_yy = rho g_y d, sigma_xx = sigma_zz = K0 sigma_yy, no shear."""
    vertical = density * vertical_gravity * depth
    return jnp.stack([k0 * vertical, vertical, k0 * vertical, jnp.zeros_like(vertical)], axis=-1)
