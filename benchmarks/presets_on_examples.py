"""Every numerics preset on every example scene: does it run, what does it cost.

    python benchmarks/presets_on_examples.py            # prints a table, updates docs/benchmarks.md
    python benchmarks/presets_on_examples.py --no-write

Each example scene's [numerics] table is replaced by the preset alone (the scene's damping
kept); its step is compiled and run for STEPS steps. Reported: points, compile time of one
step, wall time per step after compiling, and whether the state stayed finite and inside the
grid. (tests/test_presets.py runs every preset on four examples that cover every feature.)
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import platform
import re
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm.scene import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
BEGIN, END = "<!-- presets:begin -->", "<!-- presets:end -->"
STEPS = 20


def run_preset(path: Path, preset: str) -> dict:
    scene = jaxmpm.load_scene(path)
    scene = dataclasses.replace(scene, numerics=jaxmpm.Numerics(preset=preset, damping=scene.numerics.damping))
    sim = jaxmpm.Simulation(scene)
    params = sim.cast(sim.params)
    state = sim.initial_state(params)
    step = jax.jit(sim.step)
    started = time.perf_counter()
    state, _ = jax.block_until_ready(step(params, state))
    compiled = time.perf_counter() - started
    started = time.perf_counter()
    for _ in range(STEPS - 1):
        state, _ = step(params, state)
    jax.block_until_ready(state)
    per_step = (time.perf_counter() - started) / (STEPS - 1)
    particles = state.particles
    healthy = bool(np.all(np.isfinite(np.asarray(particles.stress))) and int(np.max(np.asarray(particles.flags))) == 0)
    return {"points": sim.point_count, "compile": compiled - per_step, "step": per_step, "healthy": healthy}


def table(rows) -> str:
    lines = ["| example | preset | points | compile one step | per step | finite, on the grid |",
             "|---|---|---:|---:|---:|---|"]
    for name, preset, row in rows:
        lines.append(f"| {name} | {preset} | {row['points']:,} | {row['compile']:.1f} s | "
                     f"{1e3 * row['step']:.2f} ms | {'yes' if row['healthy'] else 'NO'} |")
    return "\n".join(lines)


def write_section(text: str):
    doc = DOC.read_text()
    section = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in doc:
        doc = re.sub(re.escape(BEGIN) + ".*?" + re.escape(END), lambda _: section, doc, flags=re.S)
    else:
        doc = doc.rstrip() + "\n\n" + section + "\n"
    DOC.write_text(doc)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    arguments = parser.parse_args()
    scenes = sorted(p for p in (ROOT / "examples").glob("*.toml") if not p.name.endswith(".calibration.toml"))
    rows = []
    for path in scenes:
        for preset in PRESETS:
            row = run_preset(path, preset)
            rows.append((path.name, preset, row))
            print(f"{path.name:28s} {preset:9s} {row}", flush=True)
    body = table(rows)
    print(body)
    if not arguments.no_write:
        heading = (f"## Every preset on every example scene\n\nMachine: {platform.processor() or platform.machine()}, "
                   f"JAX {jax.__version__}; {datetime.date.today()}; `python benchmarks/presets_on_examples.py`. "
                   f"One step compiled, then {STEPS - 1} steps timed (wall time, float64 scenes with JAX's 64-bit "
                   "mode on; `fast` runs in float32).\n\n")
        write_section(heading + body)


if __name__ == "__main__":
    main()
