"""How the twin calibration degrades with noise: recovered values, errors and standard errors.

    python examples/calibrate_noise_study.py [--levels 0 1e-5 3e-5 1e-4] [--max-iterations 40]

For each noise level (std in metres; the footing settles about 1.2 mm), make noisy twin data
(examples/calibrate_twin.py), calibrate from the same wrong guess, and print one table row per
parameter: recovered value, error against the truth, standard error, and iterations.
"""

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import inverse  # noqa: E402
import jaxmpm  # noqa: E402
from calibrate_twin import FIT, WRONG_GUESS, twin_observations  # noqa: E402

HERE = Path(__file__).parent


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", type=float, nargs="+", default=[0.0, 1e-5, 3e-5, 1e-4])
    parser.add_argument("--max-iterations", type=int, default=40)
    arguments = parser.parse_args()
    sim = jaxmpm.Simulation(jaxmpm.load_scene(HERE / "calibrate_twin_scene.toml"))
    truth = {name: sim.params["materials"]["sand"][name.split(".")[1]] for name in FIT}
    print("| noise [m] | parameter | truth | recovered | error | std. error | error / std. error | iterations | simulations | wall [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise in arguments.levels:
        started = time.monotonic()
        fit = inverse.calibrate(sim, twin_observations(sim, noise, seed=1), FIT, starts=[WRONG_GUESS],
                                max_iterations=arguments.max_iterations, progress=False)
        wall = time.monotonic() - started
        for name in FIT:
            error = fit.params[name] - truth[name]
            ratio = abs(error) / fit.stderr[name] if fit.stderr[name] > 0 else float("nan")
            print(f"| {noise:g} | {name} | {truth[name]:g} | {fit.params[name]:.5g} | {error:+.3g} | "
                  f"{fit.stderr[name]:.3g} | {ratio:.2f} | {fit.iterations} | {fit.evaluations} | {wall:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
