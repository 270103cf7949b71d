"""Synthetic twin: make data with known parameters, add noise, recover them from a wrong guess.

    python examples/calibrate_twin.py [--noise 2e-5]
    python examples/calibrate_twin.py --write-observations examples/calibrate_twin_observations.csv

1. simulate examples/calibrate_twin_scene.toml with its own (true) parameters;
2. sample the footing settlement and a surface point every 0.01 s and add Gaussian noise;
3. calibrate friction angle, fluidity and exponent starting 20 % or more away;
4. print recovered values, standard errors, errors against the truth, iterations, cost.
With --write-observations PATH it only writes the noisy observations (the file that
`jaxmpm calibrate examples/calibrate_twin.calibration.toml` reads) and stops.
"""

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import inverse  # noqa: E402
import jaxmpm  # noqa: E402

HERE = Path(__file__).parent
FIT = {"sand.friction_angle": (15.0, 40.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
WRONG_GUESS = {"sand.friction_angle": 30.0, "sand.fluidity": 3.5, "sand.exponent": 2.5}


def twin_observations(sim, noise, seed=0, every=0.01):
    """Probe histories of the true run at `every` seconds, plus N(0, noise^2) noise [m]."""
    probes = sim.probes()
    stride = max(1, int(round(every / sim.dt)))
    times = sim.time[::stride]
    rng = np.random.default_rng(seed)
    data, sigma = {}, {}
    for name, components in (("footing", [1]), ("surface", [0, 1])):
        values = np.asarray(probes[name])[::stride][:, components]
        data[name] = (times, values + noise * rng.standard_normal(values.shape), components)
        sigma[name] = noise if noise > 0 else None
    return inverse.Observations.from_arrays(data, sigma={k: v for k, v in sigma.items() if v})


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=2e-5, help="noise std [m] (settlement ~1 mm)")
    parser.add_argument("--write-observations", metavar="PATH", help="write the observations CSV and stop")
    parser.add_argument("--max-iterations", type=int, default=40)
    arguments = parser.parse_args()

    sim = jaxmpm.Simulation(jaxmpm.load_scene(HERE / "calibrate_twin_scene.toml"))
    truth = {name: sim.params["materials"]["sand"][name.split(".")[1]] for name in FIT}
    observations = twin_observations(sim, arguments.noise)
    if arguments.write_observations:
        observations.to_csv(arguments.write_observations)
        print(f"wrote {arguments.write_observations}")
        return
    fit = inverse.calibrate(sim, observations, FIT, starts=[WRONG_GUESS], max_iterations=arguments.max_iterations)
    print(fit.summary())
    for name in FIT:
        error = fit.params[name] - truth[name]
        print(f"  {name}: truth {truth[name]:g}, error {error:+.4g} ({error / truth[name]:+.2%}), "
              f"{abs(error) / max(fit.stderr[name], 1e-300):.2f} standard errors")


if __name__ == "__main__":
    main()
