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


def entries(tensor):
    """The 9 entries of (..., 3, 3) tensors, row-major, as a list of (...,) arrays, read with ONE
    split: reverse mode turns it into one concatenation, where 9 index reads would become 9 pads
    of the whole array (slow in XLA:CPU's backward pass). Plain JAX (no custom VJP), so forward
    mode works too."""
    return components(tensor.reshape(tensor.shape[:-2] + (9,)))


def stack_last(values):
    """jnp.stack(values, axis=-1), built as a stack along a leading axis moved to the end.

    The same array, but XLA:CPU then keeps each entry contiguous (entry-major) instead of
    interleaving the entries point by point, and the kernels that read the entries back one
    by one read them in place instead of re-deriving them."""
    return jnp.moveaxis(jnp.stack(values), 0, -1)


def components(values):
    """values[..., k] for each k of the last axis, read with one split (see `entries`)."""
    return [part[..., 0] for part in jnp.split(values, values.shape[-1], axis=-1)]


def from_entries(values):
    """(..., 3, 3) tensors from 9 row-major entries (...,) (one stack; its reverse mode is one split)."""
    return stack_last(values).reshape(values[0].shape + (3, 3))


DIAGONAL = (0, 4, 8)


def trace(tensor):
    """t_00 + t_11 + t_22 of (..., 3, 3) tensors, written as two adds: jnp.trace is a masked
    reduction, which XLA:CPU sends to a slow library (YNNPACK) kernel."""
    e = entries(tensor)
    return e[0] + e[4] + e[8]


def pressure(stress):
    """Mean pressure p = -tr(sigma)/3, compression positive."""
    return -trace(stress) / 3.0


def deviator_entries(e):
    """Entries of the deviatoric part of a tensor given by its 9 entries."""
    mean = (e[0] + e[4] + e[8]) / 3.0
    return [value - mean if index in DIAGONAL else value for index, value in enumerate(e)]


def von_mises_of_deviator(s):
    """q = sqrt(3/2 s:s) from the 9 entries of a deviator, finite gradient at s = 0."""
    return safe_sqrt(1.5 * sum(value * value for value in s))   # not a reduce


def von_mises(stress):
    """Equivalent deviatoric stress q = sqrt(3/2 s:s), finite gradient at s = 0."""
    return von_mises_of_deviator(deviator_entries(entries(stress)))


def voigt(tensor):
    """[t_xx, t_yy, t_zz, t_xy] of symmetric (..., 3, 3) tensors without out-of-plane shear
    (t_xz = t_yz = 0: every stress and rate of deformation of plane strain and axisymmetry),
    t_xy read as the mean of t_xy and t_yx. The stress updates work on these four values:
    the other five of the nine entries are zeros or copies."""
    e = entries(tensor)
    return [e[0], e[4], e[8], 0.5 * (e[1] + e[3])]


def from_voigt(values):
    """(..., 3, 3) symmetric tensors from [t_xx, t_yy, t_zz, t_xy] (see `voigt`)."""
    xx, yy, zz, xy = values
    zero = jnp.zeros_like(xx)
    return from_entries([xx, xy, zero, xy, yy, zero, zero, zero, zz])


def voigt_deviator(v):
    """[s_xx, s_yy, s_zz, s_xy] of the deviator of [t_xx, t_yy, t_zz, t_xy]; the map is its
    own transpose."""
    mean = (v[0] + v[1] + v[2]) / 3.0
    return [v[0] - mean, v[1] - mean, v[2] - mean, v[3]]


def voigt_von_mises_of_deviator(s):
    """q = sqrt(3/2 s:s) of a deviator [s_xx, s_yy, s_zz, s_xy] (s_xy counted twice in s:s),
    finite gradient at s = 0."""
    return safe_sqrt(1.5 * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2] + 2.0 * s[3] * s[3]))


def rotate_voigt(v, cos, sin):
    """[xx, yy, zz, xy] of Q t Q^T, Q the rotation by (cos, sin) about z."""
    xx, yy, zz, xy = v
    cc, ss, cs = cos * cos, sin * sin, cos * sin
    return [cc * xx + ss * yy - 2.0 * cs * xy, ss * xx + cc * yy + 2.0 * cs * xy, zz, cs * (xx - yy) + (cc - ss) * xy]


def in_plane_rotation(velocity_gradient, dt):
    """(cos, sin) of the Hughes-Winget incremental rotation Q = (I - dt W/2)^-1 (I + dt W/2) of
    the spin W of (..., 3, 3) velocity gradients (Hughes & Winget 1980).

    In plane strain and axisymmetry the spin has only its in-plane (x, y) part, so Q is a
    rotation by 2 atan(a) about z with a = dt (L_yx - L_xy) / 4; written in closed form,
    Q is exactly orthogonal, so stress invariants are preserved to round-off under rigid
    rotation. Q sigma Q^T (`rotate_voigt`) integrates the spin part of the paper's Jaumann
    rate, sigma_dot = sigma_jaumann + sigma omega + (sigma omega)^T."""
    a = spin_parameter(velocity_gradient, dt)
    scale = 1.0 / (1.0 + a * a)
    return (1.0 - a * a) * scale, 2.0 * a * scale


def spin_parameter(velocity_gradient, dt):
    """a = dt (L_yx - L_xy) / 4 of (..., 3, 3) velocity gradients: the Hughes-Winget rotation
    (`in_plane_rotation`) turns by 2 atan(a)."""
    e = entries(velocity_gradient)
    return 0.25 * dt * (e[3] - e[1])
