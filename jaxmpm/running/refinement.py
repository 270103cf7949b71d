"""A run against the same scene at refined numerics: how much its probes owe to the discretisation.

An explicit MPM result depends on the time step, the cell, the transfer's relaxation and,
with a viscoplastic sand, the step of its stress update (docs/convergence.md).
`refined_scene` makes the scene one step finer in one of them;
`compare_results` reads how far each probe moves over the run. Probes are recorded every step,
and forces ripple from one step to the next (a contact tip crossing a row of nodes), so each
run's probe is averaged over each output interval (the trapezoidal rule on its own steps) and
the means are compared:

    change = max_k |A_k - B_k|,   relative = change / max_k max(|A_k|, |B_k|)

(A_k, B_k the run's and the refined run's means over the k-th output interval, up to the time
both reached), the largest difference against the component's largest mean, so that a
quantity passing through zero does not read as a large relative change. Halving dt from the
scene's own should change every probe by well under the accuracy a user needs; if it does not,
the run is not converged in dt and its numbers carry that error.

"stress" doubles numerics.stress_substeps: the stress update's own step halved, the rest of
the step unchanged (the Perzyna update's share of the Delta-t error).

"relaxation" is a sensitivity, not a refinement: the relaxation kappa doubled. kappa moves the
results without a limit as it grows (docs/convergence.md, "The relaxation's own effect").
"""

from __future__ import annotations

import dataclasses

import numpy as np

# What each refinement does, in a few words (for summaries such as a calibration's).
REFINEMENT_LABELS = {"dt": "time step halved", "cell": "cell halved", "relaxation": "relaxation doubled",
                     "stress": "stress substeps doubled"}
REFINEMENTS = tuple(REFINEMENT_LABELS)


def refined_scene(scene, refinement: str):
    """The scene with its time step halved ("dt": scene.dt, or scene.cfl when dt is not
    given), its cell halved ("cell": the time step follows from the cfl, and a given
    scene.dt is halved with it), its relaxation doubled ("relaxation") or its stress substeps
    doubled ("stress")."""
    if refinement == "dt":
        if scene.dt is not None:
            return scene.with_value("scene.dt", scene.dt / 2.0)
        return scene.with_value("scene.cfl", scene.cfl / 2.0)
    if refinement == "cell":
        scene = scene.with_value("grid.cell", scene.grid.cell / 2.0)
        return scene if scene.dt is None else scene.with_value("scene.dt", scene.dt / 2.0)
    if refinement == "relaxation":
        return scene.with_value("numerics.relaxation", 2.0 * scene.numerics.relaxation)
    if refinement == "stress":
        return scene.with_value("numerics.stress_substeps", 2 * scene.numerics.stress_substeps)
    raise ValueError(f"refinement {refinement!r} is not one of {REFINEMENTS}")


def refinement_refused(scene, refinement: str) -> str | None:
    """Why `refinement` cannot be made on `scene` (a sentence's end), or None."""
    from jaxmpm.scene.parts import MAX_STRESS_SUBSTEPS       # here: the CLI's parser imports this module

    if refinement == "relaxation" and (scene.numerics.transfer != "apic" or scene.numerics.relaxation <= 0.0):
        return (f"the scene {scene.name!r} has no relaxation to double (numerics.transfer = "
                f"{scene.numerics.transfer!r}, numerics.relaxation = {scene.numerics.relaxation:g}; it needs "
                "'apic' and a relaxation > 0)")
    if refinement == "stress" and not any(body.kinematics.type == "free" and scene.material_of(body).law.yields
                                          for body in scene.bodies):
        return (f"the scene {scene.name!r} has no free body that can yield, whose stress update "
                "numerics.stress_substeps would refine")
    if refinement == "stress" and 2 * scene.numerics.stress_substeps > MAX_STRESS_SUBSTEPS:
        return (f"numerics.stress_substeps = {scene.numerics.stress_substeps} cannot be doubled: "
                f"{MAX_STRESS_SUBSTEPS} is the largest")
    return None


def describe_refinement(scene, refinement: str) -> str:
    """'scene.cfl 0.4 -> 0.2' and the like: what the refinement changes in `scene`."""
    refined = refined_scene(scene, refinement)
    if refinement == "dt":
        key, before, after = ("scene.dt", scene.dt, refined.dt) if scene.dt is not None else (
            "scene.cfl", scene.cfl, refined.cfl)
    elif refinement == "cell":
        key, before, after = "grid.cell", scene.grid.cell, refined.grid.cell
        if scene.dt is not None:
            return f"{key} {before:g} -> {after:g}, scene.dt {scene.dt:g} -> {refined.dt:g}"
    elif refinement == "stress":
        key, before, after = "numerics.stress_substeps", scene.numerics.stress_substeps, refined.numerics.stress_substeps
    else:
        key, before, after = "numerics.relaxation", scene.numerics.relaxation, refined.numerics.relaxation
    return f"{key} {before:g} -> {after:g}"


