"""One explicit MPM step (paper eq. 3, M a = F - R), as a straight run of named phases.

    stencil   = shape functions of the points on the grid
    nodes     = particles_to_grid            each field's mass, momentum, internal + external
                                             force (and mass gradient, with contact pairs)
    velocity  = update_grid_velocity         local damping, M a = F, edge conditions
    motions   = solve_rigid_motions          (rigid and subcycled bodies only) each one's velocity
                                             and spin, solved with the impulses the next phase
                                             applies (`bodies`)
    velocity  = apply_interfaces             (several fields only) prescribed and rigid
                                             fields take their motion; contact and bonding
                                             impulses between fields, in turn (`contact`);
                                             with structure_hold = "points" a structure's
                                             contact is its push on the soil's points and
                                             friction at their nodes (`point_contact`)
    particles = grid_to_particles            velocity (the points' own, fading, and the grid's),
                                             positions
    state     = move_kinematic_bodies        prescribed points move on their path, rigid
                                             bodies as one body; free points put back out of
                                             the bodies they contact (`bodies`)
    velocity  = remap_velocity (MUSL only)   nodal velocity from the updated points
    particles = update_stress                L = grad v, each free body's material, volume

A subcycled free body (a stiff structure, `subcycling`) takes its own n steps of dt / n alone
on the grid twice: before the rigid-body solve (`predict`: its motion if nothing touched it,
from which the solve starts, the body meeting its contacts as one) and after the contacts
(`correct`: again from the start, with the impulses it received); its points then take that
result in place of the step's update.

Bodies talk to the grid through velocity fields (node arrays carry a leading field axis):
bodies of a contact pair and prescribed or rigid bodies get one each, all others share one.
A scene with neither has one field and compiles exactly the single-field step.

MUSL (Sulsky et al. 1994, "modified update stress last") is the default: the strain rate is
computed from nodal velocities re-projected from the updated points, so a node touched by a
point with a tiny weight cannot inject a huge velocity into the stress (the cell-crossing
weakness of USL). `update = "usl"` uses the grid velocity directly (one scatter fewer).

Transfers: FLIP/PIC blend (`flip` = 1 pure FLIP, 0 pure PIC, per step), or APIC (Jiang et al.
2015): points carry an affine velocity C_p; momentum goes to the grid as m_p N_I (v_p + C_p
(x_I - x_p)) and comes back as sum N_I v_I, C_p = sum v_I (x) grad N_I (for multilinear shape
functions this is B_p D_p^-1 exactly; for gimp and bspline2 it is the velocity gradient, as in
MLS-MPM). C_p is the velocity gradient that drives the stress: with MUSL it comes from the
re-mapped velocities, so nodes of tiny mass at a free surface (where f / m is large while grad N
is not small) cannot inject a huge affine velocity.

Every grid-to-point transfer that replaces the points' velocity by the grid's filters it, and a
filter applied once per step dissipates in proportion to the number of steps: plain APIC (as
PIC) made results drift with dt (a wall's displacement halved with each halving of dt,
docs/convergence.md). So with APIC the points keep a memory of their own FLIP velocity that
fades over a fixed time tau, not a fixed number of steps (`transfer_memory`): the filtering
per unit time, and so the result, no longer depends on dt.

`make_step(structure)` closes over the static structure and returns a pure
`step(params, state) -> (state, diagnostics)`; every physical value comes from `params`
(namespaced: params["materials"], params["contacts"], params["bodies"], params["scene"]
(gravity), params["numerics"] (damping); `jaxmpm.scene.parameters`), the structure decides only which
code exists; the diagnostics are what probes read beyond the points (contact forces, reactions).
"""

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from jaxmpm.physics.bodies import (
    Grid, held_by_outline, held_structures, impose_body_motions, keep_points_outside, move_kinematic_bodies,
    node_positions, normal_cones, prescribed_outline_normals, received_impulses,
)
from jaxmpm.physics.contact import Interface, PointPush, apply_interfaces, normals_of, unit
from jaxmpm.physics.point_contact import pushed_interfaces, pushes
from jaxmpm.physics.subcycling import alone, correct, predict, put_back, subcycled_blocks
from jaxmpm.physics.grid import (
    GridLayout, apply_edge_conditions, boundary_mask, fold_ghosts, gather_from_nodes, per_unit_mass, scatter_to_nodes,
    sum_over_stencil,
)
from jaxmpm.materials.base import points_update_voigt
from jaxmpm.kernels.checkpoint_names import KEPT_GRID, KEPT_RATE
from jaxmpm.physics.state import Diagnostics, record_errors
from jaxmpm.tensors import components, entries, from_entries, stack_last

