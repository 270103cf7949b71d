"""Where the pile's heave goes as the cell is refined: the surface profile and the volume budget.

    python benchmarks/pile_heave_study.py                       # runs h and h/2 (about 15 minutes on 2 cores)
    python benchmarks/pile_heave_study.py --files H.h5 H2.h5    # reads runs of examples/pile_driving.toml
                                                                 # made with snapshot_fields including "volume"

examples/pile_driving.toml at its cell h and at h/2, at the end of the run (26 cm of
penetration): the sand surface's rise against the radius (the mean over the top row of
points in 2.5-cm bins of their present radius), the heave probe (the point nearest r = 2.5 R on
the surface), and where the pile's volume went: the volume of the surface's rise beyond the
pile (sum of r dz dr over the top row, per radian), the sand's own change of volume, and that
change beside the shaft (r < R + 2 cm above the tip), where the points are pulled apart
(non-dilatant sand, so any change of volume there is the stress-free sand spreading).
Writes docs/images/pile_heave_cells.png. A study, not a test.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
IMAGE = ROOT / "docs" / "images" / "pile_heave_cells.png"
PILE_RADIUS = 0.05
BIN = 0.025
FIELDS = ["x", "displacement", "stress", "plastic_strain", "volume", "mass"]


def run_example(cell_factor):
    """A Result of the pile example at its cell / cell_factor, with the point volumes kept."""
    import jaxmpm

    scene = jaxmpm.load_scene(ROOT / "examples" / "pile_driving.toml")
    scene = scene.with_value("grid.cell", scene.grid.cell / cell_factor).with_value("scene.snapshot_fields", FIELDS)
    return jaxmpm.Simulation(scene).run(progress=False)


def surface_and_budget(result):
    """(bin centres (B,), mean rise of the top row in each bin (B,) [m], {name: value})."""
    import jaxmpm

    sand = result.snapshots["sand"]
    start, end = np.asarray(sand["x"][0]), np.asarray(sand["x"][-1])
    before, after = np.asarray(sand["volume"][0]), np.asarray(sand["volume"][-1])
    rows = np.unique(start[:, 1])
    top = start[:, 1] > rows[-1] - 0.5 * (rows[-1] - rows[-2])
    spacing = rows[-1] - rows[-2]
    radius, rise = end[top, 0], end[top, 1] - start[top, 1]
    edges = np.arange(0.0, radius.max() + BIN, BIN)
    centres = 0.5 * (edges[1:] + edges[:-1])
    profile = np.array([rise[(radius >= a) & (radius < b)].mean() if np.any((radius >= a) & (radius < b)) else np.nan
                        for a, b in zip(edges[:-1], edges[1:])])
    penetration = -float(np.asarray(result.probes["penetration"])[-1, 1])
    tip = float(start[:, 1].max()) - penetration
    beside = (end[:, 0] < PILE_RADIUS + 0.02) & (end[:, 1] > tip)
    budget = {
        "cell": jaxmpm.Scene.from_toml(result.scene_toml).grid.cell,
        "heave probe [mm]": 1e3 * float(np.asarray(result.probes["heave"])[-1, 1]),
        "pile volume in the sand [m^3/rad]": 0.5 * PILE_RADIUS**2 * penetration,
        "surface rise beyond the pile [m^3/rad]": float(np.sum((radius * rise * spacing)[radius > PILE_RADIUS])),
        "sand's change of volume [m^3/rad]": float(np.sum(after - before)),
        "of it beside the shaft [m^3/rad]": float(np.sum((after - before)[beside])),
        "largest J beside the shaft": float(np.max(after[beside] / before[beside])),
    }
    return centres, profile, budget


def draw(profiles, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxmpm.pictures.plotting import save_png

    figure, axes = plt.subplots(figsize=(7, 3.6), layout="constrained")
    for (centres, profile, budget), style in zip(profiles, ("-o", "-s", "-^")):
        axes.plot(centres / PILE_RADIUS, 1e3 * profile, style, ms=3, label=f"cell {1e3 * budget['cell']:g} mm")
    axes.axvline(2.5, color="k", lw=0.8, ls=":", label="heave probe (r = 2.5 R)")
    axes.axhline(0.0, color="k", lw=0.5)
    axes.set_xlim(0.0, None)
    axes.set_ylim(-12.0, None)
    axes.set_xlabel("radius / pile radius R")
    axes.set_ylabel("surface rise at 26 cm [mm]")
    axes.set_title("pile_driving: the sand surface at the end, mean over 2.5-cm bins", fontsize=9)
    axes.legend(fontsize=8)
    save_png(figure, path)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", nargs="+", help="runs of the pile example to read, coarsest cell first")
    arguments = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxmpm

    results = ([jaxmpm.Result.load(path) for path in arguments.files] if arguments.files
               else [run_example(factor) for factor in (1, 2)])
    profiles = [surface_and_budget(result) for result in results]
    centres = profiles[0][0]
    print("| r / R | " + " | ".join(f"rise at cell {1e3 * budget['cell']:g} mm [mm]" for _, _, budget in profiles) + " |")
    print("|---:|" + "---:|" * len(profiles))
    for index, centre in enumerate(centres):
        print(f"| {centre / PILE_RADIUS:.2f} | " + " | ".join(f"{1e3 * profile[index]:.2f}" for _, profile, _ in profiles) + " |")
    print()
    print("| quantity | " + " | ".join(f"cell {1e3 * budget['cell']:g} mm" for _, _, budget in profiles) + " |")
    print("|---|" + "---:|" * len(profiles))
    for key in profiles[0][2]:
        if key != "cell":
            print(f"| {key} | " + " | ".join(f"{budget[key]:.4g}" for _, _, budget in profiles) + " |")
    draw(profiles, IMAGE)


if __name__ == "__main__":
    sys.exit(main())
