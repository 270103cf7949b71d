"""Time-step and cell convergence of the headline quantities: the tables of docs/convergence.md.

    python benchmarks/convergence_study.py                 # every study (about 25 min on 2 cores)
    python benchmarks/convergence_study.py --study wall    # one: wall | stiff | subcycled | examples | cells | example_cells | relaxation | shapes | pile_jitter | stress | perzyna_law | perzyna_noise

Each run is a forward run of a scene at some numerics; the quantities are read at every
output time and the largest relative change between two runs is reported.

- wall: a small rigid wall (0.05 x 0.35 m, concrete density) on a 0.1 m sand foundation holds a
  0.3 m rate-independent Drucker-Prager backfill and is released: its top's horizontal
  displacement at 0.1 and 0.2 s, at cfl 0.4, 0.2, 0.1, with plain APIC (numerics.relaxation
  = 0, the default) and with relaxation 10.
- stiff: the same wall as a rigid body and as a free elastic body (E = 3 and 30 GPa; the
  elastic wall's p-wave sets a step 20-60 times shorter), each elastic wall against the rigid
  one at the same dt; and a pile (0.04 x 0.3 m, steel density, E = 30 GPa as an elastic body)
  dropped at 2 m/s into the same sand, its sinking (mean displacement) to rest over 0.1 s, as a
  rigid body at cfl 0.4 ... 0.05 and at the elastic pile's dt, and as an elastic body at cfl
  0.4 ... 0.05 of its own.
- examples: the headline quantities of examples/retaining_wall.toml (wall top, rotation;
  every 0.05 s), pile_driving.toml (head force every 5 cm of penetration, heave) and
  column_collapse.toml (front, centre of mass), each over its whole run, at the shipped cfl
  and at half, and at a quarter with the shipped relaxation. Changes against the finer run's
  largest value (`relative_change`) and against each output's own (`own_change`).
- subcycled: the same two elastic walls and the elastic pile (in plane strain, and in
  axisymmetry on the axis) subcycled at the sand's step (`kinematics.substeps = "auto"`),
  against each as an ordinary free body at its own step (brute force) and against the rigid
  body at the sand's step; with run times.
- cells: the small wall at h, h/2, h/4 (ppc 2) and at h with ppc 3: observed order and the
  Richardson-extrapolated value p = log2((q_h - q_h/2) / (q_h/2 - q_h/4)),
  q* = q_h/4 + (q_h/4 - q_h/2) / (2^p - 1).
- example_cells: the same for each example's headline quantities at their last time (about
  an hour on 2 cores: h/4 has 16 times the points and twice the steps of h each).
- relaxation: each example at its shipped cfl with numerics.relaxation (kappa) = 10, 25, 100
  and 1000, at its shipped cell h and at h/2: the headline quantities at the last time of the
  dt study, and how far each lies from kappa = 1000 (almost pure FLIP). kappa is a numerical
  parameter; this shows how much the answer depends on it and whether that shrinks with the
  cell (about an hour on 2 cores, most of it the wall at h/2).
- stress: the retaining wall (to 0.35 s) with its stress update in K = 1, 2, 4, 16 substeps
  (numerics.stress_substeps), and with the Perzyna exponent 1 and 3, at cfl 0.4 and 0.2: the
  update's own share of the Delta-t error (about 75 minutes on 2 cores, most of it K = 16).
- perzyna_law: the small wall over 0.12 s with its backfill made Perzyna-viscoplastic
  (exponent N, fluidity gamma) and its stress update in 4-64 substeps, so that the update's
  own error is gone, at cfl 0.4, 0.2 and 0.1: the first-order error the rest of the step leaves,
  in mm and against the top's own value, beside the rate-independent backfill's (about 25
  minutes).
- perzyna_noise: why a Perzyna law of exponent N > 1 adds to that error. The same small wall
  (fluidity 0.5 1/s; N = 3 in 16 substeps, N = 1 in 4) at numerics.relaxation 10, 25, 100 and
  cfl 0.4 and 0.2, with every step kept: the top, its change per halving, and the rectification
  J = mean(rate^(1/N)) / mean(rate)^(1/N) of each sand point's plastic rate over 2 ms windows
  (0.04-0.12 s; 1 for a steady rate, below 1 when the rate fluctuates: the overstress the
  law carries on average falls short of what the mean rate needs, since (q - m p) / m p =
  (rate / gamma)^(1/N) is concave in the rate for N > 1; J is taken with the power 1/3 for
  both laws, so that for N = 1 it measures the same fluctuation, which that law averages
  out). Then the same laws and the rate-independent one with quadratic B-splines and with
  uGIMP, and each law's top after a friction angle 0.5 degrees higher: how sensitive the
  problem is, so that errors can be compared in friction-angle equivalents (about 10
  minutes).
- shapes: the retaining wall (to 0.35 s) and the pile (whole run) with each shape function
  (linear, gimp, bspline2) at cfl 0.4 and 0.2, and with bspline2 at h/2: which shape carries
  the examples' remaining Delta-t error, and what a smoother shape costs in the cell (about
  30 minutes, most of it the wall at h/2).
- pile_jitter: the pile example at cfl 0.4 and 0.2, each against a step 1 % shorter, 1 % longer
  and half as long: whether what half the step changes in the head force and in the heave is
  more than the spread of a reading that a 1 % change of the step already moves (about 10
  minutes).
A study, not a test: it prints markdown tables.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

WALL_SCENE = """
[scene]
name = "small_wall"
gravity = [0.0, -9.81]
duration = 0.2
cfl = 0.4
output_every = 0.02
[grid]
size = [1.0, 0.55]
cell = 0.025
boundaries = {{ left = "slip", right = "slip", bottom = "fixed", top = "free" }}
[numerics]
shape = "linear"
transfer = "apic"
ppc = 2
dtype = "float64"
[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 5.0e6
poisson = 0.3
friction_angle = 30.0
[materials.concrete]
model = "linear_elastic"
density = 2400.0
young = {young}
poisson = 0.2
[[bodies]]
name = "sand"
material = "sand"
region = {{ polygon = [[0.0, 0.0], [1.0, 0.0], [1.0, 0.4], [0.55, 0.4], [0.55, 0.1], [0.0, 0.1]] }}
initial_stress = {{ geostatic = {{ k0 = "jaky" }} }}
[[bodies]]
name = "wall"
material = "concrete"
region = {{ rectangle = [[0.5, 0.1], [0.55, 0.45]] }}
kinematics = {{ type = "{kinematics}" }}
[[contacts]]
pair = ["sand", "wall"]
friction = 0.4
[[probes]]
name = "wall_top"
kind = "displacement"
at = [0.525, 0.45]
"""

PILE_SCENE = """
[scene]
name = "dropped_pile"
gravity = [0.0, -9.81]
duration = 0.1
cfl = 0.4
output_every = 0.01
[grid]
size = [0.6, 0.7]
cell = 0.02
boundaries = {{ left = "slip", right = "slip", bottom = "fixed", top = "free" }}
[numerics]
shape = "linear"
transfer = "apic"
ppc = 2
dtype = "float64"
relaxation = 10.0
[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 5.0e6
poisson = 0.3
friction_angle = 30.0
[materials.steel]
model = "linear_elastic"
density = 7850.0
young = 30.0e9
poisson = 0.3
[[bodies]]
name = "sand"
material = "sand"
region = {{ rectangle = [[0.0, 0.0], [0.6, 0.3]] }}
initial_stress = {{ geostatic = {{ k0 = "jaky" }} }}
[[bodies]]
name = "pile"
material = "steel"
region = {{ rectangle = [[0.28, 0.32], [0.32, 0.62]] }}
velocity = [0.0, -2.0]
kinematics = {{ type = "{kinematics}" }}
[[contacts]]
pair = ["sand", "pile"]
friction = 0.3
[[probes]]
name = "sink"
kind = "body_displacement"
body = "pile"
"""

WALL_RELAXATION = 10.0      # numerics.relaxation of the small wall (tests/test_convergence.py's)


def small_wall(kinematics="rigid", young=30.0e9, **values):
    """The small wall scene (module docstring) with numerics.relaxation = WALL_RELAXATION and
    `values` ({dotted key: value}) set."""
    import jaxmpm

    scene = jaxmpm.Scene.from_toml(WALL_SCENE.format(kinematics=kinematics, young=young))
    scene = scene.with_value("numerics.relaxation", WALL_RELAXATION)
    for key, value in values.items():
        scene = scene.with_value(key, value)
    return scene


def run(scene):
    """(time (T,), probes {name: (T, k)}, steps, wall seconds) of a forward run."""
    import jaxmpm

    started = time.perf_counter()
    sim = jaxmpm.Simulation(scene)
    result = sim.run(progress=False)
    return np.asarray(result.time), {k: np.asarray(v) for k, v in result.probes.items()}, sim.steps, time.perf_counter() - started


def at_times(time_axis, values, times):
    return np.asarray([values[int(np.argmin(np.abs(time_axis - t)))] for t in times])


def relative_change(a, b):
    """max |a - b| / max |b| over the rows (the output times)."""
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / max(np.max(np.abs(np.asarray(b))), 1e-30))


def wall_study():
    print("\n### Small rigid wall: top displacement [mm] at 0.1 / 0.2 s\n")
    print("| transfer | cfl | dt [µs] | steps | top at 0.1 s | top at 0.2 s | change from the half step | run [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for relaxation, label in ((0.0, "plain APIC (relaxation 0)"), (WALL_RELAXATION, f"APIC, relaxation {WALL_RELAXATION:g}")):
        rows = []
        for cfl in (0.4, 0.2, 0.1):
            scene = small_wall(**{"scene.cfl": cfl, "numerics.relaxation": relaxation})
            t, probes, steps, seconds = run(scene)
            top = -1e3 * at_times(t, probes["wall_top"][:, 0], (0.1, 0.2))
            rows.append((cfl, scene, steps, top, seconds))
        for index, (cfl, scene, steps, top, seconds) in enumerate(rows):
            change = f"{100 * relative_change(top, rows[index + 1][3]):.1f} %" if index + 1 < len(rows) else ""
            dt = scene.duration / steps
            print(f"| {label} | {cfl} | {1e6 * dt:.0f} | {steps} | {top[0]:.2f} | {top[1]:.2f} | {change} | {seconds:.0f} |")


def stiff_study():
    print("\n### Rigid and stiff elastic wall: top displacement [mm] at 0.1 / 0.2 s\n")
    print("| wall | dt [µs] | steps | top at 0.1 s | top at 0.2 s | against the rigid wall at the same dt | run [s] |")
    print("|---|---|---|---|---|---|---|")
    t, probes, steps, seconds = run(small_wall("rigid"))
    top = -1e3 * at_times(t, probes["wall_top"][:, 0], (0.1, 0.2))
    print(f"| rigid | {1e6 * t[1]:.1f} | {steps} | {top[0]:.2f} | {top[1]:.2f} | | {seconds:.0f} |")
    for young in (3.0e9, 30.0e9):
        t, elastic, steps, seconds = run(small_wall("free", young))
        top = -1e3 * at_times(t, elastic["wall_top"][:, 0], (0.1, 0.2))
        t_rigid, rigid, rigid_steps, rigid_seconds = run(small_wall("rigid", **{"scene.dt": float(t[1])}))
        rigid_top = -1e3 * at_times(t_rigid, rigid["wall_top"][:, 0], (0.1, 0.2))
        change = most_apart(t, elastic["wall_top"][:, 0], t_rigid, rigid["wall_top"][:, 0], 0.02)
        print(f"| rigid at the next row's dt | {1e6 * t_rigid[1]:.2f} | {rigid_steps} | {rigid_top[0]:.2f} | "
              f"{rigid_top[1]:.2f} | | {rigid_seconds:.0f} |")
        print(f"| elastic, E = {young / 1e9:g} GPa | {1e6 * t[1]:.2f} | {steps} | {top[0]:.2f} | {top[1]:.2f} | "
              f"{change} | {seconds:.0f} |")
    pile_study()


def most_apart(t, values, t_reference, reference, every):
    """'x.x % (at t s)': the largest relative difference of `values` from `reference` at the
    output times (every `every` s) where the reference has moved more than 1 mm."""
    times = np.arange(every, t[-1] + every / 2, every)
    a, b = at_times(t, values, times), at_times(t_reference, reference, times)
    moving = np.abs(b) > 1e-3
    relative = np.abs(a - b)[moving] / np.abs(b)[moving]
    worst = int(np.argmax(relative))
    return f"{100 * relative[worst]:.1f} % (at {times[moving][worst]:.2f} s)"


def pile_study():
    import jaxmpm

    print("\n### Dropped pile, rigid and elastic (E = 30 GPa): sinking [mm] at 0.05 / 0.07 / 0.1 s\n")
    print("| pile | cfl | dt [µs] | steps | 0.05 s | 0.07 s | 0.1 s | against the rigid pile at the elastic one's dt | run [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    times = (0.05, 0.07, 0.1)
    elastic_runs = [(cfl, run(jaxmpm.Scene.from_toml(PILE_SCENE.format(kinematics="free")).with_value("scene.cfl", cfl)))
                    for cfl in (0.4, 0.2, 0.1, 0.05)]
    t_fine, fine, *_ = run(jaxmpm.Scene.from_toml(PILE_SCENE.format(kinematics="rigid")).with_value(
        "scene.dt", float(elastic_runs[0][1][0][1])))
    rigid_runs = [(cfl, run(jaxmpm.Scene.from_toml(PILE_SCENE.format(kinematics="rigid")).with_value("scene.cfl", cfl)))
                  for cfl in (0.4, 0.2, 0.1, 0.05)]
    for label, runs in (("rigid", rigid_runs), ("elastic", elastic_runs)):
        for cfl, (t, probes, steps, seconds) in runs:
            sink = -1e3 * at_times(t, probes["sink"][:, 1], times)
            change = most_apart(t, probes["sink"][:, 1], t_fine, fine["sink"][:, 1], 0.01)
            print(f"| {label} | {cfl} | {1e6 * t[1]:.2f} | {steps} | " + " | ".join(f"{v:.2f}" for v in sink)
                  + f" | {change} | {seconds:.0f} |")
    sink = -1e3 * at_times(t_fine, fine["sink"][:, 1], times)
    print(f"| rigid, at the elastic pile's dt (cfl 0.4) | | {1e6 * t_fine[1]:.2f} | {len(t_fine) - 1} | "
          + " | ".join(f"{v:.2f}" for v in sink) + " | | |")


def subcycled_study():
    """Stiff walls and a pile subcycled at the sand's step, against the same body as an ordinary
    free body at its own step (brute force) and the rigid body at the sand's step."""
    import jaxmpm

    print("\n### Subcycled stiff walls: top displacement [mm] at 0.1 / 0.2 s\n")
    print("| wall | cfl (sand) | dt [µs] | substeps | steps | top at 0.1 s | top at 0.2 s | against brute force | run [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for young in (3.0e9, 30.0e9):
        t_ref, reference, steps, seconds = run(small_wall("free", young))
        top = -1e3 * at_times(t_ref, reference["wall_top"][:, 0], (0.1, 0.2))
        print(f"| elastic, E = {young / 1e9:g} GPa, brute force | | {1e6 * t_ref[1]:.2f} | 1 | {steps} | {top[0]:.2f} | "
              f"{top[1]:.2f} | | {seconds:.0f} |")
        for label, kinematics in (("subcycled", "free"), ("rigid", "rigid")):
            for cfl in (0.4, 0.2):
                scene = small_wall(kinematics, young, **{"scene.cfl": cfl})
                if kinematics == "free":
                    scene = scene.with_value("bodies.wall.kinematics.substeps", "auto")
                substeps = {b.name: b.substeps for b in jaxmpm.Simulation(scene).structure.bodies}["wall"]
                t, probes, steps, seconds = run(scene)
                top = -1e3 * at_times(t, probes["wall_top"][:, 0], (0.1, 0.2))
                change = most_apart(t, probes["wall_top"][:, 0], t_ref, reference["wall_top"][:, 0], 0.02)
                print(f"| {label}, E = {young / 1e9:g} GPa | {cfl} | {1e6 * t[1]:.1f} | {substeps} | {steps} | {top[0]:.2f} | "
                      f"{top[1]:.2f} | {change} | {seconds:.0f} |")
    print("\n### Dropped pile subcycled (E = 30 GPa): sinking [mm] at 0.05 / 0.07 / 0.1 s\n")
    print("| geometry | pile | dt [µs] | substeps | steps | 0.05 s | 0.07 s | 0.1 s | against brute force | run [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    times = (0.05, 0.07, 0.1)
    for axisymmetric in (False, True):
        geometry = "axisymmetric, on the axis" if axisymmetric else "plane strain"
        t_ref, reference, steps, seconds = run(dropped_pile("free", axisymmetric))
        sink = -1e3 * at_times(t_ref, reference["sink"][:, 1], times)
        print(f"| {geometry} | elastic, brute force | {1e6 * t_ref[1]:.2f} | 1 | {steps} | "
              + " | ".join(f"{v:.2f}" for v in sink) + f" | | {seconds:.0f} |")
        for label, base in (("subcycled", dropped_pile("free", axisymmetric).with_value(
                "bodies.pile.kinematics.substeps", "auto")), ("rigid", dropped_pile("rigid", axisymmetric))):
            for cfl in (0.4, 0.2):
                scene = base.with_value("scene.cfl", cfl)
                substeps = {b.name: b.substeps for b in jaxmpm.Simulation(scene).structure.bodies}["pile"]
                t, probes, steps, seconds = run(scene)
                sink = -1e3 * at_times(t, probes["sink"][:, 1], times)
                change = most_apart(t, probes["sink"][:, 1], t_ref, reference["sink"][:, 1], 0.01)
                print(f"| {geometry} | {label}, cfl {cfl} | {1e6 * t[1]:.1f} | {substeps} | {steps} | "
                      + " | ".join(f"{v:.2f}" for v in sink) + f" | {change} | {seconds:.0f} |", flush=True)


def dropped_pile(kinematics, axisymmetric=False):
    """PILE_SCENE with the pile's kinematics type; axisymmetric: the same sand 0.4 m wide and a
    pile of radius 0.04 m on the axis."""
    import jaxmpm

    text = PILE_SCENE.format(kinematics=kinematics)
    if axisymmetric:
        for old, new in (('name = "dropped_pile"', 'name = "dropped_pile"\ngeometry = "axisymmetric"'),
                         ("size = [0.6, 0.7]", "size = [0.4, 0.7]"),
                         ("[[0.0, 0.0], [0.6, 0.3]]", "[[0.0, 0.0], [0.4, 0.3]]"),
                         ("[[0.28, 0.32], [0.32, 0.62]]", "[[0.0, 0.32], [0.04, 0.62]]")):
            text = text.replace(old, new)
    return jaxmpm.Scene.from_toml(text)


PILE_DEPTHS = (0.05, 0.1, 0.15, 0.2, 0.25)


def pile_force(t, probes):
    """Head force [N] averaged within 5 mm of each of PILE_DEPTHS of penetration that the run
    passes, and the heave [mm] at the end (examples/pile_driving.toml)."""
    force = -(probes["tip_reaction"][:, 1] + probes["shaft_reaction"][:, 1])
    depth = -probes["penetration"][:, 1]
    means = [float(force[(depth > d - 0.005) & (depth <= d + 0.005)].mean()) for d in PILE_DEPTHS
             if depth.max() >= d + 0.005]
    return np.asarray(means + [1e3 * float(probes["heave"][-1, 1])])


def example_quantities(name, t, probes):
    if name == "retaining_wall":
        times = np.arange(0.05, t[-1] + 1e-4, 0.05)
        return {"wall top x [mm]": -1e3 * at_times(t, probes["wall_top"][:, 0], times),
                "rotation [deg]": np.degrees(at_times(t, probes["rotation"][:, 0], times))}
    if name == "pile_driving":
        values = pile_force(t, probes)
        return {"head force every 5 cm [N]": values[:-1], "heave [mm]": values[-1:]}
    times = np.arange(0.1, 1.0001, 0.1)
    return {"corner x [mm]": 1e3 * at_times(t, probes["corner"][:, 0], times),
            "centre of mass x [mm]": 1e3 * at_times(t, probes["mass_centre"][:, 0], times)}


def own_change(a, b):
    """max |a - b| / |b| over the rows whose |b| is at least a tenth of the largest (a value
    near zero early in a run would read as a huge relative change)."""
    a, b = np.asarray(a), np.asarray(b)
    kept = np.abs(b) >= 0.1 * np.max(np.abs(b))
    return float(np.max(np.abs(a - b)[kept] / np.abs(b)[kept]))


def examples_study(names=("retaining_wall", "pile_driving", "column_collapse"), relaxations=(0.0, None)):
    """Each example over its whole run at cfl 0.4 and 0.2 (and 0.1 at the shipped relaxation),
    with each of `relaxations` (None: as shipped)."""
    import jaxmpm

    print("\n### Examples at the shipped cfl and at half, over the whole run\n")
    print("Change: the largest over the output times against the largest value; in brackets, "
          "against each output's own value (outputs under a tenth of the largest left out).\n")
    print("| example | quantity | relaxation | at cfl 0.4 (last) | 0.2 | 0.1 | change 0.4 → 0.2 | change 0.2 → 0.1 | runs [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in names:
        shipped = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml").numerics.relaxation
        values = list(dict.fromkeys(shipped if relaxation is None else relaxation for relaxation in relaxations))
        for relaxation in values:
            found = {}
            seconds = 0.0
            for cfl in (0.4, 0.2, 0.1) if relaxation == shipped else (0.4, 0.2):
                scene = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml")
                scene = scene.with_value("scene.cfl", cfl).with_value("numerics.relaxation", relaxation)
                try:
                    t, probes, _, spent = run(scene)
                except jaxmpm.SimulationError as error:
                    print(f"| {name} | (failed at cfl {cfl}: {error}) | | | | | | | |")
                    break
                seconds += spent
                found[cfl] = example_quantities(name, t, probes)
            if len(found) < 2:
                continue
            label = f"{relaxation:g}" + (" (shipped)" if relaxation == shipped else "") + (" (plain APIC)" if relaxation == 0 else "")
            for quantity in found[0.4]:
                runs = [found[cfl][quantity] for cfl in (0.4, 0.2, 0.1) if cfl in found]
                last = [f"{values[-1]:.4g}" for values in runs] + [""] * (3 - len(runs))
                changes = [f"{100 * relative_change(a, b):.2f} % ({100 * own_change(a, b):.2f} %)"
                           for a, b in zip(runs, runs[1:])] + [""] * (3 - len(runs))
                print(f"| {name} | {quantity} | {label} | {' | '.join(last)} | {' | '.join(changes[:2])} | {seconds:.0f} |")


def cells_study():
    print("\n### Small rigid wall under cell refinement (cfl 0.4): top displacement [mm] at 0.2 s\n")
    print("| cell [m] | ppc | points | steps | top at 0.1 s | top at 0.2 s | run [s] |")
    print("|---|---|---|---|---|---|---|")
    tops = []
    for cell, ppc in ((0.025, 2), (0.0125, 2), (0.00625, 2), (0.025, 3)):
        scene = small_wall(**{"grid.cell": cell, "numerics.ppc": ppc})
        t, probes, steps, seconds = run(scene)
        top = -1e3 * at_times(t, probes["wall_top"][:, 0], (0.1, 0.2))
        import jaxmpm
        points = jaxmpm.Simulation(scene).point_count
        print(f"| {cell} | {ppc} | {points} | {steps} | {top[0]:.2f} | {top[1]:.2f} | {seconds:.0f} |")
        if ppc == 2:
            tops.append(top)
    coarse, middle, fine = tops
    for index, time_label in enumerate(("0.1 s", "0.2 s")):
        order, extrapolated = richardson(coarse[index], middle[index], fine[index])
        if math.isfinite(order):
            print(f"\nat {time_label}: observed order {order:.2f}, Richardson value {extrapolated:.2f} mm; "
                  f"error of h = 0.025: {100 * abs(coarse[index] - extrapolated) / abs(extrapolated):.0f} %")
        else:
            print(f"\nat {time_label}: not monotone (differences {coarse[index] - middle[index]:.2f}, "
                  f"{middle[index] - fine[index]:.2f} mm): no order")


def richardson(coarse, middle, fine):
    """(observed order p, extrapolated value q*) from q at h, h/2, h/4; (nan, nan) when the
    differences change sign (not in the asymptotic range)."""
    ratio = (coarse - middle) / (middle - fine) if middle != fine else math.nan
    if not ratio > 1.0:      # differences changing sign, or growing: not converging (yet)
        return math.nan, math.nan
    order = math.log2(ratio)
    return order, fine + (fine - middle) / (2 ** order - 1)


# The coarsest cell h of the cell study where it is not the example's own: the retaining wall
# shipped 0.025 m until this study showed it 35 % off, and now ships h/2 = 0.0125 m.
COARSEST_CELL = {"retaining_wall": 0.025}


def example_cells_study(names=("retaining_wall", "pile_driving", "column_collapse")):
    """Each example at cells h, h/2, h/4 (ppc 2, the shipped cfl; h its own cell or
    COARSEST_CELL) and at h with ppc 3: each headline quantity at its last time, the observed
    order, the Richardson value and the error of h against it."""
    import jaxmpm

    print("\n### Examples under cell refinement (shipped cfl; the last output time of the dt study)\n")
    print("| example | quantity | h | h/2 | h/4 | h, ppc 3 | order | Richardson value | error of h | runs [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    durations = {"retaining_wall": 0.4, "pile_driving": 0.2, "column_collapse": 1.0}
    for name in names:
        base = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml").with_value("scene.duration", durations[name])
        cell = COARSEST_CELL.get(name, base.grid.cell)
        found, seconds = [], 0.0
        for factor, ppc in ((1, base.numerics.ppc), (2, base.numerics.ppc), (4, base.numerics.ppc), (1, 3)):
            scene = base.with_value("grid.cell", cell / factor).with_value("numerics.ppc", ppc)
            try:
                t, probes, steps, spent = run(scene)
            except jaxmpm.SimulationError as error:
                print(f"| {name} | (failed at h/{factor}, ppc {ppc}: {error}) | | | | | | | | |")
                found.append(None)
                continue
            seconds += spent
            found.append({quantity: values[-1] for quantity, values in example_quantities(name, t, probes).items()})
            print(f"<!-- {name} h/{factor} ppc {ppc}: {steps} steps, {spent:.0f} s -->", flush=True)
        known = next((values for values in found if values is not None), None)
        if known is None:
            continue
        for quantity in known:
            q = [values[quantity] if values is not None else math.nan for values in found]
            order, extrapolated = richardson(*q[:3])
            error = f"{100 * abs(q[0] - extrapolated) / abs(extrapolated):.1f} %" if math.isfinite(extrapolated) else "–"
            cells = " | ".join("failed" if math.isnan(value) else f"{value:.4g}" for value in q)
            order_text = f"{order:.2f}" if math.isfinite(order) else "not converging"
            extrapolated_text = f"{extrapolated:.4g}" if math.isfinite(extrapolated) else "–"
            print(f"| {name} | {quantity} | {cells} | {order_text} | {extrapolated_text} | {error} | {seconds:.0f} |",
                  flush=True)


RELAXATIONS = (10.0, 25.0, 100.0, 1000.0)


def relaxation_study(names=("retaining_wall", "pile_driving", "column_collapse"), factors=(1, 2), until=None,
                     stress_substeps=None):
    """Each example at its shipped cfl with each of RELAXATIONS, at cells h / factor; run to
    `until` [s] instead of the dt study's last time, and with `stress_substeps`, if given."""
    import jaxmpm

    print("\n### Examples against the relaxation kappa (shipped cfl; at "
          + (f"{until:g} s" if until else "the last output time of the dt study")
          + (f"; {stress_substeps} stress substeps" if stress_substeps else "") + ")\n")
    print("| example | quantity | cell [m] | " + " | ".join(f"kappa = {k:g}" for k in RELAXATIONS)
          + " | shipped kappa against 1000 | runs [s] |")
    print("|---|---|---|" + "---|" * len(RELAXATIONS) + "---|---|")
    durations = {"retaining_wall": 0.4, "pile_driving": 0.2, "column_collapse": 1.0}
    for name in names:
        base = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml").with_value("scene.duration", until or durations[name])
        if stress_substeps is not None:
            base = base.with_value("numerics.stress_substeps", stress_substeps)
        shipped = base.numerics.relaxation
        for factor in factors:
            cell = base.grid.cell / factor
            found, seconds = {}, 0.0
            for relaxation in RELAXATIONS:
                scene = base.with_value("grid.cell", cell).with_value("numerics.relaxation", relaxation)
                try:
                    t, probes, steps, spent = run(scene)
                except jaxmpm.SimulationError as error:
                    print(f"<!-- {name} cell {cell:g} kappa {relaxation:g} failed: {error} -->", flush=True)
                    continue
                seconds += spent
                found[relaxation] = {quantity: values[-1] for quantity, values in example_quantities(name, t, probes).items()}
                print(f"<!-- {name} cell {cell:g} kappa {relaxation:g}: {steps} steps, {spent:.0f} s -->", flush=True)
            if not found:
                continue
            for quantity in next(iter(found.values())):
                values = [found[k][quantity] if k in found else math.nan for k in RELAXATIONS]
                against = "–"
                if shipped in found and RELAXATIONS[-1] in found:
                    reference = found[RELAXATIONS[-1]][quantity]
                    against = f"{100 * (found[shipped][quantity] - reference) / abs(reference):+.1f} %"
                cells = " | ".join("failed" if math.isnan(value) else f"{value:.4g}" for value in values)
                print(f"| {name} | {quantity} | {cell:g} | {cells} | {against} | {seconds:.0f} |", flush=True)


SHAPES = ("linear", "gimp", "bspline2")
PILE_CENTIMETRES = np.arange(14, 27) / 100.0     # every cm of the pile's second half


def pile_force_every_cm(t, probes, centimetres=PILE_CENTIMETRES, window=0.0125):
    """The pile's head force [N] averaged over `window` of penetration [m] (by default one
    cell, 12.5 mm) centred on every one of `centimetres` [m] (by default 14 to 26 cm)."""
    force = -(probes["tip_reaction"][:, 1] + probes["shaft_reaction"][:, 1])
    depth = -probes["penetration"][:, 1]
    return np.asarray([float(force[np.abs(depth - d) <= window / 2].mean()) for d in centimetres])


JITTER_CENTIMETRES = np.arange(3, 25.01, 0.5) / 100.0   # every 5 mm, windows of up to 4 cells inside the run
JITTER_WINDOWS = (1, 2, 4)                              # cells of travel a reading averages over


def pile_jitter_study(cfls=(0.4, 0.2), nudge=0.01):
    """The pile example at cfl c, c (1 - nudge), c (1 + nudge) and c / 2 for each c of `cfls`:
    how far a step 1 % shorter or longer moves the head force (the spread of a reading that
    is not a smooth function of the step), against how far half the step moves it. The force
    is read every 5 mm from 3 to 25 cm, averaged over 1, 2 and 4 cells of travel."""
    import jaxmpm

    print("\n### The pile's head force: a 1 % change of the step against half the step\n")
    print("Head force (weight included) every 5 mm from 3 to 25 cm, averaged over a window of "
          "travel; each change against the run at cfl c: range over the readings (rms).\n")
    print("| c | compared with | window [cells] | change: range | rms | mean |")
    print("|---|---|---|---|---|---|")
    base = jaxmpm.load_scene(ROOT / "examples" / "pile_driving.toml")
    cell = base.grid.cell
    runs = {}

    def force_at(cfl, window):
        if cfl not in runs:
            t, probes, _, seconds = run(base.with_value("scene.cfl", cfl))
            runs[cfl] = (t, probes)
            print(f"<!-- cfl {cfl:g}: {seconds:.0f} s -->", flush=True)
        return pile_force_every_cm(*runs[cfl], JITTER_CENTIMETRES, window * cell)

    for cfl in cfls:
        for other, label in ((cfl * (1 - nudge), f"cfl {cfl * (1 - nudge):g} (1 % shorter)"),
                             (cfl * (1 + nudge), f"cfl {cfl * (1 + nudge):g} (1 % longer)"),
                             (cfl / 2, f"cfl {cfl / 2:g} (half)")):
            for window in JITTER_WINDOWS:
                reference = force_at(cfl, window)
                change = 100 * (force_at(other, window) - reference) / reference
                print(f"| {cfl:g} | {label} | {window} | {change.min():+.2f} … {change.max():+.2f} % | "
                      f"{np.sqrt(np.mean(change ** 2)):.2f} % | {change.mean():+.2f} % |", flush=True)

    print("\n### The heave: a 1 % change of the step against half the step\n")
    print("The heave probe's rise [mm] when the tip passes 10, 15, 20 and 25 cm and at the end; each "
          "change against the run at cfl c.\n")
    print("| c | compared with | heave at 10 / 15 / 20 / 25 cm / end [mm] | change: range over the readings |")
    print("|---|---|---|---|")
    for cfl in cfls:
        reference = pile_heave(*runs[cfl])
        print(f"| {cfl:g} | itself | {' / '.join(f'{h:.3f}' for h in reference)} | |")
        for other, label in ((cfl * (1 - nudge), "1 % shorter"), (cfl * (1 + nudge), "1 % longer"),
                             (cfl / 2, "half")):
            heave = pile_heave(*runs[other])
            change = 100 * (heave - reference) / reference
            print(f"| {cfl:g} | cfl {other:g} ({label}) | {' / '.join(f'{h:.3f}' for h in heave)} | "
                  f"{change.min():+.2f} … {change.max():+.2f} % |", flush=True)


def pile_heave(t, probes, centimetres=(0.10, 0.15, 0.20, 0.25)):
    """The heave probe's rise [mm] at the first step the tip passes each of `centimetres` [m]
    of penetration, and at the end."""
    heave = 1e3 * probes["heave"][:, 1]
    depth = -probes["penetration"][:, 1]
    return np.asarray([heave[int(np.argmax(depth >= d))] for d in centimetres] + [heave[-1]])


def shapes_study(finer_cell=True):
    """The retaining wall (to 0.35 s) and the pile (its whole run) at their shipped cell and
    relaxation with each shape function of SHAPES, at cfl 0.4 and 0.2; and with bspline2 at
    h/2 (cfl 0.4). Where the examples' remaining Delta-t error lives, and what a smoother
    shape costs in the cell."""
    import jaxmpm

    print("\n### The examples' Delta-t change with each shape function\n")
    print("Wall: rotation every 0.05 s to 0.35 s. Pile: head force every cm from 14 to 26 cm of "
          "penetration (and their mean). Change: largest over the outputs against the largest value "
          "(in brackets against each output's own).\n")
    print("| example | quantity | shape | cell [m] | at cfl 0.4 (last) | at cfl 0.2 (last) | change 0.4 → 0.2 | mean 0.4 → 0.2 | runs [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    cases = [("retaining_wall", 0.35), ("pile_driving", None)]
    for name, duration in cases:
        base = jaxmpm.load_scene(ROOT / "examples" / f"{name}.toml")
        if duration is not None:
            base = base.with_value("scene.duration", duration)
        runs = [(shape, base.grid.cell, (0.4, 0.2)) for shape in SHAPES]
        if finer_cell:
            runs.append(("bspline2", base.grid.cell / 2, (0.4,)))
        for shape, cell, cfls in runs:
            found, seconds = [], 0.0
            for cfl in cfls:
                scene = base.with_value("numerics.shape", shape).with_value("grid.cell", cell).with_value("scene.cfl", cfl)
                t, probes, _, spent = run(scene)
                seconds += spent
                if name == "pile_driving":
                    found.append(pile_force_every_cm(t, probes))
                else:
                    found.append(np.degrees(at_times(t, probes["rotation"][:, 0], np.arange(0.05, duration + 1e-4, 0.05))))
            quantity = "head force 14–26 cm [N]" if name == "pile_driving" else "rotation [°]"
            if len(found) == 1:
                print(f"| {name} | {quantity} | {shape} | {cell:g} | {found[0][-1]:.4g} (mean {found[0].mean():.4g}) | | | | {seconds:.0f} |",
                      flush=True)
                continue
            coarse, fine = found
            mean = 100 * (fine.mean() - coarse.mean()) / abs(fine.mean())
            print(f"| {name} | {quantity} | {shape} | {cell:g} | {coarse[-1]:.4g} (mean {coarse.mean():.4g}) | "
                  f"{fine[-1]:.4g} (mean {fine.mean():.4g}) | {100 * relative_change(coarse, fine):.2f} % "
                  f"({100 * own_change(coarse, fine):.2f} %) | {mean:+.2f} % | {seconds:.0f} |", flush=True)


def stress_study(cases=((1, {}), (2, {}), (4, {}), (16, {}), (1, {"materials.sand.exponent": 1.0}),
                        (1, {"materials.sand.exponent": 3.0}), (4, {"materials.sand.exponent": 3.0}),
                        (16, {"numerics.relaxation": 10.0}))):
    """The retaining wall to 0.35 s with K stress substeps and one changed value, at cfl 0.4 and
    0.2: its rotation every 0.05 s, and the change per halving against each output's value."""
    import jaxmpm

    print("\n### The retaining wall's stress update in K substeps (rotation every 0.05 s to 0.35 s)\n")
    print("| K | changed | rotation at 0.35 s, cfl 0.4 / 0.2 [°] | change per halving at each output | runs [s] |")
    print("|---|---|---|---|---|")
    base = jaxmpm.load_scene(ROOT / "examples" / "retaining_wall.toml").with_value("scene.duration", 0.35)
    times = np.arange(0.05, 0.35 + 1e-4, 0.05)
    for substeps, changed in cases:
        scene = base.with_value("numerics.stress_substeps", substeps)
        for key, value in changed.items():
            scene = scene.with_value(key, value)
        found, seconds = [], 0.0
        for cfl in (0.4, 0.2):
            t, probes, _, spent = run(scene.with_value("scene.cfl", cfl))
            found.append(np.degrees(at_times(t, probes["rotation"][:, 0], times)))
            seconds += spent
        coarse, fine = found
        change = " / ".join(f"{100 * (c - f) / abs(f):+.2f}" for c, f in zip(coarse, fine))
        label = ", ".join(f"{key} = {value:g}" for key, value in changed.items()) or "–"
        print(f"| {substeps} | {label} | {coarse[-1]:.4f} / {fine[-1]:.4f} | {change} % | {seconds:.0f} |", flush=True)


def perzyna_law_study(cases=((None, None, 1), (1.0, 50.0, 4), (1.0, 5.0, 4), (1.0, 0.5, 4), (3.0, 50.0, 16),
                             (3.0, 5.0, 16), (2.0, 0.5, 16), (3.0, 0.5, 16), (3.0, 0.5, 64)), duration=0.12):
    """The small wall's top at `duration` with a Perzyna backfill of exponent N and fluidity
    gamma (None: rate-independent) and K stress substeps, at cfl 0.4, 0.2 and 0.1."""
    print(f"\n### Small rigid wall, Perzyna backfill, its update in K substeps: top at {duration:g} s [mm]\n")
    print("| N | fluidity [1/s] | K | cfl 0.4 / 0.2 / 0.1 | change per halving 0.4 → 0.2 / 0.2 → 0.1 | runs [s] |")
    print("|---|---|---|---|---|---|")
    for exponent, fluidity, substeps in cases:
        values = {"scene.duration": duration, "numerics.stress_substeps": substeps}
        if fluidity is not None:
            values.update({"materials.sand.fluidity": fluidity, "materials.sand.exponent": exponent})
        tops, seconds = [], 0.0
        for cfl in (0.4, 0.2, 0.1):
            t, probes, _, spent = run(small_wall(**values, **{"scene.cfl": cfl}))
            tops.append(-1e3 * at_times(t, probes["wall_top"][:, 0], (duration,))[0])
            seconds += spent
        changes = " / ".join(f"{fine - coarse:+.3f} mm ({100 * (fine - coarse) / abs(fine):+.2f} %)"
                             for coarse, fine in zip(tops, tops[1:]))
        law = ("–", "rate-independent") if fluidity is None else (f"{exponent:g}", f"{fluidity:g}")
        print(f"| {law[0]} | {law[1]} | {substeps} | {' / '.join(f'{top:.3f}' for top in tops)} | {changes} | "
              f"{seconds:.0f} |", flush=True)


def plastic_rate_rectification(result, exponent, start=0.04, window=0.002):
    """Mean over `window`-long windows from `start` of J = mean(r^(1/N)) / mean(r)^(1/N), each
    sand point's plastic rate r over the window (from every step's snapshot), the points'
    values weighted by mean(r)^(1/N) (the steady overstress); points below 1e-3 of the
    largest mean rate left out."""
    times = np.asarray(result.snapshots["time"])
    strain = np.asarray(result.snapshots["sand"]["plastic_strain"])
    rate = np.diff(strain, axis=0) / np.diff(times)[:, None]
    middle = 0.5 * (times[1:] + times[:-1])
    ratios = []
    for begin in np.arange(start, times[-1] - 1e-9, window):
        rows = rate[(middle >= begin) & (middle < begin + window)]
        mean = rows.mean(axis=0)
        active = mean > 1e-3 * mean.max()
        steady = mean[active] ** (1.0 / exponent)
        fluctuating = (np.maximum(rows[:, active], 0.0) ** (1.0 / exponent)).mean(axis=0)
        ratios.append(fluctuating.sum() / steady.sum())
    return float(np.mean(ratios))


def perzyna_noise_study(duration=0.12, fluidity=0.5, relaxations=(10.0, 25.0, 100.0)):
    """The small wall's top at `duration` and the plastic rate's rectification J for Perzyna
    sand of exponent 3 and 1 against the relaxation and the step; then with quadratic
    B-splines and uGIMP, and each law's sensitivity to the friction angle."""
    import jaxmpm

    laws = {"N = 3": {"materials.sand.exponent": 3.0, "numerics.stress_substeps": 16},
            "N = 1": {"materials.sand.exponent": 1.0, "numerics.stress_substeps": 4}}

    def top_of(t, probes):
        return -1e3 * at_times(np.asarray(t), np.asarray(probes["wall_top"])[:, 0], (duration,))[0]

    def top(scene):
        t, probes, _, _ = run(scene)
        return top_of(t, probes)

    print(f"\n### Small rigid wall, Perzyna backfill (fluidity {fluidity:g} 1/s): top at {duration:g} s and the "
          f"plastic rate's rectification J\n")
    print("| law | relaxation | top at cfl 0.4 / 0.2 [mm] | change per halving | J (power 1/3) at cfl 0.4 / 0.2 |")
    print("|---|---|---|---|---|")
    for law, values in laws.items():
        for relaxation in relaxations:
            tops, ratios = [], []
            for cfl in (0.4, 0.2):
                scene = small_wall(**{"materials.sand.fluidity": fluidity, **values, "scene.duration": duration,
                                      "numerics.relaxation": relaxation, "scene.cfl": cfl})
                scene = scene.with_value("scene.output_every", jaxmpm.Simulation(scene).dt)   # every step kept
                result = jaxmpm.Simulation(scene).run(progress=False)
                tops.append(top_of(result.time, result.probes))
                ratios.append(plastic_rate_rectification(result, 3.0))
            print(f"| {law} | {relaxation:g} | {tops[0]:.3f} / {tops[1]:.3f} | {100 * (tops[1] - tops[0]) / tops[1]:+.2f} % | "
                  f"{ratios[0]:.4f} / {ratios[1]:.4f} |", flush=True)

    print(f"\n### The same laws (relaxation {WALL_RELAXATION:g}) with quadratic B-splines and uGIMP, and against the "
          f"friction angle\n")
    print("| law | linear: change per halving | bspline2: top at cfl 0.4 / 0.2 [mm] | bspline2: change per halving | "
          "gimp: top at cfl 0.4 / 0.2 [mm] | gimp: change per halving | "
          "linear: top change for phi + 0.5 deg | halving in phi-equivalents [deg] |")
    print("|---|---|---|---|---|---|---|---|")
    laws["rate-independent"] = {}
    for law, values in laws.items():
        if values:
            values = {"materials.sand.fluidity": fluidity, **values}
        values = {**values, "scene.duration": duration}
        linear = [top(small_wall(**values, **{"scene.cfl": cfl})) for cfl in (0.4, 0.2)]
        smooth = [top(small_wall(**values, **{"scene.cfl": cfl, "numerics.shape": "bspline2"})) for cfl in (0.4, 0.2)]
        gimp = [top(small_wall(**values, **{"scene.cfl": cfl, "numerics.shape": "gimp"})) for cfl in (0.4, 0.2)]
        stronger = top(small_wall(**values, **{"materials.sand.friction_angle": 30.5}))
        halving = (linear[1] - linear[0]) / linear[1]
        per_degree = (stronger - linear[0]) / linear[0] / 0.5
        print(f"| {law} | {100 * halving:+.2f} % | {smooth[0]:.3f} / {smooth[1]:.3f} | "
              f"{100 * (smooth[1] - smooth[0]) / smooth[1]:+.2f} % | {gimp[0]:.3f} / {gimp[1]:.3f} | "
              f"{100 * (gimp[1] - gimp[0]) / gimp[1]:+.2f} % | {100 * per_degree * 0.5:+.2f} % | "
              f"{halving / per_degree:.3f} |", flush=True)


STUDIES = {"wall": wall_study, "stiff": stiff_study, "subcycled": subcycled_study, "examples": examples_study, "cells": cells_study,
           "example_cells": example_cells_study, "relaxation": relaxation_study, "shapes": shapes_study,
           "pile_jitter": pile_jitter_study, "stress": stress_study,
           "perzyna_law": perzyna_law_study, "perzyna_noise": perzyna_noise_study}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--study", choices=tuple(STUDIES), action="append", help="run only these (repeatable)")
    parser.add_argument("--examples", nargs="+", default=None, help="examples study: only these examples")
    parser.add_argument("--relaxation", type=float, nargs="+", default=None,
                        help="examples study: these numerics.relaxation values (default: 0 and as shipped)")
    parser.add_argument("--cell-factors", type=int, nargs="+", default=(1, 2),
                        help="relaxation study: the cells h / factor (default: 1 2)")
    parser.add_argument("--until", type=float, default=None, help="relaxation study: run each example to this time [s]")
    parser.add_argument("--stress-substeps", type=int, default=None,
                        help="relaxation study: numerics.stress_substeps for every run")
    arguments = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"jaxmpm convergence study, {time.strftime('%Y-%m-%d')}, {jax.devices()[0].device_kind}, "
          f"{__import__('os').cpu_count()} cores")
    for name in arguments.study or STUDIES:
        if name == "examples":
            examples_study(tuple(arguments.examples or ("retaining_wall", "pile_driving", "column_collapse")),
                           tuple(arguments.relaxation or (0.0, None)))
            continue
        if name == "example_cells":
            example_cells_study(tuple(arguments.examples or ("retaining_wall", "pile_driving", "column_collapse")))
            continue
        if name == "relaxation":
            relaxation_study(tuple(arguments.examples or ("retaining_wall", "pile_driving", "column_collapse")),
                             tuple(arguments.cell_factors), arguments.until, arguments.stress_substeps)
            continue
        STUDIES[name]()
        sys.stdout.flush()


if __name__ == "__main__":
    main()