MASS_FLOOR = 1e-10   # nodes lighter than this fraction of the heaviest point count as empty
FACE_COSINE = math.sqrt(0.5)   # a face of a contact: normals within 45 degrees of its direction


@dataclasses.dataclass(frozen=True)
class BodyBlock:
    """A body's points occupy [start, stop) and talk to velocity field `field` of the grid.

    law: its material's static constitutive law (values come from params["materials"]
    [material_name]); kinematics: "free" | "prescribed" | "rigid"; times: the prescribed
    velocity table's times [s] (None: a constant velocity); outline: a prescribed or rigid
    body's region as convex polygon corners, counter-clockwise, at t = 0 (None: not convex, or a
    free body), and outline_centre the mean of its points then (`bodies.keep_points_outside`);
    a free elastic body whose outline bounds a contact's normal (`contact.Interface.bounded_by`)
    has its outline too, and reference_arms, its points' offsets from that mean at t = 0
    (`bodies.elastic_outline_now`);
    joined: its outline's edges that lie on another prescribed body moving with it
    (`bodies.joined_edges`; None: none), and partners the fields of those bodies: together
    they are one structure (a pile's tip and shaft), whose contacts take the normal of their
    union (`bodies.prescribed_outline_normals`);
    memory: the fraction of its own velocity update its points keep per step, where it differs
    from the scene's `Structure.memory` (`body_memory`); substeps: the steps a free body takes
    of its own within each step (> 1: subcycled, `subcycling`)."""

    name: str
    material_name: str
    law: object
    start: int
    stop: int
    field: int = 0
    kinematics: str = "free"
    times: tuple[float, ...] | None = None
    outline: tuple | None = None
    outline_centre: tuple[float, float] | None = None
    reference_arms: tuple | None = None
    joined: tuple[bool, ...] | None = None
    partners: tuple[int, ...] = ()
    memory: float | None = None
    substeps: int = 1

    @property
    def points(self):
        return slice(self.start, self.stop)

    @property
    def deforms_in_step(self):
        """Whether the step's own stress update moves it: a free body that is not subcycled."""
        return self.kinematics == "free" and self.substeps == 1


@dataclasses.dataclass(frozen=True)
class Structure:
    """Everything static about a scene: changing any field compiles a new step.

    layout: the grid; boundaries: edge conditions; dt [s];
    transfer: "flip" | "apic"; memory: the fraction of each point's own (FLIP) velocity update
    it keeps per step (`grid_to_particles`); damped: whether the step has local (Cundall)
    damping (its coefficient is params["numerics"]["damping"]); update:
    "musl" | "usl"; bodies: the contiguous body blocks; fields: number of velocity fields on
    the grid; interfaces: the pairs of fields that meet (`contact.Interface`); point_spacing:
    h / ppc [m] (a rigid body's points are squares of this side); axisymmetric: x is the
    radius r, y the axial z, and the hoop terms exist (masses, volumes and forces per radian);
    derivatives: which derivatives the step's programs take: "any" (plain JAX), "forward"
    (never reverse mode: the transfers may use kernels without one, `jaxmpm.kernels.scatter`;
    `Simulation.forward_only`) or "reverse" (never forward mode: kernels without one,
    `jaxmpm.kernels.transposes`; `Simulation.reverse_only`); damps: what local damping acts on,
    "motion" (the nodes' velocity) or "deformation" (their velocity relative to the body's mean,
    for a subcycled body alone on the grid: `local_damping`); corner_radius: in cells, the
    rounding of prescribed bodies' corners in their contact normal (`bodies.corner_radius`);
    stress_substeps: the updates of dt / stress_substeps each step's stress update of a free body
    that can yield is made of (`materials.base.points_update`); structure_hold: "mass" or
    "outline", the nodes at which a prescribed or rigid body holds the fields in contact with it
    (`bodies.held_by_outline`); facings: the (pair name, unit
    direction) whose face of the contact force the step reports (`facing_forces`).
    """

    layout: GridLayout
    boundaries: object
    dt: float
    transfer: str
    memory: float
    damped: bool
    update: str
    bodies: tuple[BodyBlock, ...]
    fields: int = 1
    interfaces: tuple[Interface, ...] = ()
    point_spacing: float = 0.0
    axisymmetric: bool = False
    derivatives: str = "any"
    damps: str = "motion"
    corner_radius: float = 1.0
    stress_substeps: int = 1
    structure_hold: str = "mass"
    facings: tuple[tuple[str, tuple[float, float]], ...] = ()

    @property
    def has_kinematic_bodies(self):
        return any(block.kinematics != "free" for block in self.bodies)

    @property
    def has_contact(self):
        return any(interface.contact is not None for interface in self.interfaces)

    def blocks_of(self, kinematics):
        return tuple(block for block in self.bodies if block.kinematics == kinematics)


