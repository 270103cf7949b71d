"""Convergence in the time step, drawn: the figures of docs/convergence.md.

    python benchmarks/convergence_figures.py            # runs (about 30 minutes on 2 cores), then draws
    python benchmarks/convergence_figures.py --report   # draws from benchmarks/results/convergence_histories.npz
    python benchmarks/convergence_figures.py --examples column_collapse   # runs one again, keeps the others

Each example over its whole run at cfl 0.4 (shipped), 0.2 and 0.1 with the shipped
relaxation kappa, and at cfl 0.4 and 0.2 with plain APIC (kappa = 0), for contrast:

- retaining_wall: the wall's rotation against time;
- pile_driving: the head force (tip and shaft reactions, the pile's 180 N weight included) averaged
  within half a cell of every centimetre of penetration from 2 to 26 cm;
- column_collapse: the front's displacement (the `corner` probe, x) against time, and the
  deposit's surface at 1 s.

Left column: the quantity. Right column: each run's difference from the run at half its step,
against that run's value (%), with the +-1 % band: first-order convergence shows as each curve
half the one before. Histories are kept in benchmarks/results/convergence_histories.npz;
figures go to docs/images/convergence_dt.png and docs/images/convergence_deposit.png.
A study, not a test.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HISTORIES = ROOT / "benchmarks" / "results" / "convergence_histories.npz"
IMAGES = ROOT / "docs" / "images"
SHIPPED_CFLS = (0.4, 0.2, 0.1)
PLAIN_CFLS = (0.4, 0.2)
EXAMPLES = ("retaining_wall", "pile_driving", "column_collapse")
PILE_CENTIMETRES = np.arange(2, 27) / 100.0
sys.path.insert(0, str(ROOT / "benchmarks"))

from convergence_study import pile_force_every_cm  # noqa: E402


KEPT_SAMPLES = 1000      # a history is kept at about this many times (every step is 10^4 of them)


def quantity(name, result):
    """(abscissa, values) of an example's headline quantity from its Result."""
    t, probes = np.asarray(result.time), {k: np.asarray(v) for k, v in result.probes.items()}
    if name == "pile_driving":
        return PILE_CENTIMETRES, pile_force_every_cm(t, probes, PILE_CENTIMETRES)
    every = max(1, len(t) // KEPT_SAMPLES)
    if name == "retaining_wall":
        return t[::every], np.degrees(probes["rotation"][::every, 0])
    return t[::every], probes["corner"][::every, 0]


def deposit_surface(positions, width):
    """(x bin centres, highest point y) of the points (N, 2) in bins `width` wide (a cell, so
    that every bin holds a column of points)."""
    bins = np.floor(positions[:, 0] / width).astype(int)
    top = np.full(bins.max() + 1, np.nan)
    np.fmax.at(top, bins, positions[:, 1])
    return (np.arange(top.size) + 0.5) * width, top


def run_all(names=EXAMPLES, kept=None):
    """{key: array} of every run's quantity (and the column's final surface), added to `kept`
    and saved to HISTORIES after each run, so that a study stopped part-way keeps its runs."""
    import jaxmpm

    kept = {} if kept is None else kept
    for name in names:
        shipped = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml")
        for relaxation, cfls in ((shipped.numerics.relaxation, SHIPPED_CFLS), (0.0, PLAIN_CFLS)):
            for cfl in cfls:
                scene = shipped.with_value("scene.cfl", cfl).with_value("numerics.relaxation", relaxation)
                started = time.perf_counter()
                try:
                    result = jaxmpm.Simulation(scene).run(progress=False)
                except jaxmpm.SimulationError as error:
                    print(f"{name} kappa {relaxation:g} cfl {cfl}: {error}", flush=True)
                    result = error.result
                key = f"{name}/kappa{relaxation:g}/cfl{cfl}"
                kept[key + "/x"], kept[key + "/y"] = quantity(name, result)
                if name == "column_collapse":
                    body = scene.bodies[0].name
                    kept[key + "/surface_x"], kept[key + "/surface_y"] = deposit_surface(
                        np.asarray(result.snapshots[body]["x"][-1]), scene.grid.cell)
                print(f"{key}: {time.perf_counter() - started:.0f} s", flush=True)
                save_histories(kept)
    return kept


def save_histories(kept):
    """Write the histories to HISTORIES through a temporary file (a stopped run leaves the
    previous file whole)."""
    HISTORIES.parent.mkdir(parents=True, exist_ok=True)
    partial = HISTORIES.with_suffix(".partial.npz")
    np.savez(partial, **kept)
    partial.replace(HISTORIES)


LABELS = {"retaining_wall": ("time [s]", "wall rotation [°]", 1.0),
          "pile_driving": ("penetration [cm]", "head force [N]", 100.0),
          "column_collapse": ("time [s]", "front's displacement x [mm]", 1.0)}


def differences(x_coarse, coarse, x_fine, fine):
    """(x, 100 (coarse - fine) / fine) at the coarse run's abscissae, outputs where |fine| is
    under a tenth of its largest left out (a value near zero reads as a huge relative change)."""
    fine_there = np.interp(x_coarse, x_fine, fine)
    kept = np.abs(fine_there) >= 0.1 * np.nanmax(np.abs(fine))
    return x_coarse[kept], 100.0 * (coarse[kept] - fine_there[kept]) / fine_there[kept]


def draw(kept):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(len(EXAMPLES), 2, figsize=(11, 3.2 * len(EXAMPLES)))
    for row, name in zip(axes, EXAMPLES):
        xlabel, ylabel, scale = LABELS[name]
        factor = 1e3 if name == "column_collapse" else 1.0
        shipped = sorted({key.split("/")[1] for key in kept if key.startswith(name) and key.split("/")[1] != "kappa0"})
        largest = 0.0
        for kappa, style in [(k, "-") for k in shipped] + [("kappa0", "--")]:
            cfls = SHIPPED_CFLS if kappa != "kappa0" else PLAIN_CFLS
            label = "plain APIC" if kappa == "kappa0" else f"κ = {kappa[5:]}"
            runs = [(cfl, kept[f"{name}/{kappa}/cfl{cfl}/x"], kept[f"{name}/{kappa}/cfl{cfl}/y"]) for cfl in cfls]
            shades = ("C0", "C1", "C2") if kappa != "kappa0" else ("0.3", "0.6")
            width = 1.2 if kappa != "kappa0" else 0.8
            for (cfl, x, y), shade in zip(runs, shades):
                row[0].plot(scale * x, factor * y, style, color=shade, lw=width, label=f"{label}, cfl {cfl}")
            for (cfl, x, y), (_, x_fine, y_fine), shade in zip(runs, runs[1:], shades):
                at, change = differences(x, y, x_fine, y_fine)
                largest = max(largest, float(np.nanmax(np.abs(change))))
                row[1].plot(scale * at, change, style, color=shade, lw=width, label=f"{label}: cfl {cfl} against {cfl / 2:g}")
        row[1].axhspan(-1.0, 1.0, color="0.9", zorder=0, label="±1 %")
        limit = min(20.0, max(3.0, 1.15 * largest))
        row[1].set_ylim(-limit, limit)
        for axis in row:
            axis.set_xlabel(xlabel)
            axis.grid(alpha=0.3)
        row[0].set_ylabel(ylabel)
        row[1].set_ylabel("change per halving of Δt [%]")
        row[0].set_title(name, loc="left", fontsize=10)
        row[0].legend(fontsize=7)
        row[1].legend(fontsize=7)
    figure.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    figure.savefig(IMAGES / "convergence_dt.png", dpi=110)
    print(f"wrote {IMAGES / 'convergence_dt.png'}")

    figure, axis = plt.subplots(figsize=(9, 3.0))
    kappa = next(key.split("/")[1] for key in kept if key.startswith("column_collapse/") and key.split("/")[1] != "kappa0")
    for cfl, shade in zip(SHIPPED_CFLS, ("C0", "C1", "C2")):
        axis.plot(1e3 * kept[f"column_collapse/{kappa}/cfl{cfl}/surface_x"], 1e3 * kept[f"column_collapse/{kappa}/cfl{cfl}/surface_y"],
                  color=shade, lw=1.2, label=f"κ = {kappa[5:]}, cfl {cfl}")
    for cfl, shade in zip(PLAIN_CFLS, ("0.3", "0.6")):
        axis.plot(1e3 * kept[f"column_collapse/kappa0/cfl{cfl}/surface_x"], 1e3 * kept[f"column_collapse/kappa0/cfl{cfl}/surface_y"],
                  "--", color=shade, lw=0.8, label=f"plain APIC, cfl {cfl}")
    axis.set_xlabel("x [mm]")
    axis.set_ylabel("highest point at 1 s [mm]")
    axis.set_aspect("equal")
    axis.legend(fontsize=7)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(IMAGES / "convergence_deposit.png", dpi=110)
    print(f"wrote {IMAGES / 'convergence_deposit.png'}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="draw from the kept histories, no runs")
    parser.add_argument("--examples", nargs="+", choices=EXAMPLES, default=EXAMPLES,
                        help="run only these again; the kept histories of the others are drawn")
    arguments = parser.parse_args()
    kept = dict(np.load(HISTORIES)) if HISTORIES.exists() else {}
    if not arguments.report:
        import jax

        jax.config.update("jax_enable_x64", True)
        print(f"jaxmpm convergence figures, {time.strftime('%Y-%m-%d')}, {jax.devices()[0].device_kind}, "
              f"{__import__('os').cpu_count()} cores", flush=True)
        kept = {key: value for key, value in kept.items() if key.split("/")[0] not in arguments.examples}
        kept = run_all(arguments.examples, kept)
    draw(kept)


if __name__ == "__main__":
    main()
