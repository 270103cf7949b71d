"""The speed-accuracy trade of the numerics choices, on four problems with known answers.

    python benchmarks/speed_accuracy.py                 # the full study (about 40 min on 2 cores)
    python benchmarks/speed_accuracy.py --quick         # coarse levels only (a few minutes)
    python benchmarks/speed_accuracy.py --problems bar column   # some problems; others kept
    python benchmarks/speed_accuracy.py --report        # tables and plot from the JSON, no runs

Problems (docs/speed_accuracy.md says what each error is):
  bar       vibrating bar, first axial mode (docs/validation.md §1): rms of the tip displacement
            history over two periods against (v0 / omega) sin(omega t) sin(pi x / 2L), relative;
  column    confined elastic column released under gravity from zero stress, damped to rest
            (examples/elastic_column.toml, damping 0.7, 0.15 s): max and rms over the points of
            |sigma_yy + rho g (H - y)| / (rho g H);
  collapse  granular column collapse (examples/column_collapse.toml, Bui et al. 2008): runout
            (L - L0) / L0 against the finest, most accurate run afforded and against the
            published range 0.60-0.90 (Lube et al. 2005, Lajeunesse et al. 2005);
  wall      active thrust on a smooth wall moving away (examples/retaining_wall_active.toml):
            mean contact force over the last 0.05 s against Rankine's 1/2 Ka rho g H^2.

Configurations: the three presets at every cell size, and a one-at-a-time sweep around
"balanced" and "fast" (shape, transfer, update, dtype, ppc) at the sweep cell sizes. Cost: the
forward run after compilation (the AOT-compiled output step replaces `Simulation._advance`, so
compilation is timed apart), as process CPU seconds and wall seconds, with the 1-minute load
average at the start. One process with JAX's 64-bit mode on: float32 scenes compute in float32
throughout (the tests check this with strict dtype promotion). A run that stops (non-finite
state, point off the grid) or gives a non-finite answer is marked unstable, never fatal.

Results go to benchmarks/results/speed_accuracy.json (merged by configuration, so a partial
rerun keeps the rest); the tables go into docs/speed_accuracy.md between marker comments and the
plot to docs/images/speed_accuracy.png. A study, not a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
RESULTS = ROOT / "benchmarks" / "results" / "speed_accuracy.json"
DOC = ROOT / "docs" / "speed_accuracy.md"
PLOT = ROOT / "docs" / "images" / "speed_accuracy.png"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(EXAMPLES))

G = 9.81
PRESET_NAMES = ("fast", "balanced", "accurate")
# One-at-a-time variations around a preset: (label, overrides)
AROUND = {
    "balanced": [("linear", {"shape": "linear"}), ("gimp", {"shape": "gimp"}), ("flip 0.99", {"transfer": "flip"}),
                 ("usl", {"update": "usl"}), ("float32", {"dtype": "float32"})],
    "fast": [("gimp", {"shape": "gimp"}), ("bspline2", {"shape": "bspline2"}), ("apic", {"transfer": "apic"}),
             ("usl", {"update": "usl"}), ("float64", {"dtype": "float64"}), ("ppc 3", {"ppc": 3})],
}


# =========================================================================== problems


class Bar:
    """Vibrating bar (Sulsky et al. 1994; docs/validation.md §1): L = 25 m, E = 100 Pa,
    rho = 1, nu = 0, fixed at x = 0, free at x = L, on a grid one cell high with slip top and
    bottom; started in its first mode v(x, 0) = v0 sin(pi x / 2L), v0 = 0.1 m/s (the example's
    speed: the tip moves 0.16 m, so points cross cells once h < 0.64 m), for two periods
    (T = 4L/c = 10 s)."""

    name, title = "bar", "vibrating bar"
    length, young, density, v0 = 25.0, 100.0, 1.0, 0.1
    cells = {"full": [2.5, 1.25, 0.625], "quick": [2.5, 1.25]}         # 10, 20, 40 cells along the bar
    sweep = {"full": [1.25, 0.625], "quick": [1.25]}
    error_label = "tip history rms error / rms"

    @property
    def omega(self):
        return math.pi * math.sqrt(self.young / self.density) / (2.0 * self.length)

    def scene(self, cell, numerics):
        from jaxmpm import Body, Boundaries, Grid, LinearElastic, Probe, Rectangle, Scene

        duration = 2.0 * 2.0 * math.pi / self.omega
        return Scene(
            name="vibrating_bar_first_mode",
            grid=Grid(size=(self.length + 2.0 * cell, cell), cell=cell,
                      boundaries=Boundaries(left="fixed", right="free", bottom="slip", top="slip")),
            materials={"rod": LinearElastic(density=self.density, young=self.young, poisson=0.0)},
            bodies=(Body("bar", "rod", Rectangle((0.0, 0.0), (self.length, cell))),),
            duration=duration, gravity=(0.0, 0.0), cfl=0.4, output_every=duration / 4.0,
            snapshot_fields=("x",), numerics=numerics,
            probes=(Probe("tip", "displacement", at=(self.length, 0.5 * cell)),
                    Probe("centre_of_mass", "body_displacement", body="bar")),
        )

    def initial(self, sim, params):
        import jax.numpy as jnp

        state = sim.initial_state(params)
        x = state.particles.x[:, 0]
        speed = self.v0 * jnp.sin(jnp.pi * x / (2.0 * self.length))
        return state.replace(particles=state.particles.replace(v=jnp.stack([speed, jnp.zeros_like(speed)], axis=1)))

    def measure(self, sim, result):
        from jaxmpm.physics.probes import nearest_point

        t = result.time
        x0 = np.asarray(sim.seeds.positions)
        tip_x = x0[nearest_point(sim.seeds, (self.length, 0.5 * sim.scene.grid.cell)), 0]
        mode = (self.v0 / self.omega) * np.sin(self.omega * t)
        exact_tip = mode * math.sin(math.pi * tip_x / (2.0 * self.length))
        exact_cm = mode * np.mean(np.sin(math.pi * x0[:, 0] / (2.0 * self.length)))
        tip, cm = result.probes["tip"][:, 0], result.probes["centre_of_mass"][:, 0]
        rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
        return {"error": rms(tip - exact_tip) / rms(exact_tip), "cm_error": rms(cm - exact_cm) / rms(exact_cm),
                "tip_peak_error": float(np.max(np.abs(tip - exact_tip)) / np.max(np.abs(exact_tip)))}


class Column:
    """Confined elastic column (examples/elastic_column.toml; CB-Geo benchmark): H = 0.1 m,
    released under gravity from zero stress (no geostatic initialisation), local damping 0.7
    for 0.15 s (about 9 periods of its first mode): at rest sigma_yy = -rho g (H - y)."""

    name, title = "column", "column under self-weight"
    height, rho = 0.1, 1800.0
    cells = {"full": [0.01, 0.005, 0.0025], "quick": [0.01, 0.005]}    # 10, 20, 40 cells over H
    sweep = {"full": [0.01], "quick": [0.01]}
    error_label = "max |sigma_yy + rho g (H - y)| / (rho g H)"
    damping = 0.7

    def scene(self, cell, numerics):
        import jaxmpm

        scene = jaxmpm.load_scene(EXAMPLES / "elastic_column.toml")
        scene = dataclasses.replace(scene, numerics=numerics)
        for key, value in [("grid.cell", cell), ("scene.duration", 0.15), ("scene.output_every", 0.05),
                           ("scene.snapshot_fields", ["v", "stress"])]:
            scene = scene.with_value(key, value)
        return scene

    def measure(self, sim, result):
        y = np.asarray(sim.seeds.positions)[:, 1]
        final = result.snapshots["column"]
        sigma = final["stress"][-1][:, 1, 1]
        rho_g = self.rho * G
        error = np.abs(sigma + rho_g * (self.height - y)) / (rho_g * self.height)
        cell = sim.scene.grid.cell
        inside = (y > 3 * cell) & (y < self.height - 3 * cell)
        return {"error": float(error.max()), "rms": float(np.sqrt(np.mean(error**2))),
                "interior_max": float(error[inside].max()) if inside.any() else None,
                "worst_y_over_h": float(y[np.argmax(error)] / cell),
                "residual_speed": float(np.max(np.abs(final["v"][-1])))}


class Collapse:
    """Granular column collapse (examples/column_collapse.toml; Bui et al. 2008): a = 0.5,
    phi = 19.8 deg, from its geostatic state; runout (L - L0) / L0 and H / H0 of the deposit
    (outermost / highest point + half a point spacing, as benchmarks/column_collapse_study.py)."""

    name, title = "collapse", "column collapse"
    cells = {"full": [0.01, 0.005], "quick": [0.01]}
    sweep = {"full": [0.01], "quick": [0.01]}
    reference = ("accurate", {}, 0.0025)            # preset, overrides, cell (full study only)
    error_label = "|runout / reference - 1|"
    published = (0.60, 0.90)                         # Lube et al. 2005 to Lajeunesse et al. 2005, a = 0.5
    duration = 1.0                                   # the example's: the front still creeps after 0.6 s

    def scene(self, cell, numerics):
        import jaxmpm

        scene = jaxmpm.load_scene(EXAMPLES / "column_collapse.toml")
        scene = dataclasses.replace(scene, numerics=numerics)
        for key, value in [("grid.cell", cell), ("scene.duration", self.duration), ("scene.output_every", 0.1),
                           ("scene.snapshot_fields", ["x"])]:
            scene = scene.with_value(key, value)
        return scene

    def measure(self, sim, result):
        positions = result.snapshots["column"]["x"]
        half = 0.5 * sim.scene.grid.cell / sim.scene.numerics.ppc
        length0, height0 = positions[0][:, 0].max() + half, positions[0][:, 1].max() + half
        fronts = positions[:, :, 0].max(axis=1) + half
        runout = (fronts[-1] - length0) / length0
        low, high = self.published
        return {"runout": float(runout), "height_ratio": float((positions[-1][:, 1].max() + half) / height0),
                "runout_0.2s_before_end": float((fronts[-3] - length0) / length0),
                "outside_published": float(max(low - runout, runout - high, 0.0)),
                "published_mid_error": float(abs(runout / (0.5 * (low + high)) - 1.0))}


class Wall:
    """Active thrust on a smooth retaining wall (examples/retaining_wall_active.toml): the wall
    moves away at 5 mm/s from t = 0.05 s to 0.3 s (1.2 mm, 0.24 % of H); the thrust (contact
    force of the backfill on the wall) averaged over the last 0.05 s against Rankine's
    1/2 Ka rho g H^2 = 735.75 N/m, and over 0.01-0.05 s (wall still) against 1/2 K0 rho g H^2."""

    name, title = "wall", "retaining wall, active thrust"
    cells = {"full": [0.05, 0.025], "quick": [0.05]}
    sweep = {"full": [0.05, 0.025], "quick": [0.05]}
    error_label = "|thrust / Rankine - 1|"

    def scene(self, cell, numerics):
        import jaxmpm

        scene = jaxmpm.load_scene(EXAMPLES / "retaining_wall_active.toml")
        scene = dataclasses.replace(scene, numerics=numerics)
        for key, value in [("grid.cell", cell), ("scene.output_every", 0.05), ("scene.snapshot_fields", ["x"])]:
            scene = scene.with_value(key, value)
        return scene

    def measure(self, sim, result):
        scene = sim.scene
        sand = scene.materials[scene.bodies[0].material]
        height = max(vertex[1] for vertex in scene.bodies[0].region.vertices)
        phi = math.radians(sand.friction_angle)
        weight = 0.5 * sand.density * G * height**2
        at_rest, rankine = weight * (1 - math.sin(phi)), weight * (1 - math.sin(phi)) / (1 + math.sin(phi))
        t, thrust = result.time, -result.probes["thrust"][:, 0]
        last = thrust[t > t[-1] - 0.05]
        before = thrust[(t > 0.01) & (t < 0.05)].mean()
        return {"error": float(abs(last.mean() / rankine - 1.0)), "thrust": float(last.mean()),
                "thrust_scatter": float(last.std()), "at_rest": float(before),
                "at_rest_error": float(abs(before / at_rest - 1.0))}


PROBLEMS = {problem.name: problem for problem in (Bar(), Column(), Wall(), Collapse())}


# =========================================================================== configurations


def configurations(problem, level):
    """[(preset, label, overrides, cell)], presets first, duplicates (same resolved numerics) dropped."""
    from jaxmpm import Numerics

    chosen, seen = [], set()

    def add(preset, label, overrides, cell):
        numerics = Numerics(preset=preset, **overrides)
        key = (cell, numerics.shape, numerics.transfer, numerics.flip, numerics.ppc, numerics.dtype, numerics.update)
        if key not in seen:
            seen.add(key)
            chosen.append((preset, label, overrides, cell))

    for cell in problem.cells[level]:
        for preset in PRESET_NAMES:
            add(preset, preset, {}, cell)
    for cell in problem.sweep[level]:
        for preset, variations in AROUND.items():
            for label, overrides in variations:
                add(preset, f"{preset} + {label}", overrides, cell)
    if level == "full" and getattr(problem, "reference", None):
        preset, overrides, cell = problem.reference
        add(preset, preset, overrides, cell)
    return chosen


def config_id(problem, preset, overrides, cell):
    extra = ",".join(f"{key}={value}" for key, value in sorted(overrides.items()))
    return f"{problem}|{cell:g}|{preset}|{extra}"


def run_one(problem, preset, label, overrides, cell):
    """One run: a record with the numerics, cost and the problem's errors (or 'unstable')."""
    import jax
    from jaxmpm import Numerics, Simulation, SimulationError

    numerics = Numerics(preset=preset, damping=getattr(problem, "damping", 0.0), **overrides)
    scene = problem.scene(cell, numerics)
    sim = Simulation(scene)
    params = sim.cast(sim.params)
    initial = problem.initial(sim, params) if hasattr(problem, "initial") else sim.initial_state(params)
    record = {
        "id": config_id(problem.name, preset, overrides, cell), "problem": problem.name, "preset": preset,
        "label": label, "overrides": overrides, "cell": cell,
        "numerics": {k: getattr(scene.numerics, k) for k in ("shape", "transfer", "flip", "ppc", "dtype", "update")},
        "points": sim.point_count, "steps": sim.steps, "dt": sim.dt,
    }
    start = time.perf_counter()
    compiled = sim._advance.lower(params, initial, initial.particles.x).compile()
    record["compile_s"] = time.perf_counter() - start
    sim._advance = compiled                    # run() now calls the compiled step: no compile inside the timing
    record["load_average"] = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        result = sim.run(params=params, initial=initial, progress=False)
        record["status"] = "ok"
    except SimulationError as error:
        result = None
        record["status"] = "unstable"
        record["message"] = str(error)
    record["cpu_s"] = time.process_time() - cpu
    record["wall_s"] = time.perf_counter() - wall
    record["mps_wall"] = sim.point_count * sim.steps / record["wall_s"] / 1e6
    record["mps_cpu"] = sim.point_count * sim.steps / record["cpu_s"] / 1e6
    if result is not None:
        errors = problem.measure(sim, result)
        record["errors"] = errors
        if not all(value is None or math.isfinite(value) for value in errors.values()):
            record["status"] = "unstable"
            record["message"] = "non-finite answer"
    jax.clear_caches()
    return record


