"""How a rigid structure bears on a deformable base, under each structure hold and shape
(numerics.structure_hold = "mass", "outline" and "points").

    python benchmarks/wall_base_study.py shift      # the calibration twin with its grid lines moved
    python benchmarks/wall_base_study.py rocking    # a rigid block tilted on an elastic layer
    python benchmarks/wall_base_study.py figure     # the block's rotation under each hold as the cell shrinks

shift: the wall top's x displacement [mm] of examples/calibrate_wall_scene.toml at 0.3 s
(cfl 0.4 and 0.2) with the wall and the backfill moved 0.3 cell along x (the backfill 0.3 cell
narrower), with the foundation 0.3 cell deeper (the grid's origin moved down with it), and
with both: the same wall on the same sand, with its faces off the grid lines. How far the
answer moves is a measure of the discretisation error at that cell that costs no refinement.

rocking: the twin's wall (0.075 x 0.35 m, rigid, 2400 kg/m^3) standing on a 0.15 m layer of
linear-elastic sand (E = 2 MPa, nu = 0.3) over a fixed base, gravity tilted 2 degrees, local
damping 0.3, for 1.5 s; the wall's rotation [mrad] averaged over 1.2-1.5 s at h and h/2 (cfl 0.4),
at h and cfl 0.2, at h with the layer 0.3 cell deeper (the base off the grid lines), and at h
with the block moved half a cell along x (its sides off the grid lines); then,
with a base that cannot slip (friction 10), the rotation at 0.5 / 1.0 / 1.5 s. figure: the
rotation's history under each hold with quadratic B-splines at h, h/2 (and h/4 under
"points"), drawn to docs/images/rocking_block.png. Against a rigid strip
footing on an elastic half-space in plane strain (the flat punch turned by theta: pressure
p(x) = E' theta x / (2 sqrt(a^2 - x^2)); K. L. Johnson, Contact Mechanics, 1985, chapter 2):
M = pi E' a^2 theta / 4, with E' = E / (1 - nu^2), a the half-width, and M the overturning
moment about the base's centre, m g sin(2 deg) times the centre's height, taken less its
weight's moment m g cos(2 deg) times the centre's height times theta as the wall leans
(theta = M / (pi E' a^2 / 4 - m g h_c)). The layer's finite depth (four half-widths) makes the
true value somewhat smaller than the half-space's. A study, not a test: it prints markdown tables.
"""

import math
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm.scene.files import read_scene_file  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TWIN = ROOT / "examples" / "calibrate_wall_scene.toml"
SHIFT = 0.3                       # of a cell
TILT = math.radians(2.0)
DURATION, SETTLED = 1.5, 1.2       # the rocking run [s], and the time from which it has settled
HOLDS = ("mass", "outline", "points")   # numerics.structure_hold


def body(data, name):
    return next(values for values in data["bodies"] if values["name"] == name)


def deepen_foundation(data, cells):
    """The foundation `cells` cells deeper, the grid's origin moved down with it (the grid one
    cell taller), in a scene file's dict: the bodies stay where they were, the grid lines move."""
    step = cells * data["grid"]["cell"]
    (x0, y0), (x1, y1) = body(data, "foundation")["region"]["rectangle"]
    body(data, "foundation")["region"]["rectangle"] = [[x0, y0 - step], [x1, y1]]
    data["grid"]["origin"] = [data["grid"]["origin"][0], data["grid"]["origin"][1] - step]
    data["grid"]["size"] = [data["grid"]["size"][0], data["grid"]["size"][1] + data["grid"]["cell"]]


def shifted_twin(along_x: bool, along_y: bool) -> jaxmpm.Scene:
    """The twin with the wall and backfill moved SHIFT cells along x (the backfill that much
    narrower) and/or the foundation SHIFT cells deeper with the grid's origin."""
    data = read_scene_file(TWIN)
    step = SHIFT * data["grid"]["cell"]
    if along_x:
        for name in ("wall", "backfill"):
            (x0, y0), (x1, y1) = body(data, name)["region"]["rectangle"]
            body(data, name)["region"]["rectangle"] = [[x0 + step, y0], [x1 if name == "backfill" else x1 + step, y1]]
        probe = next(values for values in data["probes"] if values["name"] == "wall_top")
        probe["at"] = [probe["at"][0] + step, probe["at"][1]]
    if along_y:
        deepen_foundation(data, SHIFT)
    return jaxmpm.Scene.from_dict(data)


