"""A stiff free body stepped n times within each step of the scene (subcycling).

A concrete wall's p-wave crosses a cell 20-60 times faster than sand's, so as an ordinary free
body it sets a step that much shorter for the whole scene. A subcycled body (`kinematics.substeps`
in the scene file) takes n steps of dt / n of its own instead, alone on the grid, inside each
step of the scene:

  predict  its n substeps under gravity and its own stress, nothing touching it; their end
           velocities v*_p as one body: V* = sum m_p v*_p / M, w* = sum m_p r_p x v*_p / J_c
           (r_p = x_p - c at the start of the step; M, c, J_c as for a rigid body)
  contact  its interfaces are resolved once per scene step with the body moving as one, as a
           rigid body's are (`bodies.solve_rigid_motions`): V, w solve M (V - V*) = sum_I J_I,
           J_c (w - w*) = sum_I (x_I - c) x J_I, and the free fields end the step moving with
           V + w e_z x (x_I - c) where they meet it (in axisymmetry only along the axis: a
           ring keeps its predicted radial and turning motion)
  correct  its n substeps again from the start of the step: its points first take the change
           (V - V*) + (w - w*) e_z x r_p as one body, and at every substep each point carries
           its share of the impulses less that rigid part,
               f_p = m_p sum_I N_I(x_p) J_I / (m_I dt) - m_p (a + alpha e_z x r_p),
           (a, alpha) the uniform and rotational acceleration of the shares themselves, so the
           f_p have no resultant and no moment: they only strain the body, as the contact load
           and the inertia of its motion do (its bending under the earth pressure). In
           axisymmetry only the axial part a_z is taken off: the radial shares squeeze the ring.

So the body meets its contacts exactly as a rigid body of its shape does (its stiff limit),
and carries the stresses of its weight, its motion and its contact loads. The contact does not
see its deformation velocities: a body whose deflection moves its face comparably to its motion
as a whole is not stiff enough to be subcycled. Its answer counts no support either: a body held
by a grid edge answers its contacts as if free. The shares go to points, not to nodes: a node the
body only grazes can receive the impulse of much more sand, and as a node force it accelerated
that node without bound. Letting the contact see the predicted nodal velocities instead of the
motion as one made the local load's vibration a ratchet (a small wall moved 16 % too far,
docs/convergence.md). It costs 2 n substeps of the body's points alone on the grid (n when it
meets no other field); docs/convergence.md measures it against the same body at its own small step.
"""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxmpm.physics.bodies import RigidStep, cross, rigid_body_frame, spin_velocity
from jaxmpm.physics.grid import per_unit_mass, read_at_stencils
from jaxmpm.physics.state import State, counters_at_start


def subcycled_blocks(structure):
    """(index, block) of every body that takes steps of its own (`BodyBlock.substeps` > 1)."""
    return tuple((index, block) for index, block in enumerate(structure.bodies) if block.substeps > 1)


def touches(structure, block):
    """Whether the body's field meets another at an interface (else nothing corrects it)."""
    return any(block.field in (interface.first, interface.second) for interface in structure.interfaces)


def alone(structure, block):
    """The Structure of `block` alone on the scene's grid, stepping at dt / n: one field, no
    interfaces (and no contact faces to read); with APIC its transfer memory exp(-dt / tau) becomes exp(-dt / (n tau)); local
    damping, if any, acts on its deformation only (`solver.local_damping`)."""
    memory = structure.memory if block.memory is None else block.memory
    if structure.transfer == "apic":
        memory = memory ** (1.0 / block.substeps)
    own = dataclasses.replace(block, start=0, stop=block.stop - block.start, field=0, substeps=1, memory=None)
    return dataclasses.replace(structure, dt=structure.dt / block.substeps, memory=memory, bodies=(own,), fields=1,
                               interfaces=(), damps="deformation", facings=())


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


