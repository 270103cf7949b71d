"""The interface every material model shares, and the checks its inputs go through.

A material is a frozen dataclass holding what the scene file says (SI units, angles in
degrees). What the solver compiles is its `law`: a small frozen object holding only the static
options (a `Law`), whose `update` reads every physical value from `params`, so no parameter value is ever
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

import abc
import dataclasses

import jax

from jaxmpm.keys import Key, check_value
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


class Law(abc.ABC):
    """What the solver compiles of a material: its static options only (a frozen dataclass),
    every physical value read from `params`. Required: `init_state`, `update`, `wave_speed`.
    Optional, with their defaults here: `kept_solves_per_point`, `yields`."""

    # Values per point that `update` solves an implicit equation for and names
    # `rollout.KEPT_SOLVES` (a checkpointed step keeps them); counted in reverse mode's memory.
    kept_solves_per_point = 0
    # Whether the material can yield and flow. The transfer's relaxation (numerics.relaxation)
    # damps the velocity noise of flowing bodies; the points of a body that cannot flow keep
    # their own velocity (`solver.body_memory`).
    yields = True

    @abc.abstractmethod
    def init_state(self, count, dtype) -> dict:
        """History variables of `count` points, {name: (count, ...) array}."""

    @abc.abstractmethod
    def update(self, params, stress, velocity_gradient, dt, state):
        """One point: (stress (3, 3), state) at the end of the step from the stress and
        state at its start and the velocity gradient L (3, 3)."""

    @abc.abstractmethod
    def wave_speed(self, params):
        """The p-wave speed [m/s] that sets the stable time step."""


class Material:
    """The law's methods on the material itself (subclasses define `law`)."""

    def update(self, params, stress, velocity_gradient, dt, state):
        return self.law.update(params, stress, velocity_gradient, dt, state)

    def init_state(self, count, dtype):
        return self.law.init_state(count, dtype)

    def wave_speed(self, params):
        return self.law.wave_speed(params)


def points_update(law, dt, substeps=1):
    """`law.update` over every point: (params, stress (N, 3, 3), L (N, 3, 3), state) -> (stress, state).

    substeps > 1 (static): the step's update done as that many updates of dt / substeps with the
    step's L, one after the other (the substepping of Sloan 1987, *IJNME* 24, 893-911, at a fixed
    count): a law whose update is first order in its step (the Perzyna backward Euler) is then
    that many times more accurate within the step, whatever the grid's step."""
    def one_point(params, stress, velocity_gradient, state):
        if substeps == 1:
            return law.update(params, stress, velocity_gradient, dt, state)

        def substep(_, carry):
            stress, state = carry
            return law.update(params, stress, velocity_gradient, dt / substeps, state)

        return jax.lax.fori_loop(0, substeps, substep, (stress, state))

    return jax.vmap(one_point, in_axes=(None, 0, 0, 0))


def points_update_voigt(law, dt, substeps=1):
    """`points_update` (with its `substeps`) on stresses stored as (N, 4) [sigma_xx, sigma_yy, sigma_zz, sigma_xy]
    (`Particles.stress_voigt`): (params, stress (N, 4), L (N, 3, 3), state) -> (stress (N, 4),
    state). The laws read and write these four values of their 3 x 3 stresses (`voigt`,
    `from_voigt`), so the conversions around them cancel inside the compiled step."""
    update = points_update(law, dt, substeps)

    def on_voigt(params, stress, velocity_gradient, state):
        stress, state = update(params, from_voigt(components(stress)), velocity_gradient, state)
        return stack_last(voigt(stress)), state

    return on_voigt
