"""Ensemble throughput on 1 and 2 devices: `jaxmpm.ensemble` of a batch of Drucker–Prager
footings (2,048 points, bspline2 + APIC, float64), each process with its own forced host
device count. Reports compile and run time (the second call) per batch.

    python benchmarks/ensemble_scaling.py [--members 8] [--devices 1 2]

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
from jaxmpm.ensembles import stack
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
    arguments = parser.parse_args()
    print(f"{'devices':>8} {'members':>8} {'points':>7} {'steps':>6} {'compile+run s':>14} {'run s':>7} "
          f"{'M point-steps/s':>16}")
    for count in arguments.devices:
        environment = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={count}",
                           PYTHONPATH=str(ROOT))
        done = subprocess.run([sys.executable, "-c", CHILD, str(arguments.members)], capture_output=True,
                              text=True, check=True, env=environment)
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rate = row["members"] * row["points"] * row["steps"] / row["second"] / 1e6
        print(f"{row['devices']:>8} {row['members']:>8} {row['points']:>7} {row['steps']:>6} "
              f"{row['first']:>14.1f} {row['second']:>7.2f} {rate:>16.2f}", flush=True)


if __name__ == "__main__":
    main()
