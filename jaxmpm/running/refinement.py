"""A run against the same scene at refined numerics: how much its probes owe to the discretisation.

An explicit MPM result depends on the time step, the cell and the transfer's relaxation
(docs/convergence.md). `refined_scene` makes the scene one step finer in one of them;
`compare_results` reads how far each probe moves, at the scene's output times:

    change = max_t |a(t) - b(t)|,   relative = change / max_t |a(t)|

(a the run, b the refined run, both interpolated linearly to the output times they share),
the largest difference over the run against the component's largest value, so that a
quantity passing through zero does not read as a large relative change. Halving dt from the
scene's own should change every probe by well under the accuracy a user needs; if it does not,
the run is not converged in dt and its numbers carry that error.

"relaxation" is a sensitivity, not a refinement: the relaxation kappa doubled. kappa moves the
results without a limit as it grows (docs/convergence.md, "The relaxation's own effect").
"""

from __future__ import annotations

import dataclasses

import numpy as np

REFINEMENTS = ("dt", "cell", "relaxation")


def refined_scene(scene, refinement: str):
    """The scene with its time step halved ("dt": scene.dt, or scene.cfl when dt is not
    given), its cell halved ("cell": the time step follows from the cfl, and a given
    scene.dt is halved with it) or its relaxation doubled ("relaxation")."""
    if refinement == "dt":
        if scene.dt is not None:
            return scene.with_value("scene.dt", scene.dt / 2.0)
        return scene.with_value("scene.cfl", scene.cfl / 2.0)
    if refinement == "cell":
        scene = scene.with_value("grid.cell", scene.grid.cell / 2.0)
        return scene if scene.dt is None else scene.with_value("scene.dt", scene.dt / 2.0)
    if refinement == "relaxation":
        return scene.with_value("numerics.relaxation", 2.0 * scene.numerics.relaxation)
    raise ValueError(f"refinement {refinement!r} is not one of {REFINEMENTS}")


def refinement_refused(scene, refinement: str) -> str | None:
    """Why `refinement` cannot be made on `scene` (a sentence's end), or None."""
    if refinement == "relaxation" and (scene.numerics.transfer != "apic" or scene.numerics.relaxation <= 0.0):
        return (f"the scene {scene.name!r} has no relaxation to double (numerics.transfer = "
                f"{scene.numerics.transfer!r}, numerics.relaxation = {scene.numerics.relaxation:g}; it needs "
                "'apic' and a relaxation > 0)")
    return None


def describe_refinement(scene, refinement: str) -> str:
    """'scene.cfl 0.4 -> 0.2' and the like: what the refinement changes in `scene`."""
    refined = refined_scene(scene, refinement)
    if refinement == "dt":
        key, before, after = ("scene.dt", scene.dt, refined.dt) if scene.dt is not None else (
            "scene.cfl", scene.cfl, refined.cfl)
    elif refinement == "cell":
        key, before, after = "grid.cell", scene.grid.cell, refined.grid.cell
    else:
        key, before, after = "numerics.relaxation", scene.numerics.relaxation, refined.numerics.relaxation
    return f"{key} {before:g} -> {after:g}"


@dataclasses.dataclass(frozen=True)
class ProbeChange:
    """One probe component's largest change over the shared output times: `axis` its name
    ("x", "y"; "r", "z" in axisymmetry; "" for a probe of one value), `change` (the
    probe's unit), `largest` max |value| of the run, `relative` change / largest (nan when
    the value is 0 throughout), `at` the time of the largest change [s]."""

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
    """`changes` (one ProbeChange per probe component) over `times` (the output times both
    runs reached); `refined_complete` False when the refined run stopped early."""

    changes: tuple
    times: np.ndarray
    refined_complete: bool = True

    def largest(self) -> ProbeChange | None:
        """The component with the largest relative change (None without probes)."""
        finite = [change for change in self.changes if np.isfinite(change.relative)]
        return max(finite, key=lambda change: change.relative, default=None)

    def describe(self) -> str:
        """A table, one line a probe component, largest relative change first."""
        if not self.changes:
            return "the scene has no probes to compare"
        span = f"{len(self.times)} output times to t = {self.times[-1]:.4g} s"
        if not self.refined_complete:
            span += " (the refined run stopped there)"
        width = max(len(change.label) for change in self.changes)
        lines = [f"largest change over {span}:", f"  {'probe':<{width}}  {'change':>12}  {'of largest':>10}  {'at t [s]':>9}"]
        order = sorted(self.changes, key=lambda c: -c.relative if np.isfinite(c.relative) else np.inf)
        for change in order:
            relative = f"{100.0 * change.relative:.3g} %" if np.isfinite(change.relative) else "-"
            lines.append(f"  {change.label:<{width}}  {change.change:>12.4g}  {relative:>10}  {change.at:>9.4g}")
        return "\n".join(lines)


def output_times(scene, end):
    """The scene's output times k * output_every from 0 up to `end` [s]."""
    count = int(np.floor(end / scene.output_every * (1.0 + 1e-9))) + 1
    return scene.output_every * np.arange(count)


def compare_results(result, refined) -> Comparison:
    """How far each probe of `result` (a Result) moves in `refined` (the Result of its scene at
    refined numerics, `refined_scene`), at the output times both reached."""
    from jaxmpm.scene import Scene

    scene = Scene.from_toml(result.scene_toml)
    axes = ("r", "z") if scene.geometry == "axisymmetric" else ("x", "y")
    times = output_times(scene, min(result.time[-1], refined.time[-1]))
    changes = []
    for name, values in result.probes.items():
        ours, theirs = np.asarray(values, float), np.asarray(refined.probes[name], float)
        ours, theirs = ours.reshape(len(ours), -1), theirs.reshape(len(theirs), -1)
        names = axes if ours.shape[1] == 2 else [""] if ours.shape[1] == 1 else [str(i) for i in range(ours.shape[1])]
        for component, axis in enumerate(names):
            a = np.interp(times, result.time, ours[:, component])
            b = np.interp(times, refined.time, theirs[:, component])
            difference = np.abs(a - b)
            at = int(np.argmax(difference))
            largest = float(np.max(np.abs(a)))
            relative = float(difference[at] / largest) if largest > 0.0 else float("nan")
            changes.append(ProbeChange(name, axis, float(difference[at]), largest, relative, float(times[at])))
    return Comparison(tuple(changes), times, bool(refined.complete))