def wall_top_x(scene, hold, cfl, at=0.3):
    scene = (scene.with_value("scene.duration", at).with_value("scene.cfl", cfl)
             .with_value("numerics.structure_hold", hold))
    result = jaxmpm.Simulation(scene).run(progress=False)
    return 1e3 * float(np.asarray(result.probes["wall_top"])[-1, 0])


def shift_study():
    print("| geometry | hold | wall top x at 0.3 s, cfl 0.4 [mm] | cfl 0.2 [mm] | change |")
    print("|---|---|---|---|---|")
    for label, along_x, along_y in (("on the grid lines (shipped)", False, False), ("wall 0.3 cell along x", True, False),
                                    ("foundation 0.3 cell deeper", False, True), ("both", True, True)):
        scene = shifted_twin(along_x, along_y)
        for hold in HOLDS:
            coarse, fine = wall_top_x(scene, hold, 0.4), wall_top_x(scene, hold, 0.2)
            print(f"| {label} | {hold} | {coarse:.2f} | {fine:.2f} | {100 * (fine / coarse - 1):+.1f} % |", flush=True)


def rocking_scene(shape: str, hold: str, refinement: int, cfl: float, lower: float = 0.0, along: float = 0.0) -> jaxmpm.Scene:
    """The rocking block (module docstring); lower: the layer that many cells deeper with the
    grid's origin, so that the block's base lies off the grid lines; along: the block moved
    that many cells along x."""
    data = read_scene_file(TWIN)
    data["scene"].update(gravity=[9.81 * math.sin(TILT), -9.81 * math.cos(TILT)], duration=DURATION, cfl=cfl)
    data["grid"]["cell"] /= refinement
    data["numerics"].update(shape=shape, structure_hold=hold, damping=0.3)
    data["materials"]["layer"] = {"model": "linear_elastic", "density": 1800.0, "young": 2.0e6, "poisson": 0.3}
    foundation = body(data, "foundation")
    foundation["material"] = "layer"
    foundation["initial_stress"] = {"geostatic": {"k0": 0.3 / 0.7}}
    if lower:
        deepen_foundation(data, lower)
    wall = body(data, "wall")
    (x0, y0), (x1, y1) = wall["region"]["rectangle"]
    across = along * data["grid"]["cell"]
    wall["region"]["rectangle"] = [[x0 + across, y0], [x1 + across, y1]]
    data["bodies"] = [foundation, wall]
    data["contacts"] = [{"pair": ["foundation", "wall"], "friction": 0.4}]
    data["probes"] = [{"name": "top", "kind": "displacement", "at": [0.4875 + across, 0.5]},
                      {"name": "base", "kind": "displacement", "at": [0.4875 + across, 0.156]}]
    return jaxmpm.Scene.from_dict(data)


def strip_footing_rotation() -> float:
    """theta [rad] of the rigid strip on an elastic half-space (module docstring)."""
    width, height, density = 0.075, 0.35, 2400.0
    mass, centre = density * width * height, 0.5 * height
    plane_modulus, half = 2.0e6 / (1.0 - 0.3 ** 2), 0.5 * width
    moment = mass * 9.81 * math.sin(TILT) * centre
    return moment / (math.pi * plane_modulus * half ** 2 / 4.0 - mass * 9.81 * math.cos(TILT) * centre)


def rocking_history(shape, hold, refinement, cfl, lower=0.0, along=0.0, friction=None):
    """(times, the block's rotation [rad]) over the rocking run."""
    scene = rocking_scene(shape, hold, refinement, cfl, lower, along)
    if friction is not None:
        scene = scene.with_value("contacts.foundation/wall.friction", friction)
    result = jaxmpm.Simulation(scene).run(progress=False)
    top, base = np.asarray(result.probes["top"]), np.asarray(result.probes["base"])
    return np.asarray(result.time), (top[:, 0] - base[:, 0]) / (0.5 - 0.156)


