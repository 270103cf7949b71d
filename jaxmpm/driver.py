"""The material-point driver: one point under a prescribed velocity-gradient history.

The element test behind every calibration: `drive(material, L, dt)` integrates a material's
`update` over a (T, 3, 3) history of velocity gradients and returns the (T + 1, 3, 3) stress
history, differentiable with respect to the material's parameters (pass them as JAX values).
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmpm.errors import SceneError
from jaxmpm.materials import MODELS, material_parameters


def as_material(material):
    """A material object from a material object or a scene-style table {"model": ..., ...}."""
    if not isinstance(material, dict):
        return material
    table = dict(material)
    model = table.pop("model", None)
    if model not in MODELS:
        raise SceneError(f"material model = {model!r} is not one of {', '.join(map(repr, MODELS))}.")
    cls = MODELS[model]
    known = {field.name for field in dataclasses.fields(cls)}
    for key in table:
        if key not in known:
            raise SceneError(f"material.{key} is not a parameter of the {model} model.")
    missing = [field.name for field in dataclasses.fields(cls)
               if field.name not in table and field.default is dataclasses.MISSING]
    if missing:
        raise SceneError(f"material.{missing[0]} is missing: the {model} model needs it.")
    material = cls(**table)
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