class Prediction(NamedTuple):
    """The predict phase of the subcycled bodies, each {body name: ...}: their Particles at the
    start of the step (`before`) and after their substeps untouched (`after`), and their
    motion as one body then (`motions`: RigidStep, the contact solve's starting point)."""

    before: dict
    after: dict
    motions: dict


def predict(steps_alone, params, particles, structure, blocks):
    """The predict phase of every subcycled body (module docstring), a Prediction."""
    before, after, motions = {}, {}, {}
    for index, block in blocks:
        before[block.name] = points_of(particles, index, block)
        after[block.name] = advance_alone(steps_alone[block.name], params, before[block.name], block.substeps)
        motions[block.name] = as_one(particles, block, after[block.name], structure.point_spacing)
    return Prediction(before, after, motions)


def as_one(particles, block, moved, spacing):
    """RigidStep of a body's points `moved` (they alone) as one body: its frame (M, c, J_c)
    from `particles` (all, at the start of the step), V = sum m_p v_p / M and
    w = sum m_p r_p x v_p / J_c with r_p from the start."""
    mass, centre, inertia = rigid_body_frame(particles, block, spacing)
    velocity = jnp.dot(moved.mass, moved.v) / mass
    spin = jnp.dot(moved.mass, cross(particles.x[block.points] - centre, moved.v)) / inertia
    return RigidStep(mass, centre, inertia, velocity, spin)


def correct(steps_alone, params, structure, blocks, prediction, motions, received, mass, floor):
    """The correct phase: {body: its Particles at the end of the step}. A body that meets
    another field takes its substeps again from the start, its points first given the change
    of its motion as one (its solved `motions` less `prediction.motions`), each then carrying
    its balanced share of the impulses `received` ({field: (nx, ny, 2)}; `mass` (F, nx, ny)
    the step's node masses). One that meets none keeps its prediction."""
    ended = dict(prediction.after)
    for _, block in blocks:
        if not touches(structure, block):
            continue
        points, motion, guess = prediction.before[block.name], motions[block.name], prediction.motions[block.name]
        arm = points.x - motion.centre
        taken = motion.velocity - guess.velocity + spin_velocity(motion.spin - guess.spin, arm)
        shares = balanced(impulse_shares(structure, points, received[block.field], mass[block.field], floor), points.mass,
                          arm, structure.axisymmetric)
        ended[block.name] = advance_alone(steps_alone[block.name], params, points.replace(v=points.v + taken),
                                          block.substeps, shares)
    return ended


def impulse_shares(structure, points, received, mass, floor):
    """f_p = m_p sum_I N_I(x_p) J_I / (m_I dt) (n, 2) [N/m]: each point's share of the impulses
    `received` (nx, ny, 2) by its field (node masses `mass`), as a force over the step; they
    sum to sum_I J_I / dt."""
    stencil = structure.layout.stencil(points.x)
    support = stencil.weights.shape[1]
    gathered = read_at_stencils(structure.layout, stencil.base, per_unit_mass(received, mass, floor)[None], support)
    return points.mass[:, None] * jnp.sum(stencil.weights[..., None] * gathered, axis=(1, 2)) / structure.dt


def balanced(forces, masses, arms, axial_only=False):
    """forces (n, 2) less m_p (a + alpha e_z x r_p), the uniform and rotational acceleration
    they give the points (masses (n,), arms r_p (n, 2) from any centre): no resultant, no moment.
    axial_only (axisymmetry, where the body moves as one along the axis only): less m_p a_z e_z."""
    total = jnp.sum(masses)
    acceleration = jnp.sum(forces, axis=0) / total
    if axial_only:
        return forces - masses[:, None] * acceleration.at[0].set(0.0)
    arms = arms - jnp.dot(masses, arms) / total
    inertia = jnp.dot(masses, arms[:, 0] ** 2 + arms[:, 1] ** 2)      # 0 only for a body of one point
    turning = jnp.where(inertia > 0.0, jnp.sum(cross(arms, forces)) / jnp.where(inertia > 0.0, inertia, 1.0), 0.0)
    return forces - masses[:, None] * (acceleration + spin_velocity(turning, arms))
