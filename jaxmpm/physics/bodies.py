"""Prescribed and rigid bodies on the grid: how each kind meets the free fields in a step.

Each kind (`Prescribed`, `Rigid`; `KINDS`) answers the same questions, so the step's phases
(`impose_body_motions`, `move_kinematic_bodies`, `keep_points_outside`) hold no kind `if`s:
its motion over the step if nothing touched it (`free_motion`), its velocity at given
positions (`velocity_at`: imposed on its field's nodes), how its points move from the impulses its field received (`moved`), and where its
outline is now (`outline_now`). The impulses themselves come from `contact`; a rigid body's
motion is solved with them (`solve_rigid_motions`).

A prescribed body moves on its given path: its field's nodes take its velocity, it acts as
infinitely heavy in contact, and the impulse it receives is reported as the reaction that
kept it on its path.

A rigid body moves as one body. Its velocity V and spin omega at the end of the step are
solved *together* with the impulses of every interface it has with free fields (contact pairs
and bonded interfaces): with u_I(V, omega) = V + omega e_z x (x_I - c) at each node,

    M (V - V*)         = sum_I J_I(u_I)                      V* = V^n + dt g
    J_c (omega - w*)   = sum_I (x_I - c) x J_I(u_I)          w* = omega^n

where J_I(u) is the impulse the body receives at node I when the free fields' trial
velocities are corrected by the step's interfaces in their order, the body moving at u
(`contact.apply_interfaces`: Coulomb contact, only where closing; or full no-slip for bonded
fields; a bond between two free fields before the body's contacts changes what they meet).
The free nodes then end the step moving exactly as the body does, and the body moves as the
impulses it received say: no lag and no feedback. The residual is piecewise linear in
(V, omega), so Newton's method with its exact Jacobian (an active-set method) reaches the
solution in a few iterations; its derivative is that of the implicit function theorem, taken
by one last Newton step.

The earlier scheme predicted the body's velocity from the last step's contact force and
corrected it after the contact: a lagged explicit coupling whose error is first order in dt
with a large constant (a rigid wall moved ten times too far at the default step,
docs/convergence.md) and whose feedback gain m_contact / M made it unstable for bodies
lighter than the sand they touch.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.physics.contact import apply_interfaces, bounding_fields, cross, safe_norm, unit

OUTLINE_RESOLUTION = 1e-9    # of an outline's longest edge: nearer than that, a position counts as on it
TIED_OPPOSITE = 1e-3         # |sum of the tied edges' normals| below this: opposite faces (mid-plane of a
                             # slab), whose mean has no direction; the first of them is taken
NEWTON_ITERATIONS = 3   # 2-3 reach round-off (the same wall motion as 8, bit for bit or within
                        # 1e-12) on retaining_wall, the wall twin and the small wall of docs/convergence.md


class PrescribedStep(NamedTuple):
    """A prescribed body's velocity (2,) at the start and at the end of a step [m/s]."""

    before: jax.Array
    after: jax.Array


class RigidStep(NamedTuple):
    """A rigid body in one step: mass M [kg/m], centre of mass c (2,) [m], polar moment J about
    c [kg m^2/m] at the start of the step; the velocity (2,) and spin () it ends the step with
    (before the solve: V + dt g and omega, its motion if nothing touched it). A subcycled body
    meets its contacts as one too (`subcycling`): before the solve, its velocity and spin are
    those its substeps predict."""

    mass: jax.Array
    centre: jax.Array
    inertia: jax.Array
    velocity: jax.Array
    spin: jax.Array


def prescribed_velocity(block, velocity, time):
    """A prescribed body's velocity (2,) at `time` [s]: the constant `velocity` (2,), or the
    table `velocity` (K, 2) at `block.times`, linear in between, held beyond the ends."""
    if block.times is None:
        return velocity
    times = jnp.asarray(block.times, velocity.dtype)
    return jnp.stack([jnp.interp(time, times, velocity[:, axis]) for axis in range(2)])


def rigid_body_frame(particles, block, spacing):
    """(mass M, centre of mass c (2,), polar moment J about c) of a rigid body from its points,
    each a square of side `spacing`: J = sum m_p (|x_p - c|^2 + spacing^2 / 6)."""
    mass, positions = particles.mass[block.points], particles.x[block.points]
    total = jnp.sum(mass)
    centre = jnp.dot(mass, positions) / total
    arm = positions - centre
    inertia = jnp.dot(mass, arm[:, 0] * arm[:, 0] + arm[:, 1] * arm[:, 1] + spacing * spacing / 6.0)
    return total, centre, inertia


def node_positions(layout, dtype):
    """(nx, ny, 2) positions of the node arrays' nodes [m] (ghosts included)."""
    nx, ny = layout.nodes
    i, j = jnp.meshgrid(jnp.arange(nx, dtype=dtype), jnp.arange(ny, dtype=dtype), indexing="ij")
    origin = jnp.asarray(layout.origin, dtype)
    return jnp.stack([i - layout.ghost, j - layout.ghost], axis=-1) * layout.cell + origin


