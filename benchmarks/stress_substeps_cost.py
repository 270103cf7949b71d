"""What numerics.stress_substeps costs: the retaining wall example's step at K = 1, 4, 16.

    python benchmarks/stress_substeps_cost.py            # prints a table (docs/benchmarks.md)
    python benchmarks/stress_substeps_cost.py --substeps 1 2 4 8

Each K compiles the example's rollout over its first 0.05 s (612 steps), then runs it twice;
the faster of the two runs, per step, is reported. Each extra substep is another stress update
of the viscoplastic sand, with its Perzyna Newton solve (docs/convergence.md, "The Perzyna
update's own step").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from common import machine_info  # noqa: E402  (same directory)

ROOT = Path(__file__).resolve().parents[1]


def step_time(substeps):
    """(steps, seconds a step) of the retaining wall's first 0.05 s at `substeps`."""
    import jax

    import jaxmpm

    scene = (jaxmpm.load_scene(ROOT / "examples" / "retaining_wall.toml").with_value("scene.duration", 0.05)
             .with_value("numerics.stress_substeps", substeps))
    sim = jaxmpm.Simulation(scene)
    jax.block_until_ready(sim.final_state())                 # compiles
    runs = []
    for _ in range(2):
        started = time.perf_counter()
        jax.block_until_ready(sim.final_state())
        runs.append(time.perf_counter() - started)
    return sim.steps, min(runs) / sim.steps


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--substeps", type=int, nargs="+", default=[1, 4, 16])
    arguments = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    print(machine_info())
    print("| stress_substeps | steps timed | ms a step | against K = 1 |")
    print("|---:|---:|---:|---:|")
    first = None
    for substeps in arguments.substeps:
        steps, seconds = step_time(substeps)
        first = first or seconds
        print(f"| {substeps} | {steps} | {1e3 * seconds:.1f} | ×{seconds / first:.2f} |", flush=True)


if __name__ == "__main__":
    main()
