"""The state carried from step to step, and the diagnostics each step reports.

`State` holds the material points (bodies in contiguous slices), the motion of each rigid
body, the step counter and the error bits. `Diagnostics` holds what a step computed on the
grid that probes read and the points do not keep: the contact force of every pair and the
force that keeps every prescribed body on its path.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmpm.tensors import components, from_voigt

LEFT_GRID = 1       # error bit: the point left the grid
NON_FINITE = 2      # error bit: position, velocity or stress became NaN or Inf


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Particles:
    """State of N material points (plane strain: per metre of thickness).

    Attributes:
      x: (N, 2) position [m].
      v: (N, 2) velocity [m/s].
      affine: (N, 2, 2) APIC affine velocity C_p = sum_I v_I (x) grad N_I [1/s] (zero with FLIP).
      stress_voigt: (N, 4) Cauchy stress [sigma_xx, sigma_yy, sigma_zz, sigma_xy], tension
        positive [Pa]: plane strain and axisymmetry have no out-of-plane shear, and the stress
        is symmetric, so these four values are the whole tensor (`stress` gives it as 3 x 3).
        In axisymmetry x, y, z are r, z, theta: sigma_zz is the hoop stress.
      volume: (N,) current volume [m^3/m].
      mass: (N,) mass [kg/m].
      history: tuple, one dict per body of (n_body,) history variables of its material.
      flags: (N,) int32 error bits (LEFT_GRID, NON_FINITE); errors inside jit are data.
    """

    x: jax.Array
    v: jax.Array
    affine: jax.Array
    stress_voigt: jax.Array
    volume: jax.Array
    mass: jax.Array
    history: tuple
    flags: jax.Array

    @property
    def stress(self):
        """(N, 3, 3) Cauchy stress tensors, tension positive [Pa]; [2, 2] is sigma_zz."""
        return from_voigt(components(self.stress_voigt))

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RigidMotion:
    """The motion of one rigid body (plane strain: per metre of thickness).

    Attributes:
      translation: (2,) displacement of its centre of mass since t = 0 [m].
      rotation: () angle turned since t = 0, counter-clockwise positive [rad].
      velocity: (2,) velocity of its centre of mass [m/s].
      spin: () angular velocity, counter-clockwise positive [rad/s].
    Each step solves the velocity and spin together with the impulses the body receives
    (`bodies.solve_rigid_motions`).
    """

    translation: jax.Array
    rotation: jax.Array
    velocity: jax.Array
    spin: jax.Array

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Everything that changes from step to step.

    Attributes:
      particles: the material points (`Particles`).
      rigid: {body name: RigidMotion} of the scene's rigid bodies (empty without).
      step: () int32 steps taken; the time is step * dt.
      error_step: () int32 first step at which any point's flag was raised, -1 if none.
      error_point: () int32 a point flagged at that first step (the lowest index), -1 if none.
    """

    particles: Particles
    rigid: dict
    step: jax.Array
    error_step: jax.Array
    error_point: jax.Array

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Diagnostics:
    """What one step computed on the grid for the probes (plane strain: N per m).

    Attributes:
      contact_force: {pair name "first/second": (2,) force of the first body on the second
        through their contact in this step [N/m]}.
      reaction: {prescribed body name: (2,) force that kept it on its path in this step, i.e.
        its rate of change of momentum minus its weight and the forces of the bodies around
        it [N/m]}.
      facing_force: {(pair name, (dx, dy)): (2,) the part of that pair's contact force that
        passes through the nodes whose contact normal, from the first body into the second,
        lies within 45 degrees of the unit direction (dx, dy) [N/m]}: one face of a body
        (`Structure.facings` says which are computed).
    """

    contact_force: dict
    reaction: dict
    facing_force: dict = dataclasses.field(default_factory=dict)


def counters_at_start():
    """{step, error_step, error_point} of a state that has taken no step and seen no error."""
    return {
        "step": jnp.zeros((), jnp.int32),
        "error_step": jnp.full((), -1, jnp.int32),
        "error_point": jnp.full((), -1, jnp.int32),
    }


def record_errors(state, outside):
    """Raise the error bits of points that left the grid or went non-finite; count the step."""
    particles = state.particles
    finite = (
        jnp.all(jnp.isfinite(particles.x), axis=1)
        & jnp.all(jnp.isfinite(particles.v), axis=1)
        & jnp.all(jnp.isfinite(particles.stress_voigt), axis=1)
    )
    flags = particles.flags | jnp.where(outside, LEFT_GRID, 0) | jnp.where(finite, 0, NON_FINITE)
    step = state.step + 1
    first = (state.error_step < 0) & jnp.any(flags != 0)
    return state.replace(
        particles=particles.replace(flags=flags),
        step=step,
        error_step=jnp.where(first, step, state.error_step),
        error_point=jnp.where(first, jnp.argmax(flags != 0).astype(jnp.int32), state.error_point),
    )
