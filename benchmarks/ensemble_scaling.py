"""Ensemble throughput on 1 and 2 devices: `jaxmpm.ensemble` of a batch of Drucker–Prager
blocks (4,096 points, bspline2 + APIC, float64), each process with its own forced host
device count. Reports compile and run time (the second call) per batch. With
`--calibration`, a Levenberg–Marquardt calibration of Young's modulus from `--members`
experiments of the same block (one start: the experiments are what is sharded), reporting
the first iteration and the seconds per later iteration.

    python benchmarks/ensemble_scaling.py [--members 8] [--devices 1 2] [--calibration]

On this machine the forced host devices share its two cores with XLA's own thread pool, so
the figure says how the sharded program behaves, not what a second GPU would add.
"""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jaxmpm
from jaxmpm.running.ensembles import stack
members = int(sys.argv[1])
text = '''
[scene]
duration = 0.05
[grid]
size = [1.6, 0.8]
cell = 0.025
[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 5.0e6
poisson = 0.3
friction_angle = 30.0
[[bodies]]
name = "sand"
material = "sand"
region = { rectangle = [[0.0, 0.0], [1.6, 0.4]] }
[[probes]]
name = "top"
kind = "displacement"
at = [0.8, 0.4]
'''
sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(text))
if sys.argv[2] == "calibration":
    import inverse
    experiments = []
    for k in range(members):
        truth = jaxmpm.with_values(sim.params, {"sand.young": 5.0e6, "sand.density": 1700.0 + 50.0 * k})
        experiments.append(inverse.Experiment(sim, sim.run(truth, progress=False), set={"sand.density": 1700.0 + 50.0 * k}))
    start = time.perf_counter()
    fit = inverse.calibrate(experiments, fit={"sand.young": {"low": 1.0e6, "high": 2.0e7, "start": 8.0e6}}, max_iterations=6, progress=False)
    cost = fit.cost
    print(json.dumps({"devices": len(jax.devices()), "members": members, "points": sim.point_count,
                      "steps": sim.steps, "first": cost["first_iteration"], "second": cost["seconds_per_iteration"],
                      "iterations": cost["iterations"], "total": time.perf_counter() - start,
                      "young": float(fit.params["sand.young"])}))
    sys.exit()
batch = stack([jaxmpm.with_values(sim.params, {"sand.friction_angle": 25.0 + k}) for k in range(members)])
start = time.perf_counter()
jax.block_until_ready(jaxmpm.ensemble(sim, batch))
first = time.perf_counter() - start
start = time.perf_counter()
jax.block_until_ready(jaxmpm.ensemble(sim, batch))
second = time.perf_counter() - start
print(json.dumps({"devices": len(jax.devices()), "members": members, "points": sim.point_count,
                  "steps": sim.steps, "first": first, "second": second}))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--members", type=int, default=8)
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--calibration", action="store_true", help="time a calibration of --members experiments")
    arguments = parser.parse_args()
    mode = "calibration" if arguments.calibration else "ensemble"
    if arguments.calibration:
        print(f"{'devices':>8} {'experiments':>12} {'points':>7} {'steps':>6} {'first iteration s':>18} "
              f"{'s per iteration':>16} {'total s':>8} {'fitted young':>15}")
    else:
        print(f"{'devices':>8} {'members':>8} {'points':>7} {'steps':>6} {'compile+run s':>14} {'run s':>7} "
              f"{'M point-steps/s':>16}")
    for count in arguments.devices:
        environment = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={count}",
                           PYTHONPATH=str(ROOT))
        done = subprocess.run([sys.executable, "-c", CHILD, str(arguments.members), mode], capture_output=True,
                              text=True, check=True, env=environment)
        row = json.loads(done.stdout.strip().splitlines()[-1])
        if arguments.calibration:
            print(f"{row['devices']:>8} {row['members']:>12} {row['points']:>7} {row['steps']:>6} "
                  f"{row['first']:>18.1f} {row['second']:>16.2f} {row['total']:>8.1f} {row['young']:>15.6g}",
                  flush=True)
            continue
        rate = row["members"] * row["points"] * row["steps"] / row["second"] / 1e6
        print(f"{row['devices']:>8} {row['members']:>8} {row['points']:>7} {row['steps']:>6} "
              f"{row['first']:>14.1f} {row['second']:>7.2f} {rate:>16.2f}", flush=True)


if __name__ == "__main__":
    main()
