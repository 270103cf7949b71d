"""The material-point driver: one point under a prescribed velocity-gradient history.

The element test behind every calibration: `drive(material, L, dt)` integrates a material's
`update` over a (T, 3, 3) history of velocity gradients and returns the (T + 1, 3, 3) stress
history, differentiable with respect to the material's parameters (pass them as JAX values).
"""

import jax
import jax.numpy as jnp

from jaxmpm.errors import SceneError
from jaxmpm.materials import material_parameters
from jaxmpm.scene import read_material


def as_material(material):
    """A material object from a material object or a scene-style table {"model": ..., ...}
    (read and checked as a [materials.NAME] table is; values may be JAX values)."""
    if not isinstance(material, dict):
        return material
    material = read_material(dict(material), "material")
    material.check("material")
    return material


def drive(material, velocity_gradient, dt, stress0=None):
    """Stress history (T + 1, 3, 3) [Pa] of one point driven by L (T, 3, 3) [1/s] at step dt [s].

    stress0 is the initial 3x3 stress (default zero), tension positive.
    """
    material = as_material(material)
    velocity_gradient = jnp.asarray(velocity_gradient)
    dtype = jnp.result_type(velocity_gradient.dtype, float)
    velocity_gradient = velocity_gradient.astype(dtype)
    if velocity_gradient.ndim != 3 or velocity_gradient.shape[1:] != (3, 3):
        raise SceneError(f"velocity_gradient has shape {velocity_gradient.shape}: it must be (T, 3, 3).")
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), material_parameters(material))
    stress = jnp.zeros((3, 3), dtype) if stress0 is None else jnp.asarray(stress0, dtype)
    state = jax.tree_util.tree_map(lambda h: h[0], material.init_state(1, dtype))

    def one_step(carry, gradient):
        stress, state = carry
        stress, state = material.update(params, stress, gradient, dt, state)
        return (stress, state), stress

    _, history = jax.lax.scan(one_step, (stress, state), velocity_gradient)
    return jnp.concatenate([stress[None], history])