# =========================================================================== results file


def load_results():
    if RESULTS.exists():
        return json.loads(RESULTS.read_text())
    return {"machine": {}, "runs": {}}


def save_results(data):
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


def add_reference_errors(data):
    """Collapse: the error of each run against the reference run (the finest, most accurate one
    in the file); without it, against the finest balanced run."""
    runs = [r for r in data["runs"].values() if r["problem"] == "collapse" and r["status"] == "ok"]
    if not runs:
        return None
    preset, overrides, cell = Collapse.reference
    ref = data["runs"].get(config_id("collapse", preset, overrides, cell))
    if ref is None or ref["status"] != "ok":
        ref = min((r for r in runs if r["label"] == "accurate"), key=lambda r: r["cell"], default=runs[0])
    for r in runs:
        r["errors"]["error"] = None if r is ref else abs(r["errors"]["runout"] / ref["errors"]["runout"] - 1.0)
        r["is_reference"] = r is ref
    return ref


# =========================================================================== report


def fmt(value, digits=2):
    if value is None:
        return "–"
    if value == 0:
        return "0"
    return f"{value:.{digits}g}" if abs(value) < 1e-3 or abs(value) >= 1e4 else f"{value:.{digits + 1}g}" if abs(value) < 1 else f"{value:.{digits}f}"