def spin_velocity(spin, arm):
    """omega e_z x arm, (..., 2)."""
    return jnp.stack([-spin * arm[..., 1], spin * arm[..., 0]], axis=-1)


def turned_by(angle, arms):
    """(n, 2) arms rotated counter-clockwise by `angle` [rad]."""
    return rotated(jnp.cos(angle), jnp.sin(angle), arms)


def rotated(cos, sin, arms):
    """(n, 2) arms rotated counter-clockwise by the angle whose cosine and sine are given."""
    return jnp.stack([cos * arms[:, 0] - sin * arms[:, 1], sin * arms[:, 0] + cos * arms[:, 1]], axis=-1)


class Prescribed:
    """A body moved on its given path (params["bodies"][name]["velocity"]): what the step asks
    of each kind of kinematic body, for this kind."""

    @staticmethod
    def free_motion(params, state, block, structure, time_new):
        """Its velocity at the start and at the end of the step (PrescribedStep)."""
        velocity = params["bodies"][block.name]["velocity"]
        before = prescribed_velocity(block, velocity, time_new - structure.dt)
        return PrescribedStep(before, prescribed_velocity(block, velocity, time_new))

    @staticmethod
    def velocity_at(motion, positions):
        """Its velocity at `positions` (..., 2) during the step: the same everywhere."""
        return jnp.broadcast_to(motion.after, positions.shape)

    @staticmethod
    def moved(block, state, start, motion, received, structure, gravity):
        """(x, v of its points, its reaction, its RigidMotion (None)): the points move at its
        velocity from `start`; the reaction is the force that kept it on its path,
        m (v_after - v_before) / dt - m g - J / dt for the impulse J its field `received`."""
        before, after = motion
        mass = jnp.sum(state.particles.mass[block.points])
        total = 0.0 if received is None else jnp.sum(received, axis=(0, 1))
        reaction = mass * (after - before) / structure.dt - mass * gravity - total / structure.dt
        count = block.stop - block.start
        return start[block.points] + structure.dt * after, jnp.broadcast_to(after, (count, 2)), reaction, None

    @staticmethod
    def outline_now(block, state, corners, centre):
        """Its outline's corners now: shifted as the mean of its points moved."""
        return corners + (jnp.mean(state.particles.x[block.points], axis=0) - centre)


class Rigid:
    """A body that moves as one under gravity and the impulses of its interfaces, solved with
    them in `solve_rigid_motions`: what the step asks of each kind, for this kind."""

    @staticmethod
    def free_motion(params, state, block, structure, time_new):
        """Its frame and the motion it would end the step with if nothing touched it (RigidStep)."""
        mass, centre, inertia = rigid_body_frame(state.particles, block, structure.point_spacing)
        motion = state.rigid[block.name]
        return RigidStep(mass, centre, inertia, motion.velocity + structure.dt * params["scene"]["gravity"], motion.spin)

    @staticmethod
    def velocity_at(motion, positions):
        """V + omega e_z x (x - c) at `positions` (..., 2): its velocity field with the centre
        of mass where it is at the start of the step."""
        return motion.velocity + spin_velocity(motion.spin, positions - motion.centre)

    @staticmethod
    def moved(block, state, start, motion, received, structure, gravity):
        """(x, v of its points, no reaction, its RigidMotion): the points turn by dt omega
        about the centre of mass, which moves by dt V."""
        dt, rigid = structure.dt, state.rigid[block.name]
        turn = dt * motion.spin
        turned = turned_by(turn, start[block.points] - motion.centre)
        updated = rigid.replace(translation=rigid.translation + dt * motion.velocity, rotation=rigid.rotation + turn,
                                velocity=motion.velocity, spin=motion.spin)
        return (motion.centre + dt * motion.velocity + turned, motion.velocity + spin_velocity(motion.spin, turned),
                None, updated)

    @staticmethod
    def outline_now(block, state, corners, centre):
        """Its outline's corners now: turned and moved as the body was (state.rigid)."""
        motion = state.rigid[block.name]
        return centre + motion.translation + turned_by(motion.rotation, corners - centre)


KINDS = {"prescribed": Prescribed, "rigid": Rigid}   # the kinematic body kinds; "free" bodies have no motion


def elastic_outline_now(block, state, corners, centre, turns=True):
    """A free elastic body's outline corners now: turned and moved by the rigid motion that
    best fits its points' (least squares, Kabsch in 2-D): the mean of its points moved, and
    the rotation (cos, sin) ~ (sum r0_p . r_p, sum r0_p x r_p) with r0_p its points' arms
    from their mean at t = 0 (`BodyBlock.reference_arms`) and r_p now. Exact for a body that
    has only moved as one; a stiff structure's strain (1e-4) moves its faces by that fraction
    of its size, far below a cell. A ring (axisymmetry, `turns` False) moves along the axis
    only, as a rigid one does: a fitted turn would read its bending as a tilt, and its radial
    swelling would move an edge on the axis off it, where it became a surface."""
    points = state.particles.x[block.points]
    mean = jnp.mean(points, axis=0)
    if not turns:
        return corners + jnp.stack([jnp.zeros_like(mean[1]), mean[1] - centre[1]])
    reference = jnp.asarray(block.reference_arms, points.dtype)
    arms = points - mean
    cos, sin = unit(jnp.stack([jnp.sum(reference * arms), jnp.sum(cross(reference, arms))]))
    return mean + rotated(cos, sin, corners - centre)


