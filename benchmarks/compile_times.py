"""Compile time of every example scene: its probe rollout forward, and its gradient.

    python benchmarks/compile_times.py            # prints a table, updates docs/benchmarks.md
    python benchmarks/compile_times.py --no-write
    python benchmarks/compile_times.py --only calibrate_wall_scene.toml

What a user waits for before the first step of a calibration runs: for each example scene,
the program `Simulation.probes` builds (the whole rollout, checkpointed as jaxmpm chooses for
the scene), and the gradient of a misfit of its probe histories with respect to every
material parameter, both with the XLA options jaxmpm compiles them with
(`jaxmpm.kernels.xla_options`). Scenes without probes get a probe of the mean displacement of their
first body. Trace (Python tracing and lowering to XLA, with Python's garbage collector paused as
jaxmpm pauses it for its own programs: `jaxmpm.running.tracing`) and XLA compilation are timed apart.
Each scene runs in a fresh process (nothing cached in memory; JAX's persistent compilation
cache off), float64 as the scenes' own dtype asks (JAX's 64-bit mode on).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from common import machine_info, write_section  # noqa: E402  (same directory)

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- compile_times:begin -->", "<!-- compile_times:end -->"
CALIBRATION_FILES = ".calibration.toml"


def example_scenes() -> list[Path]:
    return sorted(path for path in (ROOT / "examples").glob("*.toml") if not path.name.endswith(CALIBRATION_FILES))


def timed(stage):
    start = time.perf_counter()
    value = stage()
    return value, time.perf_counter() - start


def measure(path: Path) -> dict:
    """Trace and compile seconds of the forward probe program and of its gradient."""
    import dataclasses

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxmpm
    from jaxmpm.running.tracing import collector_paused
    from jaxmpm.kernels.xla_options import jit_reverse_mode, jit_with_options

    scene = jaxmpm.load_scene(path)
    if not scene.probes:
        scene = dataclasses.replace(scene, probes=(jaxmpm.Probe("moved", "body_displacement", body=scene.bodies[0].name),))
    sim = jaxmpm.Simulation(scene)
    params = sim.cast(sim.params)

    def misfit_of(simulation):
        def misfit(materials):
            probes = simulation.probes({**params, "materials": materials})
            return sum(jnp.sum(history * history) for history in probes.values())
        return misfit

    materials = params["materials"]
    chosen = sim.checkpointing_for(sim.initial_state(params))
    result = {"scene": path.name, "points": sim.point_count, "steps": sim.steps, "dtype": str(sim.dtype),
              "segment": chosen.segment_length(sim.steps), "kept": chosen.step}
    programs = (("forward", jit_with_options(misfit_of(sim), several_fields=sim.several_fields)),
                ("gradient", jit_reverse_mode(jax.grad(misfit_of(sim.reverse_only())), sim.several_fields)))
    for name, program in programs:
        with collector_paused():        # as a calibration traces its programs
            lowered, trace_s = timed(lambda: program.trace(materials).lower())
            _, compile_s = timed(lowered.compile)
        result[f"{name}_trace_s"], result[f"{name}_compile_s"] = trace_s, compile_s
    return result


def table(results: list[dict]) -> str:
    lines = [
        "| example | points | steps | segment | forward: trace + compile | gradient: trace + compile |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        forward = r["forward_trace_s"] + r["forward_compile_s"]
        gradient = r["gradient_trace_s"] + r["gradient_compile_s"]
        lines.append(
            f"| {r['scene']} | {r['points']:,} | {r['steps']:,} | {'whole' if r['segment'] == r['steps'] else r['segment']} | "
            f"{r['forward_trace_s']:.1f} + {r['forward_compile_s']:.1f} = {forward:.1f} s | "
            f"{r['gradient_trace_s']:.1f} + {r['gradient_compile_s']:.1f} = {gradient:.1f} s |"
        )
    return "\n".join(lines)


def machine_sentence(command: str, how: str) -> str:
    """The machine, versions, commit, date and load of a per-scene benchmark, and how it ran."""
    machine = machine_info()
    return (f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory']}; Python {machine['python']}, "
            f"JAX {machine['jax']}; jaxmpm {machine['commit']}; {machine['date']}; 1-minute load average "
            f"{machine['load']:.1f} after the run. `python {command}`, {how}.")


def run_each_scene(script: str, paths: list[Path], only, extra=(), env=None) -> list[dict]:
    """Run `script --scene PATH *extra` in a fresh process per scene (those named in `only`,
    or all); each prints its result as a JSON line last. Failed scenes are reported, skipped."""
    results = []
    for path in paths:
        if only and path.name not in only:
            continue
        print(f"scene {path.name} ...", file=sys.stderr, flush=True)
        done = subprocess.run([sys.executable, script, "--scene", str(path), *extra], capture_output=True, text=True,
                              env=env)
        if done.returncode:
            print(done.stderr[-2000:], file=sys.stderr)
            continue
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(json.dumps(results[-1]), file=sys.stderr)
    return results


def section(results: list[dict]) -> str:
    return "\n".join([
        "## Compile time of the example scenes",
        "",
        machine_sentence("benchmarks/compile_times.py", "one fresh process per scene, persistent compilation cache off"),
        "",
        table(results),
        "",
        "The forward program is the scene's whole probe rollout (`Simulation.probes`); the gradient is that of the "
        "sum of squares of its probe histories with respect to every material parameter, as a calibration compiles "
        "it. Segment: the checkpoint segment jaxmpm chose (whole: one segment, the rollout's states fit the "
        "memory budget). Trace is Python tracing and lowering (Python's garbage collector paused, as jaxmpm does "
        "for its own programs), compile is XLA. A calibration or a `jaxmpm run` "
        "with the persistent cache on (the CLI default) pays this once per scene structure.",
    ])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print the table only")
    parser.add_argument("--only", nargs="*", help="example file names to measure (default: all)")
    parser.add_argument("--scene", help=argparse.SUPPRESS)   # the worker's own run
    args = parser.parse_args()
    if args.scene:
        print(json.dumps(measure(Path(args.scene))))
        return
    results = run_each_scene(__file__, example_scenes(), args.only)
    print(table(results))
    if not args.no_write and not args.only:
        write_section(BEGIN, END, section(results))


if __name__ == "__main__":
    main()
