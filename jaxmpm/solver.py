"""One explicit MPM step (paper eq. 3, M a = F - R), as a straight run of named phases.

    stencil   = shape functions of the points on the grid
    nodes     = particles_to_grid            mass, momentum, internal + external force
    velocity  = update_grid_velocity         local damping, M a = F, edge conditions
    particles = grid_to_particles            FLIP/PIC velocity blend, positions
    velocity  = remap_velocity (MUSL only)   nodal velocity from the updated points
    particles = update_stress                L = grad v, each body's material, volume

MUSL (Sulsky et al. 1994, "modified update stress last") is the default: the strain rate is
computed from nodal velocities re-projected from the updated points, so a node touched by a
point with a tiny weight cannot inject a huge velocity into the stress (the cell-crossing
weakness of USL). `update = "usl"` uses the grid velocity directly (one scatter fewer).

Transfers: FLIP/PIC blend (`flip` = 1 pure FLIP, 0 pure PIC), or APIC (Jiang et al. 2015):
points carry an affine velocity C_p; momentum goes to the grid as m_p N_I (v_p + C_p (x_I - x_p))
and comes back as v_p = sum N_I v_I, C_p = sum v_I (x) grad N_I (for multilinear shape functions
this is B_p D_p^-1 exactly; for gimp and bspline2 it is the velocity gradient, as in MLS-MPM,
not B_p D_p^-1). C_p is the velocity gradient that drives the stress: with MUSL it
comes from the re-mapped velocities, so nodes of tiny mass at a free surface (where f / m is
large while grad N is not small) cannot inject a huge affine velocity; the price is that
angular momentum is then kept only approximately (exactly with `update = "usl"` and linear
shape functions). APIC avoids
FLIP's noise and PIC's dissipation, and has no blend to tune.

`make_step(structure)` closes over the static structure and returns a pure
`step(params, particles) -> particles`; every physical value comes from `params`.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmpm.grid import (
    GridLayout, apply_edge_conditions, boundary_mask, fold_ghosts, gather_from_nodes, scatter_to_nodes, sum_over_stencil,
)
from jaxmpm.state import record_errors

MASS_FLOOR = 1e-10   # nodes lighter than this fraction of the heaviest point count as empty


@dataclasses.dataclass(frozen=True)
class BodyBlock:
    """A body's points occupy [start, stop); its material object supplies only static options."""

    name: str
    material_name: str
    material: object
    start: int
    stop: int


@dataclasses.dataclass(frozen=True)
class Structure:
    """Everything static about a scene: changing any field compiles a new step.

    layout: the grid; boundaries: edge conditions; gravity (2,) [m/s^2]; dt [s];
    transfer: "flip" | "apic"; flip: FLIP fraction of the velocity update (1 = FLIP, 0 = PIC),
    used with transfer = "flip"; damping: local (Cundall)
    damping coefficient; update: "musl" | "usl"; bodies: the contiguous body blocks.
    """

    layout: GridLayout
    boundaries: object
    gravity: tuple[float, float]
    dt: float
    transfer: str
    flip: float
    damping: float
    update: str
    bodies: tuple[BodyBlock, ...]


def point_momentum(particles, stencil, offsets):
    """Momentum each point gives its stencil nodes, (N, s, s, 2): m_p N_I v_p, plus the APIC
    affine part m_p N_I C_p (x_I - x_p) when `offsets` (x_I - x_p) are given."""
    weighted = particles.mass[:, None, None] * stencil.weights
    terms = [(weighted, particles.v)]
    if offsets is not None:
        affine = particles.affine
        terms += [(weighted * offsets[..., 0], affine[:, :, 0]), (weighted * offsets[..., 1], affine[:, :, 1])]
    return combine_on_stencil(terms)


def combine_on_stencil(terms):
    """sum_k a_k[p, I] b_k[p, :] for terms [(a_k (N, s, s), b_k (N, C))]: stencil values built
    by broadcast multiply-adds, which XLA:CPU vectorises (a concatenation along the channel
    axis of (N, s, s, C) arrays it does not)."""
    return sum(coefficient[..., None] * vector[:, None, None, :] for coefficient, vector in terms)


def particles_to_grid(particles, stencil, offsets, layout, boundaries, gravity):
    """Node mass m_I, momentum p_I and force f_I = sum_p (m_p N_I g - V_p sigma_p . grad N_I).

    Built as one (N, s, s, 5) array [m, p_x, p_y, f_x, f_y] for the single scatter."""
    weights, gradients = stencil.weights, stencil.gradients
    mass, velocity = particles.mass, particles.v
    zero = jnp.zeros_like(mass)
    gravity = jnp.asarray(gravity, mass.dtype)
    stress = -particles.volume[:, None, None] * particles.stress[:, :2, :2]     # -V_p sigma_p

    def channels(*columns):
        return jnp.stack(columns, axis=1)

    terms = [   # N_I [m, m v, m g] + dN_I/dx_j [0, 0, 0, -V sigma_xj, -V sigma_yj]
        (weights, channels(mass, mass * velocity[:, 0], mass * velocity[:, 1], mass * gravity[0], mass * gravity[1])),
        (gradients[..., 0], channels(zero, zero, zero, stress[:, 0, 0], stress[:, 1, 0])),
        (gradients[..., 1], channels(zero, zero, zero, stress[:, 0, 1], stress[:, 1, 1])),
    ]
    if offsets is not None:   # APIC: m_p N_I C_p (x_I - x_p) joins the momentum
        weighted, affine = mass[:, None, None] * weights, particles.affine
        for axis in range(2):
            terms.append((weighted * offsets[..., axis], channels(zero, affine[:, 0, axis], affine[:, 1, axis], zero, zero)))
    nodes = fold_ghosts(scatter_to_nodes(layout, stencil.base, combine_on_stencil(terms)), layout, boundaries)
    return nodes[..., 0], nodes[..., 1:3], nodes[..., 3:5]


