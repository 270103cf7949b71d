"""Reverse-mode memory against rollout length: checkpointed segments vs one long scan.

    python benchmarks/gradient_memory.py [--no-write] [--large]

For the elastic block of benchmarks/throughput.py (2,500 points here, float64) and rollouts of
100 to 3,200 steps, compile jax.grad of a probe-history loss and read XLA's temporary buffer
size (`memory_analysis().temp_size_in_bytes`) for
- `Checkpointing(step="recompute")` (segments of ceil(sqrt(steps)) steps, each step recomputed):
  expected ~ sqrt(steps);
- `Checkpointing(segment=steps)` (one segment: every step checkpointed, but all T states kept
  for the backward pass): expected ~ steps.
`--large` measures instead the case the speed goal names: 16,384 points of Drucker-Prager sand,
bspline2 + APIC, float32, 200 to 10,000 steps, default checkpointing; `--run` also runs the
10,000-step gradient once for its wall time and the process's peak resident memory (minutes).
Otherwise nothing is run, only compiled, so the figures do not depend on the machine's load.
Writes its table to docs/benchmarks.md between marker comments.
"""

import argparse
import datetime
import math
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from common import block_scene, write_section  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm.kernels.xla_options import compiler_options  # noqa: E402

BEGIN, END = "<!-- gradient_memory:begin -->", "<!-- gradient_memory:end -->"
LARGE_BEGIN, LARGE_END = "<!-- gradient_memory_large:begin -->", "<!-- gradient_memory_large:end -->"
STEPS = (100, 400, 1600, 3200)
LARGE_STEPS = (200, 1000, 10_000)


def temporary_megabytes(steps, checkpointing):
    sim = jaxmpm.Simulation(block_scene(50, "float64", steps), checkpointing)

    def loss(young):
        probes = sim.probes(jaxmpm.with_values(sim.params, {"block.young": young}))
        return jax.numpy.sum(probes["top"]) + jax.numpy.sum(probes["centre_of_mass"])

    compiled = jax.jit(jax.grad(loss)).lower(1.0e6).compile()
    return compiled.memory_analysis().temp_size_in_bytes / 1e6, sim.point_count


def large_case(steps, run):
    """(XLA temporary MB, wall seconds of one gradient or None, peak RSS MB after it or None)
    of the gradient for 16,384 points, float32, Drucker-Prager, bspline2 + APIC."""
    scene = block_scene(128, "float32", steps, "drucker_prager", "bspline2", "apic")
    sim = jaxmpm.Simulation(scene)

    def loss(young):
        probes = sim.probes(jaxmpm.with_values(sim.params, {"block.young": young}))
        return jax.numpy.sum(probes["top"]) + jax.numpy.sum(probes["centre_of_mass"])

    young = jax.numpy.float32(1.0e6)
    compiled = jax.jit(jax.grad(loss), compiler_options=compiler_options(reverse_mode=True)).lower(young).compile()
    temporary = compiled.memory_analysis().temp_size_in_bytes / 1e6
    if not run:
        return temporary, None, None
    start = time.perf_counter()
    value = float(compiled(young))
    assert math.isfinite(value) and value != 0.0, value
    return temporary, time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


LARGE_POLICIES = "one segment of \"recompute_grid\" steps at 200 steps, segments of about sqrt(steps) of them beyond"


def large_table(run_longest):
    rows = []
    for steps in LARGE_STEPS:
        temporary, seconds, rss = large_case(steps, run_longest and steps == LARGE_STEPS[-1])
        ran = "" if seconds is None else f"{seconds:.0f} s, peak RSS {rss:.0f} MB"
        rows.append(f"| {steps} | {temporary:.1f} MB | {ran} |")
        print(rows[-1], flush=True)
    return "\n".join([
        "16,384 points of Drucker-Prager sand, bspline2 + APIC, float32 (the 16k block of the throughput "
        f"table), the default checkpointing (\"auto\": {LARGE_POLICIES}), measured {datetime.date.today()} (JAX {jax.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores):",
        "",
        "| steps | XLA temporary memory of the gradient | one gradient run: wall time, process peak RSS |",
        "|---:|---:|---|",
        *rows,
    ])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--large", action="store_true", help="the 16k-point float32 case only")
    parser.add_argument("--run", action="store_true", help="with --large: also run the longest gradient once")
    arguments = parser.parse_args()
    if arguments.large:
        jax.config.update("jax_enable_x64", False)
        text = large_table(arguments.run)
        if not arguments.no_write:
            write_section(LARGE_BEGIN, LARGE_END, text)
        return
    rows = []
    for steps in STEPS:
        sqrt_mb, points = temporary_megabytes(steps, jaxmpm.Checkpointing(step="recompute"))
        flat_mb, _ = temporary_megabytes(steps, jaxmpm.Checkpointing(segment=steps))
        rows.append((steps, sqrt_mb, flat_mb))
        print(f"{steps:5d} steps: segments {sqrt_mb:8.1f} MB, one scan {flat_mb:8.1f} MB", flush=True)
    steps, sqrt_mb, flat_mb = (np.array(column) for column in zip(*rows))
    slope_sqrt = np.polyfit(np.log(steps), np.log(sqrt_mb), 1)[0]
    slope_flat = np.polyfit(np.log(steps), np.log(flat_mb), 1)[0]
    lines = [
        "## Reverse-mode memory against rollout length",
        "",
        f"Measured {datetime.date.today()} with `python benchmarks/gradient_memory.py` (JAX {jax.__version__}): "
        f"XLA temporary memory of the compiled gradient of a probe loss, elastic block of "
        f"{points} points, float64.",
        "",
        "| steps | `Checkpointing(step=\"recompute\")` (segments of ceil(sqrt(steps))) | `Checkpointing(segment=steps)` |",
        "|---:|---:|---:|",
        *[f"| {s} | {a:.1f} MB | {b:.1f} MB |" for s, a, b in rows],
        "",
        f"Fitted growth: memory ~ steps^{slope_sqrt:.2f} with segments, steps^{slope_flat:.2f} with one scan.",
    ]
    text = "\n".join(lines)
    print(text)
    if not arguments.no_write:
        write_section(BEGIN, END, text)


if __name__ == "__main__":
    main()