def point_momentum(particles, stencil):
    """Momentum m_p N_I v_p each point gives its stencil nodes, (N, s, s, 2)."""
    weighted = particles.mass[:, None, None] * stencil.weights
    return stack_last([weighted * per_point(velocity) for velocity in components(particles.v)])


def per_point(values):
    """(N,) values broadcast against (N, s, s) stencil arrays."""
    return values[:, None, None]


class Nodes(NamedTuple):
    """Grid values of every velocity field: mass (F, nx, ny) [kg/m]; momentum, force
    (F, nx, ny, 2); mass_gradient (F, nx, ny, 2) sum_p m_p grad N_I(x_p), pointing out of the body [kg/m^2] (None without contact pairs)."""

    mass: jax.Array
    momentum: jax.Array
    force: jax.Array
    mass_gradient: jax.Array | None


def particles_to_grid(particles, stencil, offsets, field, structure, gravity, point_force=None):
    """Node mass m_I, momentum p_I, force f_I = sum_p (N_I (m_p g + f_p) - V_p sigma_p . grad N_I)
    (f_p: `point_force` (N, 2), None for none) and,
    with contact pairs, the mass gradient sum_p m_p grad N_I, each point into its own field.
    With APIC (`offsets`: x_I - x_p and y_I - y_p, (N, s, s) each) the momentum is
    m_p N_I (v_p + C_p (x_I - x_p)).

    Built as one (N, s, s, 5 or 7) array [m, p_x, p_y, f_x, f_y (, dm/dx, dm/dy)] for the
    single scatter, each channel written out (no products with zero channels). The point
    values are read as whole columns (`components`, `entries`), never indexed one by one."""
    mass, volume = particles.mass, particles.volume
    weighted = per_point(mass) * stencil.weights
    sigma_xx, sigma_yy, sigma_zz, sigma_xy = components(particles.stress_voigt)
    sigma = [[sigma_xx, sigma_xy], [sigma_xy, sigma_yy]]
    velocity = components(particles.v)
    affine = components(particles.affine.reshape(-1, 4)) if offsets is not None else None   # C_xx, C_xy, C_yx, C_yy
    external = [mass * gravity[0], mass * gravity[1]]
    if point_force is not None:
        external = [external[axis] + point_force[:, axis] for axis in range(2)]
    if structure.axisymmetric:   # the hoop stress pulls the ring inwards: -V_p sigma_tt N_I / r_p
        external[0] = external[0] - volume * sigma_zz / point_radius(particles.x, structure)
    momentum, force = [], []
    for axis in range(2):
        moving = per_point(velocity[axis])
        if offsets is not None:
            moving = moving + per_point(affine[2 * axis]) * offsets[0] + per_point(affine[2 * axis + 1]) * offsets[1]
        momentum.append(weighted * moving)
        # -V_p sigma_p . grad N_I
        force.append(stencil.weights * per_point(external[axis]) - stencil.gradients[0] * per_point(volume * sigma[axis][0])
                     - stencil.gradients[1] * per_point(volume * sigma[axis][1]))
    channels = [weighted, *momentum, *force]
    if structure.has_contact:
        channels += [per_point(mass) * stencil.gradients[0], per_point(mass) * stencil.gradients[1]]
    layout = structure.layout
    nodes = scatter_to_nodes(layout, stencil.base, stack_last(channels), field, structure.fields, structure.derivatives)
    mass_gradient = None
    if structure.has_contact:   # the mirror image of a mass gradient flips only its normal component (as at a slip edge)
        mirror = dataclasses.replace(structure.boundaries, **{
            edge: "slip" for edge, kind in dataclasses.asdict(structure.boundaries).items() if kind != "free"
        })
        mass_gradient = fold_ghosts(nodes[..., 5:7], layout, mirror, scalars=0)
    nodes = checkpoint_name(fold_ghosts(nodes[..., :5], layout, structure.boundaries), KEPT_GRID)
    return Nodes(nodes[..., 0], nodes[..., 1:3], nodes[..., 3:5], mass_gradient)