def kinematic_blocks(structure):
    """The prescribed and rigid bodies' blocks, in scene order."""
    return tuple(block for block in structure.bodies if block.kinematics in KINDS)


def free_motions(params, state, structure, time_new):
    """{body: PrescribedStep or RigidStep}: each kinematic body's motion over the step if
    nothing touched it (`free_motion` of its kind)."""
    return {block.name: KINDS[block.kinematics].free_motion(params, state, block, structure, time_new)
            for block in kinematic_blocks(structure)}


def impose_kinematic_fields(velocity, structure, motions, positions):
    """Node velocities of each kinematic body's field set to the body's velocity at the nodes
    (`velocity_at` of its kind, in the step's starting frame)."""
    for block in kinematic_blocks(structure):
        velocity = velocity.at[block.field].set(KINDS[block.kinematics].velocity_at(motions[block.name], positions))
    return velocity


def answering_blocks(structure):
    """The bodies that answer their contacts as a whole, solved with their impulses: rigid
    bodies, and subcycled free bodies (`subcycling`)."""
    return tuple(block for block in structure.bodies if block.kinematics == "rigid" or block.substeps > 1)


def interfaces_to_answer(structure):
    """The interfaces, in the step's order, up to the last one between a rigid (or subcycled)
    body's field and a free field: those whose impulses the body's motion is solved with.
    The ones before a body's own interfaces count too: a bond between two free fields (a
    backfill and its foundation) sets the velocities the body's contacts then correct."""
    answering = {block.field for block in answering_blocks(structure)}
    touching = [index for index, interface in enumerate(structure.interfaces)
                if answering & {interface.first, interface.second}]
    return structure.interfaces[:touching[-1] + 1] if touching else ()


class Grid(NamedTuple):
    """The node values the rigid-body solve reads: mass (F, nx, ny), trial velocity and
    outward mass gradient (F, nx, ny, 2) (None without contact pairs), occupied (F, nx, ny)."""

    mass: jax.Array
    velocity: jax.Array
    mass_gradient: jax.Array | None
    occupied: jax.Array


def rigid_residual(motion, grid, frictions, structure, frames, positions, normals):
    """Momentum balance of every rigid body, (3 K,): M (V - V*) - sum J and
    J_c (omega - w*) - sum r x J, with `motion` (3 K,) the bodies' (V_x, V_y, omega) in
    block order, `frames` their RigidStep before the solve and `normals` the contact normal
    of each of `interfaces_to_answer` (None for a bonded one; they do not depend on the
    motion). The impulses J are those the step applies (`contact.apply_interfaces`, in
    its order) with the bodies' fields moving at `motion`.
    In axisymmetry only the axial row takes the impulses: the body, a ring, keeps V_r = V*_r
    and omega = w*."""
    blocks = answering_blocks(structure)
    velocity = grid.velocity
    for index, block in enumerate(blocks):
        arm = positions - frames[block.name].centre
        velocity = velocity.at[block.field].set(motion[3 * index:3 * index + 2] + spin_velocity(motion[3 * index + 2], arm))
    interfaces = interfaces_to_answer(structure)
    _, impulses = apply_interfaces(interfaces, grid.mass, velocity, normals, frictions, grid.occupied)
    received = received_impulses(interfaces, impulses)
    balances = []
    for index, block in enumerate(blocks):
        frame = frames[block.name]
        impulse = received.get(block.field, jnp.zeros_like(velocity[0]))
        linear = frame.mass * (motion[3 * index:3 * index + 2] - frame.velocity) - jnp.sum(impulse, axis=(0, 1))
        angular = frame.inertia * (motion[3 * index + 2] - frame.spin) - jnp.sum(cross(positions - frame.centre, impulse))
        if structure.axisymmetric:      # a ring moves along the axis only: no impulse moves it radially or turns it
            linear = linear.at[0].set(frame.mass * (motion[3 * index] - frame.velocity[0]))
            angular = frame.inertia * (motion[3 * index + 2] - frame.spin)
        balances.append(jnp.concatenate([linear, angular[None]]))
    return jnp.concatenate(balances)


