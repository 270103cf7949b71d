"""Which numerical settings stay stable, at scene level: the tables of docs/stability.md.

    python benchmarks/stability_study.py                 # every part; rewrites docs/stability.md
    python benchmarks/stability_study.py --parts cfl     # one part (cfl, sweeps, float32)
    python benchmarks/stability_study.py --no-write      # print only

Parts (small scenes, each run a few seconds; float64 unless stated):

cfl      the largest stable scene.cfl on a 0.1 grid up to 1.0 (the most validation allows) for
         every shape x transfer (FLIP 0.99, APIC) x update (MUSL, USL), on a released elastic
         column under gravity (no initial stress, no damping) and on a dry sand column collapse
         (Drucker-Prager, geostatic start). Searched downwards from 1.0: the first stable
         value is reported.
sweeps   the default numerics (preset "balanced") on the collapse and on a rigid footing
         resting on a geostatic sand layer, with the friction angle 5-50 degrees, Young's
         modulus 1e5-1e8 Pa and Perzyna gamma*dt 1e-8-1e8; the Perzyna result is placed between
         the elastic and the rate-independent (Drucker-Prager) one.
bonded   the rigid footing bonded to the sand (no contact pair) for each shape function (it
         was unstable with bspline2 until the bonded interface was solved with the body).
float32  an undamped vibrating bar over 1e5 steps in float32 and float64: energy drift, and
         the derivative of the tip displacement with respect to Young's modulus (forward mode).

A run is *stable* when it finishes without the solver's error flags (a point non-finite or
off the grid: SimulationError) and its energy balance holds at every output:
    kinetic + elastic energy  <=  1.1 x (largest work done by gravity so far
                                         + initial elastic energy) + 1e-9 J/m
(a stable run can only dissipate what gravity released; an unstable mode grows without bound).
The elastic energy is sum V sigma : C^-1 : sigma / 2 with each body's E and nu.

A study, not a test: about 10 minutes on 2 cores. It writes docs/stability.md between
<!-- NAME:begin --> and <!-- NAME:end --> markers (the whole file if it is missing).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "stability.md"
CFLS = tuple(round(0.1 * k, 1) for k in range(10, 0, -1))        # 1.0, 0.9, ..., 0.1
SCHEMES = [(shape, transfer, update) for shape in ("linear", "gimp", "bspline2")
           for transfer in ("flip", "apic") for update in ("musl", "usl")]
ENERGY_SLACK, ENERGY_FLOOR = 1.1, 1e-9
FIELDS = ["x", "v", "mass", "volume", "stress"]


# --------------------------------------------------------------------------- scenes


def numerics(shape=None, transfer=None, update=None, dtype="float64", preset=None):
    table = {"dtype": dtype, "ppc": 2}
    if preset is not None:
        table["preset"] = preset
    for key, value in (("shape", shape), ("transfer", transfer), ("update", update)):
        if value is not None:
            table[key] = value
    if transfer == "flip":
        table["flip"] = 0.99
    return table


def elastic_column(cfl=0.4, duration=0.1, **choices):
    """A 0.2 x 0.1 m elastic column (E = 1 MPa, nu = 0, rho = 1800), 20 x 10 cells, released
    under gravity with no initial stress and no damping: it oscillates about its settled state
    (c_p = 23.6 m/s; 0.1 s is about six periods of its first mode)."""
    import jaxmpm

    return jaxmpm.Scene.from_dict({
        "scene": {"name": "elastic_column", "duration": duration, "cfl": cfl, "output_every": duration / 40,
                  "snapshot_fields": FIELDS},
        "grid": {"size": [0.2, 0.12], "cell": 0.01,
                 "boundaries": {"left": "slip", "right": "slip", "bottom": "fixed", "top": "free"}},
        "numerics": numerics(**choices),
        "materials": {"soil": {"model": "linear_elastic", "density": 1800.0, "young": 1.0e6, "poisson": 0.0}},
        "bodies": [{"name": "column", "material": "soil", "region": {"rectangle": [[0.0, 0.0], [0.2, 0.1]]}}],
    })


SAND = {"model": "drucker_prager", "density": 2650.0, "young": 0.84e6, "poisson": 0.3, "friction_angle": 19.8,
        "cone": "plane_strain"}


def collapse(cfl=0.4, duration=0.25, sand=None, **choices):
    """examples/column_collapse.toml at a quarter of its size: a 0.1 x 0.05 m column of dry
    sand (16 x 8 cells of 6.25 mm, 512 points) in its geostatic state against a smooth wall,
    released onto a rough base; the grid is 40 x 10 cells."""
    import jaxmpm

    return jaxmpm.Scene.from_dict({
        "scene": {"name": "collapse", "duration": duration, "cfl": cfl, "output_every": duration / 25,
                  "snapshot_fields": FIELDS},
        "grid": {"size": [0.25, 0.0625], "cell": 0.00625,
                 "boundaries": {"left": "slip", "right": "free", "bottom": "fixed", "top": "free"}},
        "numerics": numerics(**choices),
        "materials": {"sand": dict(SAND) | (sand or {})},
        "bodies": [{"name": "column", "material": "sand", "region": {"rectangle": [[0.0, 0.0], [0.1, 0.05]]},
                    "initial_stress": {"geostatic": {"k0": "jaky"}}}],
    })


def footing(cfl=0.4, duration=0.2, sand=None, **choices):
    """A rigid strip footing, 0.1 m wide and 0.05 m high (rho = 20000: 9.8 kPa on the sand),
    resting on a 0.4 x 0.15 m layer of sand in its geostatic state through a rough contact
    (mu = 0.5), released at t = 0 (16 x 10 cells of 25 mm; examples/calibrate_twin_scene.toml
    with a rigid footing). Bonded (no [[contacts]]), it was unstable with bspline2 before
    bodies.solve_rigid_motions (docs/stability.md)."""
    import jaxmpm

    material = {"model": "drucker_prager", "density": 1800.0, "young": 2.0e6, "poisson": 0.3,
                "friction_angle": 30.0, "cone": "plane_strain"} | (sand or {})
    return jaxmpm.Scene.from_dict({
        "scene": {"name": "footing", "duration": duration, "cfl": cfl, "output_every": duration / 20,
                  "snapshot_fields": FIELDS},
        "grid": {"size": [0.4, 0.25], "cell": 0.025,
                 "boundaries": {"left": "slip", "right": "slip", "bottom": "fixed", "top": "free"}},
        "numerics": numerics(**choices),
        "materials": {"sand": material,
                      "block": {"model": "linear_elastic", "density": 20000.0, "young": 5.0e7, "poisson": 0.2}},
        "bodies": [
            {"name": "layer", "material": "sand", "region": {"rectangle": [[0.0, 0.0], [0.4, 0.15]]},
             "initial_stress": {"geostatic": {"k0": "jaky"}}},
            {"name": "footing", "material": "block", "region": {"rectangle": [[0.15, 0.15], [0.25, 0.2]]},
             "kinematics": {"type": "rigid"}},
        ],
        "contacts": [{"pair": ["layer", "footing"], "friction": 0.5}],
        "probes": [{"name": "footing", "kind": "body_displacement", "body": "footing"}],
    })


def elastic_stand_in(scene, name="sand"):
    """The scene with material `name` made linear elastic (same density, E, nu; Jaky's K0 of
    the sand's friction angle given as a number, since the elastic material has none)."""
    import jaxmpm
    from jaxmpm.scene import Geostatic

    sand = scene.materials[name]
    elastic = jaxmpm.LinearElastic(density=sand.density, young=sand.young, poisson=sand.poisson)
    k0 = Geostatic(1.0 - math.sin(math.radians(sand.friction_angle)))
    bodies = tuple(dataclasses.replace(body, initial_stress=k0) if body.material == name and body.initial_stress
                   else body for body in scene.bodies)
    return dataclasses.replace(scene, materials={**scene.materials, name: elastic}, bodies=bodies)


def rate_independent(scene, name="sand"):
    material = dataclasses.replace(scene.materials[name], fluidity=None, exponent=1.0)
    return dataclasses.replace(scene, materials={**scene.materials, name: material})


# --------------------------------------------------------------------------- measures


def elastic_energy(stress, volume, young, poisson):
    """sum V sigma : C^-1 : sigma / 2 over points (stress (..., N, 3, 3))."""
    import numpy as np

    square = np.sum(stress * stress, axis=(-2, -1))
    trace = np.trace(stress, axis1=-2, axis2=-1)
    density = ((1.0 + poisson) * square - poisson * trace**2) / (2.0 * young)
    return np.sum(volume * density, axis=-1)


def energies(scene, result, params=None):
    """(kinetic, elastic, gravity work) per snapshot [J/m], summed over bodies."""
    import numpy as np

    kinetic = elastic = work = 0.0
    for body in scene.bodies:
        snap = result.snapshots[body.name]
        mass, v, x = snap["mass"], snap["v"], snap["x"]
        kinetic = kinetic + 0.5 * np.sum(mass * np.sum(v * v, axis=-1), axis=-1)
        work = work + np.sum(mass * ((x - x[0]) @ np.asarray(scene.gravity)), axis=-1)
        if body.kinematics.type == "free":
            values = (params or {}).get(body.material) or dataclasses.asdict(scene.material_of(body))
            elastic = elastic + elastic_energy(snap["stress"], snap["volume"], values["young"], values["poisson"])
    return kinetic, elastic, work


@dataclasses.dataclass
class Outcome:
    status: str            # "stable", "energy", "error"
    message: str
    steps: int
    dt: float
    ratio: float           # max over outputs of (kinetic + elastic) / (work + initial elastic)
    result: object = None
    finite: bool = True


def run(scene, sim=None, params=None):
    """Run a scene (or a built Simulation with other params) and classify the outcome."""
    import jaxmpm
    import numpy as np

    sim = sim or jaxmpm.Simulation(scene)
    try:
        result = sim.run(params, progress=False)
    except jaxmpm.SimulationError as error:
        return Outcome("error", str(error), sim.steps, sim.dt, math.nan, error.result, False)
    values = None
    if params is not None:
        values = {name: {key: float(value) for key, value in entry.items()}
                  for name, entry in params["materials"].items()}
    kinetic, elastic, work = energies(scene, result, values)
    budget = np.maximum.accumulate(work) + elastic[0]      # the most energy released so far
    excess = kinetic + elastic - (ENERGY_SLACK * budget + ENERGY_FLOOR)
    ratio = float(np.max((kinetic + elastic)[1:] / np.maximum(budget[1:], ENERGY_FLOOR)))
    finite = all(np.all(np.isfinite(v)) for body in result.snapshots.values() if isinstance(body, dict)
                 for v in body.values())
    status = "stable" if np.all(excess <= 0.0) and finite else "energy"
    message = "" if status == "stable" else f"energy grew to {ratio:.3g} x the work of gravity"
    return Outcome(status, message, sim.steps, sim.dt, ratio, result, finite)


def runout(scene, result):
    """(L - L0) / L0 of the collapse, from the rightmost point at the start and the end."""
    x = result.snapshots["column"]["x"][..., 0]
    half = 0.5 * scene.grid.cell / scene.numerics.ppc
    return float((x[-1].max() - x[0].max()) / (x[0].max() + half))


def settlement(result):
    """Downward displacement of the footing's centre of mass at the end [m]."""
    return float(-result.probes["footing"][-1, 1])


# --------------------------------------------------------------------------- parts


def short(message):
    """The failure kind and step of a SimulationError message, for a table cell."""
    match = re.search(r"step (\d+) .* (left the grid|became non-finite)", message)
    return f"{match.group(2)} at step {match.group(1)}" if match else message


def largest_stable_cfl(build, scheme, log):
    """(largest stable cfl on CFLS or None, [(cfl, Outcome)] tried), searching down from 1.0."""
    tried = []
    for cfl in CFLS:
        outcome = run(build(cfl=cfl, shape=scheme[0], transfer=scheme[1], update=scheme[2]))
        tried.append((cfl, outcome))
        log(f"    {build.__name__} {'/'.join(scheme)} cfl {cfl}: {outcome.status} {outcome.message}")
        if outcome.status == "stable":
            return cfl, tried
    return None, tried


def part_cfl(log):
    rows = ["| shape | transfer | update | elastic column: largest stable cfl | (unstable above it: how) "
            "| sand collapse: largest stable cfl | (unstable above it: how) |",
            "|---|---|---|---:|---|---:|---|"]
    findings = {}
    for scheme in SCHEMES:
        cells = []
        for build in (elastic_column, collapse):
            best, tried = largest_stable_cfl(build, scheme, log)
            findings[(build.__name__, scheme)] = (best, tried)
            failures = [(cfl, o) for cfl, o in tried if o.status != "stable"]
            how = "; ".join(f"{cfl}: {short(o.message)}" for cfl, o in failures[:2]) or "none up to 1.0"
            if len(failures) > 2:
                how += f"; ... ({len(failures)} unstable values)"
            cells += ["< 0.1" if best is None else f"{best:.1f}", how]
        transfer = "FLIP 0.99" if scheme[1] == "flip" else "APIC"
        rows.append(f"| {scheme[0]} | {transfer} | {scheme[2].upper()} | " + " | ".join(cells) + " |")
        log(rows[-1])
    text = "\n".join(rows)

    # What validation does beyond cfl = 1: cfl > 1 and dt above the limit are refused.
    import jaxmpm

    refusals = []
    for key, value in (("scene.cfl", 1.1), ("scene.dt", 1.5 * elastic_column().stable_dt)):
        try:
            elastic_column().with_value(key, value)
            refusals.append(f"- `{key} = {value:.4g}`: accepted")
        except jaxmpm.SceneError as error:
            refusals.append(f"- `{key} = {value:.4g}`: refused, *{error}*")
    text += "\n\nBeyond cfl = 1 (the elastic column, stable limit h / c_p = "
    text += f"{elastic_column().stable_dt:.4g} s):\n\n" + "\n".join(refusals)
    return text, findings


def part_sweeps(log):
    import jaxmpm

    sections = {}
    choices = {"preset": "balanced"}

    # Friction angle: one Simulation per scene (phi is a parameter; Jaky's K0 follows it).
    rows = ["| friction angle | collapse: outcome | runout (L - L0)/L0 | footing: outcome | settlement [mm] |",
            "|---:|---|---:|---|---:|"]
    sims = {"collapse": jaxmpm.Simulation(collapse(**choices)), "footing": jaxmpm.Simulation(footing(**choices))}
    for phi in (5.0, 15.0, 30.0, 45.0, 50.0):
        cells = []
        for name, sim in sims.items():
            params = jaxmpm.with_values(sim.params, {"sand.friction_angle": phi})
            outcome = run(sim.scene, sim, params)
            measure = math.nan if outcome.status == "error" else (
                runout(sim.scene, outcome.result) if name == "collapse" else 1e3 * settlement(outcome.result))
            cells += [describe(outcome), f"{measure:.3g}"]
        rows.append(f"| {phi:g} | " + " | ".join(cells) + " |")
        log(rows[-1])
    sections["friction"] = "\n".join(rows)

    # Young's modulus: dt shrinks like 1 / sqrt(E), so each is its own Simulation.
    rows = ["| E [Pa] | collapse: steps (dt) | outcome | runout | footing: steps (dt) | outcome | settlement [mm] |",
            "|---:|---|---|---:|---|---|---:|"]
    for young in (1e5, 1e6, 1e7, 1e8):
        cells = []
        for name, build, duration in (("collapse", collapse, 0.25), ("footing", footing, 0.1)):
            scene = build(duration=duration, sand={"young": young}, **choices)
            outcome = run(scene)
            measure = math.nan if outcome.status == "error" else (
                runout(scene, outcome.result) if name == "collapse" else 1e3 * settlement(outcome.result))
            cells += [f"{outcome.steps:,} ({outcome.dt:.2g} s)", describe(outcome), f"{measure:.3g}"]
        rows.append(f"| {young:.0e} | " + " | ".join(cells) + " |")
        log(rows[-1])
    sections["young"] = "\n".join(rows)

    # Perzyna gamma*dt: one Simulation per scene (fluidity is a parameter), against the
    # rate-independent and the elastic runs of the same scene.
    rows = ["| gamma*dt | collapse: outcome | runout | fraction of the way elastic -> DP | footing: outcome "
            "| settlement [mm] | fraction elastic -> DP |", "|---:|---|---:|---:|---|---:|---:|"]
    columns = []
    for name, build in (("collapse", collapse), ("footing", footing)):
        scene = build(sand={"fluidity": 1.0, "exponent": 1.0}, **choices)
        measure = (lambda r, s=scene: runout(s, r)) if name == "collapse" else (lambda r: 1e3 * settlement(r))
        limits = {}
        for label, variant in (("DP", rate_independent(scene)), ("elastic", elastic_stand_in(scene))):
            outcome = run(variant)
            limits[label] = measure(outcome.result) if outcome.status != "error" else math.nan
            log(f"    {name} {label}: {describe(outcome)} {limits[label]:.4g}")
        sim = jaxmpm.Simulation(scene)
        column = []
        for exponent in range(-8, 9):
            rate = 10.0**exponent
            params = jaxmpm.with_values(sim.params, {"sand.fluidity": rate / sim.dt})
            outcome = run(scene, sim, params)
            value = measure(outcome.result) if outcome.status != "error" else math.nan
            fraction = (value - limits["elastic"]) / (limits["DP"] - limits["elastic"])
            column.append((rate, describe(outcome), value, fraction))
            log(f"    {name} gamma*dt {rate:.0e}: {describe(outcome)} {value:.4g} ({fraction:.3f})")
        columns.append((limits, column))
    for index in range(17):
        (rate, *a), (_, *b) = columns[0][1][index], columns[1][1][index]
        rows.append(f"| {rate:.0e} | {a[0]} | {a[1]:.4g} | {a[2]:.3f} | {b[0]} | {b[1]:.4g} | {b[2]:.3f} |")
    (c_lim, _), (f_lim, _) = columns
    rows.append(f"| elastic | | {c_lim['elastic']:.4g} | 0 | | {f_lim['elastic']:.4g} | 0 |")
    rows.append(f"| Drucker-Prager | | {c_lim['DP']:.4g} | 1 | | {f_lim['DP']:.4g} | 1 |")
    sections["perzyna"] = "\n".join(rows)
    return sections


def describe(outcome):
    if outcome.status == "stable":
        return "finished, finite"
    if outcome.status == "energy":
        return f"finished, **energy grew** ({outcome.ratio:.2g} x)"
    return f"**stopped**: {short(outcome.message)}"


BAR_NUMERICS = {
    "linear, FLIP 1.0 (the example's)": {"shape": "linear", "transfer": "flip", "flip": 1.0, "update": "musl"},
    "bspline2, APIC (the default)": {"shape": "bspline2", "transfer": "apic", "update": "musl"},
}


def bar(dtype, steps, cell=0.5, choices=None):
    """examples/vibrating_bar.toml (E = 100 Pa, rho = 1, nu = 0, c = 10 m/s, v0 = 0.1 m/s, no
    gravity, FLIP 1.0, linear shapes) with cells of `cell` m: 25 m x 1 m, 400 points at 0.5 m;
    `steps` steps at cfl 0.4."""
    import jaxmpm

    dt = 0.4 * cell / 10.0
    output = steps // 100
    return jaxmpm.Scene.from_dict({
        "scene": {"name": "bar", "gravity": [0.0, 0.0], "duration": steps * dt, "dt": dt,
                  "output_every": output * dt, "snapshot_fields": FIELDS},
        "grid": {"size": [30.0, 1.0], "cell": cell,
                 "boundaries": {"left": "fixed", "right": "free", "bottom": "slip", "top": "slip"}},
        "numerics": {"ppc": 2, "dtype": dtype} | (choices or BAR_NUMERICS["linear, FLIP 1.0 (the example's)"]),
        "materials": {"rod": {"model": "linear_elastic", "density": 1.0, "young": 100.0, "poisson": 0.0}},
        "bodies": [{"name": "bar", "material": "rod", "region": {"rectangle": [[0.0, 0.0], [25.0, 1.0]]},
                    "velocity": [0.1, 0.0]}],
        "probes": [{"name": "tip", "kind": "displacement", "at": [25.0, 0.5]}],
    })


def part_bonded(log):
    """The rigid footing bonded to the sand (no [[contacts]]) against the same footing in a
    rough contact, for each shape function, at two cfl values."""
    rows = ["| shape | cfl | bonded rigid footing | in contact (mu = 0.5) |", "|---|---:|---|---|"]
    for shape in ("linear", "gimp", "bspline2"):
        for cfl in (0.4, 0.1):
            cells = []
            for bonded in (True, False):
                scene = footing(cfl=cfl, duration=0.1, shape=shape, transfer="apic", update="musl")
                if bonded:
                    scene = dataclasses.replace(scene, contacts=())
                outcome = run(scene)
                cells.append(describe(outcome))
            rows.append(f"| {shape} | {cfl} | " + " | ".join(cells) + " |")
            log(rows[-1])
    return "\n".join(rows)


def part_float32(log, steps):
    rows = ["| numerics | dtype | steps | wall [s] | energy drift (E_end - E_0)/E_0 | max abs(E - E_0)/E_0 "
            "| tip at the end [m] | d tip / d E [m/Pa] | forward-mode wall [s] |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    found, notes = {}, []
    for label, choices in BAR_NUMERICS.items():
        found[label] = bar_pair(log, steps, choices, label, rows)
        a, b = found[label]["float64"], found[label]["float32"]
        notes.append(f"- {label}: float32 against float64, the tip at the end differs by "
                     f"{abs(b['tip'] - a['tip']) / abs(a['tip']):.2e} (relative), d tip / d E by "
                     f"{abs(b['slope'] - a['slope']) / abs(a['slope']):.2e}; energy drift {b['drift']:.2e} "
                     f"(float32) against {a['drift']:.2e} (float64).")
    return "\n".join(rows) + "\n\n" + "\n".join(notes), found


def bar_pair(log, steps, choices, label, rows):
    import jax
    import jax.numpy as jnp
    import jaxmpm
    import numpy as np

    found = {}
    for dtype in ("float64", "float32"):
        scene = bar(dtype, steps, choices=choices)
        sim = jaxmpm.Simulation(scene)
        start = time.perf_counter()
        outcome = run(scene, sim)
        wall = time.perf_counter() - start
        kinetic, elastic, _ = energies(scene, outcome.result)
        total = kinetic + elastic
        drift = (total[-1] - total[0]) / total[0]
        spread = np.max(np.abs(total - total[0])) / total[0]
        tip = float(outcome.result.probes["tip"][-1, 0])

        def tip_of(young):
            params = jaxmpm.with_values(sim.params, {"rod.young": young})
            return sim.probes(params)["tip"][-1, 0]

        start = time.perf_counter()
        young = jnp.asarray(100.0, sim.dtype)
        _, slope = jax.jvp(tip_of, (young,), (jnp.ones_like(young),))
        slope = float(slope)
        jvp_wall = time.perf_counter() - start
        found[dtype] = dict(drift=drift, spread=spread, tip=tip, slope=slope, status=outcome.status)
        rows.append(f"| {label} | {dtype} | {sim.steps:,} | {wall:.1f} | {drift:.2e} | {spread:.2e} | {tip:.6f} "
                    f"| {slope:.6e} | {jvp_wall:.1f} |")
        log(rows[-1])
    return found


# --------------------------------------------------------------------------- document


def machine_info() -> str:
    import jax

    cpu = "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    commit = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"],
                            capture_output=True, text=True).stdout.strip() or "unknown"
    return (f"{datetime.date.today().isoformat()}, {cpu}, {cores} cores, Python {platform.python_version()}, "
            f"jax {jax.__version__} ({jax.default_backend()}), commit {commit}")