def point_radius(positions, structure):
    """(N,) radius r_p of each point [m], kept above 1e-3 of a point spacing so that 1 / r is
    finite (with its gradient) even for a point that reaches the axis."""
    return jnp.maximum(positions[:, 0], 1e-3 * structure.point_spacing)


def local_damping(force, velocity, coefficient):
    """Cundall's local damping: f - alpha |f| sign(v), componentwise at each node."""
    return force - coefficient * jnp.abs(force) * jnp.sign(velocity)


def deformation_damping(nodes, velocity, coefficient):
    """Cundall's local damping of a body's deformation only: f - alpha |f - m A| sign(v - V),
    with V = sum p / sum m and A = sum f / sum m the body's mean velocity and acceleration
    over the nodes. A subcycled body takes its support as a velocity change at the start of its
    substeps (`subcycling`), so its nodes are out of balance by m g all through them: damped
    on the plain force, it lost 10 % of its weight's momentum a step, which its contact then
    gave back (a block at rest read 1.098 times its weight)."""
    total = jnp.sum(nodes.mass)
    mean_velocity = jnp.sum(nodes.momentum, axis=(0, 1, 2)) / total
    mean_acceleration = jnp.sum(nodes.force, axis=(0, 1, 2)) / total
    unbalanced = nodes.force - nodes.mass[..., None] * mean_acceleration
    return nodes.force - coefficient * jnp.abs(unbalanced) * jnp.sign(velocity - mean_velocity)


def update_grid_velocity(nodes, dt, damping, constrain, floor, damps="motion"):
    """Nodal velocities before and after M a = F (trial: before any contact), with the edge
    conditions applied; `damping` the local damping coefficient (None: undamped, no code),
    acting on the motion or on the deformation only (`Structure.damps`)."""
    velocity_old = constrain(per_unit_mass(nodes.momentum, nodes.mass, floor))
    force = nodes.force
    if damping is not None and damps == "deformation":
        force = deformation_damping(nodes, velocity_old, damping)
    elif damping is not None:
        force = local_damping(force, velocity_old, damping)
    velocity_new = constrain(per_unit_mass(nodes.momentum + dt * force, nodes.mass, floor))
    return velocity_old, velocity_new


