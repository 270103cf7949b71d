"""The stress updates' algebra on [xx, yy, zz, xy] (`tensors.voigt`) against the same algebra on
3x3 matrices, and the hand-written transposes against JAX's reverse mode.

References, written with numpy matrices: Q t Q^T for the Hughes-Winget rotation
Q = (I - dt W/2)^-1 (I + dt W/2), W = (L - L^T) / 2 (Hughes & Winget 1980), and the elastic
increment dt (K tr(d) I + 2 G dev(d)), d = (L + L^T) / 2.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import tensors
from jaxmpm.materials.linear_elastic import bulk_and_shear_moduli, elastic_trial

IN_PLANE = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])   # no out-of-plane shear


def plane_states(count=50, seed=0):
    """Symmetric stresses without out-of-plane shear, and in-plane velocity gradients with a hoop
    rate (what plane strain and axisymmetry produce)."""
    rng = np.random.default_rng(seed)
    noise = IN_PLANE * rng.normal(size=(count, 3, 3))
    stress = -1e4 * (np.eye(3) + 0.5 * (noise + noise.transpose(0, 2, 1)))
    gradient = 3.0 * IN_PLANE * rng.normal(size=(count, 3, 3))
    return stress, gradient


def hughes_winget(gradient, dt):
    spin = 0.5 * (gradient - gradient.transpose(0, 2, 1))
    return np.linalg.solve(np.eye(3) - 0.5 * dt * spin, np.eye(3) + 0.5 * dt * spin)


def test_voigt_values_match_the_matrix_algebra():
    stress, gradient = plane_states()
    v = tensors.voigt(jnp.asarray(stress))
    np.testing.assert_array_equal(tensors.from_voigt(v), stress)
    dt = 0.05
    rotation = hughes_winget(gradient, dt)
    cos, sin = tensors.in_plane_rotation(jnp.asarray(gradient), dt)
    rotated = rotation @ stress @ rotation.transpose(0, 2, 1)
    np.testing.assert_allclose(tensors.from_voigt(tensors.rotate_voigt(v, cos, sin)), rotated, rtol=0, atol=1e-10 * 1e4)
    deviator = stress - np.trace(stress, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
    q = np.sqrt(1.5 * np.sum(deviator * deviator, axis=(1, 2)))
    np.testing.assert_allclose(tensors.voigt_von_mises_of_deviator(tensors.voigt_deviator(v)), q, rtol=1e-13)
    np.testing.assert_allclose(tensors.from_voigt(tensors.voigt_deviator(v)), deviator, rtol=0, atol=1e-11 * 1e4)


def test_elastic_trial_matches_the_matrix_formula():
    stress, gradient = plane_states(seed=1)
    params = {"young": 2e6, "poisson": 0.3}
    dt = 0.02
    bulk, shear = bulk_and_shear_moduli(params["young"], params["poisson"])
    rotation = hughes_winget(gradient, dt)
    rate = 0.5 * (gradient + gradient.transpose(0, 2, 1))
    volumetric = np.trace(rate, axis1=1, axis2=2)[:, None, None]
    expected = (rotation @ stress @ rotation.transpose(0, 2, 1)
                + dt * (bulk * volumetric * np.eye(3) + 2.0 * shear * (rate - volumetric / 3.0 * np.eye(3))))
    ours = jax.vmap(elastic_trial, in_axes=(None, 0, 0, None))(params, jnp.asarray(stress), jnp.asarray(gradient), dt)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-11 * np.max(np.abs(expected)))
