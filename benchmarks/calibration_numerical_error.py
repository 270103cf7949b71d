"""The numerical error of a calibration, measured on the wall twin: docs/calibration.md's table.

    python benchmarks/calibration_numerical_error.py [--relaxation 0 10] [--refinement dt|cell|relaxation|stress]
                                                     [--stress-substeps K]

The twin's observations (wall-top displacement, thrust; examples/calibrate_wall_scene.toml)
are made at fine numerics, the time step halved (cfl 0.2), noise-free, at the true values
(phi = 30 deg, gamma = 5 1/s, N = 2). The fit runs at the default numerics (cfl 0.4) from the
calibration study's start, with `numerical_check=("dt",)`. The fitted values' bias (fit -
truth) is then the numerical error a user inherits, and the check's predicted shift (what the
values would do at the refined numerics) should be minus that bias. A second fit to the same
observations with 2 % noise gives the noise standard errors to compare with. With
`--refinement relaxation` the observations are made at the relaxation doubled instead (the
time step as the fit's), and the check is `numerical_check=("relaxation",)`; with
`--refinement stress` at the stress substeps doubled (`numerical_check=("stress",)`); with
`--refinement cell` at half the cell (and the step its cfl gives there).
`--stress-substeps K` sets the fit's own substeps (default 1); `--structure-hold outline` runs
the fit and the observations under `numerics.structure_hold = "outline"`; `--shape linear` with linear
shape functions instead of the twin's quadratic B-splines. A study, not a test: about
10 minutes per relaxation on 2 cores at one substep.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


import inverse  # noqa: E402
import jaxmpm  # noqa: E402
from calibration_study import WALL_FIT, WALL_SCENE, WALL_START, WALL_TRUTH, wall_observations  # noqa: E402
from jaxmpm.running.refinement import refined_scene  # noqa: E402


def study(relaxation, refinement="dt", stress_substeps=1, structure_hold="mass", shape=None):
    scene = (jaxmpm.load_scene(WALL_SCENE).with_value("numerics.relaxation", relaxation)
             .with_value("numerics.stress_substeps", stress_substeps)
             .with_value("numerics.structure_hold", structure_hold))
    if shape is not None:
        scene = scene.with_value("numerics.shape", shape)
    coarse = jaxmpm.Simulation(scene)
    fine = jaxmpm.Simulation(refined_scene(scene, refinement))
    made = {"dt": f"{fine.steps} steps at cfl {scene.cfl / 2:g}", "cell": f"cell {fine.scene.grid.cell:g} m",
            "relaxation": f"relaxation {2 * relaxation:g}",
            "stress": f"{2 * stress_substeps} stress substeps"}[refinement]
    print(f"\n### relaxation = {relaxation:g}, {stress_substeps} stress substep(s), structure hold "
          f"{structure_hold!r}, shape {scene.numerics.shape!r}: {coarse.point_count} points, "
          f"{coarse.steps} steps at cfl {scene.cfl:g} (observations made at {made})\n")
    print(f"| parameter | truth | fit at cfl {scene.cfl:g}, relaxation {relaxation:g} | bias | predicted shift "
          f"({refinement} refined) | bias / noise standard error (2 %) |")
    print("|---|---|---|---|---|---|")
    started = time.perf_counter()
    fit = inverse.calibrate(coarse, wall_observations(fine, 0.0), WALL_FIT, starts=[WALL_START],
                            progress=False, numerical_check=(refinement,))
    noisy = inverse.calibrate(coarse, wall_observations(fine, 0.02), WALL_FIT, starts=[WALL_START], progress=False)
    shift = fit.numerical_shifts[refinement]
    for index, name in enumerate(fit.names):
        bias = fit.params[name] - WALL_TRUTH[name]
        print(f"| {name} | {WALL_TRUTH[name]:g} | {fit.params[name]:.4g} | {bias:+.3g} | {shift[index]:+.3g} | "
              f"{abs(bias) / noisy.stderr[name]:.2g} |")
    print(f"\n{fit.summary()}\n({time.perf_counter() - started:.0f} s for both fits)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--relaxation", type=float, nargs="+", default=[0.0, 10.0])
    parser.add_argument("--refinement", choices=("dt", "cell", "relaxation", "stress"), default="dt",
                        help="what the observations are made finer in (default: dt)")
    parser.add_argument("--stress-substeps", type=int, default=1, help="the fit's numerics.stress_substeps")
    parser.add_argument("--structure-hold", choices=("mass", "outline"), default="mass",
                        help="numerics.structure_hold of the fit and the observations (default: mass)")
    parser.add_argument("--shape", choices=("linear", "gimp", "bspline2"), default=None,
                        help="numerics.shape of the fit and the observations (default: the twin's, bspline2)")
    arguments = parser.parse_args()
    print(f"jaxmpm calibration numerical error, {time.strftime('%Y-%m-%d')}, {jax.devices()[0].device_kind}")
    for relaxation in arguments.relaxation:
        study(relaxation, arguments.refinement, arguments.stress_substeps, arguments.structure_hold, arguments.shape)
        sys.stdout.flush()


if __name__ == "__main__":
    main()