@dataclasses.dataclass(frozen=True)
class ProbeChange:
    """One probe component's largest change of its output-interval means: `axis` its name
    ("x", "y"; "r", "z" in axisymmetry; "" for a probe of one value), `change` (the probe's
    unit), `largest` its largest |mean| in either run, `relative` change / largest (nan when
    it is 0 in both throughout, or when a run holds a non-finite value), `at` the middle of
    the interval of the largest change [s]."""

    probe: str
    axis: str
    change: float
    largest: float
    relative: float
    at: float

    @property
    def label(self) -> str:
        return f"{self.probe} {self.axis}".rstrip()


@dataclasses.dataclass(frozen=True)
class Comparison:
    """`changes` (one ProbeChange per probe component) up to `end` [s], the time both runs
    reached; `refined_complete` False when the refined run stopped early."""

    changes: tuple
    end: float
    refined_complete: bool = True

    def largest_change(self) -> ProbeChange | None:
        """The component with the largest relative change (None without probes)."""
        finite = [change for change in self.changes if np.isfinite(change.relative)]
        return max(finite, key=lambda change: change.relative, default=None)

    def describe(self) -> str:
        """A table, one line a probe component, largest relative change first (a non-finite
        change before all)."""
        if not self.changes:
            return "the scene has no probes to compare"
        span = f"to t = {self.end:.4g} s" + ("" if self.refined_complete else " (the refined run stopped there)")
        span += ", means over each output interval"
        width = max(len(change.label) for change in self.changes)
        lines = [f"largest change over the run {span}:",
                 f"  {'probe':<{width}}  {'change':>12}  {'of largest':>10}  {'at t [s]':>9}"]
        for change in sorted(self.changes, key=order):
            relative = f"{100.0 * change.relative:.3g} %" if np.isfinite(change.relative) else "-"
            if not np.isfinite(change.change):
                relative = "not finite"
            lines.append(f"  {change.label:<{width}}  {change.change:>12.4g}  {relative:>10}  {change.at:>9.4g}")
        return "\n".join(lines)


def order(change):
    """Sort key: a non-finite change first, then the largest relative change, then by name."""
    if not np.isfinite(change.change):
        return (0, 0.0, change.label)
    if not np.isfinite(change.relative):
        return (2, 0.0, change.label)
    return (1, -change.relative, change.label)


def interval_means(time, values, edges):
    """(K, k) time averages of `values` (T, k) over each interval edges[i] <= t <= edges[i + 1],
    by the trapezoidal rule on the run's own steps (exact for a value linear in time, so
    runs at different steps are compared without a bias of their own)."""
    means = np.zeros((len(edges) - 1, values.shape[1]))
    for index, (start, stop) in enumerate(zip(edges[:-1], edges[1:])):
        inside = (time >= start - 1e-9 * stop) & (time <= stop * (1.0 + 1e-9))
        t, v = time[inside], values[inside]
        span = t[-1] - t[0] if len(t) > 1 else 0.0
        area = np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], axis=0)
        means[index] = area / span if span > 0.0 else v.mean(axis=0)
    return means


def compare_results(result, refined) -> Comparison:
    """How far each probe of `result` (a Result) moves in `refined` (the Result of its scene at
    refined numerics, `refined_scene`): their means over each output interval, up to the time
    both reached (module docstring)."""
    from jaxmpm.scene import Scene

    scene = Scene.from_toml(result.scene_toml)
    end = float(min(result.time[-1], refined.time[-1]))
    interval = scene.output_interval
    edges = interval * np.arange(int(np.floor(end / interval * (1.0 + 1e-9))) + 1)
    if edges[-1] < end * (1.0 - 1e-9):
        edges = np.append(edges, end)             # the part of an interval the shorter run reached
    if len(edges) < 2:
        edges = np.array([0.0, end])
    middles = 0.5 * (edges[1:] + edges[:-1])
    changes = []
    for name, values in result.probes.items():
        run_means = interval_means(result.time, np.asarray(values, float).reshape(len(values), -1), edges)
        refined_values = np.asarray(refined.probes[name], float)
        refined_means = interval_means(refined.time, refined_values.reshape(len(refined_values), -1), edges)
        count = run_means.shape[1]
        names = [""] if count == 1 else scene.component_names(count)
        for component, axis in enumerate(names):
            ours, theirs = run_means[:, component], refined_means[:, component]
            difference = np.abs(ours - theirs)
            at = int(np.argmax(np.where(np.isfinite(difference), difference, np.inf)))
            largest = float(np.max(np.maximum(np.abs(ours), np.abs(theirs))))
            relative = float(difference[at] / largest) if largest > 0.0 and np.isfinite(largest) else float("nan")
            changes.append(ProbeChange(name, axis, float(difference[at]), largest, relative, float(middles[at])))
    return Comparison(tuple(changes), end, bool(refined.complete))
