"""Synthetic twin on a collapsing heap: the large-deformation calibration MPM is needed for.

    python examples/calibrate_heap.py [--noise 0.02] [--optimizer lm] [--shape bspline2] [--seed 0]
    python examples/calibrate_heap.py --noise 0.02 --write-observations examples/calibrate_heap_observations.csv

1. simulate examples/calibrate_heap_scene.toml (a viscoplastic sand column slumping into a
   heap; its crest travels about five cells) with its own, true parameters;
2. sample the crest and the middle of the top surface every 0.01 s, and add Gaussian noise
   of `--noise` times each component's largest magnitude (0 = noise-free);
3. calibrate friction angle, fluidity and exponent from a start 30 % away from the truth;
4. print recovered values, standard errors, errors against the truth and the cost.
With --write-observations PATH it only writes the noisy observations (the file that
`jaxmpm calibrate examples/calibrate_heap.calibration.toml` reads) and stops; their noise
standard deviations go in that file's [noise] table.
"""

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import inverse  # noqa: E402
import jaxmpm  # noqa: E402

HERE = Path(__file__).parent
SCENE = HERE / "calibrate_heap_scene.toml"
TRUTH = {"sand.friction_angle": 20.0, "sand.fluidity": 5.0, "sand.exponent": 2.0}
FIT = {"sand.friction_angle": (10.0, 40.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
START = {"sand.friction_angle": 26.0, "sand.fluidity": 3.5, "sand.exponent": 2.6}   # 30 % away
OBSERVED = (("crest", [0, 1]), ("top", [0, 1]))


def twin_observations(sim, noise, seed=0, every=0.01, params=None):
    """Probe histories of the true run at `every` seconds, plus Gaussian noise of standard
    deviation `noise` x (largest |value| of each component); the noise is stated as sigma."""
    probes = sim.probes(params)
    stride = max(1, int(round(every / sim.dt)))
    times = sim.time[::stride]
    rng = np.random.default_rng(seed)
    data, sigma = {}, {}
    for name, components in OBSERVED:
        values = np.asarray(probes[name])[::stride][:, components]
        scale = noise * np.max(np.abs(values), axis=0)
        data[name] = (times, values + scale * rng.standard_normal(values.shape), components)
        sigma[name] = scale
    return inverse.Observations.from_arrays(data, sigma=sigma if noise > 0 else None)


def heap_simulation(shape="bspline2", **changes):
    scene = jaxmpm.load_scene(SCENE).with_value("numerics.shape", shape)
    for key, value in changes.items():
        scene = scene.with_value(key, value)
    return jaxmpm.Simulation(scene)


def report(fit, truth=TRUTH):
    print(fit.summary())
    for name in fit.names:
        error = fit.params[name] - truth[name]
        print(f"  {name}: truth {truth[name]:g}, error {error:+.4g} ({error / truth[name]:+.2%}), "
              f"{abs(error) / max(fit.stderr[name], 1e-300):.2f} standard errors")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=0.0, help="noise std as a fraction of each component's peak")
    parser.add_argument("--optimizer", default="lm", choices=["lm", "lbfgs", "adam"])
    parser.add_argument("--shape", default="bspline2", choices=["linear", "gimp", "bspline2"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-iterations", type=int, default=50)
    parser.add_argument("--write-observations", metavar="PATH", help="write the observations CSV and stop")
    arguments = parser.parse_args()
    sim = heap_simulation(arguments.shape)
    observations = twin_observations(sim, arguments.noise, arguments.seed)
    if arguments.write_observations:
        observations.to_csv(arguments.write_observations)
        for name, channel in observations.channels.items():
            print(f"{name}: sigma {channel.sigma.tolist() if channel.sigma is not None else None}")
        print(f"wrote {arguments.write_observations}")
        return
    fit = inverse.calibrate(sim, observations, FIT, starts=[START], optimizer=arguments.optimizer,
                            max_iterations=arguments.max_iterations)
    report(fit)


if __name__ == "__main__":
    main()
