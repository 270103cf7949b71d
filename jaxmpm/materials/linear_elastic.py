"""Hypoelastic isotropic linear elasticity with the Jaumann rate.

sigma_jaumann = K tr(d) I + 2 G dev(d), with K = E / (3 (1 - 2 nu)), G = E / (2 (1 + nu)),
d = sym(L). Used for walls and piles, and as the elastic part of the soil models.
"""

import dataclasses
from typing import ClassVar

import jax.numpy as jnp

from jaxmpm import tensors
from jaxmpm.materials.base import ELASTIC_KEYS, Law, Material, check_keys


def bulk_and_shear_moduli(young, poisson):
    """K = E / (3 (1 - 2 nu)) and G = E / (2 (1 + nu)) [Pa]."""
    return young / (3.0 * (1.0 - 2.0 * poisson)), young / (2.0 * (1.0 + poisson))


def elastic_moduli(params):
    """The constants the elastic trial reads: {"bulk": K, "shear": G} [Pa]."""
    bulk, shear = bulk_and_shear_moduli(params["young"], params["poisson"])
    return {"bulk": bulk, "shear": shear}


def rate_of_deformation(velocity_gradient):
    """d = sym(L) as [d_xx, d_yy, d_zz, d_xy] (`tensors.voigt`) of (..., 3, 3) velocity gradients."""
    return tensors.voigt(velocity_gradient)


def elastic_increment_voigt(moduli, rate, dt):
    """dt (K tr(d) I + 2 G dev(d)) as [xx, yy, zz, xy] from d = [d_xx, d_yy, d_zz, d_xy] [Pa];
    moduli = elastic_moduli(params). The map is its own transpose."""
    bulk, shear = moduli["bulk"], moduli["shear"]
    volumetric = bulk * (rate[0] + rate[1] + rate[2])
    return [dt * (2.0 * shear * value + (volumetric if index < 3 else 0.0))
            for index, value in enumerate(tensors.voigt_deviator(rate))]


def elastic_increment(params, rate_of_deformation, dt):
    """dt (K tr(d) I + 2 G dev(d)): the elastic stress increment for a strain-rate d [Pa]."""
    return tensors.from_voigt(elastic_increment_voigt(elastic_moduli(params), tensors.voigt(rate_of_deformation), dt))


def elastic_trial_voigt(moduli, stress, velocity_gradient, dt):
    """elastic_trial as [xx, yy, zz, xy] (`tensors.voigt`: what the plastic corrections continue
    with); moduli = elastic_moduli(params)."""
    cos, sin = tensors.in_plane_rotation(velocity_gradient, dt)
    rotated = tensors.rotate_voigt(tensors.voigt(stress), cos, sin)
    increment = elastic_increment_voigt(moduli, rate_of_deformation(velocity_gradient), dt)
    return [a + b for a, b in zip(rotated, increment)]


def elastic_trial(params, stress, velocity_gradient, dt):
    """Q sigma Q^T + dt (K tr(d) I + 2 G dev(d)): the stress rotated with the step's spin
    (Jaumann, Hughes-Winget) plus the elastic increment; the trial state of every model.
    Written on the four values of `tensors.voigt` (one split in, one stack out): reverse mode
    of per-entry reads, of matrix products and of broadcasts of scalars over 3x3 is slow on
    XLA:CPU."""
    return tensors.from_voigt(elastic_trial_voigt(elastic_moduli(params), stress, velocity_gradient, dt))


def p_wave_speed(params):
    """c_p = sqrt((K + 4 G / 3) / rho) [m/s], the speed that sets the CFL time step."""
    bulk, shear = bulk_and_shear_moduli(params["young"], params["poisson"])
    return jnp.sqrt((bulk + 4.0 * shear / 3.0) / params["density"])


@dataclasses.dataclass(frozen=True)
class ElasticLaw(Law):
    """The static side of `LinearElastic`: no options, so one compiled update for every value."""

    yields = False

    def init_state(self, count, dtype):
        """History variables: only the accumulated plastic strain (always zero here)."""
        return {"plastic_strain": jnp.zeros((count,), dtype)}

    def update(self, params, stress, velocity_gradient, dt, state):
        """One point: rotate sigma with the step's spin, add the elastic increment."""
        return elastic_trial(params, stress, velocity_gradient, dt), state

    def wave_speed(self, params):
        return p_wave_speed(params)


@dataclasses.dataclass(frozen=True)
class LinearElastic(Material):
    """An isotropic hypoelastic material.

    Attributes:
      density: rho [kg/m^3].
      young: Young's modulus E [Pa].
      poisson: Poisson's ratio nu, -1 < nu < 0.5.
    """

    density: float
    young: float
    poisson: float

    model: ClassVar[str] = "linear_elastic"
    parameter_names: ClassVar[tuple[str, ...]] = ("density", "young", "poisson")
    option_names: ClassVar[tuple[str, ...]] = ()
    keys: ClassVar[tuple] = ELASTIC_KEYS

    def check(self, where):
        check_keys(self, where)

    @property
    def law(self):
        """The static constitutive law (what the solver compiles; values come from params)."""
        return ElasticLaw()