def safe_velocity(momentum, mass, floor):
    """p / m on nodes with mass, 0 on empty nodes; finite value and gradient (double where)."""
    occupied = (mass > floor)[..., None]
    return jnp.where(occupied, momentum / jnp.where(occupied, mass[..., None], 1.0), 0.0)


def local_damping(force, velocity, coefficient):
    """Cundall's local damping: f - alpha |f| sign(v), componentwise at each node."""
    return force - coefficient * jnp.abs(force) * jnp.sign(velocity)


def update_grid_velocity(mass, momentum, force, dt, damping, constrain, floor):
    """Nodal velocities before and after the step, with the edge conditions applied."""
    velocity_old = constrain(safe_velocity(momentum, mass, floor))
    if damping:
        force = local_damping(force, velocity_old, damping)
    velocity_new = constrain(safe_velocity(momentum + dt * force, mass, floor))
    return velocity_old, velocity_new


def grid_to_particles(particles, stencil, velocity_old, velocity_new, transfer, flip, dt):
    """Points take the new grid velocity and move: x_p <- x_p + dt sum N_I v_I.

    FLIP/PIC: v_p <- flip (v_p + sum N_I dv_I) + (1 - flip) sum N_I v_I.
    APIC: v_p <- sum N_I v_I (its C_p is set with the velocity gradient, in `make_step`).
    """
    support = stencil.weights.shape[1]
    if transfer == "apic":
        flip = 0.0
    nodal = jnp.concatenate([velocity_new, velocity_new - velocity_old], axis=-1)
    at_points = sum_over_stencil(stencil.weights[..., None] * gather_from_nodes(stencil.base, nodal, support))
    grid_velocity, increment = at_points[:, :2], at_points[:, 2:]
    velocity = flip * (particles.v + increment) + (1.0 - flip) * grid_velocity
    return particles.replace(x=particles.x + dt * grid_velocity, v=velocity)


def remap_velocity(particles, stencil, layout, boundaries, mass, constrain, floor):
    """MUSL: nodal velocity sum_p m_p v_p N_I / m_I from the updated point velocities."""
    momentum = scatter_to_nodes(layout, stencil.base, point_momentum(particles, stencil, None))
    return constrain(safe_velocity(fold_ghosts(momentum, layout, boundaries, scalars=0), mass, floor))


def velocity_gradient(stencil, velocity):
    """L_p = sum_I v_I (x) grad N_I, embedded in 3x3 (plane strain: no out-of-plane rate)."""
    support = stencil.weights.shape[1]
    nodal = gather_from_nodes(stencil.base, velocity, support)
    in_plane = sum_over_stencil(nodal[..., :, None] * stencil.gradients[..., None, :])
    return jnp.pad(in_plane, ((0, 0), (0, 1), (0, 1)))


def update_stress(params, particles, gradient, bodies, dt):
    """Each body's material updates its own slice; volumes follow det(I + dt L)."""
    stresses, histories = [], []
    for block, history in zip(bodies, particles.history):
        points = slice(block.start, block.stop)
        update = jax.vmap(block.material.update, in_axes=(None, 0, 0, None, 0))
        stress, history = update(
            params[block.material_name], particles.stress[points], gradient[points], dt, history
        )
        stresses.append(stress)
        histories.append(history)
    # det(I + dt L) of the in-plane 2x2 block, written out (cheaper than an LU per point)
    stretch = (1.0 + dt * gradient[:, 0, 0]) * (1.0 + dt * gradient[:, 1, 1]) - dt * dt * gradient[:, 0, 1] * gradient[:, 1, 0]
    return particles.replace(
        stress=jnp.concatenate(stresses),
        history=tuple(histories),
        volume=particles.volume * stretch,
    )


def make_step(structure: Structure):
    """The pure step function of a scene: step(params, particles) -> particles."""
    layout, dt = structure.layout, structure.dt

    def step(params, particles):
        mask = boundary_mask(layout, structure.boundaries, particles.x.dtype)

        def constrain(velocity):
            return apply_edge_conditions(velocity, mask, layout, structure.boundaries)

        floor = MASS_FLOOR * jnp.max(particles.mass)
        stencil = jax.named_call(layout.stencil, name="shape_functions")(particles.x)
        offsets = None
        if structure.transfer == "apic":
            offsets = layout.node_offsets(stencil.base, particles.x, stencil.weights.shape[1])
        mass, momentum, force = jax.named_call(particles_to_grid, name="particles_to_grid")(
            particles, stencil, offsets, layout, structure.boundaries, structure.gravity
        )
        velocity_old, velocity_new = jax.named_call(update_grid_velocity, name="update_grid")(
            mass, momentum, force, dt, structure.damping, constrain, floor
        )
        particles = jax.named_call(grid_to_particles, name="grid_to_particles")(
            particles, stencil, velocity_old, velocity_new, structure.transfer, structure.flip, dt
        )
        if structure.update == "musl":
            velocity_new = jax.named_call(remap_velocity, name="remap_velocity")(
                particles, stencil, layout, structure.boundaries, mass, constrain, floor
            )
        gradient = velocity_gradient(stencil, velocity_new)
        if structure.transfer == "apic":
            particles = particles.replace(affine=gradient[:, :2, :2])
        particles = jax.named_call(update_stress, name="update_stress")(
            params, particles, gradient, structure.bodies, dt
        )
        return record_errors(particles, layout.outside(particles.x))

    return step
