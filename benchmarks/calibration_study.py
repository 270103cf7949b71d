"""Calibration on large-deformation twins: the figures of docs/calibration.md.

    python benchmarks/calibration_study.py                  # every study (about an hour on 2 cores)
    python benchmarks/calibration_study.py --only heap_noise

- heap_optimizers: the heap twin (examples/calibrate_heap_scene.toml, a viscoplastic column
  slumping several cells), noise-free, from a start 30 % away: Levenberg–Marquardt with
  quadratic B-splines and with linear shape functions; heap_lbfgs: L-BFGS with B-splines;
- smoothness: on the heap, the forward-mode derivative of the observed residuals against
  central secants of relative step 1e-6 ... 1e-2, per shape function;
- heap_noise: the heap twin with Gaussian noise of 2 % of each component's peak, ten seeds:
  is the truth inside the reported 2 sigma?
- rates: the footing pushed at one and at two rates (examples/calibrate_rates_scene.toml):
  the correlation of fluidity and exponent, and the recovered values;
- wall: a rigid retaining wall released against a viscoplastic backfill (examples/
  calibrate_wall_scene.toml), fitted to the wall top's displacement and the thrust, noise-free
  and with 2 % noise; wall_variants: the same with L-BFGS and with linear shape functions;
- pile: a pile pushed into viscoplastic sand at one and at two rates (examples/
  calibrate_pile_scene.toml, axisymmetric), fitted to the driving force.
A study, not a test: it prints markdown tables and writes each into its section of
docs/calibration.md (between <!-- NAME:begin --> and <!-- NAME:end -->; --no-write to print only).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "calibration.md"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import calibrate_heap as heap  # noqa: E402
import calibrate_rates as rates  # noqa: E402
import inverse  # noqa: E402
import jaxmpm  # noqa: E402
from contact_study import Table  # noqa: E402
from common import machine_info, write_section  # noqa: E402

WALL_SCENE = ROOT / "examples" / "calibrate_wall_scene.toml"
WALL_TRUTH = {"sand.friction_angle": 30.0, "sand.fluidity": 5.0, "sand.exponent": 2.0}
WALL_START = {"sand.friction_angle": 39.0, "sand.fluidity": 3.5, "sand.exponent": 2.6}
WALL_FIT = {"sand.friction_angle": (15.0, 45.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
WALL_OBSERVED = (("wall_top", [0, 1]), ("thrust", [0]))


def machine_line():
    info = machine_info()
    return (f"Measured {time.strftime('%Y-%m-%d')} on {info.get('cpu', 'this machine')} "
            f"({info.get('cores', '?')} cores), JAX {jax.__version__}, float64.")


def section(table, title):
    """A study's heading and the machine it ran on."""
    table(f"### {title}")
    table()
    table(machine_line())
    table()


def recovery_rows(table, label, fit, truth, *, first=True):
    errors = {name: fit.params[name] - truth[name] for name in fit.names}
    cost = fit.cost
    cells = []
    for name in fit.names:
        relative = errors[name] / truth[name]
        shown = f"{errors[name]:+.2g}°" if name.endswith("friction_angle") else f"{relative:+.2%}"
        cells.append(f"{fit.params[name]:.4f} ± {fit.stderr[name]:.2g} ({shown})")
    table(f"| {label} | {' | '.join(cells)} | {fit.iterations} | {fit.evaluations} | "
          f"{cost['wall_time']:.0f} ({cost['first_iteration']:.0f}) | {cost['seconds_per_iteration']:.1f} | "
          f"{cost['peak_memory_mb']:.0f} | {fit.reasons[fit.best_start]} |")


def recovery_header(table, names):
    table(f"| case | {' | '.join(names)} | iterations | simulations | wall s (first it.) | s / it. | peak MB | stopped |")
    table("|---|" + "---|" * (len(names) + 6))


