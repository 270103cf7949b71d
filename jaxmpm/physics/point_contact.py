"""Contact at the points: a structure pushes the soil's points, not its nodes
(numerics.structure_hold = "points").

On the grid (`contact`) a prescribed or rigid body holds every node it shares with the soil, so
its outline is resolved to whole nodes: a rigid block three cells wide on an elastic layer
turned a third as far as elasticity says with quadratic B-splines, and 60 % further with the
grid lines moved half a cell (docs/convergence.md, "A rigid base on deformable soil"). Here
it holds no node. Each point p of a free body in contact with it, a square of side
s (the point spacing), that reaches into the outline, d_p < s / 2 (d_p the signed distance of
its centre from the outline, `bodies.outline_distances`), is pushed out along the outline's
outward normal n_p:

    f_p = max(0, k_p (s / 2 - d_p) - c_p v_n) n_p,    k_p = PENALTY E V_p / s^2,
    c_p = 2 DAMPING_RATIO sqrt(k_p m_p),               v_n = (v_p - v_b(x_p)) . n_p

with E the free body's Young's modulus, V_p and m_p the point's volume and mass and v_b the
body's velocity at the point: a layer s / PENALTY thick, as stiff as the soil, between the two,
so its compliance vanishes with the cell (the penalty method: Wriggers, Computational Contact
Mechanics, 2nd ed., 2006, ch. 6). The push reaches the grid
as the impulse dt sum_p N_I(x_p) f_p at the free field's nodes; Coulomb friction acts at those
nodes with that impulse as its normal one (`contact.pushed_impulse`), and the body receives
minus both (a rigid body's motion is solved with the friction, `bodies.solve_rigid_motions`).

Stability: the push adds a spring k_p to a point of mass m_p, omega dt = sqrt(k_p / m_p) dt =
sqrt(PENALTY E / (rho c^2)) cfl ppc (c the p-wave speed): 1.4 for sand (nu = 0.3) at the
shipped cfl 0.4 and two points per cell. Where a larger step or more points per cell would
take it past 1.5, k_p is held at 2.25 m_p / dt^2 (`STABLE_SPRING`).
"""

import jax.numpy as jnp

from jaxmpm.physics.bodies import (
    OUTLINE_RESOLUTION, no_surface, outline_distances, outline_now, prescribed_velocity, rigid_body_frame, spin_velocity,
    union_of,
)
from jaxmpm.physics.contact import PointPush
from jaxmpm.physics.grid import fold_ghosts, scatter_to_nodes
from jaxmpm.tensors import stack_last

PENALTY = 4.0          # k_p s^2 / (E V_p): the contact layer is s / PENALTY thick, as stiff as the soil
STABLE_SPRING = 2.25   # k_p dt^2 / m_p at most: the point's own spring turns by omega dt <= 1.5 a step
DAMPING_RATIO = 0.5    # of the point's spring k_p on its mass m_p, against its normal rate only


def safe_sqrt(values):
    """sqrt(x) for x >= 0 with a finite gradient at 0 (an inert point that pads a sharded state
    has no mass)."""
    positive = values > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, values, 1.0)), 0.0)


def pushed_interfaces(structure):
    """{interface index: (free block, structure parts, this part's index among them)}: the
    contacts between a free body and a prescribed or rigid body with a convex outline, when
    structures push points (structure_hold = "points"). A structure of joined parts
    (`BodyBlock.partners`, a pile's tip and shaft) pushes as their union, each part the points
    whose nearest surface is its own."""
    if structure.structure_hold != "points":
        return {}
    blocks_of_field = {}
    for block in structure.bodies:
        blocks_of_field.setdefault(block.field, []).append(block)
    pushed = {}
    for index, interface in enumerate(structure.interfaces):
        if interface.contact is None or interface.kinematic_first == interface.kinematic_second:
            continue
        body_field, free_field = ((interface.first, interface.second) if interface.kinematic_first
                                  else (interface.second, interface.first))
        body = blocks_of_field[body_field][0]
        if body.outline is None:
            continue
        fields = sorted((body_field, *body.partners))
        parts = tuple(blocks_of_field[field][0] for field in fields)
        pushed[index] = (blocks_of_field[free_field][0], parts, fields.index(body_field))
    return pushed


def body_velocity_now(params, state, block, structure, positions):
    """A prescribed or rigid body's velocity (n, 2) at `positions` at the start of the step."""
    if block.kinematics == "prescribed":
        time = state.step.astype(positions.dtype) * structure.dt
        velocity = prescribed_velocity(block, params["bodies"][block.name]["velocity"], time)
        return jnp.broadcast_to(velocity, positions.shape)
    motion = state.rigid[block.name]
    _, centre, _ = rigid_body_frame(state.particles, block, structure.point_spacing)
    return motion.velocity + spin_velocity(motion.spin, positions - centre)


def point_pushes(params, state, structure, free, parts):
    """((N_free, 2) force f_p [N/m] each point of `free` receives from the structure made of
    `parts` (the module's docstring), (N_free,) the part whose surface is nearest the point,
    which pushes it (`bodies.union_of`))."""
    particles = state.particles
    positions = particles.x[free.points]
    measured = []
    for part in parts:
        corners = outline_now(part, state, positions.dtype, structure.axisymmetric)
        measured.append(outline_distances(corners, positions, no_surface(part, corners, structure)))
    distance, normal = union_of(measured, OUTLINE_RESOLUTION * structure.layout.cell)
    owner = jnp.argmax(jnp.stack([part_distance == distance for part_distance, _ in measured]), axis=0)
    spacing = structure.point_spacing
    depth = 0.5 * spacing - distance
    material = params["materials"][free.material_name]
    mass = particles.mass[free.points]
    stiffness = jnp.minimum(PENALTY * material["young"] * particles.volume[free.points] / (spacing * spacing),
                            STABLE_SPRING * mass / (structure.dt * structure.dt))
    dashpot = 2.0 * DAMPING_RATIO * safe_sqrt(stiffness * mass)
    moving = jnp.stack([body_velocity_now(params, state, part, structure, positions) for part in parts])
    relative = particles.v[free.points] - jnp.take_along_axis(moving, owner[None, :, None], axis=0)[0]
    leaving = relative[:, 0] * normal[:, 0] + relative[:, 1] * normal[:, 1]
    pressed = jnp.where(depth > 0.0, jnp.maximum(stiffness * depth - dashpot * leaving, 0.0), 0.0)
    return pressed[:, None] * normal, owner


def pushes(params, state, structure, stencil):
    """{interface index: PointPush} of every pushed interface (`pushed_interfaces`): the points'
    forces (`point_pushes`) times dt, spread to their nodes as their weights are, each part's
    share in its own channels of one scatter of the free body's points per structure."""
    groups = {}
    for index, (free, parts, own) in pushed_interfaces(structure).items():
        groups.setdefault((free, parts), []).append((index, own))
    found = {}
    for (free, parts), members in groups.items():
        force, owner = point_pushes(params, state, structure, free, parts)
        weights = stencil.weights[free.points]
        channels = [weights * jnp.where(owner == own, force[:, axis], 0.0)[:, None, None]
                    for _, own in members for axis in range(2)]
        nodes = scatter_to_nodes(structure.layout, stencil.base[free.points], stack_last(channels),
                                 derivatives=structure.derivatives)
        nodes = fold_ghosts(nodes, structure.layout, structure.boundaries, scalars=0)[0]
        for number, (index, _) in enumerate(members):
            found[index] = PointPush(structure.dt * nodes[..., 2 * number:2 * number + 2])
    return found