def solve_rigid_motions(structure, motions, grid, frictions, positions, normals):
    """Each rigid body's end-of-step velocity and spin, solved with its interfaces' impulses
    (the module's docstring; `normals`: each of structure.interfaces', `contact.normals_of`):
    NEWTON_ITERATIONS Newton steps from the free motion, all but the last on values only; the
    last one differentiable with its Jacobian held, so that its derivative is
    -(dR/dq)^-1 dR/dparams, the implicit function theorem's."""
    blocks = answering_blocks(structure)
    if not blocks:
        return motions
    frames = {block.name: motions[block.name] for block in blocks}
    solved = jnp.concatenate([jnp.concatenate([frames[b.name].velocity, frames[b.name].spin[None]]) for b in blocks])
    answered = interfaces_to_answer(structure)
    if answered:
        assert len(normals) == len(structure.interfaces), "a normal (or None) for every interface"
        normals = tuple(normals[:len(answered)])

        def residual(motion, grid, frictions, frames, normals):
            return rigid_residual(motion, grid, frictions, structure, frames, positions, normals)

        inputs = (grid, frictions, frames, normals)
        fixed = jax.lax.stop_gradient(inputs)

        def newton(_, motion):
            return motion - jnp.linalg.solve(jax.jacfwd(residual)(motion, *fixed), residual(motion, *fixed))

        solved = jax.lax.stop_gradient(jax.lax.fori_loop(0, NEWTON_ITERATIONS - 1, newton, jax.lax.stop_gradient(solved)))
        jacobian = jax.lax.stop_gradient(jax.jacfwd(residual)(solved, *fixed))
        solved = solved - jnp.linalg.solve(jacobian, residual(solved, *inputs))
    motions = dict(motions)
    for index, block in enumerate(blocks):
        motions[block.name] = frames[block.name]._replace(velocity=solved[3 * index:3 * index + 2], spin=solved[3 * index + 2])
    return motions


def impose_body_motions(params, state, structure, grid, frictions, time_new, normals, predicted=None):
    """(nodal velocities with each prescribed, rigid and subcycled body's field moving as the
    body, {body: its motion over the step}) from the free fields' trial `grid`: prescribed
    bodies on their path (set first: the rigid bodies' solve meets them so), rigid bodies and
    subcycled ones (`predicted`: {name: RigidStep of its predicted motion,
    `subcycling.predict`}) solved with their interfaces' impulses (`solve_rigid_motions`, with
    each interface's contact normal, `normals`). A scene without such bodies: the trial
    velocities and {}."""
    predicted = predicted or {}
    if not structure.has_kinematic_bodies and not predicted:
        return grid.velocity, {}
    positions = node_positions(structure.layout, state.particles.x.dtype)
    motions = {**free_motions(params, state, structure, time_new), **predicted}
    on_path = grid._replace(velocity=impose_kinematic_fields(grid.velocity, structure, motions, positions))
    motions = jax.named_call(solve_rigid_motions, name="rigid_bodies")(structure, motions, on_path, frictions,
                                                                        positions, normals)
    velocity = impose_kinematic_fields(grid.velocity, structure, motions, positions)
    for block in structure.bodies:
        if block.name in predicted:
            velocity = velocity.at[block.field].set(Rigid.velocity_at(motions[block.name], positions))
    return velocity, motions


def received_impulses(interfaces, impulses):
    """{field: (nx, ny, 2) total impulse the field received from the `interfaces`}."""
    received = {}
    for interface, impulse in zip(interfaces, impulses):
        received[interface.first] = received.get(interface.first, 0.0) + impulse
        received[interface.second] = received.get(interface.second, 0.0) - impulse
    return received


def move_kinematic_bodies(state, start, structure, motions, impulses, gravity):
    """Each kinematic body's points moved from their positions `start` (N, 2) at the start of
    the step as its kind says (`moved`): prescribed points on their path, rigid bodies as one.

    Returns (state, reactions {prescribed body: (2,) force that kept it on its path, gravity
    (2,) taken off})."""
    particles = state.particles
    x, v, rigid = particles.x, particles.v, dict(state.rigid)
    received = received_impulses(structure.interfaces, impulses)
    reactions = {}
    for block in kinematic_blocks(structure):
        moved_x, moved_v, reaction, motion = KINDS[block.kinematics].moved(
            block, state, start, motions[block.name], received.get(block.field), structure, gravity)
        x, v = x.at[block.points].set(moved_x), v.at[block.points].set(moved_v)
        if reaction is not None:
            reactions[block.name] = reaction
        if motion is not None:
            rigid[block.name] = motion
    return state.replace(particles=particles.replace(x=x, v=v), rigid=rigid), reactions


def convex_outline(vertices):
    """The vertices (K, 2) of a convex polygon in counter-clockwise order, as a tuple of pairs,
    or None if the polygon is not convex or repeats a vertex (a zero-length edge has no
    normal; its points are then not kept outside)."""
    corners = np.asarray(vertices, float)
    edges = np.roll(corners, -1, axis=0) - corners
    if np.any(np.hypot(edges[:, 0], edges[:, 1]) == 0.0):
        return None
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if np.all(turns <= 0.0):
        corners, turns = corners[::-1], -turns
    if not np.all(turns >= 0.0) or not np.any(turns > 0.0):
        return None
    return tuple(map(tuple, corners.tolist()))