def heap_optimizers(table, cases=(("LM, bspline2", "lm", "bspline2"), ("LM, linear", "lm", "linear"))):
    section(table, "Heap twin, noise-free, start 30 % away")
    recovery_header(table, ["φ [°]", "γ [1/s]", "N"])
    for label, optimizer, shape in cases:
        sim = heap.heap_simulation(shape)
        observations = heap.twin_observations(sim, 0.0)
        fit = inverse.calibrate(sim, observations, heap.FIT, starts=[heap.START], optimizer=optimizer,
                                max_iterations=50, progress=False)
        recovery_rows(table, label, fit, heap.TRUTH)
    table()
    table("Simulations: for LM one forward pass carrying 3 tangents; for L-BFGS one forward and one "
          "reverse pass (line-search evaluations included). The first iteration's time includes compiling. "
          "The linear-shape data are the linear-shape scene's own (a twin of itself), so the optimum is the truth there too.")


def heap_lbfgs(table):
    heap_optimizers(table, cases=(("L-BFGS, bspline2", "lbfgs", "bspline2"),))


def smoothness(table):
    section(table, "How smooth is the heap's misfit? Forward-mode derivative against central secants")
    table("| shape | parameter | 1e-6 | 1e-5 | 1e-4 | 1e-3 | 1e-2 |")
    table("|---|---|---|---|---|---|---|")
    for shape in ("linear", "gimp", "bspline2"):
        sim = heap.heap_simulation(shape)
        observations = heap.twin_observations(sim, 0.0)
        experiment = inverse.experiments.experiments_from(sim, observations)[0]
        space = inverse.ParameterSpace(sim.params, heap.FIT)
        residuals = inverse.experiments.residual_function(sim, experiment.observations, space.insert)
        data = inverse.experiments.observation_data(sim, experiment.observations)
        base = sim.cast(sim.params)
        function = jax.jit(lambda values: residuals(values, data, base))
        point = jnp.array([heap.START[name] for name in heap.FIT])
        jacobian = np.asarray(jax.jit(jax.jacfwd(function))(point))
        for index, name in enumerate(heap.FIT):
            cells = []
            for relative in (1e-6, 1e-5, 1e-4, 1e-3, 1e-2):
                step = relative * float(point[index])
                secant = (np.asarray(function(point.at[index].add(step))) -
                          np.asarray(function(point.at[index].add(-step)))) / (2 * step)
                cells.append(f"{np.linalg.norm(secant - jacobian[:, index]) / np.linalg.norm(jacobian[:, index]):.1e}")
            table(f"| {shape} | {name.split('.')[1]} | {' | '.join(cells)} |")
    table()
    table("Each entry: ‖secant − J e_k‖ / ‖J e_k‖ over all observed residuals, at the start point "
          "(φ 26°, γ 3.5, N 2.6), for a central secant of the given relative step.")


def heap_noise(table, seeds=10, noise=0.02):
    section(table, f"Heap twin, {noise:.0%} noise, {seeds} seeds (LM, bspline2, start 30 % away)")
    table("| seed | φ [°] | γ [1/s] | N | error / σ (φ, γ, N) | all inside 2σ | iterations | wall s |")
    table("|---|---|---|---|---|---|---|---|")
    sim = heap.heap_simulation("bspline2")
    inside_count = 0
    for seed in range(seeds):
        observations = heap.twin_observations(sim, noise, seed=seed)
        fit = inverse.calibrate(sim, observations, heap.FIT, starts=[heap.START], max_iterations=50, progress=False)
        ratios = [abs(fit.params[n] - heap.TRUTH[n]) / fit.stderr[n] for n in fit.names]
        inside = all(r < 2.0 for r in ratios)
        inside_count += inside
        cells = [f"{fit.params[n]:.4f} ± {fit.stderr[n]:.2g}" for n in fit.names]
        table(f"| {seed} | {' | '.join(cells)} | {', '.join(f'{r:.2f}' for r in ratios)} | "
              f"{'yes' if inside else 'no'} | {fit.iterations} | {fit.wall_time:.0f} |")
    table()
    table(f"The truth is inside the reported 2σ of every parameter in {inside_count} of {seeds} repeats.")