def grid_to_particles(particles, stencil, velocity_old, velocity_new, field, memory, dt, layout, derivatives="any"):
    """Points take the new grid velocity of their field and move: x_p <- x_p + dt sum N_I v_I.

    Their velocity keeps a fraction `memory` (static: a float, or (N, 1) per point) of their
    own FLIP update, the rest is the grid's: v_p <- sum N_I v_I + memory (v_p + sum N_I dv_I -
    sum N_I v_I). With transfer = "flip", memory = flip (per step); with "apic", memory =
    exp(-dt / tau) (see `transfer_memory`, `body_memory`), and C_p is set with the velocity
    gradient in `make_step`. derivatives: see `Structure`.
    """
    support = stencil.weights.shape[1]
    blend = bool(np.any(np.asarray(memory) > 0.0))     # static: without memory only v_I is gathered
    nodal = jnp.concatenate([velocity_new, velocity_new - velocity_old], axis=-1) if blend else velocity_new
    gathered = gather_from_nodes(layout, stencil.base, nodal, support, field, derivatives)
    at_points = sum_over_stencil(stencil.weights[..., None] * gathered, derivatives)
    grid_velocity = at_points[:, :2]
    velocity = grid_velocity
    if blend:
        velocity = grid_velocity + memory * (particles.v + at_points[:, 2:] - grid_velocity)
    return particles.replace(x=particles.x + dt * grid_velocity, v=velocity)


def remap_velocity(particles, stencil, field, structure, mass, constrain, floor):
    """MUSL: nodal velocity sum_p m_p v_p N_I / m_I of each field from the updated points."""
    layout = structure.layout
    momentum = scatter_to_nodes(layout, stencil.base, point_momentum(particles, stencil), field, structure.fields,
                                structure.derivatives)
    momentum = checkpoint_name(fold_ghosts(momentum, layout, structure.boundaries, scalars=0), KEPT_GRID)
    return constrain(per_unit_mass(momentum, mass, floor))


def velocity_gradient(stencil, velocity, field, structure, positions):
    """L_p = sum_I v_I (x) grad N_I in the point's field, embedded in 3x3: plane strain has no
    out-of-plane rate; in axisymmetry L_tt = v_r / r = sum_I N_I v_rI / r_p (the hoop rate,
    Sulsky & Schreyer 1996)."""
    support = stencil.weights.shape[1]
    nodal = gather_from_nodes(structure.layout, stencil.base, velocity, support, field, structure.derivatives)
    in_plane = [sum_over_stencil(nodal[..., row] * slope, structure.derivatives) for row in range(2) for slope in stencil.gradients]   # L_xx, L_xy, L_yx, L_yy
    zero = jnp.zeros_like(in_plane[0])
    hoop = zero
    if structure.axisymmetric:
        hoop = sum_over_stencil(stencil.weights * nodal[..., 0], structure.derivatives) / point_radius(positions, structure)
    if keeps_velocity_gradient(structure):
        in_plane = [checkpoint_name(rate, KEPT_RATE) for rate in in_plane]
        hoop = checkpoint_name(hoop, KEPT_RATE) if structure.axisymmetric else hoop
    return from_entries([in_plane[0], in_plane[1], zero, in_plane[2], in_plane[3], zero, zero, zero, hoop])


def keeps_velocity_gradient(structure):
    """Whether "recompute_grid" keeps the points' velocity gradients (KEPT_RATE): with 3 x 3
    stencils, whose recomputation reads 9 node velocities a point."""
    return structure.layout.shape.support == 3


def update_stress(params, particles, gradient, bodies, dt, axisymmetric=False, substeps=1):
    """Each run of free bodies of one material (`material_runs`) updates its points with the
    material's law, in `substeps` updates of dt / substeps if it can yield (`stress_substeps`);
    volumes follow det(I + dt L). Prescribed and rigid bodies keep their stress
    and volume, and so do subcycled ones here (their substeps update them)."""
    stresses, histories, stretches = [], [], []
    # det(I + dt L), written out (cheaper than an LU per point): the in-plane 2x2 block times
    # the hoop stretch 1 + dt L_tt (which is 1 in plane strain, where L_tt = 0)
    rate = entries(gradient)
    stretch = (1.0 + dt * rate[0]) * (1.0 + dt * rate[4]) - dt * dt * rate[1] * rate[3]
    if axisymmetric:
        stretch = stretch * (1.0 + dt * rate[8])
    for run in material_runs(bodies):
        first, last = bodies[run[0]], bodies[run[-1]]
        points = slice(first.start, last.stop)
        run_histories = [particles.history[index] for index in run]
        if not first.deforms_in_step:
            stresses.append(particles.stress_voigt[points])
            histories.extend(run_histories)
            stretches.append(jnp.ones_like(stretch[points]))
            continue
        update = points_update_voigt(first.law, dt, stress_substeps(first.law, substeps))
        stress, history = update(params[first.material_name], particles.stress_voigt[points], gradient[points],
                                 joined(run_histories))
        stresses.append(stress)
        histories.extend(split_at(history, [bodies[index].stop - first.start for index in run[:-1]]))
        stretches.append(stretch[points])
    if any(not block.deforms_in_step for block in bodies):
        stretch = jnp.concatenate(stretches)
    return particles.replace(
        stress_voigt=jnp.concatenate(stresses),
        history=tuple(histories),
        volume=particles.volume * stretch,
    )