def seeded_outline(corners, positions, spacing):
    """A convex outline (K, 2, counter-clockwise) moved to the body its points make: each edge
    moved along its outward normal n to the outermost point's square, max_p n . (x_p - a) +
    (spacing / 2)(|n_x| + |n_y|) from where it was, the corners where the moved edges meet
    (numpy, at t = 0). The points fill the region on the grid's lattice, so a region whose
    edges fall between its rows holds a body up to a point spacing smaller: where two bodies
    meet, the points' squares touch while their regions overlap or part."""
    corners = np.asarray(corners, float)
    edges = np.roll(corners, -1, axis=0) - corners
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=-1) / np.hypot(edges[:, 0], edges[:, 1])[:, None]
    reach = 0.5 * spacing * (np.abs(normals[:, 0]) + np.abs(normals[:, 1]))
    levels = np.max(positions @ normals.T, axis=0) + reach                  # n_e . x on each moved edge
    moved = []
    for k in range(len(corners)):          # corner k joins edge k - 1 and edge k
        system = np.stack([normals[k - 1], normals[k]])
        moved.append(np.linalg.solve(system, np.array([levels[k - 1], levels[k]])))
    return tuple(map(tuple, np.asarray(moved).tolist()))


def outline_now(block, state, dtype, axisymmetric=False):
    """(K, 2) corners of a body's outline at the state's time: its scene region moved as its
    points moved (`outline_now` of its kind, `elastic_outline_now` for a free body)."""
    corners = jnp.asarray(block.outline, dtype)
    centre = jnp.asarray(block.outline_centre, dtype)
    if block.kinematics == "free":
        return elastic_outline_now(block, state, corners, centre, turns=not axisymmetric)
    return KINDS[block.kinematics].outline_now(block, state, corners, centre)


def outline_distances(corners, positions, excluded=None):
    """(signed distance (...), outward unit normal (..., 2)) of a convex outline (K, 2) (corners
    counter-clockwise) at `positions` (..., 2): inside or on the outline, the largest signed
    distance n_e . (x - a_e) and the normal of that edge (the nearest); outside, |x - p| and
    (x - p) / |x - p| with p the nearest point of the outline (so the normal turns smoothly
    round a corner). Inside, a position equally near two edges (within `OUTLINE_RESOLUTION`),
    a corner or the diagonal from it, takes the mean of their normals (round-off would choose
    one, 90 degrees apart); between opposite faces, the first. A position outside by less than
    `OUTLINE_RESOLUTION` of the longest edge
    counts as on it: a moved outline's round-off (~1e-17 m) would otherwise set the direction
    of x - p (a slab's top nodes then pointed 75 degrees off its face). `excluded` (K,) bool
    marks edges that are no surface, left out: edges on a held grid edge (`mirrored_edges`,
    the body continues beyond them as its mirror image) and edges joined to another prescribed
    body moving with it (`joined_edges`). Finite, with finite gradients, everywhere."""
    edges = jnp.roll(corners, -1, axis=0) - corners
    squared_lengths = edges[:, 0] ** 2 + edges[:, 1] ** 2
    normals = jnp.stack([edges[:, 1], -edges[:, 0]], axis=-1) / jnp.sqrt(squared_lengths)[:, None]
    offsets = positions[..., None, :] - corners                                # (..., K, 2)
    distances = jnp.sum(offsets * normals, axis=-1)                            # (..., K)
    along = jnp.clip(jnp.sum(offsets * edges, axis=-1) / squared_lengths, 0.0, 1.0)
    gaps = offsets - along[..., None] * edges                                  # x - p for each edge
    gap_squares = jnp.sum(gaps * gaps, axis=-1)
    resolution = OUTLINE_RESOLUTION * jnp.sqrt(jnp.max(squared_lengths))
    outside = jnp.max(distances, axis=-1) > resolution     # beyond an edge, excluded ones included
    if excluded is not None:
        distances = jnp.where(excluded, -jnp.inf, distances)
        gap_squares = jnp.where(excluded, jnp.inf, gap_squares)
    depth = jnp.max(distances, axis=-1)
    tied = distances >= depth[..., None] - resolution                         # nearest edges: two at a corner
    bisector = jnp.sum(jnp.where(tied[..., None], normals, 0.0), axis=-2)
    nearest_edge = jnp.where(safe_norm(bisector)[..., None] > TIED_OPPOSITE, unit(bisector),
                             normals[jnp.argmax(distances, axis=-1)])
    nearest = jnp.argmin(gap_squares, axis=-1)
    gap = jnp.take_along_axis(gaps, nearest[..., None, None], axis=-2)[..., 0, :]
    away = jnp.where(outside[..., None], gap, nearest_edge)                  # |gap| > 0 where used
    return jnp.where(outside, safe_norm(away), depth), jnp.where(outside[..., None], unit(away), nearest_edge)


def cell_meets_outline(corners, positions, cell):
    """(...) bool: whether the square of side `cell` centred on each of `positions` (..., 2)
    meets the convex outline `corners` (K, 2, counter-clockwise). Separating axes: the two are
    apart if, along an edge's outward normal n_e, the square's nearest extent lies beyond the
    edge, n_e . (x - a_e) > (cell / 2)(|n_x| + |n_y|), or if their extents along x or y do not
    overlap."""
    half = 0.5 * cell
    normals = edge_normals(corners)                                                          # (K, 2)
    beyond = jnp.sum((positions[..., None, :] - corners) * normals, axis=-1)                 # (..., K)
    reach = half * (jnp.abs(normals[:, 0]) + jnp.abs(normals[:, 1]))
    apart = jnp.any(beyond > reach, axis=-1)
    for axis in range(2):
        apart |= (jnp.min(corners[:, axis]) > positions[..., axis] + half)
        apart |= (jnp.max(corners[:, axis]) < positions[..., axis] - half)
    return ~apart


