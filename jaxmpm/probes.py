"""Probes: quantities recorded at every step, as functions of the state (SPEC section 8).

`make_probes(scene, seeds)` resolves each probe's target once, at setup (the nearest point,
the body's slice), and returns observe(particles, initial_x) -> {name: (k,) array}.
"""

import numpy as np
import jax.numpy as jnp


def nearest_point(seeds, at):
    """Index of the material point nearest to `at` at t = 0."""
    return int(np.argmin(np.sum((seeds.positions - np.asarray(at)) ** 2, axis=1)))


def make_probes(scene, seeds):
    readers = {}
    body_slices = {body.name: seeds.slices[index] for index, body in enumerate(scene.bodies)}
    for probe in scene.probes:
        if probe.kind == "displacement":
            readers[probe.name] = _point_displacement(nearest_point(seeds, probe.at))
        elif probe.kind == "body_displacement":
            readers[probe.name] = _body_displacement(*body_slices[probe.body])
        elif probe.kind == "body_rotation":
            readers[probe.name] = _body_rotation(*body_slices[probe.body])
        else:
            raise AssertionError(probe.kind)

    def observe(particles, initial_x):
        return {name: read(particles, initial_x) for name, read in readers.items()}

    return observe


def _point_displacement(index):
    def read(particles, initial_x):
        return particles.x[index] - initial_x[index]

    return read


def _body_displacement(start, stop):
    def read(particles, initial_x):
        mass = particles.mass[start:stop]
        moved = particles.x[start:stop] - initial_x[start:stop]
        # A dot, not jnp.sum(mass[:, None] * moved, axis=0): XLA:CPU runs that reduction slowly.
        return jnp.dot(mass, moved) / jnp.sum(mass)

    return read


def _body_rotation(start, stop):
    """Angle of the rotation that best maps the body's initial shape onto its current one
    (least squares, mass-weighted, about the centres of mass): atan2(sum m r0 x r, sum m r0 . r),
    counter-clockwise positive [rad], in (-pi, pi]."""

    def read(particles, initial_x):
        mass = particles.mass[start:stop]
        weights = mass / jnp.sum(mass)
        now = particles.x[start:stop] - jnp.dot(weights, particles.x[start:stop])
        before = initial_x[start:stop] - jnp.dot(weights, initial_x[start:stop])
        cross = jnp.dot(mass, before[:, 0] * now[:, 1] - before[:, 1] * now[:, 0])
        dot = jnp.dot(mass, before[:, 0] * now[:, 0] + before[:, 1] * now[:, 1])
        degenerate = (cross == 0.0) & (dot == 0.0)          # a one-point body: no rotation
        return jnp.arctan2(cross, jnp.where(degenerate, 1.0, dot))[None]

    return read
