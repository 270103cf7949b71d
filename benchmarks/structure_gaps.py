"""How close the sand stays to the structures of the examples, and whether any sand point ends
inside one: the pile of examples/pile_driving.toml after 10 cm of penetration, and the wall of
examples/retaining_wall.toml after 1 s.

    python benchmarks/structure_gaps.py

Gaps are between the points' extents (a point is a square of side h / ppc about its
position): beside the pile, from the shaft's face to the nearest sand point along the embedded
length; under the tip, from the tip's underside to the highest sand point below it (negative:
the point's square reaches into the tip while its centre stays outside, which is all that
`bodies.keep_points_outside` asks); at the wall, the least distance between a sand point and a
wall point less one spacing. A study, not a test: it prints a markdown table.
"""

import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def pile_gaps():
    """(side gap, tip gap, sand points inside the pile, cell) after 0.2 s (10 cm)."""
    import jaxmpm

    scene = jaxmpm.load_scene(ROOT / "examples" / "pile_driving.toml").with_value("scene.duration", 0.2)
    sim = jaxmpm.Simulation(scene)
    x = np.asarray(sim.final_state().particles.x)
    parts = {body.name: x[slice(*span)] for body, span in zip(scene.bodies, sim.body_slices)}
    cell, half = scene.grid.cell, 0.5 * scene.grid.cell / scene.numerics.ppc
    pile = np.concatenate([parts["shaft"], parts["tip"]])
    face, bottom = pile[:, 0].max() + half, pile[:, 1].min() - half
    sand = parts["sand"]
    beside = sand[(sand[:, 1] > bottom + cell) & (sand[:, 1] < 0.7)]
    below = sand[(sand[:, 0] < face - half) & (sand[:, 1] < bottom + cell)]
    depth = 1e-9     # points put back on the surface sit on it to round-off
    inside = np.sum((sand[:, 0] < face - depth) & (sand[:, 1] > bottom + depth) & (sand[:, 1] < pile[:, 1].max() + half))
    return (beside[:, 0] - half).min() - face, bottom - (below[:, 1] + half).max(), int(inside), cell


def wall_gap():
    """(least gap between sand and wall, cell) after the example's 1 s."""
    import jaxmpm
    from scipy.spatial import cKDTree

    scene = jaxmpm.load_scene(ROOT / "examples" / "retaining_wall.toml")
    sim = jaxmpm.Simulation(scene)
    x = np.asarray(sim.final_state().particles.x)
    parts = {body.name: x[slice(*span)] for body, span in zip(scene.bodies, sim.body_slices)}
    spacing = scene.grid.cell / scene.numerics.ppc
    distance, _ = cKDTree(parts["wall"]).query(parts["sand"])
    return distance.min() - spacing, scene.grid.cell


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"jaxmpm structure gaps, {time.strftime('%Y-%m-%d')}, {__import__('os').cpu_count()} cores\n")
    print("| example | where | gap [mm] | gap / cell | sand points inside |")
    print("|---|---|---|---|---|")
    side, tip, inside, cell = pile_gaps()
    print(f"| pile_driving, 10 cm | beside the shaft | {1e3 * side:.2f} | {side / cell:.2f} | {inside} |")
    print(f"| pile_driving, 10 cm | under the tip | {1e3 * tip:.2f} | {tip / cell:.2f} | |")
    gap, cell = wall_gap()
    print(f"| retaining_wall, 1 s | sand against the wall | {1e3 * gap:.2f} | {gap / cell:.2f} | |")


if __name__ == "__main__":
    main()