def settled_rotation(*args, **kwargs):
    time, rotation = rocking_history(*args, **kwargs)
    return float(np.mean(rotation[time >= SETTLED]))


def rocking_study():
    print(f"rigid strip on an elastic half-space: {1e3 * strip_footing_rotation():.3f} mrad")
    print(f"\nfriction 0.4, the rotation's mean over {SETTLED}-{DURATION} s [mrad]:\n")
    print("| shape | hold | cell h | h/2 | h at cfl 0.2 | h, the layer 0.3 cell deeper | h, the block half a cell along x |")
    print("|---|---|---|---|---|---|---|")
    for shape in ("bspline2", "linear"):
        for hold in HOLDS:
            values = [settled_rotation(shape, hold, 1, 0.4), settled_rotation(shape, hold, 2, 0.4),
                      settled_rotation(shape, hold, 1, 0.2), settled_rotation(shape, hold, 1, 0.4, lower=SHIFT),
                      settled_rotation(shape, hold, 1, 0.4, along=0.5)]
            print(f"| {shape} | {hold} | " + " | ".join(f"{1e3 * value:.2f}" for value in values) + " |", flush=True)
    print("\nfriction 10 (the base cannot slip), cell h, the rotation at 0.5 / 1.0 / 1.5 s [mrad]:\n")
    print("| shape | hold | cfl 0.4 | cfl 0.2 |")
    print("|---|---|---|---|")
    for shape in ("bspline2", "linear"):
        for hold in HOLDS:
            cells = []
            for cfl in (0.4, 0.2):
                time, rotation = rocking_history(shape, hold, 1, cfl, friction=10.0)
                cells.append(" / ".join(f"{1e3 * rotation[np.argmin(np.abs(time - at))]:.2f}" for at in (0.5, 1.0, 1.5)))
            print(f"| {shape} | {hold} | {cells[0]} | {cells[1]} |", flush=True)


def rocking_figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = {"mass": (1, 2), "outline": (1, 2), "points": (1, 2, 4)}
    colours = {"mass": "tab:blue", "outline": "tab:red", "points": "tab:green"}
    figure, (history, settled) = plt.subplots(1, 2, figsize=(11, 4.2))
    elastic = 1e3 * strip_footing_rotation()
    for hold, refinements in runs.items():
        means = []
        for refinement in refinements:
            time, rotation = rocking_history("bspline2", hold, refinement, 0.4)
            history.plot(time, 1e3 * rotation, color=colours[hold], alpha=1.0 / refinement ** 0.5,
                         label=f"{hold}, h/{refinement}" if refinement > 1 else f"{hold}, h")
            means.append(1e3 * float(np.mean(rotation[time >= SETTLED])))
            print(f"{hold} h/{refinement}: {means[-1]:.3f} mrad", flush=True)
        cells = [25.0 / refinement for refinement in refinements]
        settled.plot(cells, means, "o-", color=colours[hold], label=hold)
    for axes in (history, settled):
        axes.axhline(elastic, color="black", linestyle="--", linewidth=1, label="elastic half-space")
    history.set(xlabel="time [s]", ylabel="rotation [mrad]", title="rigid block on an elastic layer, gravity tilted 2°")
    settled.set(xlabel="cell [mm]", ylabel=f"rotation, mean over {SETTLED}-{DURATION} s [mrad]", xscale="log",
                title="under each numerics.structure_hold")
    settled.set_xticks([6.25, 12.5, 25.0], labels=["6.25", "12.5", "25"])
    settled.minorticks_off()
    history.legend(fontsize=7, ncol=2)
    settled.legend(fontsize=8)
    figure.tight_layout()
    path = ROOT / "docs" / "images" / "rocking_block.png"
    figure.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    studies = {"shift": shift_study, "rocking": rocking_study, "figure": rocking_figure}
    if len(sys.argv) != 2 or sys.argv[1] not in studies:
        sys.exit(f"usage: python {Path(__file__).name} {' | '.join(studies)}")
    studies[sys.argv[1]]()