def stress_substeps(law, substeps):
    """The updates a step's stress update of `law` is made of: `substeps` (numerics.stress_substeps)
    for a law that can yield, 1 for one that cannot (an elastic update is exact for any step's
    L; it gains nothing)."""
    return substeps if law.yields else 1


def material_runs(bodies):
    """The bodies' indices in runs: consecutive free bodies of one material share a run (one
    update of their points, so the law is compiled once for them, e.g. the wall twin
    example's foundation and backfill); any other body is a run of its own."""
    runs = []
    for index, block in enumerate(bodies):
        previous = bodies[index - 1] if index else None
        shared = (previous is not None and block.deforms_in_step and previous.deforms_in_step
                  and block.material_name == previous.material_name)
        if shared:
            runs[-1].append(index)
        else:
            runs.append([index])
    return runs


def joined(histories):
    """One history of the points of several bodies of one law (their arrays end to end)."""
    if len(histories) == 1:
        return histories[0]
    return jax.tree_util.tree_map(lambda *parts: jnp.concatenate(parts), *histories)


def split_at(history, cuts):
    """`joined` undone: the histories of the points before, between and after `cuts`."""
    if not cuts:
        return [history]
    leaves, tree = jax.tree_util.tree_flatten(history)
    pieces = [jnp.split(leaf, cuts) for leaf in leaves]
    return [tree.unflatten([piece[part] for piece in pieces]) for part in range(len(cuts) + 1)]


def kept_grid_bytes(structure, points, itemsize):
    """Bytes one step of `points` points keeps under "recompute_grid" beyond its state: the node
    arrays it names KEPT_GRID, each field's mass, momentum and force (5 values a node) and,
    with MUSL, its re-mapped momentum (2 more); and the velocity gradients it names KEPT_RATE
    (4 values a point, 5 in axisymmetry; `keeps_velocity_gradient`)."""
    values = 5 + (2 if structure.update == "musl" else 0)
    nodes = int(np.prod(structure.layout.nodes)) * structure.fields * values
    rates = points * (5 if structure.axisymmetric else 4) if keeps_velocity_gradient(structure) else 0
    return (nodes + rates) * itemsize


def kept_solve_bytes(structure, dtype):
    """Bytes of the values one step names KEPT_SOLVES: the roots of implicit equations a law
    solves at each point (`law.kept_solves_per_point`, e.g. the Perzyna root, once per stress substep), which a
    checkpointed step keeps for its reverse mode."""
    itemsize = np.dtype(dtype).itemsize
    return sum((block.stop - block.start) * block.law.kept_solves_per_point
               * stress_substeps(block.law, structure.stress_substeps) * itemsize
               for block in structure.bodies if block.kinematics == "free")


def contact_forces(structure, impulses, dt):
    """{pair name: (2,) force of the pair's first body on its second [N/m]} from the impulses
    of the contact interfaces (an interface's impulse J acts on its `first` field)."""
    return {
        interface.contact: -jnp.sum(impulse, axis=(0, 1)) / dt
        for interface, impulse in zip(structure.interfaces, impulses)
        if interface.contact is not None
    }