def write_section(name: str, body: str):
    """Replace (or append) the part of docs/stability.md between this section's markers."""
    from common import write_section as write_between

    write_between(f"<!-- {name}:begin -->", f"<!-- {name}:end -->", body, DOC)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=["cfl", "sweeps", "bonded", "float32"],
                        choices=["cfl", "sweeps", "bonded", "float32"])
    parser.add_argument("--steps", type=int, default=100_000, help="steps of the float32 bar")
    parser.add_argument("--no-write", action="store_true", help="print only; leave docs/stability.md alone")
    arguments = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    begun = time.perf_counter()

    def log(text):
        print(text, file=sys.stderr, flush=True)

    def emit(name, text, seconds):
        print(f"\n## {name}\n\n{text}\n", flush=True)
        if not arguments.no_write:
            write_section(name, f"{text}\n\n(measured {machine_info()}; {seconds:.0f} s)")

    if "cfl" in arguments.parts:
        start = time.perf_counter()
        text, _ = part_cfl(log)
        emit("cfl", text, time.perf_counter() - start)
    if "sweeps" in arguments.parts:
        start = time.perf_counter()
        sections = part_sweeps(log)
        for name, text in sections.items():
            emit(name, text, time.perf_counter() - start)
    if "bonded" in arguments.parts:
        start = time.perf_counter()
        emit("bonded", part_bonded(log), time.perf_counter() - start)
    if "float32" in arguments.parts:
        start = time.perf_counter()
        text, _ = part_float32(log, arguments.steps)
        emit("float32", text, time.perf_counter() - start)
    log(f"total {time.perf_counter() - begun:.0f} s")


if __name__ == "__main__":
    main()
