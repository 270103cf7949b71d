"""Two loading rates separate fluidity from exponent: a calibration of several experiments.

    python examples/calibrate_rates.py [--noise 0.02]

A footing is pushed into viscoplastic sand (examples/calibrate_rates_scene.toml) at 0.02 and
0.1 m/s; the driving force is measured. Fitting fluidity and exponent to one rate leaves them
strongly correlated (a steady flow fixes only (rate / fluidity)^(1 / exponent)); fitting both
experiments at once, with the same parameters, identifies each. The script prints the
correlation of the two before and after, and the recovered values.
"""

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import inverse  # noqa: E402
import jaxmpm  # noqa: E402

HERE = Path(__file__).parent
SCENE = HERE / "calibrate_rates_scene.toml"
RATES = {"slow": [0.0, -0.02], "fast": [0.0, -0.1]}
TRUTH = {"sand.friction_angle": 25.0, "sand.fluidity": 5.0, "sand.exponent": 2.0}
FIT = {"sand.friction_angle": (10.0, 40.0), "sand.fluidity": (0.1, 100.0), "sand.exponent": (1.0, 5.0)}
START = {"sand.friction_angle": 32.5, "sand.fluidity": 3.5, "sand.exponent": 2.6}   # 30 % away


def rate_observations(sim, velocity, noise, seed=0, every=0.01):
    """The footing force of the true run at `every` seconds, plus Gaussian noise of `noise`
    times its largest magnitude (stated as sigma)."""
    params = jaxmpm.with_values(sim.params, {"bodies.footing.velocity": np.asarray(velocity)})
    probes = sim.probes(params)
    stride = max(1, int(round(every / sim.dt)))
    times, values = sim.time[::stride][1:], np.asarray(probes["force"])[::stride][1:, [1]]
    scale = noise * np.max(np.abs(values), axis=0) if noise > 0 else None
    rng = np.random.default_rng(seed)
    noisy = values if scale is None else values + scale * rng.standard_normal(values.shape)
    return inverse.Observations.from_arrays({"force": (times, noisy, [1])},
                                            sigma=None if scale is None else {"force": scale})


def experiments(sim, noise, seed=0, rates=RATES):
    return [inverse.Experiment(sim, rate_observations(sim, velocity, noise, seed + index),
                               set={"bodies.footing.velocity": velocity}, name=name)
            for index, (name, velocity) in enumerate(rates.items())]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=0.02, help="noise std as a fraction of the peak force")
    parser.add_argument("--max-iterations", type=int, default=40)
    arguments = parser.parse_args()
    sim = jaxmpm.Simulation(jaxmpm.load_scene(SCENE))
    both = experiments(sim, arguments.noise)
    for label, chosen in (("fast rate alone", both[1:]), ("both rates", both)):
        fit = inverse.calibrate(chosen, fit=FIT, starts=[START], max_iterations=arguments.max_iterations)
        print(f"== {label}")
        print(fit.summary())
        gamma, exponent = fit.names.index("sand.fluidity"), fit.names.index("sand.exponent")
        print(f"  correlation(fluidity, exponent) = {fit.correlation[gamma, exponent]:+.3f}")


if __name__ == "__main__":
    main()