def held_structures(structure):
    """The blocks of the structures whose outline limits where they hold the bodies in contact
    with them (`held_by_outline`): prescribed and rigid bodies, and free bodies whose outline
    bounds a contact's normal (`contact.Interface.bounded_by`: elastic structures), each of
    convex outline."""
    bounding = bounding_fields(structure.interfaces)
    return tuple(block for block in structure.bodies
                 if block.outline is not None and (block.kinematics in KINDS or block.field in bounding))


def held_by_outline(structure, state, occupied):
    """`occupied` (F, nx, ny) with each structure (`held_structures`) kept only at the nodes
    whose cell meets its outline at the state's time (`cell_meets_outline`;
    numerics.structure_hold = "outline").

    A prescribed or rigid body counts as infinitely heavy in a contact
    (`contact.interface_impulse`): at every node it occupies it sets the other field's velocity
    (its normal part), whatever its own share of the node's mass. Its points sit a quarter cell
    inside its outline (ppc 2) and reach nodes a shape function's support beyond them, up to a
    cell and a quarter outside the outline with quadratic B-splines: the body then acts a cell
    larger all round, and a wall held up by its three-cell base moved twice as far at each
    halving of the cell. An elastic structure's contact acts wherever both fields have mass,
    and so from as far. A node whose cell the outline does not meet holds nothing of the body
    at the grid's resolution."""
    positions = node_positions(structure.layout, state.particles.x.dtype)
    for block in held_structures(structure):
        corners = outline_now(block, state, positions.dtype, structure.axisymmetric)
        meets = cell_meets_outline(corners, positions, structure.layout.cell)
        occupied = occupied.at[block.field].set(occupied[block.field] & meets)
    return occupied


def edge_normals(corners):
    """(K, 2) outward unit normals of the edges of an outline (K, 2) whose corners run
    counter-clockwise; edge k runs from corner k to corner k + 1."""
    edges = jnp.roll(corners, -1, axis=0) - corners
    return jnp.stack([edges[:, 1], -edges[:, 0]], axis=-1) / jnp.sqrt(edges[:, 0] ** 2 + edges[:, 1] ** 2)[:, None]


def outline_width(corners):
    """The width of a convex outline (K, 2): its least extent across any edge, min over the
    edges of the farthest corner's distance behind it."""
    normals = edge_normals(corners)
    behind = jnp.sum((corners[:, None, :] - corners[None, :, :]) * normals[:, None, :], axis=-1)   # (edge, corner)
    return jnp.min(jnp.max(behind, axis=1))


def rounded_outline(corners, excluded, radius):
    """(K, 2) corners of the convex outline with each surface edge moved inward by `radius`
    (edges that are no surface, `excluded`, stay where they are). `outline_distances` of it
    gives, at a position, the direction from its nearest point: the outward normal of the
    outline with its corners between surface edges rounded at `radius`, which turns
    continuously round a corner instead of jumping by the corner's angle (its distance is the
    rounded outline's plus `radius`). Faces keep their own normal. Corner k, between edges
    k - 1 and k, is where their moved lines n . x = n . a_k - r meet; where they are parallel
    (a corner on a straight edge), it moves along the normal."""
    normals = edge_normals(corners)
    shifts = jnp.where(excluded, 0.0, radius) if excluded is not None else jnp.full(len(corners), radius)
    before, shift_before = jnp.roll(normals, 1, axis=0), jnp.roll(shifts, 1)
    first = jnp.sum(before * corners, axis=-1) - shift_before
    second = jnp.sum(normals * corners, axis=-1) - shifts
    determinant = before[:, 0] * normals[:, 1] - before[:, 1] * normals[:, 0]
    turning = jnp.abs(determinant) > 1e-9
    determinant = jnp.where(turning, determinant, 1.0)
    met = jnp.stack([(first * normals[:, 1] - before[:, 1] * second) / determinant,
                     (before[:, 0] * second - first * normals[:, 0]) / determinant], axis=-1)
    return jnp.where(turning[:, None], met, corners - shifts[:, None] * normals)


def corner_radius(corners, cell, cells):
    """The radius a prescribed body's corners are rounded at: `cells` cells (the scene's
    numerics.corner_radius), at most a quarter of the outline's width (so that a thin plate
    keeps its two faces apart)."""
    return jnp.minimum(cells * cell, outline_width(corners) / 4.0)


def outline_normals(corners, positions, excluded=None):
    """The outward unit normals (..., 2) of `outline_distances`."""
    return outline_distances(corners, positions, excluded)[1]