def rate_study(table, noise=0.02):
    section(table, f"One rate against two: the footing pushed into viscoplastic sand ({noise:.0%} noise)")
    recovery_header(table, ["φ [°]", "γ [1/s]", "N"])
    sim = jaxmpm.Simulation(jaxmpm.load_scene(rates.SCENE))
    both = rates.experiments(sim, noise)
    correlations = {}
    for label, chosen, optimizer in (("0.02 m/s alone, LM", both[:1], "lm"), ("0.1 m/s alone, LM", both[1:], "lm"),
                                     ("both rates, LM", both, "lm"), ("both rates, L-BFGS", both, "lbfgs")):
        fit = inverse.calibrate(chosen, fit=rates.FIT, starts=[rates.START], optimizer=optimizer,
                                max_iterations=50, progress=False)
        recovery_rows(table, label, fit, rates.TRUTH)
        gamma, exponent = fit.names.index("sand.fluidity"), fit.names.index("sand.exponent")
        correlations[label] = fit.correlation[gamma, exponent]
    table()
    table("Correlation of fluidity and exponent: " +
          ", ".join(f"{label} {value:+.3f}" for label, value in correlations.items()) + ".")


def wall_observations(sim, noise, seed=0, every=0.01):
    """Wall-top displacement and the thrust averaged over 0.01 s (its `window`), every 0.01 s
    after the start, plus Gaussian noise of `noise` x each component's peak."""
    probes = sim.probes()
    stride = max(1, int(round(every / sim.dt)))
    rng = np.random.default_rng(seed)
    windows = {"thrust": 0.01}
    data, sigma = {}, {}
    for name, components in WALL_OBSERVED:
        width = inverse.experiments.window_steps(windows.get(name, 0.0), sim.dt)
        history = np.asarray(inverse.experiments.window_mean(probes[name], width))
        values = history[::stride][1:, components]
        scale = noise * np.max(np.abs(values), axis=0)
        data[name] = (sim.time[::stride][1:], values + scale * rng.standard_normal(values.shape), components)
        sigma[name] = scale
    return inverse.Observations.from_arrays(data, sigma=sigma if noise > 0 else None, window=windows)


def wall(table):
    section(table, "Retaining wall twin: wall-top displacement and thrust")
    sim = jaxmpm.Simulation(jaxmpm.load_scene(WALL_SCENE))
    table(f"{sim.point_count} points, {sim.steps} steps.")
    table()
    recovery_header(table, ["φ [°]", "γ [1/s]", "N"])
    for label, noise in (("LM, bspline2, noise-free", 0.0), ("LM, bspline2, 2 % noise", 0.02)):
        fit = inverse.calibrate(sim, wall_observations(sim, noise), WALL_FIT, starts=[WALL_START],
                                max_iterations=50, progress=False)
        recovery_rows(table, label, fit, WALL_TRUTH)


def wall_variants(table):
    section(table, "Retaining-wall twin, noise-free: the other optimiser and shape function")
    recovery_header(table, ["φ [°]", "γ [1/s]", "N"])
    for label, optimizer, shape, iterations in (("LM, linear", "lm", "linear", 40),
                                                ("L-BFGS, bspline2", "lbfgs", "bspline2", 20)):
        scene = jaxmpm.load_scene(WALL_SCENE).with_value("numerics.shape", shape)
        sim = jaxmpm.Simulation(scene)
        fit = inverse.calibrate(sim, wall_observations(sim, 0.0), WALL_FIT, starts=[WALL_START],
                                optimizer=optimizer, max_iterations=iterations, progress=False)
        recovery_rows(table, label, fit, WALL_TRUTH)
    table()
    table("L-BFGS is stopped after 20 iterations here (each costs a forward and a reverse pass and its "
          "line search more): the budget Levenberg–Marquardt needs for the whole fit.")


