"""A stiff free body stepped n times within each step of the scene (subcycling).

A concrete wall's p-wave crosses a cell 20-60 times faster than sand's, so as an ordinary free
body it sets a step that much shorter for the whole scene. A subcycled body (`kinematics.substeps`
in the scene file) takes n steps of dt / n of its own instead, alone on the grid, inside each
step of the scene:

  predict  its n substeps under gravity and its own stress: the velocity v*_p it would end the
           step with if nothing touched it, put on its field's nodes in the configuration of
           the start of the step, v*_I = sum_p m_p N_I (v*_p + C*_p (x_I - x_p)) / m_I
  contact  its interfaces are resolved once per scene step, the body answering the impulses J_I
           it receives as a whole, with its mass M and polar moment J_c
           (`bodies.solve_rigid_motions`): u_I = v*_I + dV + dw e_z x (x_I - c),
           M dV = sum_I J_I, J_c dw = sum_I (x_I - c) x J_I; the free fields end the step
           moving with u_I where they meet it
  correct  its n substeps again from the start of the step, each of its points pushed by its
           share of the impulses, f_p = m_p sum_I N_I(x_p) J_I / (m_I dt) (which sums to
           sum_I J_I / dt): the body takes the impulse over the step, moving and deforming

The share goes to the points, not to the nodes: a node the body only grazes (small m_I) can
receive the impulse of much more sand, and as a node force J_I / dt it accelerated that node
without bound (the small wall of docs/convergence.md then moved 14 % too far, and further as
dt shrank).

So in the stiff limit the body is a rigid body (its answer is the rigid body's exactly), and it
bends under the load it takes. What it does not hold is a response local to the contact within
one scene step (for a stiff body, small against its motion as a whole), and its answer counts no
support: a body held by a grid edge or bonded to the soil below answers as if free to move
(the correction then holds it, and the soil meets it a step late). It costs 2 n substeps of the
body's points alone on the grid (n without interfaces). docs/convergence.md measures it against
the same body at the small step.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmpm.physics.grid import fold_ghosts, scatter_to_nodes
from jaxmpm.physics.state import State, counters_at_start
from jaxmpm.tensors import stack_last


def subcycled_blocks(structure):
    """(index, block) of every body that takes steps of its own (`BodyBlock.substeps` > 1)."""
    return tuple((index, block) for index, block in enumerate(structure.bodies) if block.substeps > 1)


def touches(structure, block):
    """Whether the body's field meets another at an interface (else nothing corrects it)."""
    return any(block.field in (interface.first, interface.second) for interface in structure.interfaces)


def alone(structure, block):
    """The Structure of `block` alone on the scene's grid, stepping at dt / n: one field, no
    interfaces; with APIC its transfer memory exp(-dt / tau) becomes exp(-dt / (n tau))."""
    memory = structure.memory if block.memory is None else block.memory
    if structure.transfer == "apic":
        memory = memory ** (1.0 / block.substeps)
    own = dataclasses.replace(block, start=0, stop=block.stop - block.start, field=0, substeps=1, memory=None)
    return dataclasses.replace(structure, dt=structure.dt / block.substeps, memory=memory, bodies=(own,), fields=1,
                               interfaces=())


def points_of(particles, index, block):
    """The Particles of body `index` (`block`) alone."""
    return particles.replace(
        x=particles.x[block.points], v=particles.v[block.points], affine=particles.affine[block.points],
        stress_voigt=particles.stress_voigt[block.points], volume=particles.volume[block.points],
        mass=particles.mass[block.points], history=(particles.history[index],), flags=particles.flags[block.points],
    )


def put_back(particles, index, block, own):
    """`particles` with body `index`'s points replaced by `own` (its Particles alone)."""
    history = list(particles.history)
    history[index] = own.history[0]
    return particles.replace(
        x=particles.x.at[block.points].set(own.x), v=particles.v.at[block.points].set(own.v),
        affine=particles.affine.at[block.points].set(own.affine),
        stress_voigt=particles.stress_voigt.at[block.points].set(own.stress_voigt),
        volume=particles.volume.at[block.points].set(own.volume), history=tuple(history),
        flags=particles.flags.at[block.points].set(own.flags),
    )


def advance_alone(step_alone, params, own, substeps, force=None):
    """The body's points `own` after `substeps` steps of `step_alone` (the step of its `alone`
    structure), with the force `force` (n, 2) [N/m] on its points at every one (None: none)."""
    def substep(_, state):
        return step_alone(params, state, force)[0]

    return jax.lax.fori_loop(0, substeps, substep, State(own, {}, **counters_at_start())).particles


def per_node(values, mass, floor):
    """values / m_I on nodes with mass (..., 2), 0 on empty ones (finite value and gradient)."""
    occupied = (mass > floor)[..., None]
    return jnp.where(occupied, values / jnp.where(occupied, mass[..., None], 1.0), 0.0)


def nodal_velocity(structure, stencil, start, predicted, mass, floor):
    """v*_I (nx, ny, 2): the points' predicted velocities on the nodes of their positions
    `start` (`stencil` there) at the start of the step, sum_p m_p N_I (v*_p + C*_p (x_I - x_p))
    / m_I (without C*_p for FLIP), with m_I = `mass` (nx, ny) the field's mass."""
    layout = structure.layout
    weighted = predicted.mass[:, None, None] * stencil.weights
    moving = [jnp.broadcast_to(predicted.v[:, axis, None, None], weighted.shape) for axis in range(2)]
    if structure.transfer == "apic":
        offsets = layout.node_offsets(stencil.base, start, stencil.weights.shape[1])
        affine = predicted.affine
        moving = [moving[axis] + affine[:, axis, 0, None, None] * offsets[0] + affine[:, axis, 1, None, None] * offsets[1]
                  for axis in range(2)]
    momentum = scatter_to_nodes(layout, stencil.base, stack_last([weighted * part for part in moving]))
    momentum = fold_ghosts(momentum, layout, structure.boundaries, scalars=0)[0]
    return per_node(momentum, mass, floor)
