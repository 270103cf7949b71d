"""The interface every material model shares, and the checks its inputs go through.

A material is a frozen dataclass holding what the scene file says (SI units, angles in
degrees). What the solver compiles is its `law`: a small frozen object holding only the static
options, whose `update` reads every physical value from `params`, so no parameter value is ever
part of the compiled structure. The material's fields split in two:
- `option_names`: static string choices (e.g. the Drucker-Prager cone) that decide which code
  is compiled; changing one recompiles. Whether an optional number is given at all (e.g.
  `fluidity`) is static too;
- every other field is a number; those in `parameter_names` are dynamic values, handed to
  `update` in a `params` dict so that `jax.grad` and `jax.vmap` act on them without
  recompiling.

`law.update(params, stress, L, dt, state) -> (stress, state)` is written for ONE material point
(3x3 stress, 3x3 velocity gradient L_ij = dv_i/dx_j) and vmapped by the solver. It must read
physical values only from `params`, never from `self`, or they would be baked into the
compiled code. `Material` gives every material the law's `update`, `init_state` and
`wave_speed` as its own methods, for `drive` and for direct use.
"""

import dataclasses
import math

import jax

from jaxmpm.errors import SceneError


def is_concrete(value):
    """True for Python/numpy numbers; False for JAX tracers (which cannot be range-checked)."""
    return not isinstance(value, jax.core.Tracer)


def check_range(key, value, low=None, high=None, low_inclusive=False, high_inclusive=False):
    """Raise SceneError unless low < value < high (bounds optional, inclusivity as given)."""
    if not is_concrete(value):
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "dtype"):
        raise SceneError(f"{key} = {value!r} must be a number.")
    value = float(value)
    if not math.isfinite(value):
        raise SceneError(f"{key} = {value!r} must be finite.")
    too_low = low is not None and (value < low if low_inclusive else value <= low)
    too_high = high is not None and (value > high if high_inclusive else value >= high)
    if too_low or too_high:
        left = "[" if low_inclusive else "("
        right = "]" if high_inclusive else ")"
        span = f"{left}{'-inf' if low is None else low}, {'inf' if high is None else high}{right}"
        raise SceneError(f"{key} = {value!r} is out of range: it must lie in {span}.")


def number_fields(cls):
    """Names of the numeric fields of a material class (all fields but its options)."""
    return tuple(field.name for field in dataclasses.fields(cls) if field.name not in cls.option_names)


def material_parameters(material):
    """The dynamic parameter dict {name: value} of a material (the leaf of `sim.params`)."""
    return {name: getattr(material, name) for name in material.parameter_names}


class Material:
    """The law's methods on the material itself (subclasses define `law`)."""

    def update(self, params, stress, velocity_gradient, dt, state):
        return self.law.update(params, stress, velocity_gradient, dt, state)

    def init_state(self, count, dtype):
        return self.law.init_state(count, dtype)

    def wave_speed(self, params):
        return self.law.wave_speed(params)
