"""Are the design's predicted standard errors those a calibration achieves? (docs/experiment_design.md)

    python benchmarks/design_study.py [--seeds 30] [--noise 2e-5] [--no-write]

The scene is examples/calibrate_twin_scene.toml made small and elastic (cell 0.05 m, 0.2 s,
the sand linear elastic; as the elastic twin of tests/test_inverse.py): a heavy footing
dropped on a layer, observed through its settlement and a surface point every 0.01 s with
Gaussian noise of sigma [m]. inverse.design predicts the standard errors of the layer's
Young's modulus and Poisson's ratio at the truth; then, for each seed, the twin's noise-free
histories plus noise are calibrated (Levenberg–Marquardt from 30 % away), and the spread of the
fitted values over the seeds is set beside the prediction (ratio = empirical / predicted; its
sampling uncertainty with n seeds is about 1 / sqrt(2 (n - 1))). A study, not a test: it
prints a markdown table and writes it into docs/experiment_design.md (between
<!-- design_study:begin --> and <!-- design_study:end -->; --no-write to print only).
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import inverse  # noqa: E402
import jaxmpm  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "experiment_design.md"
TRUTH = {"sand.young": 2.0e6, "sand.poisson": 0.3}
BOUNDS = {"sand.young": (0.5e6, 8.0e6), "sand.poisson": (0.1, 0.45)}
START = {"sand.young": 2.6e6, "sand.poisson": 0.39}          # 30 % away
OBSERVED = {"footing": [1], "surface": [0, 1]}


def elastic_twin_scene():
    """The calibration twin, coarse and elastic (its plastic keys dropped)."""
    text = (ROOT / "examples" / "calibrate_twin_scene.toml").read_text()
    plastic = ("friction_angle", "cone", "fluidity", "exponent")
    lines = [line for line in text.splitlines() if not line.startswith(plastic)]
    text = "\n".join(lines).replace('model = "drucker_prager"', 'model = "linear_elastic"')
    for old, new in (('k0 = "jaky"', "k0 = 0.43"), ("cell = 0.025", "cell = 0.05"), ("duration = 0.3", "duration = 0.2")):
        assert old in text, old
        text = text.replace(old, new)
    return jaxmpm.Scene.from_toml(text)


def plan(noise):
    """{probe: plan} of inverse.planned_observations: the observed components every 0.01 s."""
    return {name: {"every": 0.01, "noise": noise, "components": components} for name, components in OBSERVED.items()}


def noisy_observations(sim, planned, truth_probes, noise, seed):
    """The planned channels filled with the truth's histories plus N(0, noise^2)."""
    rng = np.random.default_rng(seed)
    data = {}
    for name, channel in planned.channels.items():
        clean = np.stack([np.interp(channel.times, sim.time, truth_probes[name][:, k]) for k in channel.components], axis=1)
        data[name] = (channel.times, clean + noise * rng.standard_normal(clean.shape), channel.components)
    return inverse.Observations.from_arrays(data, sigma={name: noise for name in data})


def study(seeds, noise):
    sim = jaxmpm.Simulation(elastic_twin_scene())
    planned = inverse.planned_observations(sim, plan(noise))
    started = time.monotonic()
    prediction = inverse.design(inverse.Experiment(sim, planned, name="twin"), TRUTH).information()
    design_seconds = time.monotonic() - started
    truth_probes = {name: np.asarray(values) for name, values in sim.probes().items()}
    fitted, reported, seconds = [], [], []
    for seed in range(seeds):
        tick = time.monotonic()
        fit = inverse.calibrate(sim, noisy_observations(sim, planned, truth_probes, noise, seed),
                                fit={name: {"low": low, "high": high, "start": START[name]} for name, (low, high) in BOUNDS.items()},
                                max_iterations=40, progress=False)
        fitted.append(fit.values)
        reported.append([fit.stderr[name] for name in fit.names])
        seconds.append(time.monotonic() - tick)
        print(f"seed {seed}: {dict(zip(fit.names, fit.values))} ({seconds[-1]:.1f} s, {fit.reasons[fit.best_start]})")
    fitted, reported = np.array(fitted), np.array(reported)
    empirical = fitted.std(axis=0, ddof=1)
    rows = ["| parameter | truth | predicted standard error | empirical spread (std over seeds) | ratio | "
            "mean fitted − truth | calibration's own standard error (mean) |", "|---|---|---|---|---|---|---|"]
    for index, name in enumerate(prediction.names):
        rows.append(f"| `{name}` | {TRUTH[name]:g} | {prediction.stderr[index]:.4g} | {empirical[index]:.4g} | "
                    f"{empirical[index] / prediction.stderr[index]:.2f} | {fitted[:, index].mean() - TRUTH[name]:+.3g} | "
                    f"{reported[:, index].mean():.4g} |")
    machine = f"{platform.machine()}, {len(jax.devices())} {jax.default_backend()} device(s), jax {jax.__version__}"
    notes = (f"{seeds} noise seeds, sigma = {noise:g} m on {sum(len(c) for c in OBSERVED.values())} components every "
             f"0.01 s ({planned.count} values); predicted correlation {prediction.correlation[0, 1]:+.3f}, empirical "
             f"{np.corrcoef(fitted.T)[0, 1]:+.3f}. The design took {design_seconds:.1f} s (with compiling), a "
             f"calibration {np.median(seconds):.1f} s (median). Measured {datetime.date.today()} on {machine}; "
             f"the ratio's sampling uncertainty is about ±{1 / np.sqrt(2 * (seeds - 1)):.2f}.")
    return "\n".join(rows) + "\n\n" + notes + "\n"


def write_section(text, name="design_study"):
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    page = DOC.read_text()
    start, stop = page.index(begin) + len(begin), page.index(end)
    DOC.write_text(page[:start] + "\n" + text + page[stop:])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=30)
    parser.add_argument("--noise", type=float, default=2e-5, help="noise sigma [m]")
    parser.add_argument("--no-write", action="store_true")
    arguments = parser.parse_args()
    table = study(arguments.seeds, arguments.noise)
    print(table)
    if not arguments.no_write:
        write_section(table)
        print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
