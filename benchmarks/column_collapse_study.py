"""Runout of the granular column collapse against cell size, shape function and transfer.

    python benchmarks/column_collapse_study.py                        # the default table
    python benchmarks/column_collapse_study.py --shapes bspline2 --cells 0.01 0.005

Runs examples/column_collapse.toml (Bui et al. 2008; a = 0.5) with each combination and prints
a markdown table of the runout (L - L0) / L0, the final height over the initial one and the
wall time. Published scaling laws give 0.60-0.90 for this aspect ratio (Lube et al.
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


def run_case(shape: str, cell: float, transfer: str):
    """(runout / L0, H_final / H0, wall seconds, points) of one run."""
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
    return (length - length0) / length0, height / height0, seconds, positions.shape[1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["linear", "gimp", "bspline2"])
    parser.add_argument("--cells", nargs="+", type=float, default=[0.01, 0.005, 0.0025])
    parser.add_argument("--transfer", default="apic", choices=["apic", "flip"])
    arguments = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"| shape | {' | '.join(f'cell {cell:g} m' for cell in arguments.cells)} |")
    print("|---|" + "---:|" * len(arguments.cells))
    for shape in arguments.shapes:
        cells = []
        for cell in arguments.cells:
            runout, height, seconds, points = run_case(shape, cell, arguments.transfer)
            cells.append(f"{runout:.2f} (H {height:.2f}; {points:,} points, {seconds:.0f} s)")
            print(f"  {shape} {cell:g}: runout {runout:.3f}, height {height:.3f}, {seconds:.0f} s",
                  file=sys.stderr, flush=True)
        print(f"| {shape} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
