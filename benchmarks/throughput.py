"""Forward throughput, compile time, gradient/forward ratio and peak memory of an elastic scene.

    python benchmarks/throughput.py              # all cases; prints a table, updates docs/benchmarks.md
    python benchmarks/throughput.py --no-write   # print only
    python benchmarks/throughput.py --quick      # fewer repeats, 5k points in float32 only (a smoke run)
    python benchmarks/throughput.py --reference  # jaxmpm against a Taichi kernel of its step (bench extra)

The scene: a linear-elastic block (rho = 1000 kg/m^3, E = 1 MPa, nu = 0.3), or the same block as
Drucker-Prager sand (also viscoplastic, Perzyna gamma = 5 1/s, N = 2, at 16,384 points), resting on the fixed floor of a 1 m x 1 m box under gravity, 2 x 2 points
per cell, MUSL, dt = 0.4 h / 40 m/s; linear, gimp and bspline2 shape functions with APIC, and
linear with FLIP 0.99 (the `fast` preset's scheme). Sizes: 5,184, 16,384 and 65,536 points (the
0.5 m block on 72^2, 128^2 and 256^2 cells). Every case times the forward step; GRADIENT_CASES
also time the gradient.

Each case runs in its own subprocess, so that its peak resident memory
(getrusage maxrss) belongs to that case alone and float32 runs without JAX's 64-bit mode, as a
float32 user would run it. This is a script, not a test: the figures are printed and written to
docs/benchmarks.md between marker comments (the rest of that file is left alone).

`--reference` times instead, in turn and each in its own process, jaxmpm's Drucker-Prager block
(16,384 points, float32) with bspline2 + APIC and with linear + FLIP, and the Taichi kernel of the
bspline2 + APIC step in benchmarks/reference_taichi.py, and writes its own section
(REFERENCE_BEGIN / REFERENCE_END) with the ratio and the kernel's float64 agreement check.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DOC, ROOT, STEPS_PER_CALL, block_scene, machine_info, write_section  # noqa: E402
BEGIN, END = "<!-- throughput:begin -->", "<!-- throughput:end -->"

SIZES = {5_184: 72, 16_384: 128, 65_536: 256}   # points -> cells across the 1 m box (block: 0.5 m wide, 2 x 2 per cell)
# (shape function, transfer): the three shapes with APIC (the default transfer), and the
# `fast` preset's linear + FLIP 0.99
SCHEMES = [("linear", "apic"), ("gimp", "apic"), ("bspline2", "apic"), ("linear", "flip")]
GRADIENT_CASES = {  # the cases whose gradient is timed too (each costs a gradient compilation)
    (5_184, "float32", "drucker_prager", "bspline2", "apic"),
    (16_384, "float32", "drucker_prager", "linear", "apic"),
    (16_384, "float32", "drucker_prager", "gimp", "apic"),
    (16_384, "float32", "drucker_prager", "bspline2", "apic"),
    (16_384, "float32", "drucker_prager", "linear", "flip"),
    (16_384, "float64", "drucker_prager", "bspline2", "apic"),
    (16_384, "float32", "elastic", "bspline2", "apic"),
    (65_536, "float32", "drucker_prager", "bspline2", "apic"),
    (16_384, "float32", "perzyna", "bspline2", "apic"),
}
CASES = [  # (points, dtype, material, shape function, transfer)
    (points, dtype, material, shape, transfer)
    for points in SIZES for material in ("elastic", "drucker_prager") for shape, transfer in SCHEMES
    for dtype in ("float32", "float64")
] + [(16_384, dtype, "perzyna", "bspline2", "apic") for dtype in ("float32", "float64")]   # the viscoplastic sand
QUICK_CASES = [case for case in CASES if case[0] == 5_184 and case[1] == "float32"]
GRADIENT_STEPS = 200                   # steps of the rollout differentiated for the ratio


# --------------------------------------------------------------------------- one case (subprocess)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # KiB on Linux


CPU_SECONDS = []   # process CPU time of each `timed` call (all threads), in call order


def timed(function, *args):
    """Wall seconds of one call, outputs ready; its CPU seconds are appended to CPU_SECONDS."""
    import jax

    start, cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(function(*args))
    CPU_SECONDS.append(time.process_time() - cpu)
    return time.perf_counter() - start


def time_forward(sim, params, initial, repeats: int):
    """(first call [s], `repeats` steady calls [s], their CPU seconds) of `sim._advance`
    (STEPS_PER_CALL steps), every call from `initial`; the first call includes compilation."""
    first = timed(sim._advance, params, initial, initial.particles.x)
    CPU_SECONDS.clear()
    times = [timed(sim._advance, params, initial, initial.particles.x) for _ in range(repeats)]
    cpu_seconds = list(CPU_SECONDS)
    final, _ = sim._advance(params, initial, initial.particles.x)
    assert int(final.error_step) < 0, "the benchmark scene failed"
    return first, times, cpu_seconds


def run_case(points: int, dtype: str, material: str, shape: str, transfer: str, repeats: int) -> dict:
    import jax

    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxmpm import Simulation, with_values

    cells = SIZES[points]
    result = {"points": points, "dtype": dtype, "material": material, "shape": shape, "transfer": transfer,
              "rss_start_mb": None}

    # Forward: one output interval of STEPS_PER_CALL steps (lax.scan), the loop `Simulation.run`
    # drives. Every repeat starts from the same initial state.
    sim = Simulation(block_scene(cells, dtype, STEPS_PER_CALL, material, shape, transfer))
    assert sim.point_count == points, sim.point_count
    params = sim.cast(sim.params)
    initial = sim.initial_state(params)
    jax.block_until_ready(initial)
    result["rss_start_mb"] = peak_rss_mb()
    first, times, cpu_seconds = time_forward(sim, params, initial, repeats)
    cpu_best = min(cpu_seconds)
    best, median = min(times), statistics.median(times)
    result.update(
        forward_first_s=first,
        forward_best_s=best,
        forward_median_s=median,
        compile_forward_s=first - median,
        throughput_best=points * STEPS_PER_CALL / best,
        throughput_median=points * STEPS_PER_CALL / median,
        throughput_per_cpu_second=points * STEPS_PER_CALL / cpu_best,
        rss_forward_mb=peak_rss_mb(),
    )
    if (points, dtype, material, shape, transfer) not in GRADIENT_CASES:
        return result

    # Reverse mode: d/dE of a scalar of the probe histories of a GRADIENT_STEPS rollout
    # (checkpointed, default segments), against the same scalar computed forward only.
    sim = Simulation(block_scene(cells, dtype, GRADIENT_STEPS, material, shape, transfer))

    def loss_of(simulation):
        def loss(young):
            probes = simulation.probes(with_values(sim.params, {"block.young": young}))
            return jnp.sum(probes["top"][:, 1]) + jnp.sum(probes["centre_of_mass"][:, 1])
        return loss

    young = jnp.asarray(sim.params["materials"]["block"]["young"], sim.dtype)
    from jaxmpm.kernels.xla_options import jit_reverse_mode

    # the gradient compiled as jaxmpm compiles its own reverse-mode work: the transfers'
    # transposes (`Simulation.reverse_only`), YNNPACK fusions off
    forward, gradient = jax.jit(loss_of(sim)), jit_reverse_mode(jax.grad(loss_of(sim.reverse_only())))
    loss_first = timed(forward, young)
    grad_first = timed(gradient, young)
    # loss and gradient called in turn, so that a change of the VM's speed during the case
    # reaches both: timed one after the other, linear + APIC read 4.4x in the table where
    # calls in turn in one process gave 3.0x (docs/benchmarks.md, 2026-12-04)
    loss_times, grad_times = [], []
    for _ in range(max(3, repeats)):
        loss_times.append(timed(forward, young))
        grad_times.append(timed(gradient, young))
    value = float(gradient(young))
    assert value == value and value != 0.0, f"gradient {value}"
    memory = gradient.lower(young).compile().memory_analysis()
    loss_best, grad_best = min(loss_times), min(grad_times)
    result.update(
        loss_best_s=loss_best,
        grad_best_s=grad_best,
        compile_loss_s=loss_first - statistics.median(loss_times),
        compile_grad_s=grad_first - statistics.median(grad_times),
        grad_ratio=grad_best / loss_best,
        grad_over_plain_forward=grad_best / (best * GRADIENT_STEPS / STEPS_PER_CALL),
        grad_temp_mb=getattr(memory, "temp_size_in_bytes", 0) / 2**20 if memory else None,
        rss_grad_mb=peak_rss_mb(),
        gradient=value,
    )
    return result


# --------------------------------------------------------------------------- the report


def table(results: list[dict], machine: dict, load_before: float) -> str:
    lines = [
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory']}; "
        f"Python {machine['python']}, JAX {machine['jax']}; jaxmpm {machine['commit']}; "
        f"{machine['date']}; 1-minute load average {load_before:.1f} before and "
        f"{machine['load']:.1f} after the run (0 = idle machine).",
        "",
        "| points | material | shape, transfer | dtype | forward M particle-steps/s, best / median | per CPU-second | "
        "compile forward | gradient / forward time | compile gradient | "
        "peak RSS forward / gradient | XLA temp, gradient |",
        "|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        transfer = "APIC" if r["transfer"] == "apic" else "FLIP 0.99"
        gradient = ("| | | | " if "grad_ratio" not in r else
                    f"| {r['grad_ratio']:.1f}x | {r['compile_grad_s']:.1f} s | {r['rss_forward_mb']:.0f} / "
                    f"{r['rss_grad_mb']:.0f} MB | {r['grad_temp_mb']:.0f} MB ")
        lines.append(
            f"| {r['points']:,} | {r['material'].replace('_', '-')} | {r['shape']}, {transfer} | {r['dtype']} | "
            f"{r['throughput_best'] / 1e6:.2f} / {r['throughput_median'] / 1e6:.2f} | "
            f"{r['throughput_per_cpu_second'] / 1e6:.2f} | {r['compile_forward_s']:.2f} s {gradient}|"
        )
    return "\n".join(lines)


METHOD = f"""\
Method. Scene: a linear-elastic block (rho = 1000 kg/m^3, E = 1 MPa, nu = 0.3) resting on the
fixed floor of a 1 m x 1 m box under gravity, or the same block as rate-independent
Drucker-Prager sand (phi = 30 deg, the paper's cone), which slumps under its own weight (at
16,384 points with bspline2 + APIC also as Perzyna sand, gamma = 5 1/s, N = 2: "perzyna");
2 x 2 points per cell, MUSL, dt = 0.4 h / (40 m/s); each shape function with APIC (the default
transfer) and linear shapes with FLIP 0.99 (the `fast` preset's scheme); 5,184, 16,384 and
65,536 points on 72^2, 128^2 and 256^2 grids (16,384 on 128^2 is the size of a comparison of
CPU MPM codes measured on this machine kind). Forward throughput is points x {STEPS_PER_CALL} /
wall time of one `Simulation._advance` call ({STEPS_PER_CALL} steps in a `lax.scan`, the loop
`Simulation.run` drives), outputs ready (`block_until_ready`), after compilation, always from
the same initial state; best and median of the repeats. "Per CPU-second" divides by the
process CPU time of the best call instead (all threads). Compile time is the first call minus
the median steady call. For the rows with a gradient, the ratio is the best time of the
jitted `jax.grad(loss)` (compiled as jaxmpm compiles its own reverse-mode work, YNNPACK
fusions off) over the best of `jax.jit(loss)`, the two called in turn (at least three rounds
after their first calls), where loss(E) sums two probe histories of
`Simulation.probes` over a {GRADIENT_STEPS}-step rollout (default checkpointing: one segment
when every step's state and the node arrays of its particle-to-grid transfers fit in 2 GiB,
every row here on this machine, whose backward pass runs each step again but for those
transfers; otherwise one segment of steps run again whole when the states alone fit, or
segments of about sqrt(steps) steps keeping their node arrays, so the gradient runs the
forward step twice and the backward step once). Each case runs in a fresh process: peak RSS is `getrusage`
maxrss after the forward runs and after the gradient runs (including the ~0.3 GB of the Python
and JAX runtime and of compilation); XLA temp is the compiled gradient's
`memory_analysis().temp_size_in_bytes`. float32 cases run without JAX's 64-bit mode, float64
cases with it. Timings on this shared 2-core VM move by +-10 % when it is idle and by up to 2x
when other jobs run (see the load average): compare rows of one run, not runs. Regenerate with
`python benchmarks/throughput.py` (about 15 minutes; `--quick` for the 5k float32 rows)."""


def write_doc(text: str):
    write_section(BEGIN, END, f"## Throughput, compile time, gradient cost, memory\n\n{text}\n\n{METHOD}")


# --------------------------------------------------------------------------- the Taichi reference

REFERENCE_BEGIN, REFERENCE_END = "<!-- reference:begin -->", "<!-- reference:end -->"
REFERENCE_POINTS = 16_384
REFERENCE_CASES = {  # name -> (code, numerics); all float32 Drucker-Prager, 16,384 points
    "jaxmpm_apic": ("jaxmpm", "bspline2 + APIC"),
    "taichi": ("Taichi reference, serial scatters", "bspline2 + APIC"),
    "taichi_atomic": ("Taichi reference, atomic scatters", "bspline2 + APIC"),
    "jaxmpm_flip": ("jaxmpm", "linear + FLIP 0.99"),
}
REFERENCE_ROUNDS = 3                 # each case once per round, in order, each in a fresh process


def time_taichi(sim, params, initial, repeats: int, serial_scatter: bool):
    """Like `time_forward`, for the Taichi kernel of benchmarks/reference_taichi.py: each call
    runs STEPS_PER_CALL steps and ends with ti.sync(); the points are reloaded from `initial`
    (untimed) before every call."""
    import numpy as np
    import taichi as ti

    import reference_taichi

    reference = reference_taichi.reference_for(sim, params, initial, ti.f32, serial_scatter=serial_scatter)
    arrays = reference_taichi.particle_arrays(initial)

    def call():
        reference.load(arrays)
        ti.sync()
        start, cpu = time.perf_counter(), time.process_time()
        reference.advance(STEPS_PER_CALL)
        ti.sync()
        return time.perf_counter() - start, time.process_time() - cpu

    first = call()[0]
    calls = [call() for _ in range(repeats)]
    assert np.all(np.isfinite(reference.dump()["stress"])), "the Taichi run failed"
    return first, [wall for wall, _ in calls], [cpu for _, cpu in calls]


def run_reference_case(name: str, repeats: int) -> dict:
    """One case of REFERENCE_CASES in this process: its first call and steady calls [s]."""
    from jaxmpm import Simulation

    shape, transfer = ("linear", "flip") if name == "jaxmpm_flip" else ("bspline2", "apic")
    scene = block_scene(SIZES[REFERENCE_POINTS], "float32", STEPS_PER_CALL, "drucker_prager", shape, transfer)
    sim = Simulation(scene)
    assert sim.point_count == REFERENCE_POINTS, sim.point_count
    params = sim.cast(sim.params)
    initial = sim.initial_state(params)
    if name.startswith("taichi"):
        import taichi as ti

        first, times, cpu = time_taichi(sim, params, initial, repeats, serial_scatter=name == "taichi")
        version = "Taichi " + ".".join(map(str, ti.__version__))
    else:
        import jax

        first, times, cpu = time_forward(sim, params, initial, repeats)
        version = "JAX " + jax.__version__
    return {"name": name, "first_s": first, "times_s": times, "cpu_s": cpu, "version": version}


def run_reference(repeats: int, rounds: int) -> tuple[dict, dict]:
    """({case: every steady call's time and CPU time [s] and each round's first call [s]}, the float64
    agreement check of benchmarks/reference_taichi.py), each case and the check in its own process."""
    runs = {name: {"times_s": [], "cpu_s": [], "first_s": []} for name in REFERENCE_CASES}
    for round_number in range(rounds):
        for name in REFERENCE_CASES:
            print(f"reference round {round_number + 1}/{rounds}: {name} ...", file=sys.stderr, flush=True)
            result = worker([sys.executable, __file__, "--reference-case", name, "--repeats", str(repeats)])
            for key in ("times_s", "cpu_s"):
                runs[name][key] += result[key]
            runs[name]["first_s"].append(result["first_s"])
            runs[name]["version"] = result["version"]
    print("reference: float64 agreement check ...", file=sys.stderr, flush=True)
    agreement = worker([sys.executable, str(Path(__file__).with_name("reference_taichi.py")), "--json"])
    return runs, agreement


def rate(seconds: float) -> float:
    """M particle-steps/s of one call of STEPS_PER_CALL steps of REFERENCE_POINTS points."""
    return REFERENCE_POINTS * STEPS_PER_CALL / seconds / 1e6


def reference_table(runs: dict, agreement: dict, machine: dict, load_before: float) -> str:
    apic, taichi = runs["jaxmpm_apic"]["times_s"], runs["taichi"]["times_s"]
    lines = [
        f"jaxmpm with bspline2 + APIC runs at {min(taichi) / min(apic):.2f} of the throughput of the Taichi "
        f"reference kernel of the same step (best calls; {statistics.median(taichi) / statistics.median(apic):.2f} "
        "for the medians); the target is at least 1.",
        "",
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory']}; Python {machine['python']}, "
        f"{runs['jaxmpm_apic']['version']}, {runs['taichi']['version']}; jaxmpm {machine['commit']}; {machine['date']}; "
        f"1-minute load average {load_before:.1f} before and {machine['load']:.1f} after the run (0 = idle machine).",
        "",
        "| code | numerics | forward M particle-steps/s, best / median | per CPU-second | "
        "throughput of jaxmpm bspline2 + APIC / this, best / median | timed calls | first call (compiles) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for name, (code, numerics) in REFERENCE_CASES.items():
        times, cpu = runs[name]["times_s"], runs[name]["cpu_s"]
        best, median = min(times), statistics.median(times)
        ratio = "" if name.startswith("jaxmpm") else (
            f"{best / min(apic):.2f} / {median / statistics.median(apic):.2f}")
        lines.append(f"| {code} | {numerics} | {rate(best):.2f} / {rate(median):.2f} | {rate(min(cpu)):.2f} | "
                     f"{ratio} | {len(times)} | {statistics.median(runs[name]['first_s']):.1f} s |")
    checks = "; ".join(
        f"{scatter} scatters: positions {agreement[scatter]['position_m']:.1g} m, stress "
        f"{agreement[scatter]['stress']:.1g} of the largest |sigma|" for scatter in ("serial", "atomic"))
    lines += ["", f"Same scheme, checked in float64: after {agreement['steps']} steps from the same initial state "
              f"({agreement['yielded_points']:,} of {agreement['points']:,} points yielded, largest displacement "
              f"{agreement['largest_displacement_m']:.2g} m), the largest differences from jaxmpm are, {checks} "
              "(`python benchmarks/reference_taichi.py`)."]
    return "\n".join(lines)


REFERENCE_METHOD = f"""\
Method. The Drucker-Prager block of the table above (16,384 points, 128^2 grid, float32) run by
jaxmpm with numerics shape = "bspline2", transfer = "apic", update = "musl", and by
`benchmarks/reference_taichi.py`, a hand-written Taichi kernel of the same step (CPU backend,
2 threads, Taichi's default fast_math; every operation in jaxmpm's order, so that in float64
the two end states agree to round-off, the check above). jaxmpm is timed as above: one
`Simulation._advance` call of {STEPS_PER_CALL} steps, outputs ready, from the same initial state. The
Taichi kernel is called {STEPS_PER_CALL} times (one step each) and then `ti.sync()`, after reloading
the initial state untimed. Its particle-to-grid scatters (P2G and the MUSL re-map) run
serially, without atomics, which on two cores beat the parallel loop with atomic adds; the
"atomic scatters" row is that idiomatic parallel version. jaxmpm's calls also do work the kernel
does not: the finiteness and left-the-grid checks and the two probes of each step. Every case runs in its own process; {REFERENCE_ROUNDS} rounds run the cases
in turn; best and median are over all timed calls of all rounds; the first call of each process
(median over the rounds: jaxmpm compiles in it, Taichi compiles or loads its offline kernel
cache) is not among them.
Run with `pip install -e .[bench]` and `python benchmarks/throughput.py --reference` (about
3 minutes)."""


def write_reference_doc(text: str):
    write_section(REFERENCE_BEGIN, REFERENCE_END,
                  f"## Reference: a Taichi kernel of the same step\n\n{text}\n\n{REFERENCE_METHOD}")


def worker(command: list[str], environment: dict | None = None) -> dict:
    """Run a worker subprocess; its JSON result (the last line of its stdout)."""
    done = subprocess.run(command, capture_output=True, text=True, env=environment)
    if done.returncode != 0:
        sys.stderr.write(done.stderr)
        raise SystemExit(f"{' '.join(command[1:])} failed")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print the table only")
    parser.add_argument("--quick", action="store_true", help="5k points in float32, fewer repeats (with --reference: one round)")
    parser.add_argument("--repeats", type=int, default=None, help="forward repeats per case")
    parser.add_argument("--reference", action="store_true",
                        help="only the Taichi reference comparison (needs the bench extra)")
    parser.add_argument("--case", nargs=5, metavar=("POINTS", "DTYPE", "MATERIAL", "SHAPE", "TRANSFER"), help=argparse.SUPPRESS)
    parser.add_argument("--reference-case", choices=REFERENCE_CASES, help=argparse.SUPPRESS)
    args = parser.parse_args()
    repeats = args.repeats or (3 if args.quick else 5)

    if args.case:                       # worker: one case, JSON on the last line of stdout
        print(json.dumps(run_case(int(args.case[0]), *args.case[1:], repeats)))
        return
    if args.reference_case:             # worker: one reference case
        print(json.dumps(run_reference_case(args.reference_case, repeats)))
        return

    start = time.perf_counter()
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    if args.reference:
        runs, agreement = run_reference(repeats, 1 if args.quick else REFERENCE_ROUNDS)
        text, write = reference_table(runs, agreement, machine_info(), load_before), write_reference_doc
    else:
        text, write = throughput_table(repeats, args.quick, load_before), write_doc
    print(text)
    print(f"\n(total {time.perf_counter() - start:.0f} s)", file=sys.stderr)
    if not args.no_write:
        write(text)
        print(f"wrote {DOC.relative_to(ROOT)}", file=sys.stderr)


def throughput_table(repeats: int, quick: bool, load_before: float) -> str:
    """Run CASES (the 10k ones with `quick`), each in its own process; the table."""
    results = []
    for points, dtype, material, shape, transfer in QUICK_CASES if quick else CASES:
        print(f"case {points:,} points {dtype} {material} {shape} {transfer} ...", file=sys.stderr, flush=True)
        command = [sys.executable, __file__, "--case", str(points), dtype, material, shape, transfer,
                   "--repeats", str(repeats)]
        results.append(worker(command))
    return table(results, machine_info(), load_before)


if __name__ == "__main__":
    main()
