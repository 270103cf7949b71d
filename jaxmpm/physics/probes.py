"""Probes: quantities recorded at every step, read from the state and the step's diagnostics.

`make_probes(scene, seeds)` resolves each probe's target once, at setup (the nearest point,
the body's slice, the contact pair), and returns
observe(state, diagnostics, initial_x) -> {name: (k,) array}. Every probe is differentiable.

    displacement       (2,) of the point nearest `at` at t = 0 [m]
    body_displacement  (2,) mass-weighted mean displacement of a body [m]
    body_rotation      (1,) best-fit rotation of a body about its centre of mass [rad]
    peak_speed         (1,) largest speed of a body's points [m/s]
    contact_force      (2,) force of the pair's first body on its second through their
                       contact, in the step that ended at this time [N per m of thickness];
                       with `facing`, through one face only (`facing_key`)
    reaction           (2,) force that kept a prescribed body on its path in that step [N/m]

In axisymmetry forces are whole-ring newtons, 2 pi times the per-radian force the grid holds:
the z component is the ring's net axial force; the r component is its total outward radial
force (2 pi times the radial force per radian), a measure of the radial push, not a net
force (that is zero by symmetry).
"""

import math

import numpy as np
import jax.numpy as jnp

FULL_TURN = 2.0 * math.pi


def nearest_point(seeds, at):
    """Index of the material point nearest to `at` at t = 0."""
    return int(np.argmin(np.sum((seeds.positions - np.asarray(at)) ** 2, axis=1)))


def facing_key(probe, contact):
    """(pair name, unit direction) of a `contact_force` probe with a `facing`, the direction
    written for the declared pair's order (reversed when the probe names the pair the other way
    round, since the normal from its first body into its second is then the opposite one)."""
    length = math.hypot(*probe.facing)
    sign = 1.0 if tuple(probe.pair) == contact.pair else -1.0
    return contact.name, (sign * probe.facing[0] / length, sign * probe.facing[1] / length)


def contact_facings(scene):
    """The (pair name, unit direction) faces that the scene's probes read, each once, in order."""
    declared = {frozenset(contact.pair): contact for contact in scene.contacts}
    keys = [facing_key(probe, declared[frozenset(probe.pair)])
            for probe in scene.probes if probe.kind == "contact_force" and probe.facing is not None]
    return tuple(dict.fromkeys(keys))


def make_probes(scene, seeds):
    readers = {}
    body_slices = {body.name: seeds.slices[index] for index, body in enumerate(scene.bodies)}
    declared = {frozenset(contact.pair): contact for contact in scene.contacts}
    ring = FULL_TURN if scene.geometry == "axisymmetric" else 1.0       # forces per radian -> whole ring
    for probe in scene.probes:
        if probe.kind == "contact_force":
            contact = declared[frozenset(probe.pair)]
            sign = ring if tuple(probe.pair) == contact.pair else -ring
            if probe.facing is None:
                readers[probe.name] = _contact_force(contact.name, sign)
            else:
                readers[probe.name] = _facing_force(facing_key(probe, contact), sign)
        elif probe.kind == "reaction":
            readers[probe.name] = _reaction(probe.body, ring)
        elif probe.kind == "displacement":
            readers[probe.name] = _point_displacement(nearest_point(seeds, probe.at))
        elif probe.kind == "body_displacement":
            readers[probe.name] = _body_displacement(*body_slices[probe.body])
        elif probe.kind == "body_rotation":
            readers[probe.name] = _body_rotation(*body_slices[probe.body])
        elif probe.kind == "peak_speed":
            readers[probe.name] = _peak_speed(*body_slices[probe.body])
        else:
            raise AssertionError(probe.kind)

    def observe(state, diagnostics, initial_x):
        return {name: read(state, diagnostics, initial_x) for name, read in readers.items()}

    return observe


def _contact_force(pair, sign):
    def read(state, diagnostics, initial_x):
        return sign * diagnostics.contact_force[pair]

    return read


def _facing_force(key, sign):
    def read(state, diagnostics, initial_x):
        return sign * diagnostics.facing_force[key]

    return read


def _reaction(body, scale):
    def read(state, diagnostics, initial_x):
        return scale * diagnostics.reaction[body]

    return read


def _point_displacement(index):
    def read(state, diagnostics, initial_x):
        return state.particles.x[index] - initial_x[index]

    return read


def _body_displacement(start, stop):
    def read(state, diagnostics, initial_x):
        particles = state.particles
        mass = particles.mass[start:stop]
        moved = particles.x[start:stop] - initial_x[start:stop]
        # A dot, not jnp.sum(mass[:, None] * moved, axis=0): XLA:CPU runs that reduction slowly.
        return jnp.dot(mass, moved) / jnp.sum(mass)

    return read


def _body_rotation(start, stop):
    """Angle of the rotation that best maps the body's initial shape onto its current one
    (least squares, mass-weighted, about the centres of mass): atan2(sum m r0 x r, sum m r0 . r),
    counter-clockwise positive [rad], in (-pi, pi]."""

    def read(state, diagnostics, initial_x):
        particles = state.particles
        mass = particles.mass[start:stop]
        weights = mass / jnp.sum(mass)
        now = particles.x[start:stop] - jnp.dot(weights, particles.x[start:stop])
        before = initial_x[start:stop] - jnp.dot(weights, initial_x[start:stop])
        cross = jnp.dot(mass, before[:, 0] * now[:, 1] - before[:, 1] * now[:, 0])
        dot = jnp.dot(mass, before[:, 0] * now[:, 0] + before[:, 1] * now[:, 1])
        degenerate = (cross == 0.0) & (dot == 0.0)          # a one-point body: no rotation
        return jnp.arctan2(cross, jnp.where(degenerate, 1.0, dot))[None]

    return read


def _peak_speed(start, stop):
    """max_p |v_p| over the body's points [m/s]: one point thrown about by a numerical event
    shows here while mean displacements and forces hardly move. Its square root is taken of
    the largest |v|^2, guarded at zero (a body at rest)."""

    def read(state, diagnostics, initial_x):
        v = state.particles.v[start:stop]
        largest = jnp.max(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1])
        positive = largest > 0.0
        return jnp.where(positive, jnp.sqrt(jnp.where(positive, largest, 1.0)), 0.0)[None]

    return read
