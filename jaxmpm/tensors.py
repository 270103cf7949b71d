"""Small tensor algebra on one material point's 3x3 tensors (vmapped by callers).

Sign convention: tension positive; p = -tr(sigma)/3 (compression positive),
s = sigma + p I, q = sqrt(3/2 s:s). Every square root here is safe: value and gradient stay
finite at zero.
"""

import jax.numpy as jnp


def safe_sqrt(x):
    """sqrt(x) for x >= 0 whose gradient is 0 (not inf or NaN) at x = 0 (double-where)."""
    positive = x > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def trace(tensor):
    """t_00 + t_11 + t_22 of (..., 3, 3) tensors, written as two adds: jnp.trace is a masked
    reduction, which XLA:CPU sends to a slow library (YNNPACK) kernel."""
    return tensor[..., 0, 0] + tensor[..., 1, 1] + tensor[..., 2, 2]


def pressure(stress):
    """Mean pressure p = -tr(sigma)/3, compression positive."""
    return -trace(stress) / 3.0


def deviator(tensor):
    """Deviatoric part t - tr(t)/3 I of a (..., 3, 3) tensor."""
    mean = trace(tensor) / 3.0
    return tensor - mean[..., None, None] * jnp.eye(3, dtype=tensor.dtype)


def von_mises(stress):
    """Equivalent deviatoric stress q = sqrt(3/2 s:s), finite gradient at s = 0."""
    s = deviator(stress)
    squares = sum(s[..., i, j] * s[..., i, j] for i in range(3) for j in range(3))   # not a reduce
    return safe_sqrt(1.5 * squares)


def symmetric(tensor):
    """(t + t^T) / 2: the rate of deformation d from the velocity gradient L."""
    return 0.5 * (tensor + jnp.swapaxes(tensor, -1, -2))


def hughes_winget_rotation(velocity_gradient, dt):
    """Incremental rotation Q = (I - dt W/2)^-1 (I + dt W/2) of the in-plane spin W.

    In plane strain and axisymmetry the spin has only its in-plane (x, y) part, so Q is a
    rotation by 2 atan(a) about z with a = dt (L_yx - L_xy) / 4; written in closed form,
    Q is exactly orthogonal, so stress invariants are preserved to round-off under rigid
    rotation (Hughes & Winget 1980). Returns a 3x3 matrix.
    """
    a = 0.25 * dt * (velocity_gradient[1, 0] - velocity_gradient[0, 1])
    scale = 1.0 / (1.0 + a * a)
    cos, sin = (1.0 - a * a) * scale, 2.0 * a * scale
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack(
        [jnp.stack([cos, -sin, zero]), jnp.stack([sin, cos, zero]), jnp.stack([zero, zero, one])]
    )


def jaumann_rotate(stress, velocity_gradient, dt):
    """Carry sigma through the step's rigid rotation: Q sigma Q^T (objective Jaumann update).

    Integrates the spin part of the Jaumann rate of the paper,
    sigma_dot = sigma_jaumann + sigma omega + (sigma omega)^T, omega_ij = (v_j,i - v_i,j)/2.
    """
    rotation = hughes_winget_rotation(velocity_gradient, dt)
    return rotation @ stress @ rotation.T
