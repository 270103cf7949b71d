"""What one calibration iteration costs on the calibration examples, against a forward run.

    python benchmarks/calibration_passes.py            # prints a table, updates docs/benchmarks.md
    python benchmarks/calibration_passes.py --no-write
    python benchmarks/calibration_passes.py --only calibrate_heap_scene.toml

For each examples/calibrate_*_scene.toml, fitting its viscoplastic sand's friction angle,
fluidity and exponent (P = 3) at the scene's own values, the three programs a calibration
runs over the whole probe rollout (`Simulation.probes`):
- forward: the probe residuals alone (what a line search or a rejected step evaluates);
- Jacobian: the residuals with P tangents in one pass, as Levenberg-Marquardt (`lm`, the
  default optimizer) computes them (`inverse.levenberg_marquardt.residuals_and_jacobian`);
- gradient: `jax.grad` of the sum of squared residuals, as L-BFGS and Adam compute it,
  compiled as jaxmpm compiles its reverse-mode work.
All three get the XLA options a calibration gives them (`jaxmpm.kernels.xla_options`).
Each is timed best of `--repeats` calls after its first; the first call's excess over the best
is its compile time. Each scene runs in a fresh process, float64 (JAX's 64-bit mode on), the
persistent compilation cache off.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from compile_times import machine_sentence, run_each_scene  # noqa: E402  (same directory)
from common import write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- calibration_passes:begin -->", "<!-- calibration_passes:end -->"
FITTED = ("friction_angle", "fluidity", "exponent")


def calibration_scenes() -> list[Path]:
    return sorted((ROOT / "examples").glob("calibrate_*_scene.toml"))


def measure(path: Path, repeats: int) -> dict:
    """Best and first-call seconds of the forward, Jacobian and gradient programs of one scene."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxmpm
    from inverse.levenberg_marquardt import residuals_and_jacobian
    from jaxmpm.running.tracing import collector_paused
    from jaxmpm.kernels.xla_options import jit_reverse_mode, jit_with_options

    scene = jaxmpm.load_scene(path)
    sim = jaxmpm.Simulation(scene)
    params = sim.cast(sim.params)
    material = next(name for name, values in params["materials"].items() if "fluidity" in values)
    names = [f"{material}.{name}" for name in FITTED]
    z = jnp.asarray([params["materials"][material][name] for name in FITTED])

    def residuals(z):
        probes = sim.probes(jaxmpm.with_values(params, dict(zip(names, z))))
        return jnp.concatenate([history.ravel() for history in probes.values()])

    programs = {
        "forward": jit_with_options(residuals, several_fields=sim.several_fields),
        "jacobian": jit_with_options(lambda z: residuals_and_jacobian(residuals, z), several_fields=sim.several_fields),
        "gradient": jit_reverse_mode(jax.grad(lambda z: jnp.sum(residuals(z) ** 2)), sim.several_fields),
    }
    result = {"scene": path.name, "points": sim.point_count, "steps": sim.steps, "parameters": len(names)}
    for name, program in programs.items():
        start = time.perf_counter()
        with collector_paused():        # as a calibration calls its programs
            jax.block_until_ready(program(z))
        first = time.perf_counter() - start
        runs = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(program(z))
            runs.append(time.perf_counter() - start)
        result[f"{name}_s"], result[f"{name}_compile_s"] = min(runs), first - min(runs)
    return result


def table(results: list[dict]) -> str:
    lines = [
        "| example | points | steps | forward | Jacobian, 3 tangents (÷ forward) | gradient (÷ forward) | compile: forward / Jacobian / gradient |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        forward = r["forward_s"]
        lines.append(
            f"| {r['scene']} | {r['points']:,} | {r['steps']:,} | {forward:.2f} s | "
            f"{r['jacobian_s']:.2f} s ({r['jacobian_s'] / forward:.1f}x) | {r['gradient_s']:.2f} s "
            f"({r['gradient_s'] / forward:.1f}x) | {r['forward_compile_s']:.1f} / {r['jacobian_compile_s']:.1f} / "
            f"{r['gradient_compile_s']:.1f} s |"
        )
    return "\n".join(lines)


def section(results: list[dict]) -> str:
    return "\n".join([
        "## What a calibration iteration costs",
        "",
        machine_sentence("benchmarks/calibration_passes.py",
                         "one fresh process per scene, float64, persistent compilation cache off"),
        "",
        table(results),
        "",
        "Fitting the sand's friction angle, fluidity and exponent over the scene's whole probe rollout: the "
        "forward pass alone; the residuals with their Jacobian in one pass carrying three tangents, what each "
        "Levenberg-Marquardt iteration (the default optimizer) computes; the gradient of their sum of squares, "
        "what each L-BFGS or Adam evaluation computes. Best of the repeated calls; compile is the first call's "
        "excess (tracing included).",
    ])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print the table only")
    parser.add_argument("--only", nargs="*", help="example file names to measure (default: all)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scene", help=argparse.SUPPRESS)   # the worker's own run
    args = parser.parse_args()
    if args.scene:
        print(json.dumps(measure(Path(args.scene), args.repeats)))
        return
    environment = {**os.environ, "JAXMPM_CACHE_DIR": "off", "PYTHONPATH": str(ROOT)}
    results = run_each_scene(__file__, calibration_scenes(), args.only, ("--repeats", str(args.repeats)), environment)
    print(table(results))
    if not args.no_write and not args.only:
        write_section(BEGIN, END, section(results))


if __name__ == "__main__":
    main()
