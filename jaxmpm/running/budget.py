"""Memory a scene will need, estimated from its sizes before anything is allocated.

A scene whose points, grid or step count would not fit in this machine's memory is refused
with one sentence and the estimate, instead of failing in an allocation (or swapping for
hours). The estimate is an upper bound built from counts, not a measurement:
- the seeding lattice: every sub-cell of the grid, (cells ppc^2) x ~56 bytes;
- the points: N ~ the bodies' areas over the sub-cell area, each ~130 values (state,
  stencil weights and gradients, transfer and stress-update temporaries) of the dtype;
- the grid: (nx + 3)(ny + 3) nodes x velocity fields x ~16 values;
- the probe histories a run keeps: (steps + 1) x their components, twice (device and host).
"""

from __future__ import annotations

import math
import os

from jaxmpm.errors import SceneError
from jaxmpm.scene.parts import SCALAR_PROBE_KINDS

LATTICE_BYTES = 56          # per sub-cell: int64 indices (2), float64 positions (2), owner, flags
VALUES_PER_POINT = 130
VALUES_PER_NODE = 16
USABLE = 0.8                # of the memory the system reports available


def region_area(region) -> float:
    """Area of a rectangle or (shoelace) polygon [m^2]; absolute, so vertex order is free."""
    vertices = region.vertices
    twice = sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(vertices, vertices[1:] + vertices[:1]))
    return abs(twice) / 2.0


def estimate_bytes(scene, steps: int) -> dict:
    """{part: bytes} of the estimate (see the module docstring)."""
    itemsize = 4 if scene.numerics.dtype == "float32" else 8
    spacing = scene.grid.cell / scene.numerics.ppc
    nx, ny = scene.grid.cells
    subcells = float(nx) * ny * scene.numerics.ppc ** 2
    points = min(subcells, sum(1.05 * region_area(body.region) / spacing ** 2 + 64 for body in scene.bodies))
    fields = min(len(scene.bodies), 1 + len(scene.contacts) * 2 + sum(b.kinematics.type != "free" or b.kinematics.subcycled for b in scene.bodies))
    components = sum(1 if probe.kind in SCALAR_PROBE_KINDS else 2 for probe in scene.probes)
    return {
        "lattice": subcells * LATTICE_BYTES,
        "points": points * VALUES_PER_POINT * itemsize,
        "grid": float(nx + 3) * (ny + 3) * max(1, fields) * VALUES_PER_NODE * itemsize,
        "probes": 2.0 * (steps + 1) * components * itemsize + (steps + 1) * 8.0,
        "counts": (points, float(nx + 3) * (ny + 3), steps),
    }


def physical_bytes() -> float:
    """The machine's physical memory (inf where the system does not say)."""
    try:
        return float(os.sysconf("SC_PHYS_PAGES")) * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return math.inf


def available_bytes() -> float:
    """Memory the system reports available (Linux MemAvailable), else physical memory."""
    try:
        with open("/proc/meminfo") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return physical_bytes()


def check_memory(scene, steps: int, available: float | None = None):
    """SceneError, with the estimate, if the scene would need more than USABLE of the memory
    available; names the key to change (the grid's cell for points and grid, the duration
    for the probe histories)."""
    parts = estimate_bytes(scene, steps)
    points, nodes, steps = parts.pop("counts")
    need = sum(parts.values())
    have = available_bytes() if available is None else available
    if need <= USABLE * have:
        return
    largest = max(parts, key=parts.get)
    if largest == "probes":
        advice = f"scene.duration = {scene.duration:g} s gives {steps:.3g} steps: shorten it or raise scene.cfl"
    else:
        advice = (f"grid.cell = {scene.grid.cell:g} m gives {points:.3g} points and {nodes:.3g} grid nodes: "
                  "coarsen it, or shrink grid.size or the bodies")
    raise SceneError(
        f"the scene needs about {need / 1e9:.3g} GB, more than the {have / 1e9:.3g} GB this machine has "
        f"available: {advice}."
    )