def joined_edges(corners, others):
    """(K,) bool: the edges of a convex outline (K, 2) that lie on an edge of one of the
    convex outlines `others` and face it (both ends within `OUTLINE_RESOLUTION` of that edge's
    length from it, opposite directions): where two prescribed bodies that move together meet
    (a pile's tip and its shaft), that edge is inside the structure and no surface (numpy, at
    setup)."""
    corners = np.asarray(corners, float)
    ends = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)            # (K, 2 ends, 2)
    joined = np.zeros(len(corners), bool)
    for other in others:
        other = np.asarray(other, float)
        for base, along in zip(other, np.roll(other, -1, axis=0) - other):
            length = np.hypot(along[0], along[1])
            offsets = ends - base                                               # (K, 2, 2)
            fraction = offsets @ along / length**2
            off = np.abs(offsets[..., 0] * along[1] - offsets[..., 1] * along[0]) / length
            facing = (ends[:, 1] - ends[:, 0]) @ along < 0.0
            on = (off <= OUTLINE_RESOLUTION * length) & (fraction >= -OUTLINE_RESOLUTION) & (fraction <= 1.0 + OUTLINE_RESOLUTION)
            joined |= facing & np.all(on, axis=1)
    return joined


def mirrored_edges(corners, layout, boundaries):
    """(K,) bool: the outline's edges that lie on a fixed or slip grid edge (both ends within
    1e-9 of a cell of it), e.g. a pile's side on the axis in axisymmetry."""
    ends = jnp.stack([corners, jnp.roll(corners, -1, axis=0)], axis=1)        # (K, 2 ends, 2)
    tolerance = 1e-9 * layout.cell
    lines = {"left": (0, layout.origin[0]), "right": (0, layout.origin[0] + layout.cells[0] * layout.cell),
             "bottom": (1, layout.origin[1]), "top": (1, layout.origin[1] + layout.cells[1] * layout.cell)}
    mirrored = jnp.zeros(len(corners), bool)
    for edge, (axis, at) in lines.items():
        if getattr(boundaries, edge) != "free":
            mirrored = mirrored | jnp.all(jnp.abs(ends[:, :, axis] - at) <= tolerance, axis=1)
    return mirrored


def no_surface(block, corners, structure):
    """(K,) bool: the edges of a body's outline `corners` that are no surface: on a held grid
    edge (`mirrored_edges`) or joined to another prescribed body (`BodyBlock.joined`)."""
    excluded = mirrored_edges(corners, structure.layout, structure.boundaries)
    return excluded if block.joined is None else excluded | jnp.asarray(block.joined)


def union_of(parts, tolerance):
    """(signed distance, outward normal) of the union of joined parts, from each part's
    `outline_distances` (its joined edges left out), in the given order: a node takes the part
    whose surface is nearest, i.e. the smaller distance, or the larger where both are <= 0 (on
    the joint, inside both parts, the nearer surface is the less deep one); equally near
    (within `tolerance`), the mean of the two normals, unless they are opposite."""
    distance, normal = parts[0]
    for other_distance, other_normal in parts[1:]:
        inside_both = (distance <= 0.0) & (other_distance <= 0.0)
        other_nearer = jnp.where(inside_both, other_distance > distance, other_distance < distance)
        tied = jnp.abs(other_distance - distance) <= tolerance
        mean = normal + other_normal
        blended = jnp.where(safe_norm(mean)[..., None] > TIED_OPPOSITE, unit(mean), normal)
        normal = jnp.where(tied[..., None], blended, jnp.where(other_nearer[..., None], other_normal, normal))
        distance = jnp.where(other_nearer, other_distance, distance)
    return distance, normal


def prescribed_outline_normals(structure, state, positions):
    """{field: (nx, ny, 2)} outward normals at the nodes `positions` of every prescribed body
    with a convex outline, from its outline at the state's time with its corners rounded at
    `corner_radius` (`rounded_outline`, `outline_distances`; its edges on held grid edges and
    its joined edges left out, and not rounded): the normal its contacts use
    (`contact.interface_normals`). The rounding spreads the turn of the normal at a corner over
    about a cell of the body's travel: with a sharp corner, the node row a pile's tip passed
    turned at once from under the tip to beside it, and the head force fell by a third at
    every cell of penetration (docs/convergence.md). Bodies joined to it (`BodyBlock.partners`:
    prescribed bodies that share an edge with it and move with it) make one structure with it,
    and all its parts take the normal of their union (`union_of`, the parts in field order), so
    that sand flowing past a pile's tip onto its shaft meets the pile's side, not the shaft's
    lower end."""
    measured = {}
    for block in kinematic_blocks(structure):
        if block.kinematics != "prescribed" or block.outline is None:
            continue
        corners = outline_now(block, state, positions.dtype)
        excluded = no_surface(block, corners, structure)
        rounded = rounded_outline(corners, excluded, corner_radius(corners, structure.layout.cell, structure.corner_radius))
        measured[block.field] = (block, outline_distances(rounded, positions, excluded))
    tolerance = OUTLINE_RESOLUTION * structure.layout.cell
    return {field: union_of([measured[part][1] for part in sorted((field, *block.partners))], tolerance)[1]
            for field, (block, _) in measured.items()}