def facing_forces(structure, impulses, normals, dt):
    """{(pair name, (dx, dy)): (2,) force of the pair's first body on its second through the nodes
    whose contact normal n (first into second) has n . (dx, dy) >= cos 45 degrees [N/m]}, for
    each of `structure.facings`: one face of a body, e.g. a wall's back apart from its base."""
    by_contact = {interface.contact: (impulse, pushed_normal(interface, normal))
                  for interface, impulse, normal in zip(structure.interfaces, impulses, normals)
                  if interface.contact is not None}
    forces = {}
    for contact, (dx, dy) in structure.facings:
        impulse, normal = by_contact[contact]
        within = normal[..., 0] * dx + normal[..., 1] * dy >= FACE_COSINE
        forces[(contact, (dx, dy))] = -jnp.sum(jnp.where(within[..., None], impulse, 0.0), axis=(0, 1)) / dt
    return forces


def pushed_normal(interface, normal):
    """An interface's normal from its first field into its second (nx, ny, 2): as given, or
    from a contact at the points' normal impulse (`contact.PointPush`, on the free field)."""
    if not isinstance(normal, PointPush):
        return normal
    out_of_free = -unit(normal.impulse)
    return -out_of_free if interface.kinematic_first else out_of_free


def transfer_memory(transfer, flip, relaxation, dt, crossing_time):
    """The fraction of each point's own (FLIP) velocity it keeps per step: `flip` with
    transfer = "flip" (per step, as given); with "apic", exp(-dt / tau), tau = relaxation *
    crossing_time (the time the slowest free body's p-wave takes to cross a cell), so that
    the points' velocity relaxes towards the grid's (APIC) one over a fixed time whatever dt;
    0 (plain APIC) with relaxation = 0."""
    if transfer == "flip":
        return float(flip)
    if relaxation <= 0.0 or not math.isfinite(crossing_time):
        return 0.0
    return math.exp(-dt / (relaxation * crossing_time))


def body_memory(memory, law, transfer, relaxation):
    """A free body's transfer memory: the scene's `memory` (`transfer_memory`), except that with
    APIC and a relaxation (relaxation > 0) the points of a body that cannot yield (`law.yields`,
    e.g. an elastic structure) keep their own velocity (1). The relaxation damps the velocity
    noise of flowing soil; on an elastic body it would pull the points towards the APIC
    velocity, whose affine part comes from the re-mapped velocities and does not hold the
    rotation of a body a few cells thick (a stiff elastic wall lost 6 % of its motion against
    the rigid wall; docs/convergence.md)."""
    if transfer == "apic" and relaxation > 0.0 and not law.yields:
        return 1.0
    return memory


def point_memory(structure):
    """Each point's transfer memory: the scene's float when every body keeps it, else a static
    (N, 1) array of each body's (`BodyBlock.memory`)."""
    memories = [structure.memory if block.memory is None else block.memory for block in structure.bodies]
    if all(memory == structure.memory for memory in memories):
        return structure.memory
    return np.concatenate([np.full((block.stop - block.start, 1), memory)
                           for block, memory in zip(structure.bodies, memories)])


def contact_outlines(structure, state):
    """What the contact normals read of the bodies' outlines at the nodes (`contact.interface_normals`):
    {field: outward normals} of prescribed bodies, {field: NormalCone} of the outlines that
    bound a contact's normal; None when no interface asks for them."""
    pushed = pushed_interfaces(structure)      # contacts at the points take no normal (`point_contact`)
    on_grid = [interface for index, interface in enumerate(structure.interfaces) if index not in pushed]
    prescribed = any(interface.normal_from is not None for interface in on_grid)
    bounded = any(interface.bounded_by is not None for interface in on_grid)
    if not (prescribed or bounded):
        return None
    positions = node_positions(structure.layout, state.particles.x.dtype)
    return {**(prescribed_outline_normals(structure, state, positions) if prescribed else {}),
            **(normal_cones(structure, state, positions) if bounded else {})}


