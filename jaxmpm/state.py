"""The state carried from step to step: per-point arrays, bodies in contiguous slices."""

import dataclasses

import jax
import jax.numpy as jnp

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
      stress: (N, 3, 3) Cauchy stress, tension positive [Pa]; [2, 2] is sigma_zz.
      volume: (N,) current volume [m^3/m].
      mass: (N,) mass [kg/m].
      history: tuple, one dict per body of (n_body,) history variables of its material.
      flags: (N,) int32 error bits (LEFT_GRID, NON_FINITE); errors inside jit are data.
      step: () int32 steps taken.
      error_step: () int32 first step at which any flag was raised, -1 if none.
      error_point: () int32 a point flagged at that first step (the lowest index), -1 if none.
    """

    x: jax.Array
    v: jax.Array
    affine: jax.Array
    stress: jax.Array
    volume: jax.Array
    mass: jax.Array
    history: tuple
    flags: jax.Array
    step: jax.Array
    error_step: jax.Array
    error_point: jax.Array

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


def counters_at_start():
    """{step, error_step, error_point} of a state that has taken no step and seen no error."""
    return {
        "step": jnp.zeros((), jnp.int32),
        "error_step": jnp.full((), -1, jnp.int32),
        "error_point": jnp.full((), -1, jnp.int32),
    }


def record_errors(particles, outside):
    """Raise the error bits of points that left the grid or went non-finite."""
    finite = (
        jnp.all(jnp.isfinite(particles.x), axis=1)
        & jnp.all(jnp.isfinite(particles.v), axis=1)
        & jnp.all(jnp.isfinite(particles.stress), axis=(1, 2))
    )
    flags = particles.flags | jnp.where(outside, LEFT_GRID, 0) | jnp.where(finite, 0, NON_FINITE)
    step = particles.step + 1
    first = (particles.error_step < 0) & jnp.any(flags != 0)
    return particles.replace(
        flags=flags,
        step=step,
        error_step=jnp.where(first, step, particles.error_step),
        error_point=jnp.where(first, jnp.argmax(flags != 0).astype(jnp.int32), particles.error_point),
    )