class NormalCone(NamedTuple):
    """A structure's outline seen from the grid's nodes, (nx, ny, ...): its outward normal
    (`outline_distances` of the outline with rounded corners), whether that is a face's own
    normal (on_face), and the normals of the two faces nearest in direction (first, second):
    where the node is off a face, at a corner, the normals a contact there may take lie
    between them (`contact.within_cone`)."""

    normal: jax.Array
    on_face: jax.Array
    first: jax.Array
    second: jax.Array


FACE_ALIGNMENT = 1e-9   # 1 - n . n_edge below this: the node's outline normal is that face's own


def normal_cones(structure, state, positions):
    """{field: NormalCone at the nodes `positions`} of every rigid or free body whose outline
    bounds the normal of a contact (`contact.Interface.bounded_by`), from its outline at the
    state's time (`outline_now`), its corners rounded as a prescribed body's are
    (`corner_radius`) and its edges that are no surface left out."""
    fields = bounding_fields(structure.interfaces)
    cones = {}
    for block in structure.bodies:
        if block.field not in fields or block.outline is None:
            continue
        corners = outline_now(block, state, positions.dtype, structure.axisymmetric)
        excluded = no_surface(block, corners, structure)
        rounded = rounded_outline(corners, excluded, corner_radius(corners, structure.layout.cell, structure.corner_radius))
        normal = outline_distances(rounded, positions, excluded)[1]
        faces = edge_normals(corners)                                              # (K, 2)
        alignment = jnp.where(excluded, -jnp.inf, jnp.sum(normal[..., None, :] * faces, axis=-1))   # (..., K)
        best = jnp.argmax(alignment, axis=-1)
        runner_up = jnp.argmax(jnp.where(jnp.arange(len(faces)) == best[..., None], -jnp.inf, alignment), axis=-1)
        cones[block.field] = NormalCone(normal, jnp.max(alignment, axis=-1) > 1.0 - FACE_ALIGNMENT,
                                        faces[best], faces[runner_up])
    return cones


def outline_pairs(structure):
    """(free block, kinematic block) of every contact pair between a free body and a prescribed
    or rigid body with a convex outline."""
    by_field = {}
    for block in structure.bodies:
        by_field.setdefault(block.field, []).append(block)
    pairs = []
    for interface in structure.interfaces:
        if interface.contact is None or interface.kinematic_first == interface.kinematic_second:
            continue
        body_field, free_field = ((interface.first, interface.second) if interface.kinematic_first
                                  else (interface.second, interface.first))
        for body in by_field[body_field]:
            if body.outline is None:
                continue
            pairs.extend((free, body) for free in by_field[free_field] if free.kinematics == "free")
    return tuple(pairs)


def keep_points_outside(state, structure):
    """Points of free bodies that ended the step inside a prescribed or rigid body they are in
    contact with are put back on its surface; their velocity is the grid's and stays.

    Grid contact acts on nodes, while points move with velocities interpolated from nodes on
    both sides of the interface: a point under a pile tip, between a contact node moving with
    the pile and a slower node below, closes on the tip at N_lower (v_pile - v_lower) and
    enters it, where the body's normal is undefined and nothing pushes it out (16 points
    ended inside the pile tip of examples/pile_driving.toml). The body's outline is known
    exactly (its scene region, moved with it), so the point is moved to the nearest edge of
    the convex outline, x <- x - d n (d = max_e n_e . (x - a_e) < 0, the edge it is nearest,
    edges that are no surface (`no_surface`) left out). The velocity is left alone: the
    grid's contact already gave it, and removing its approach at the points alone (v <- v -
    min(0, (v - v_b) . n) n, as until 2026-12-06) set them apart from their neighbours, which
    the next transfer spread: sand at a pile tip's shoulder was kicked upward at up to 7.6
    times the pile's speed (docs/convergence.md)."""
    particles = state.particles
    x = particles.x
    for free, body in outline_pairs(structure):
        corners = outline_now(body, state, x.dtype)
        edges = jnp.roll(corners, -1, axis=0) - corners
        lengths = jnp.sqrt(edges[:, 0] ** 2 + edges[:, 1] ** 2)
        normals = jnp.stack([edges[:, 1], -edges[:, 0]], axis=-1) / lengths[:, None]   # outward (counter-clockwise)
        points = x[free.points]
        distances = (points[:, None, 0] - corners[None, :, 0]) * normals[None, :, 0] + \
            (points[:, None, 1] - corners[None, :, 1]) * normals[None, :, 1]
        inside = jnp.max(distances, axis=1) < 0.0
        distances = jnp.where(no_surface(body, corners, structure), -jnp.inf, distances)
        nearest = jnp.argmax(distances, axis=1)
        depth = jnp.max(distances, axis=1)
        normal = normals[nearest]
        moved = jnp.where(inside[:, None], points - depth[:, None] * normal, points)
        x = x.at[free.points].set(moved)
    return state.replace(particles=particles.replace(x=x))
