"""One scene sharded over 1 and 2 devices: time per step of `Simulation(scene, devices=...)`,
a Drucker–Prager block (bspline2 + APIC, float32) of 16k or 65k points, each device count in
its own process (`XLA_FLAGS=--xla_force_host_platform_device_count=N`).

    python benchmarks/sharded_scene.py [--cells 64 128] [--devices 1 2]

On a CPU, forced host devices share its cores (and XLA's thread pool): the figure shows what
the all-reduce of the grid sums costs against splitting the points, not what GPUs would gain.
"""

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys, time
import jax
import jaxmpm
cells = int(sys.argv[1])
h = 1.0 / cells
text = f'''
[scene]
duration = 1.0
[grid]
size = [2.0, 1.0]
cell = {h!r}
[numerics]
shape = "bspline2"
transfer = "apic"
dtype = "float32"
[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 5.0e6
poisson = 0.3
friction_angle = 30.0
[[bodies]]
name = "sand"
material = "sand"
region = {{ rectangle = [[0.0, 0.0], [2.0, 0.5]] }}
'''
sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(text), devices=jax.devices())
params = sim.cast(sim.params)
state = sim.initial_state(params)
# 50 steps in one program: one sharded program in flight at a time (several queued ones can
# starve XLA:CPU's in-process all-reduce of threads on a 2-core machine: docs/devices.md)
steps = jax.jit(lambda p, s: jax.lax.fori_loop(0, 50, lambda i, s: sim.step(p, s)[0], s))
start = time.perf_counter()
state = jax.block_until_ready(steps(params, state))
compile_seconds = time.perf_counter() - start
best = float("inf")
for repeat in range(3):
    start = time.perf_counter()
    state = jax.block_until_ready(steps(params, state))
    best = min(best, (time.perf_counter() - start) / 50)
print(json.dumps({"devices": len(jax.devices()), "points": sim.point_count, "compile": compile_seconds,
                  "step_ms": best * 1e3}))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    arguments = parser.parse_args()
    print(f"{'points':>8} {'devices':>8} {'compile s':>10} {'ms/step':>8} {'M point-steps/s':>16}")
    for cells in arguments.cells:
        for count in arguments.devices:
            environment = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={count}")
            done = subprocess.run([sys.executable, "-c", CHILD, str(cells)], capture_output=True, text=True,
                                  check=True, env=environment)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            rate = row["points"] / row["step_ms"] / 1e3
            print(f"{row['points']:>8} {row['devices']:>8} {row['compile']:>10.1f} {row['step_ms']:>8.2f} "
                  f"{rate:>16.2f}", flush=True)


if __name__ == "__main__":
    main()