def error_cell(r, key="error", percent=True):
    if r["status"] != "ok":
        return "**unstable**"
    value = r["errors"].get(key)
    if value is None:
        return "(reference)"
    return f"{100 * value:.2f} %" if percent else fmt(value)


def cost_cells(r):
    return f"{r['cpu_s']:.1f} | {r['wall_s']:.1f} | {r['mps_wall']:.2f}"


def numerics_text(r):
    n = r["numerics"]
    transfer = "APIC" if n["transfer"] == "apic" else f"FLIP {n['flip']:g}"
    return f"{n['shape']}, {transfer}, {n['update'].upper()}, ppc {n['ppc']}, {n['dtype']}"


def problem_table(data, name):
    problem = PROBLEMS[name]
    runs = sorted((r for r in data["runs"].values() if r["problem"] == name),
                  key=lambda r: (-r["cell"], r["label"] not in PRESET_NAMES, r["label"]))
    extra = {
        "bar": ("centre-of-mass rms error", lambda r: error_cell(r, "cm_error")),
        "column": ("rms over points", lambda r: error_cell(r, "rms")),
        "collapse": ("runout (L-L0)/L0; H/H0", lambda r: "–" if r["status"] != "ok" else
                     f"{r['errors']['runout']:.3f}; {r['errors']['height_ratio']:.3f}"),
        "wall": ("thrust [N/m] (scatter); at rest vs K0", lambda r: "–" if r["status"] != "ok" else
                 f"{r['errors']['thrust']:.1f} ({r['errors']['thrust_scatter']:.1f}); "
                 f"{100 * r['errors']['at_rest_error']:.1f} %"),
    }[name]
    lines = [f"| cell [m] | configuration | numerics | points | steps | {problem.error_label} | {extra[0]} "
             "| CPU s | wall s | M point-steps/s (wall) |",
             "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in runs:
        label = f"**{r['label']}**" if r["label"] in PRESET_NAMES else r["label"]
        lines.append(f"| {r['cell']:g} | {label} | {numerics_text(r)} | {r['points']:,} | {r['steps']:,} "
                     f"| {error_cell(r)} | {extra[1](r)} | {cost_cells(r)} |")
    return "\n".join(lines)


def preset_table(data):
    lines = ["| problem | cell [m] | " + " | ".join(f"{p}: error; CPU s (M pt-steps/s)" for p in PRESET_NAMES) + " |",
             "|---|---:|" + "---:|" * len(PRESET_NAMES)]
    for name, problem in PROBLEMS.items():
        cells = sorted({r["cell"] for r in data["runs"].values() if r["problem"] == name}, reverse=True)
        for cell in cells:
            row = []
            for preset in PRESET_NAMES:
                r = data["runs"].get(config_id(name, preset, {}, cell))
                if r is None:
                    row.append("–")
                elif r["status"] != "ok":
                    row.append(f"**unstable**; {r['cpu_s']:.1f}")
                else:
                    row.append(f"{error_cell(r)}; {r['cpu_s']:.1f} ({r['mps_wall']:.2f})")
            if any(cell != "–" for cell in row):
                lines.append(f"| {problem.title} | {cell:g} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def pareto(points):
    """Indices of the points not dominated in (cost, error), both lower-is-better."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def plot(data):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    colours = {"fast": "tab:red", "balanced": "tab:blue", "accurate": "tab:green"}
    shapes = {"linear": "s", "gimp": "D", "bspline2": "o"}
    figure, axes = plt.subplots(2, 2, figsize=(11, 8.5))
    for ax, (name, problem) in zip(axes.ravel(), PROBLEMS.items()):
        runs = [r for r in data["runs"].values() if r["problem"] == name and math.isfinite(r["cpu_s"])]
        good = [r for r in runs if r["status"] == "ok" and r["errors"].get("error") is not None]
        if not runs:
            ax.set_visible(False)
            continue
        for r in good:
            is_preset = r["label"] in PRESET_NAMES
            ax.scatter(r["cpu_s"], r["errors"]["error"], marker=shapes[r["numerics"]["shape"]],
                       s=70 if is_preset else 22, zorder=3 if is_preset else 2,
                       facecolor=colours[r["preset"]] if is_preset else "none",
                       edgecolor=colours[r["preset"]], alpha=1.0 if is_preset else 0.7)
        for preset, colour in colours.items():
            line = sorted((r for r in good if r["label"] == preset), key=lambda r: r["cpu_s"])
            if line:
                ax.plot([r["cpu_s"] for r in line], [r["errors"]["error"] for r in line], color=colour, lw=1.2,
                        label=preset)
                for r in line:
                    ax.annotate(f"h={r['cell']:g}", (r["cpu_s"], r["errors"]["error"]), fontsize=7,
                                xytext=(4, 3), textcoords="offset points", color=colour)
        if good:
            front = [good[i] for i in pareto([(r["cpu_s"], r["errors"]["error"]) for r in good])]
            ax.step([r["cpu_s"] for r in front], [r["errors"]["error"] for r in front], where="post",
                    color="0.5", ls=":", lw=1, label="Pareto front")
            top = max(r["errors"]["error"] for r in good)
            bad = [r for r in runs if r["status"] != "ok"]
            if bad:
                ax.scatter([r["cpu_s"] for r in bad], [top * 2.0] * len(bad), marker="x", color="k",
                           label="unstable", zorder=4)
        ref = [r for r in runs if r.get("is_reference")]
        title = problem.title + (f" (reference: {ref[0]['label']}, h={ref[0]['cell']:g} m)" if ref else "")
        ax.set(xscale="log", yscale="log", xlabel="CPU seconds (run, after compilation)",
               ylabel=problem.error_label, title=title)
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_formatter(matplotlib.ticker.FuncFormatter(
                lambda v, _: f"{v:g}" if round(v / 10 ** math.floor(math.log10(v) + 1e-9)) in (2, 5) else ""))
            axis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.title.set_fontsize(9)
        ax.yaxis.label.set_fontsize(8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    handles = [plt.Line2D([], [], marker=m, ls="", color="0.3", mfc="none", label=s) for s, m in shapes.items()]
    figure.legend(handles=handles, loc="lower center", ncol=3, fontsize=8,
                  title="marker: shape function (filled = preset, hollow = one-at-a-time variation)",
                  title_fontsize=8)
    figure.tight_layout(rect=(0, 0.05, 1, 1))
    PLOT.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(PLOT, dpi=110)
    plt.close(figure)


def machine_text(data):
    m = data.get("machine", {})
    loads = [r["load_average"] for r in data["runs"].values() if math.isfinite(r["load_average"])]
    load = f"load average {min(loads):.1f}–{max(loads):.1f} at the start of the runs" if loads else ""
    return (f"Measured {m.get('date', '?')} on {m.get('cpu', '?')} ({m.get('cores', '?')} cores, "
            f"{m.get('memory', '?')}), JAX {m.get('jax', '?')}, jaxmpm {m.get('jaxmpm', '?')} "
            f"(commit {m.get('commit', '?')}), {m.get('level', '?')} study; {load}. Machine total "
            f"{m.get('total_s', 0) / 60:.0f} min.")


def write_report(data):
    from common import write_section

    add_reference_errors(data)
    if not DOC.exists():
        DOC.write_text("# Speed against accuracy\n")
    write_section("<!-- machine:begin -->", "<!-- machine:end -->", machine_text(data), DOC)
    write_section("<!-- presets:begin -->", "<!-- presets:end -->", preset_table(data), DOC)
    for name in PROBLEMS:
        if any(r["problem"] == name for r in data["runs"].values()):
            write_section(f"<!-- {name}:begin -->", f"<!-- {name}:end -->", problem_table(data, name), DOC)
    plot(data)


# =========================================================================== main


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="coarse levels only")
    parser.add_argument("--problems", nargs="+", choices=list(PROBLEMS), default=list(PROBLEMS))
    parser.add_argument("--report", action="store_true", help="only rewrite the doc tables and plot from the JSON")
    parser.add_argument("--list", action="store_true", help="print the configurations and stop")
    arguments = parser.parse_args()
    data = load_results()
    if not arguments.report:
        import jax

        jax.config.update("jax_enable_x64", True)
        from common import machine_info

        level = "quick" if arguments.quick else "full"
        plan = [(name, c) for name in arguments.problems for c in configurations(PROBLEMS[name], level)]
        if arguments.list:
            for name, (preset, label, overrides, cell) in plan:
                print(name, cell, label)
            print(len(plan), "runs")
            return
        import jaxmpm

        begin = time.perf_counter()
        for number, (name, (preset, label, overrides, cell)) in enumerate(plan, 1):
            try:
                record = run_one(PROBLEMS[name], preset, label, overrides, cell)
            except Exception as error:       # noqa: BLE001 - one broken configuration must not end the study
                traceback.print_exc()
                n = jaxmpm.Numerics(preset=preset, **overrides)
                record = {"id": config_id(name, preset, overrides, cell), "problem": name, "preset": preset,
                          "label": label, "overrides": overrides, "cell": cell, "status": "failed",
                          "numerics": {k: getattr(n, k) for k in ("shape", "transfer", "flip", "ppc", "dtype", "update")},
                          "points": 0, "steps": 0, "mps_wall": math.nan, "load_average": math.nan,
                          "message": f"{type(error).__name__}: {error}", "cpu_s": math.nan, "wall_s": math.nan}
            data["runs"][record["id"]] = record
            errors = record.get("errors", {})
            print(f"[{number}/{len(plan)}] {name} h={cell:g} {label}: {record['status']} "
                  f"error={errors.get('error', errors.get('runout'))} cpu={record.get('cpu_s', math.nan):.1f}s "
                  f"wall={record.get('wall_s', math.nan):.1f}s compile={record.get('compile_s', math.nan):.1f}s "
                  f"load={record.get('load_average', math.nan):.1f} ({time.perf_counter() - begin:.0f}s)", flush=True)
            save_results(data)
        machine = machine_info()
        machine.update(jaxmpm=jaxmpm.__version__, level=level,
                       total_s=data.get("machine", {}).get("total_s", 0) * (set(arguments.problems) != set(PROBLEMS))
                       + time.perf_counter() - begin)
        data["machine"] = machine
        save_results(data)
    write_report(data)
    save_results(data)


if __name__ == "__main__":
    sys.exit(main())
