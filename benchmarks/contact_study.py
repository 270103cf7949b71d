"""Contact against closed forms, at two or three cell sizes: the figures of docs/contact.md.

    python benchmarks/contact_study.py            # all studies (about 15 minutes on 2 cores)
    python benchmarks/contact_study.py --only gap

- active: examples/retaining_wall_active.toml (a smooth, then a rough wall leaving a level
  backfill): mean thrust before the wall moves against 1/2 K0 rho g H^2, and after 2 mm
  against Rankine's 1/2 Ka rho g H^2 and Coulomb's horizontal thrust;
- slide: a block on a held slab under gravity tilted by theta: acceleration against
  g (sin theta - mu cos theta);
- gap: an elastic block moving down onto a held slab at 1 m/s without gravity: the distance
  between the two surfaces when the contact force first acts (grid contact sees the bodies
  about a cell early: their shape functions overlap before they touch);
- friction: the small released wall of benchmarks/convergence_study.py (rigid at three cells,
  and elastic with E = 3 GPa at the two coarser ones) over 0.2 s: the backfill's force on the wall's flat back face (a
  `contact_force` probe with `facing`), whose vertical part Coulomb friction bounds, |F_y| /
  |F_x| <= (mu + tan theta) / (1 - mu tan theta) on a face turned by theta.
A study, not a test: it prints markdown tables and writes each into its section of
docs/contact.md (between <!-- NAME:begin --> and <!-- NAME:end -->; --no-write to print only).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "contact.md"
G = 9.81
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import write_section  # noqa: E402


class Table:
    """Markdown lines, printed as they come and kept for the docs section."""

    def __init__(self):
        self.lines = []

    def __call__(self, line=""):
        print(line, flush=True)
        self.lines.append(line)

    def text(self):
        return "\n".join(self.lines).strip()


def block_on_slab(cell, theta_degrees=0.0, friction=0.0, drop_speed=0.0, start_gap=0.0, duration=0.2):
    """An elastic block (0.2 x 0.1 m) above (or on) a held slab, APIC, gravity tilted by theta
    (or none, with the block moving down at drop_speed)."""
    from jaxmpm import Body, Boundaries, Contact, Grid, Kinematics, LinearElastic, Numerics, Probe, Rectangle, Scene

    theta = math.radians(theta_degrees)
    gravity = (0.0, 0.0) if drop_speed else (G * math.sin(theta), -G * math.cos(theta))
    bottom = 0.1 + start_gap
    return Scene(
        name="block_on_slab",
        grid=Grid(size=(1.0, 0.4), cell=cell, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={"rubber": LinearElastic(density=1000.0, young=1.0e6, poisson=0.3)},
        bodies=(
            Body("slab", "rubber", Rectangle((0.0, 0.0), (1.0, 0.1)), kinematics=Kinematics("prescribed", (0.0, 0.0))),
            Body("block", "rubber", Rectangle((0.2, bottom), (0.4, bottom + 0.1)), velocity=(0.0, -drop_speed)),
        ),
        contacts=(Contact(("block", "slab"), friction),),
        gravity=gravity,
        duration=duration,
        output_every=duration / 4,
        numerics=Numerics(shape="linear", ppc=2, transfer="apic"),
        probes=(Probe("move", "body_displacement", body="block"), Probe("load", "contact_force", pair=("block", "slab"))),
    )


def slide_study(cells, emit):
    import jaxmpm
    import numpy as np

    emit("| theta, mu | expected a [m/s^2] | " + " | ".join(f"cell {c:g} m" for c in cells) + " |")
    emit("|---|---:|" + "---:|" * len(cells))
    for theta, mu in [(30.0, 0.3), (30.0, 0.0), (40.0, 0.5)]:
        expected = G * (math.sin(math.radians(theta)) - mu * math.cos(math.radians(theta)))
        row = []
        for cell in cells:
            sim = jaxmpm.Simulation(block_on_slab(cell, theta, mu))
            x = np.asarray(sim.probes()["move"][:, 0])
            start = len(sim.time) // 3
            measured = 2.0 * np.polyfit(sim.time[start:], x[start:], 2)[0]
            row.append(f"{measured:.4f} ({100 * (measured / expected - 1):+.2f} %)")
        emit(f"| {theta:g} deg, {mu:g} | {expected:.4f} | " + " | ".join(row) + " |")


def gap_study(cells, emit):
    import jaxmpm
    import numpy as np

    emit("| cell h [m] | gap when the contact force first acts [m] | gap / h |")
    emit("|---:|---:|---:|")
    for cell in cells:
        speed, start_gap = 1.0, 0.05
        sim = jaxmpm.Simulation(block_on_slab(cell, drop_speed=speed, start_gap=start_gap, duration=0.06))
        probes = sim.probes()
        load = np.abs(np.asarray(probes["load"][:, 1]))
        first = int(np.argmax(load > 1e-9 * load.max()))
        # the block's lowest material (points sit half a point spacing above its surface) has
        # moved by the block's displacement; the slab's top stays at y = 0.1
        surface = 0.1 + start_gap + float(probes["move"][first - 1, 1])
        gap = surface - 0.1
        emit(f"| {cell:g} | {gap:.4f} | {gap / cell:.2f} |")


def active_study(cells, emit):
    import jaxmpm
    import numpy as np

    scene = jaxmpm.load_scene(ROOT / "examples" / "retaining_wall_active.toml")
    sand = scene.materials[scene.bodies[0].material]
    height = max(vertex[1] for vertex in scene.bodies[0].region.vertices)
    phi = math.radians(sand.friction_angle)
    weight = 0.5 * sand.density * G * height**2
    at_rest, rankine = weight * (1 - math.sin(phi)), weight * (1 - math.sin(phi)) / (1 + math.sin(phi))
    emit(f"1/2 K0 rho g H^2 = {at_rest:.1f} N/m, Rankine 1/2 Ka rho g H^2 = {rankine:.1f} N/m.")
    emit()
    emit("| wall friction mu | Coulomb (horizontal) [N/m] | cell [m] | points | thrust at rest [N/m] (vs K0) "
          "| mean thrust over the last 0.05 s [N/m] (vs Rankine) | run [s] |")
    emit("|---:|---:|---:|---:|---:|---:|---:|")
    for mu in (0.0, 0.4):
        delta = math.atan(mu)
        coulomb = weight * math.cos(phi) ** 2 / (
            math.cos(delta) * (1 + math.sqrt(math.sin(phi + delta) * math.sin(phi) / math.cos(delta))) ** 2
        ) * math.cos(delta)
        for cell in cells:
            trial = scene.with_value("grid.cell", cell).with_value(f"contacts.{scene.contacts[0].name}.friction", mu)
            trial = trial.with_value("scene.snapshot_fields", ["x"])
            sim = jaxmpm.Simulation(trial)
            start = time.perf_counter()
            thrust = np.asarray(sim.probes()["thrust"][:, 0])
            seconds = time.perf_counter() - start
            before = -thrust[(sim.time > 0.01) & (sim.time < 0.05)].mean()
            after = -thrust[sim.time > sim.time[-1] - 0.05].mean()
            emit(f"| {mu:g} | {coulomb:.1f} | {cell:g} | {sim.point_count:,} | {before:.1f} ({100 * (before / at_rest - 1):+.1f} %) "
                  f"| {after:.1f} ({100 * (after / rankine - 1):+.1f} %) | {seconds:.0f} |")


def friction_study(cells, emit, duration=0.2, mu=0.4, window=0.05):
    import dataclasses

    import jaxmpm
    import numpy as np
    from convergence_study import small_wall

    emit("Mean over each 0.05 s ending at t: |F_y| / |F_x| of the back face's force against Coulomb's "
         f"bound (mu = {mu:g}), and the wall top's displacement.")
    emit()
    emit("| wall | cell [m] | t [s] | rotation [deg] | top [mm] | back face F_x [N/m] | F_y [N/m] "
         "| abs(F_y / F_x) | Coulomb's bound | run [s] |")
    emit("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    faces = (jaxmpm.Probe("back", "contact_force", pair=("sand", "wall"), facing=(-1.0, 0.0)),
             jaxmpm.Probe("rotation", "body_rotation", body="wall"))
    for label, kinematics, young in (("rigid", "rigid", 30.0e9), ("elastic, E = 3 GPa", "free", 3.0e9)):
        for cell in cells if kinematics == "rigid" else cells[:2]:   # the elastic wall at its own step: 27 min at h/4
            scene = small_wall(kinematics, young, **{"grid.cell": cell, "scene.duration": duration})
            scene = dataclasses.replace(scene, probes=scene.probes + faces)
            start = time.perf_counter()
            sim = jaxmpm.Simulation(scene)
            probes = {name: np.asarray(value) for name, value in sim.probes().items()}
            seconds = time.perf_counter() - start
            for end in np.arange(2 * window, duration + 1e-9, window):
                inside = (sim.time > end - window) & (sim.time <= end)
                force = probes["back"][inside].mean(axis=0)
                tilt = math.tan(abs(probes["rotation"][inside, 0].mean()))
                bound = (mu + tilt) / (1.0 - mu * tilt)
                last = np.flatnonzero(inside)[-1]
                emit(f"| {label} | {cell:g} | {end:.2f} | {math.degrees(probes['rotation'][last, 0]):.2f} "
                     f"| {-1e3 * probes['wall_top'][last, 0]:.2f} | {force[0]:.1f} | {force[1]:.1f} "
                     f"| {abs(force[1] / force[0]):.2f} | {bound:.2f} | {seconds:.0f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=["active", "slide", "gap", "friction"])
    parser.add_argument("--no-write", action="store_true", help="print only")
    arguments = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    studies = {"gap": (gap_study, [0.04, 0.02, 0.01]), "slide": (slide_study, [0.02, 0.01]),
               "active": (active_study, [0.025, 0.0125]), "friction": (friction_study, [0.025, 0.0125, 0.00625])}
    for name, (study, cells) in studies.items():
        if arguments.only in (None, name):
            table = Table()
            study(cells, table)
            if not arguments.no_write:
                write_section(f"<!-- {name}:begin -->", f"<!-- {name}:end -->", table.text(), DOC)


if __name__ == "__main__":
    sys.exit(main())
