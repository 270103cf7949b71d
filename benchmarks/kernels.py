"""What each kernel of jaxmpm/kernels wins: the plain step against the step with the kernel,
on example scenes, in alternated fresh processes.

    python benchmarks/kernels.py                      # 3 pairs on the two calibration scenes
    python benchmarks/kernels.py --pairs 5 --scenes calibrate_heap_scene

For each scene and each pair of processes (plain, then kernels), one process times:
- the gradient (`jax.grad`) of a misfit of the probe histories with respect to every
  parameter: plain `Simulation` against `Simulation.reverse_only()` (kernels.transposes);
- the Levenberg-Marquardt Jacobian (one pass carrying three tangents, `jax.vmap` of
  `jax.jvp`) over friction angle, fluidity and Young's modulus: plain against
  `Simulation.forward_only()` (kernels.scatter).
Each figure is the best of three calls after compiling; compile time is that of the first
call. The fusion barrier (kernels.fusion) is part of both variants: it is measured by removing
it by hand (docs/benchmarks.md, "Kernels"). Prints a table; nothing is written.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def measure(scene_name: str, variant: str) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    sys.path.insert(0, str(ROOT))
    import jaxmpm

    sim = jaxmpm.Simulation(jaxmpm.load_scene(ROOT / "examples" / f"{scene_name}.toml"))
    params = sim.cast(sim.params)
    materials = params["materials"]
    names = [(m, k) for m in materials for k in ("friction_angle", "fluidity", "young") if k in materials[m]][:3]

    def loss(simulation):
        return lambda p: sum(jnp.mean(v) for v in jax.tree_util.tree_leaves(simulation.probes(p)))

    def jacobian(simulation):
        def residuals(z):
            p = jax.tree_util.tree_map(lambda v: v, params)
            for (material, key), value in zip(names, z):
                p["materials"][material][key] = params["materials"][material][key] * (1.0 + value)
            return jnp.concatenate([jnp.ravel(v) for v in jax.tree_util.tree_leaves(simulation.probes(p))])
        return lambda z: jax.vmap(lambda t: jax.jvp(residuals, (z,), (t,))[1])(jnp.eye(len(names)))

    def timed(function, argument):
        start = time.perf_counter()
        compiled = jax.jit(function).lower(argument).compile()
        compile_seconds = time.perf_counter() - start
        jax.block_until_ready(compiled(argument))
        runs = []
        for _ in range(3):
            start = time.perf_counter()
            jax.block_until_ready(compiled(argument))
            runs.append(time.perf_counter() - start)
        return {"compile": compile_seconds, "run": min(runs)}

    backward = sim.reverse_only() if variant == "kernels" else sim
    forward = sim.forward_only() if variant == "kernels" else sim
    return {"gradient": timed(jax.grad(loss(backward)), params),
            "jacobian": timed(jacobian(forward), jnp.zeros(len(names))),
            "points": sim.point_count, "steps": sim.steps}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--scenes", nargs="+", default=["calibrate_heap_scene", "calibrate_wall_scene"])
    parser.add_argument("--measure", nargs=2, metavar=("SCENE", "VARIANT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(*args.measure)))
        return
    print("| scene | points, steps | program | plain: run (compile) | kernels: run (compile) | plain / kernels |")
    print("|---|---|---|---:|---:|---:|")
    for scene in args.scenes:
        results = {"plain": [], "kernels": []}
        for _ in range(args.pairs):
            for variant in ("plain", "kernels"):
                output = subprocess.run([sys.executable, __file__, "--measure", scene, variant],
                                        capture_output=True, text=True, check=True).stdout
                results[variant].append(json.loads(output.strip().splitlines()[-1]))
        first = results["plain"][0]
        for program in ("gradient", "jacobian"):
            best = {v: min(r[program]["run"] for r in results[v]) for v in results}
            compiles = {v: min(r[program]["compile"] for r in results[v]) for v in results}
            print(f"| {scene} | {first['points']}, {first['steps']} | {program} | {best['plain']:.2f} s "
                  f"({compiles['plain']:.1f} s) | {best['kernels']:.2f} s ({compiles['kernels']:.1f} s) | "
                  f"{best['plain'] / best['kernels']:.2f} |")


if __name__ == "__main__":
    main()
