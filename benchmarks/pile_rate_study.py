"""Pile driving at two velocities, in viscoplastic and in rate-independent sand: the rate table
of docs/pile_driving.md.

    python benchmarks/pile_rate_study.py [--out DIR] [--reuse] [--no-write]
    python examples/plot_pile_driving.py DIR/pile_vp_0.5.h5 -o PREFIX --compare DIR/pile_vp_0.25.h5 \
        DIR/pile_ri_0.5.h5 DIR/pile_ri_0.25.h5

Four runs of examples/pile_driving.toml, each to the same penetration (0.21 m): the pile at
0.25 and 0.5 m/s (both its bodies; the duration scaled to keep the penetration), in the
scene's Perzyna sand and in the same sand made rate-independent (fluidity removed: `--set`
can change a value but not remove one, so this is done on the Scene in Python, with
dataclasses.replace on the material; same friction angle, cone, elasticity). Each run is saved
as DIR/pile_{vp|ri}_{speed}.h5 (DIR defaults to pile_rate_study/ in the working folder;
--reuse skips runs whose file is there and complete). The soil resistance (weight
subtracted, examples/plot_pile_driving.py) at 0.1 and 0.2 m of penetration is compared: the
viscoplastic sand resists more when the pile is faster, the rate-independent one (nearly)
does not (inertia is small: rho v^2 A is a few newtons).

The 0.25 m/s runs take twice the steps of the 0.5 m/s ones (the time step is set by the
sand's wave speed, not the pile's); a viscoplastic step costs 4-5 times a rate-independent one
here. About 6 minutes on 2 cores. A study, not a test: it prints a markdown table and writes it into docs/pile_driving.md
between <!-- rate:begin --> and <!-- rate:end --> (--no-write to print only).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "pile_driving.md"
SCENE = ROOT / "examples" / "pile_driving.toml"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples"))

SPEEDS = (0.25, 0.5)          # m/s
PENETRATION = 0.21            # m, every run (half a cell beyond the last depth compared)
DEPTHS = (0.1, 0.2)           # m, where the forces are compared


def rate_independent(scene, sand="sand"):
    """The scene with `sand`'s Perzyna viscoplasticity removed (same phi, cone, elasticity)."""
    material = dataclasses.replace(scene.materials[sand], fluidity=None, exponent=1.0)
    return dataclasses.replace(scene, materials={**scene.materials, sand: material})


def at_speed(scene, speed, penetration=PENETRATION):
    """The scene with every prescribed body at `speed` downwards, run until `penetration`."""
    for body in scene.bodies:
        if body.kinematics.type == "prescribed":
            scene = scene.with_value(f"bodies.{body.name}.velocity", [0.0, -speed])
    return scene.with_value("scene.duration", penetration / speed)


def run(scene, path, reuse):
    """Run `scene` into `path` (or reuse a complete file there): (Result, wall-clock seconds or None)."""
    import jaxmpm

    if reuse and path.exists():
        result = jaxmpm.Result.load(path)
        if result.complete:
            print(f"reusing {path}", flush=True)
            return result, None
    sim = jaxmpm.Simulation(scene)
    print(f"{path.name}: {sim.point_count} points, {sim.steps} steps of {sim.dt:.4g} s", flush=True)
    start = time.perf_counter()
    result = sim.run(progress=False, save_to=path)
    return result, time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="pile_rate_study", help="folder of the four HDF5 files")
    parser.add_argument("--reuse", action="store_true", help="skip runs whose complete file exists")
    parser.add_argument("--no-write", action="store_true", help="print only")
    arguments = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxmpm
    from plot_pile_driving import curves, force_at, read_pile
    from common import write_section

    out = Path(arguments.out)
    out.mkdir(parents=True, exist_ok=True)
    base = jaxmpm.load_scene(SCENE)
    sands = {"vp": ("viscoplastic", base), "ri": ("rate-independent", rate_independent(base))}
    rows, forces = [], {}
    for key, (label, scene) in sands.items():
        for speed in SPEEDS:
            path = out / f"pile_{key}_{speed:g}.h5"
            result, seconds = run(at_speed(scene, speed), path, arguments.reuse)
            pile = read_pile(jaxmpm.Scene.from_toml(result.scene_toml))
            data = curves(result, pile)
            values = [[force_at(data, data.resistance[part], depth, pile.cell / 2) for part in ("total", pile.tip)]
                      for depth in DEPTHS]
            forces[key, speed] = values
            steps = len(data.time)
            rows.append((label, speed, steps, values, seconds))
            print(f"  {label}, {speed:g} m/s: " + ", ".join(f"{v[0]:.0f} N (tip {v[1]:.0f} N) at {d:g} m"
                                                            for d, v in zip(DEPTHS, values)), flush=True)

    material = base.materials["sand"]
    lines = [f"Soil resistance F_z (whole ring, pile weight subtracted; mean over +- half a cell of penetration), "
             f"sand phi = {material.friction_angle:g} deg ({material.cone} cone); viscoplastic: fluidity "
             f"{material.fluidity:g} 1/s, exponent {material.exponent:g}. Cell {base.grid.cell:g} m.", "",
             "| sand | pile velocity [m/s] | steps | " + " | ".join(
                 f"total at {d:g} m [N] | tip at {d:g} m [N]" for d in DEPTHS) + " | run [s] |",
             "|---|---:|---:|" + "---:|---:|" * len(DEPTHS) + "---:|"]
    for label, speed, steps, values, seconds in rows:
        cells = " | ".join(f"{total:.0f} | {tip:.0f}" for total, tip in values)
        lines.append(f"| {label} | {speed:g} | {steps:,} | {cells} | {'-' if seconds is None else f'{seconds:.0f}'} |")
    lines.append("")
    slow, fast = SPEEDS
    for key, (label, _) in sands.items():
        ratios = ", ".join(f"{forces[key, fast][k][0] / forces[key, slow][k][0]:.3f} at {d:g} m"
                           for k, d in enumerate(DEPTHS))
        lines.append(f"- {label}: total at {fast:g} m/s / total at {slow:g} m/s = {ratios}")
    text = "\n".join(lines)
    print(text)
    if not arguments.no_write:
        write_section("<!-- rate:begin -->", "<!-- rate:end -->", text, DOC)
        print(f"wrote the table into {DOC}")


if __name__ == "__main__":
    sys.exit(main())
