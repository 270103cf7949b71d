"""The material-point driver: one point under a prescribed velocity-gradient history.

The element test behind every calibration: `drive(material, L, dt)` integrates a material's
`update` over a (T, 3, 3) history of velocity gradients and returns the (T + 1, 3, 3) stress
history, differentiable with respect to the material's parameters (pass them as JAX values).
The materials are those of plane strain and axisymmetry: velocity gradients and stresses
without out-of-plane shear (x, y in plane, z out of plane or the hoop direction).
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.keys import is_concrete
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


OUT_OF_PLANE_SHEAR = (0, 2), (1, 2), (2, 0), (2, 1)


def check_in_plane(name, tensors, symmetric):
    """SceneError unless (..., 3, 3) `tensors` have no out-of-plane shear entry (and are
    symmetric, if asked), to round-off; values being traced by JAX are not checked."""
    if not is_concrete(tensors):
        return
    values = np.asarray(tensors, np.float64)
    scale = max(float(np.max(np.abs(values), initial=0.0)), 1e-300)
    shear = max(float(np.max(np.abs(values[..., i, j]), initial=0.0)) for i, j in OUT_OF_PLANE_SHEAR)
    if shear > 1e-12 * scale:
        raise SceneError(f"{name} has out-of-plane shear entries (xz, yz, zx, zy) up to {shear:.3g}: "
                         "the materials are those of plane strain and axisymmetry, which have none.")
    asymmetry = float(np.max(np.abs(values[..., 0, 1] - values[..., 1, 0]), initial=0.0))
    if symmetric and asymmetry > 1e-12 * scale:
        raise SceneError(f"{name} is not symmetric: its xy and yx entries differ by up to {asymmetry:.3g}.")


def drive(material, velocity_gradient, dt, stress0=None):
    """Stress history (T + 1, 3, 3) [Pa] of one point driven by L (T, 3, 3) [1/s] at step dt [s].

    stress0 is the initial 3x3 stress (default zero), tension positive, symmetric. Neither has
    out-of-plane shear (see the module docstring).
    """
    material = as_material(material)
    velocity_gradient = jnp.asarray(velocity_gradient)
    dtype = jnp.result_type(velocity_gradient.dtype, float)
    velocity_gradient = velocity_gradient.astype(dtype)
    if velocity_gradient.ndim != 3 or velocity_gradient.shape[1:] != (3, 3):
        raise SceneError(f"velocity_gradient has shape {velocity_gradient.shape}: it must be (T, 3, 3).")
    check_in_plane("velocity_gradient", velocity_gradient, symmetric=False)
    if stress0 is not None:
        check_in_plane("stress0", stress0, symmetric=True)
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), material_parameters(material))
    stress = jnp.zeros((3, 3), dtype) if stress0 is None else jnp.asarray(stress0, dtype)
    state = jax.tree_util.tree_map(lambda h: h[0], material.init_state(1, dtype))

    def one_step(carry, gradient):
        stress, state = carry
        stress, state = material.update(params, stress, gradient, dt, state)
        return (stress, state), stress

    _, history = jax.lax.scan(one_step, (stress, state), velocity_gradient)
    return jnp.concatenate([stress[None], history])
