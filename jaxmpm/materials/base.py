"""The interface every material model shares, and the checks its inputs go through.

A material is a frozen dataclass holding what the scene file says (SI units, angles in
degrees). What the solver compiles is its `law`: a small frozen object holding only the static
options, whose `update` reads every physical value from `params`, so no parameter value is ever
part of the compiled structure. Each material class declares its scene-file keys in `keys` (`jaxmpm.keys.Key`: unit, default,
range, meaning), from which the reader, the range checks and the scene reference come. The
material's fields split in two:
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
import functools

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from jaxmpm.adjoints import hand_reversed
from jaxmpm.keys import Key, check_value
from jaxmpm.rollout import KEPT_SOLVES
from jaxmpm.tensors import components, from_voigt, stack_last, voigt


ELASTIC_KEYS = (
    Key("density", "float", "mass density rho", unit="kg/m^3", low=0.0),
    Key("young", "float", "Young's modulus E", unit="Pa", low=0.0),
    Key("poisson", "float", "Poisson's ratio nu", low=-1.0, high=0.5),
)


def check_keys(material, where):
    """The range and choice checks of every key a material declares (`material.keys`)."""
    for key in material.keys:
        check_value(f"{where}.{key.name}", key, getattr(material, key.name))


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


@functools.lru_cache(maxsize=64)      # bounded: a sweep over time steps keeps only the last ones
def traced_once(law, dt, name, **options):
    """The one-point `law.<name>` at time step dt (dt left out of its arguments), jitted and
    kept: JAX traces it once per argument shapes, for every body of the law and every pass
    that calls it (the forward pass, the derivative's recomputation of it, the tangent), not
    once per call. A gradient of the wall twin example (two sand bodies) traced the stress
    update six times; it traced 12 % faster so (docs/benchmarks.md, 2026-12-04). Inside a
    program the jit is inlined: the compiled program is the same."""
    method = getattr(law, name)
    return jax.jit(lambda params, stress, gradient, *rest: method(params, stress, gradient, dt, *rest, **options))


def points_update(law, dt):
    """`law.update` over every point: (params, stress (N, 3, 3), L (N, 3, 3), state) ->
    (stress, state). When the law writes its reverse mode by hand (`constants(params)` and
    the one-point `update_adjoint(constants, stress, L, dt, state, remembered, stress_bar,
    state_bar)`), reverse mode uses it: per-point cotangents of the constants are summed over
    the points and carried to the parameters by JAX. XLA's own reverse mode of a stress update
    emits many small kernels (each parameter use becomes its own reduction); forward mode is
    unchanged. A law may remember values of its forward pass for the adjoint
    (`update_remembering(params, stress, L, dt, state, remembered=None) -> ((stress, state),
    remembered)`, e.g. the root of the Perzyna equation), which then need not compute them
    again; they are named KEPT_SOLVES, so a checkpointed step keeps them and its recomputation
    does not solve again (viscoplastic gradients 11-16 % faster; docs/benchmarks.md,
    2026-12-04). Forward mode calls it with `shared_once=True`, where the law computes once the
    values its outputs' tangents share."""
    def plain(params, stress, velocity_gradient, state):
        return jax.vmap(law.update, in_axes=(None, 0, 0, None, 0))(params, stress, velocity_gradient, dt, state)

    if not hasattr(law, "update_adjoint"):
        return plain

    def remembering(params, stress, velocity_gradient, state, remembered=None, shared_once=False):
        if not hasattr(law, "update_remembering"):
            return plain(params, stress, velocity_gradient, state), ()
        one_point = traced_once(law, dt, "update_remembering", shared_once=shared_once)
        points = jax.vmap(one_point, in_axes=(None, 0, 0, 0, 0))
        updated, remembered = points(params, stress, velocity_gradient, state, remembered)
        return updated, jax.tree_util.tree_map(lambda value: checkpoint_name(value, KEPT_SOLVES), remembered)

    keeps_history = getattr(law, "keeps_history", False)

    def adjoint(primals, remembered, cotangents):
        params, stress, velocity_gradient, state = primals
        if keeps_history:
            cotangents = (cotangents, jax.tree_util.tree_map(jnp.zeros_like, state))
        constants, constants_vjp = jax.vjp(law.constants, params)
        one_point = jax.vmap(traced_once(law, dt, "update_adjoint"), in_axes=(None, 0, 0, 0, 0, 0, 0))
        constants_bar, stress_bar, gradient_bar, state_bar = one_point(
            constants, stress, velocity_gradient, state, remembered, *cotangents)
        (params_bar,) = constants_vjp(jax.tree_util.tree_map(lambda bar: jnp.sum(bar, axis=0), constants_bar))
        return params_bar, stress_bar, gradient_bar, state_bar

    if not keeps_history:
        return hand_reversed(remembering, adjoint, functools.partial(remembering, shared_once=True))
    # A history the law passes through unchanged stays outside the custom derivative: its
    # tangent must keep the batching of its primal (under vmap, inside loops).
    def new_stress(*args, remembered=None):
        (stress, _), remembered = remembering(*args, remembered=remembered)
        return stress, remembered

    new_stress = hand_reversed(new_stress, adjoint)
    return lambda params, stress, velocity_gradient, state: (new_stress(params, stress, velocity_gradient, state), state)


def points_update_voigt(law, dt):
    """`points_update` on stresses stored as (N, 4) [sigma_xx, sigma_yy, sigma_zz, sigma_xy]
    (`Particles.stress_voigt`): (params, stress (N, 4), L (N, 3, 3), state) -> (stress (N, 4),
    state). The laws read and write these four values of their 3 x 3 stresses (`voigt`,
    `from_voigt`), so the conversions around them cancel inside the compiled step."""
    update = points_update(law, dt)

    def on_voigt(params, stress, velocity_gradient, state):
        stress, state = update(params, from_voigt(components(stress)), velocity_gradient, state)
        return stack_last(voigt(stress)), state

    return on_voigt
