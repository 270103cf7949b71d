"""Runout of the granular column collapse against cell size, shape function and transfer.

    python benchmarks/column_collapse_study.py                        # the default table
    python benchmarks/column_collapse_study.py --shapes bspline2 --cells 0.01 0.005

Runs examples/column_collapse.toml (Bui et al. 2008; a = 0.5) with each combination and prints
a markdown table of the runout (L - L0) / L0 to the outermost point, and to where the final
deposit is still one cell and a tenth of the column's height thick (`front_where_thicker`),
the final height over the initial one and the wall time. Published scaling laws give 0.60-0.90 for this aspect ratio (Lube et al.
2005, Lajeunesse et al. 2005; docs/column_collapse.md). A study, not a test: the finest cells take minutes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

from plot_column_collapse import deposit_measures  # noqa: E402


def front_where_thicker(final, cell, thickness):
    """The largest x [m] of a cell-wide column of the deposit (final positions (N, 2), the
    base at y = 0) whose top stands at least `thickness` above the base."""
    import numpy as np

    columns = np.floor(final[:, 0] / cell).astype(int)
    tops = np.zeros(columns.max() + 1)
    np.maximum.at(tops, columns, final[:, 1])
    thick = np.nonzero(tops >= thickness)[0]
    return (thick.max() + 1) * cell if thick.size else 0.0


def run_case(shape: str, cell: float, transfer: str):
    """(runout / L0 to the outermost point, to one cell thick, to H0 / 10 thick, H_final / H0,
    wall seconds, points) of one run."""
    import jaxmpm

    scene = jaxmpm.load_scene(ROOT / "examples" / "column_collapse.toml")
    for key, value in [("grid.cell", cell), ("numerics.shape", shape), ("numerics.transfer", transfer),
                       ("scene.snapshot_fields", ["x"])]:
        scene = scene.with_value(key, value)
    start = time.perf_counter()
    result = jaxmpm.simulate(scene, progress=False)
    seconds = time.perf_counter() - start
    positions = result.snapshots[scene.bodies[0].name]["x"]
    spacing = cell / scene.numerics.ppc
    length0, height0, length, height = deposit_measures(positions[0], positions[-1], spacing)
    fronts = [front_where_thicker(positions[-1], cell, thickness) for thickness in (cell, height0 / 10.0)]
    return ((length - length0) / length0, *[(front - length0) / length0 for front in fronts], height / height0,
            seconds, positions.shape[1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["linear", "gimp", "bspline2"])
    parser.add_argument("--cells", nargs="+", type=float, default=[0.01, 0.005, 0.0025])
    parser.add_argument("--transfer", default="apic", choices=["apic", "flip"])
    arguments = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    print("runout / L0 to the outermost point / where the deposit is one cell thick / H0 / 10 thick")
    print(f"| shape | {' | '.join(f'cell {cell:g} m' for cell in arguments.cells)} |")
    print("|---|" + "---:|" * len(arguments.cells))
    for shape in arguments.shapes:
        cells = []
        for cell in arguments.cells:
            runout, one_cell, tenth, height, seconds, points = run_case(shape, cell, arguments.transfer)
            cells.append(f"{runout:.2f} / {one_cell:.2f} / {tenth:.2f} (H {height:.2f}; {points:,} points, "
                         f"{seconds:.0f} s)")
            print(f"  {shape} {cell:g}: runout {runout:.3f}, height {height:.3f}, {seconds:.0f} s",
                  file=sys.stderr, flush=True)
        print(f"| {shape} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