def make_step(structure: Structure):
    """The pure step function of a scene: step(params, state) -> (state, diagnostics)."""
    layout, dt = structure.layout, structure.dt
    memory = point_memory(structure)
    fields = None
    if structure.fields > 1:   # each point's velocity field, a compile-time constant
        fields = np.concatenate([np.full(b.stop - b.start, b.field, np.int32) for b in structure.bodies])

    subcycled = subcycled_blocks(structure)
    steps_alone = {block.name: make_step(alone(structure, block)) for _, block in subcycled}

    def step(params, state, external=None):
        """`external`: (N, 2) forces on the points besides their weight [N/m] (a subcycled
        body's share of its contact impulses, `subcycling`), None for none."""
        field = None if fields is None else jnp.asarray(fields)
        particles = state.particles
        mask = boundary_mask(layout, structure.boundaries, particles.x.dtype)

        def constrain(velocity):
            return apply_edge_conditions(velocity, mask, layout, structure.boundaries)

        floor = MASS_FLOOR * jnp.max(particles.mass)
        stencil = jax.named_call(layout.stencil, name="shape_functions")(particles.x)
        offsets = None
        if structure.transfer == "apic":
            offsets = layout.node_offsets(stencil.base, particles.x, stencil.weights.shape[1])
        frictions = {name: values["friction"] for name, values in params.get("contacts", {}).items()}
        gravity = params["scene"]["gravity"]
        damping = params["numerics"]["damping"] if structure.damped else None
        nodes = jax.named_call(particles_to_grid, name="particles_to_grid")(
            particles, stencil, offsets, field, structure, gravity, external
        )
        velocity_old, velocity_new = jax.named_call(update_grid_velocity, name="update_grid")(
            nodes, dt, damping, constrain, floor, structure.damps
        )
        time_new = (state.step + 1).astype(particles.x.dtype) * dt
        prediction = predict(steps_alone, params, particles, structure, subcycled)
        occupied = nodes.mass > floor
        if structure.structure_hold == "outline" and held_structures(structure):
            occupied = held_by_outline(structure, state, occupied)
        grid = Grid(nodes.mass, velocity_new, nodes.mass_gradient, occupied)
        normals = normals_of(structure.interfaces, nodes.mass, nodes.mass_gradient, contact_outlines(structure, state),
                             pushes(params, state, structure, stencil))
        velocity_new, motions = impose_body_motions(params, state, structure, grid, frictions, time_new, normals,
                                                    prediction.motions)
        impulses = []
        if structure.interfaces:
            velocity_new, impulses = jax.named_call(apply_interfaces, name="contact")(
                structure.interfaces, nodes.mass, velocity_new, normals, frictions, occupied
            )
            velocity_new = constrain(velocity_new)
        ended = correct(steps_alone, params, structure, subcycled, prediction, motions,
                        received_impulses(structure.interfaces, impulses), nodes.mass, floor)
        start = particles.x
        particles = jax.named_call(grid_to_particles, name="grid_to_particles")(
            particles, stencil, velocity_old, velocity_new, field, memory, dt, layout, structure.derivatives
        )
        state, reactions = move_kinematic_bodies(state.replace(particles=particles), start, structure, motions, impulses,
                                                 gravity)
        state = keep_points_outside(state, structure)
        particles = state.particles
        if structure.update == "musl":
            velocity_new = jax.named_call(remap_velocity, name="remap_velocity")(
                particles, stencil, field, structure, nodes.mass, constrain, floor
            )
        gradient = velocity_gradient(stencil, velocity_new, field, structure, start)
        if structure.transfer == "apic":   # C_p = the in-plane block of L_p, from its entries (no pads in reverse mode)
            rate = entries(gradient)
            affine = stack_last([rate[0], rate[1], rate[3], rate[4]]).reshape(-1, 2, 2)
            particles = particles.replace(affine=affine)
        particles = jax.named_call(update_stress, name="update_stress")(
            params["materials"], particles, gradient, structure.bodies, dt, structure.axisymmetric,
            structure.stress_substeps
        )
        for index, block in subcycled:
            particles = put_back(particles, index, block, ended[block.name])
        state = record_errors(state.replace(particles=particles), layout.outside(particles.x))
        return state, Diagnostics(contact_forces(structure, impulses, dt), reactions,
                                  facing_forces(structure, impulses, normals, dt))

    return step