PILE_SCENE = ROOT / "examples" / "calibrate_pile_scene.toml"
PILE_RATES = {"slow": [0.0, -0.25], "fast": [0.0, -0.5]}
PILE_TRUTH = {"sand.friction_angle": 30.0, "sand.fluidity": 10.0, "sand.exponent": 1.0}
PILE_START = {"sand.friction_angle": 39.0, "sand.fluidity": 7.0, "sand.exponent": 1.3}
PILE_FIT = {"sand.friction_angle": (15.0, 45.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (0.5, 5.0)}


def pile_experiments(sim, noise, seed=0, every=0.01, window=0.1):
    """The pile's driving force (axial, whole ring) averaged over `window` seconds, every `every`
    seconds, at each of PILE_RATES, plus Gaussian noise of `noise` x its peak."""
    experiments = []
    width = inverse.experiments.window_steps(window, sim.dt)
    stride = max(1, int(round(every / sim.dt)))
    for index, (name, velocity) in enumerate(PILE_RATES.items()):
        params = jaxmpm.with_values(sim.params, {"bodies.pile.velocity": np.asarray(velocity)})
        history = np.asarray(inverse.experiments.window_mean(sim.probes(params)["force"], width))
        values = history[::stride][1:, [1]]
        scale = noise * np.max(np.abs(values), axis=0)
        noisy = values + scale * np.random.default_rng(seed + index).standard_normal(values.shape)
        observations = inverse.Observations.from_arrays({"force": (sim.time[::stride][1:], noisy, [1])},
                                                        sigma={"force": scale} if noise > 0 else None,
                                                        window={"force": window})
        experiments.append(inverse.Experiment(sim, observations, set={"bodies.pile.velocity": velocity}, name=name))
    return experiments


def pile(table):
    section(table, "Pile twin: the driving force at two rates (axisymmetric, contact)")
    sim = jaxmpm.Simulation(jaxmpm.load_scene(PILE_SCENE))
    table(f"{sim.point_count} points, {sim.steps} steps; the force observed as its mean over 0.1 s, every 0.01 s.")
    table()
    recovery_header(table, ["φ [°]", "γ [1/s]", "N"])
    correlations = {}
    for label, noise, chosen in (("0.5 m/s alone, noise-free", 0.0, slice(1, 2)),
                                 ("0.25 and 0.5 m/s, noise-free", 0.0, slice(0, 2)),
                                 ("0.5 m/s alone, 2 % noise", 0.02, slice(1, 2)),
                                 ("0.25 and 0.5 m/s, 2 % noise", 0.02, slice(0, 2))):
        experiments = pile_experiments(sim, noise)[chosen]
        fit = inverse.calibrate(experiments, fit=PILE_FIT, starts=[PILE_START], max_iterations=50, progress=False)
        recovery_rows(table, label, fit, PILE_TRUTH)
        gamma, exponent = fit.names.index("sand.fluidity"), fit.names.index("sand.exponent")
        correlations[label] = fit.correlation[gamma, exponent]
    table()
    table("Correlation of fluidity and exponent: " +
          ", ".join(f"{label} {value:+.3f}" for label, value in correlations.items()) + ".")


STUDIES = {"heap_optimizers": heap_optimizers, "heap_lbfgs": heap_lbfgs, "smoothness": smoothness, "heap_noise": heap_noise,
           "rates": rate_study, "wall": wall, "wall_variants": wall_variants, "pile": pile}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=list(STUDIES), action="append")
    parser.add_argument("--no-write", action="store_true")
    arguments = parser.parse_args()
    for name in arguments.only or list(STUDIES):
        table = Table()
        STUDIES[name](table)
        if not arguments.no_write:
            write_section(f"<!-- {name}:begin -->", f"<!-- {name}:end -->", table.text(), DOC)


if __name__ == "__main__":
    main()
