"""Filling bodies with material points: ppc x ppc points per cell on a lattice tied to the grid.

Points sit at the centres of the ppc x ppc sub-cells of every grid cell, so the points of
different bodies never coincide unless the bodies overlap. A point belongs to a body if its
sub-cell centre lies inside the body's region; each point carries the sub-cell's area
(h / ppc)^2 [m^3 per m of thickness in plane strain], or in axisymmetry the sub-cell's area
times its radius, r (h / ppc)^2 [m^3 per radian: the ring it stands for holds 2 pi times that].
"""

import dataclasses

import numpy as np
from matplotlib.path import Path

from jaxmpm.errors import SceneError
from jaxmpm.scene import Rectangle


@dataclasses.dataclass(frozen=True)
class Seeds:
    """positions: (N, 2) [m]; volumes: (N,); slices: (start, stop) of each body, in scene order."""

    positions: np.ndarray
    volumes: np.ndarray
    slices: tuple[tuple[int, int], ...]


def lattice(grid, ppc):
    """Integer lattice indices (M, 2) and positions (M, 2) of every sub-cell centre."""
    spacing = grid.cell / ppc
    counts = [cells * ppc for cells in grid.cells]
    i, j = np.meshgrid(np.arange(counts[0]), np.arange(counts[1]), indexing="ij")
    indices = np.stack([i.ravel(), j.ravel()], axis=1)
    positions = np.asarray(grid.origin) + (indices + 0.5) * spacing
    return indices, positions


def inside(region, positions):
    """(M,) bool: which positions lie in the region (boundary points of a rectangle count)."""
    if isinstance(region, Rectangle):
        lower, upper = np.asarray(region.lower), np.asarray(region.upper)
        return np.all((positions >= lower) & (positions <= upper), axis=1)
    return Path(np.asarray(region.vertices)).contains_points(positions)


def seed_bodies(scene) -> Seeds:
    """Points of every body, body after body; SceneError if a body is empty or bodies overlap."""
    indices, positions = lattice(scene.grid, scene.numerics.ppc)
    owner = np.full(len(positions), -1)
    chosen, slices, start = [], [], 0
    for number, body in enumerate(scene.bodies):
        members = inside(body.region, positions)
        if not members.any():
            raise SceneError(
                f"bodies[{number}] ({body.name!r}) holds no material point: its region is "
                f"smaller than a sub-cell of {scene.grid.cell / scene.numerics.ppc:g} m."
            )
        clash = members & (owner >= 0)
        if clash.any():
            other = scene.bodies[owner[clash][0]].name
            raise SceneError(
                f"bodies[{number}] ({body.name!r}) overlaps body {other!r} near "
                f"{positions[clash][0].round(6).tolist()}."
            )
        owner[members] = number
        chosen.append(np.flatnonzero(members))
        slices.append((start, start + len(chosen[-1])))
        start += len(chosen[-1])
    order = np.concatenate(chosen)
    volumes = np.full(len(order), (scene.grid.cell / scene.numerics.ppc) ** 2)
    if scene.geometry == "axisymmetric":
        volumes = volumes * positions[order, 0]
    return Seeds(positions[order], volumes, tuple(slices))


def padded(seeds: Seeds, multiple: int) -> Seeds:
    """`seeds` with inert points appended to the last body until their number is a multiple
    of `multiple` (particles sharded evenly over devices). Each sits on the last point with
    zero volume, hence zero mass: it gives the grid nothing (mass, momentum and stress all
    weigh by mass or volume), takes the grid's motion like a tracer, and the outputs leave it
    out (`Simulation.body_slices`)."""
    extra = -len(seeds.positions) % multiple
    if extra == 0:
        return seeds
    positions = np.concatenate([seeds.positions, np.repeat(seeds.positions[-1:], extra, axis=0)])
    volumes = np.concatenate([seeds.volumes, np.zeros(extra)])
    *rest, (start, stop) = seeds.slices
    return Seeds(positions, volumes, (*rest, (start, stop + extra)))
