"""Peak memory of a forward run against its length: streamed to a file, and held in memory.

Each run is its own process (peak RSS, `resource.getrusage`), a 4,096-point Drucker–Prager
block settling under gravity with a snapshot (x, stress, plastic strain) every 20 steps, for
1,000 to 100,000 steps. Streamed (`save_to`), memory should not grow with the run; in memory
it grows by a snapshot per output.

    python benchmarks/long_run_memory.py [--steps 1000 10000 100000]
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time

CHILD = r"""
import json, resource, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jaxmpm
steps, mode, path = int(sys.argv[1]), sys.argv[2], sys.argv[3]
text = '''
[scene]
duration = 1.0
snapshot_fields = ["x", "stress", "plastic_strain"]
[grid]
size = [1.6, 0.8]
cell = 0.025
[numerics]
preset = "balanced"
damping = 0.1
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
scene = jaxmpm.Scene.from_toml(text)
dt = jaxmpm.Simulation(scene).dt
scene = scene.with_value("scene.output_every", 20 * dt).with_value("scene.duration", steps * dt)
sim = jaxmpm.Simulation(scene)
start = time.perf_counter()
sim.run(progress=False, save_to=path if mode == "file" else None)
seconds = time.perf_counter() - start
print(json.dumps({"steps": sim.steps, "outputs": sim.outputs, "points": sim.point_count, "mode": mode,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "seconds": seconds}))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, nargs="+", default=[1000, 10000, 100000])
    arguments = parser.parse_args()
    print(f"{'steps':>8} {'outputs':>8} {'mode':>7} {'peak RSS MB':>12} {'run s':>8}")
    with tempfile.TemporaryDirectory() as folder:
        for steps in arguments.steps:
            for mode in ("file", "memory"):
                done = subprocess.run([sys.executable, "-c", CHILD, str(steps), mode, f"{folder}/run.h5"],
                                      capture_output=True, text=True, check=True)
                row = json.loads(done.stdout.strip().splitlines()[-1])
                print(f"{row['steps']:>8} {row['outputs']:>8} {mode:>7} {row['peak_rss_mb']:>12.0f} "
                      f"{row['seconds']:>8.1f}", flush=True)


if __name__ == "__main__":
    started = time.time()
    main()
    print(f"total {time.time() - started:.0f} s")
