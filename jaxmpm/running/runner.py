"""Host work around a `Simulation`: the forward run that users watch and files keep.

`run_forward` advances the compiled chunks of steps (`chunk_length`: well under a second each;
whole chunks and a remainder make up an output interval), shows the progress, streams the
probe rows and snapshots to the run's file (`jaxmpm.running.output.RunFile`), resumes an interrupted run from it, acts on Ctrl-C and
SIGTERM between chunks (`output.deferred_interrupts`), and says in one sentence why a run
stopped early (`describe_failure`). The differentiable description of the scene, its step and
its probes, is `jaxmpm.running.simulation.Simulation`, which this module only drives.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxmpm.physics import state as state_bits
from jaxmpm.errors import SceneError, SimulationError
from jaxmpm.running.output import RunFile, deferred_interrupts, uninterrupted
from jaxmpm.running.progress import progress_bar, restart_clock
from jaxmpm.running.results import FileSnapshots, Result
from jaxmpm.physics.state import counters_at_start
from jaxmpm.running.tracing import collector_paused

CHUNK_POINT_STEPS = 1e6   # point-steps per compiled call of a run: 0.1-0.5 s on a 2-core CPU (1-8 M/s)


def chunk_length(steps_per_output: int, points: int) -> int:
    """Steps per compiled call of `Simulation.run`: at most the output interval and at most
    CHUNK_POINT_STEPS point-steps (at least 1 step), so that an interrupt is acted on, the
    progress bar moves and the file grows within about a second at any scene size, while
    small scenes still run a whole interval per call. The largest divisor of the interval
    within that bound if it is at least half the bound; else the bound, and each interval
    ends with a shorter call of the remainder (`interval_calls`), so that the cost of a call
    (about 1 ms: dispatch, the file's append) stays small beside its steps."""
    most = min(steps_per_output, max(1, int(CHUNK_POINT_STEPS // max(points, 1))))
    divisor = max(d for d in range(1, most + 1) if steps_per_output % d == 0)
    return divisor if 2 * divisor >= most else most


def interval_calls(sim) -> list:
    """[(compiled program, its steps)] of one output interval of `sim`: its whole chunks,
    then the remainder if `Simulation.chunk` does not divide the interval."""
    calls = [(sim._advance, sim.chunk)] * (sim.steps_per_output // sim.chunk)
    rest = sim.steps_per_output % sim.chunk
    return calls + [(sim._advance_rest, rest)] if rest else calls


def snapshot_fields(particles, initial_x, fields):
    """Host copies of the requested per-point fields of one state: {field: (N, ...)}."""
    history = particles.history
    values = {
        "x": lambda: particles.x,
        "v": lambda: particles.v,
        "displacement": lambda: particles.x - initial_x,
        "stress": lambda: particles.stress,
        "plastic_strain": lambda: jnp.concatenate([h["plastic_strain"] for h in history]),
        "volume": lambda: particles.volume,
        "mass": lambda: particles.mass,
    }
    return {field: np.asarray(values[field]()) for field in fields}


def run_forward(sim, params=None, initial=None, progress=True, save_to=None, resume=False) -> Result:
    """A forward run of `sim` (Simulation) with a progress bar: its Result; with `save_to`,
    written to that file as it goes, and with `resume`, continued from it. SimulationError
    (holding the Result of the part done) if a point leaves the grid or goes non-finite;
    KeyboardInterrupt after the file is closed on Ctrl-C or SIGTERM."""
    params = sim.cast(sim.params if params is None else params)
    sim.check_time_step(params, initial)
    state = sim.initial_state(params) if initial is None else sim.place(initial)
    state = state.replace(**counters_at_start())
    fields = sim.scene.snapshot_fields
    if resume:
        if save_to is None:
            raise SceneError("resume=True needs save_to, the file of the run to continue.")
        writer, state, done, stored, initial_x = RunFile.reopen(save_to, sim, params, state)
        state = sim.place(state)
        probes = {name: [values] for name, values in stored.items()}
    else:
        done, initial_x = 0, state.particles.x
        probes = {name: [np.asarray(value)[None]] for name, value in sim.observe_start(state).items()}
        first = snapshot_fields(state.particles, initial_x, fields)
        writer = None if save_to is None else RunFile.create(
            save_to, sim, params, state, {name: rows[0][0] for name, rows in probes.items()}, first)
    snapshots = [] if writer is not None else [first]       # a file keeps them, memory does not

    steps_done = [done * sim.steps_per_output]        # steps whose probe rows are kept

    def finish(complete, message):
        steps = steps_done[0]
        if writer is None:
            return Result.from_run(sim, probes, snapshots, steps, complete, message)
        writer.finish(complete, message)
        return Result(sim.scene.to_toml(), sim.time[: steps + 1],
                      {name: np.concatenate(rows) for name, rows in probes.items()},
                      FileSnapshots(writer.path), complete, message)

    bar = progress_bar(progress, total=sim.steps, initial=done * sim.steps_per_output, unit="step",
                       desc=sim.scene.name, postfix="compiling")
    compiled = False            # the first call compiles: the bar's clock starts after it
    calls = interval_calls(sim)
    with deferred_interrupts() as stop:
        try:
            for output in range(done, sim.outputs):
                for advance, length in calls:
                    with collector_paused():
                        state, values = advance(params, state, initial_x)
                    error_step = int(state.error_step)
                    rows = length if error_step < 0 else error_step - steps_done[0] - 1
                    with uninterrupted(stop):
                        for name, value in values.items():
                            probes[name].append(np.asarray(value)[:rows])
                        if writer is not None:
                            writer.append_rows(values, rows)
                        steps_done[0] += rows
                    if compiled:
                        bar.update(rows)
                    else:
                        restart_clock(bar, steps_done[0])
                        compiled = True
                    if error_step >= 0:
                        message = describe_failure(sim, state)
                        raise SimulationError(message, finish(False, message))
                    if stop["requested"] and steps_done[0] < sim.steps:
                        raise KeyboardInterrupt
                snapshot = snapshot_fields(state.particles, initial_x, fields)
                with uninterrupted(stop):
                    if writer is None:
                        snapshots.append(snapshot)
                    else:
                        writer.append_snapshot(snapshot, state, output + 1)
        except KeyboardInterrupt:
            finish(False, f"interrupted at t = {steps_done[0] * sim.dt:.6g} s")
            raise
        finally:
            bar.close()
    return finish(True, "")


def describe_failure(sim, state) -> str:
    """One sentence: which step, body and point went wrong, and how."""
    flags = np.asarray(state.particles.flags)
    index = int(state.error_point)
    block = next(b for b in sim.structure.bodies if b.start <= index < b.stop)
    what = "left the grid" if flags[index] & state_bits.LEFT_GRID else "became non-finite"
    step = int(state.error_step)
    return (
        f"the run stopped at step {step} (t = {step * sim.dt:.6g} s): point {index - block.start} "
        f"of body {block.name!r} {what}; the output holds the run up to the step before"
        f"{instability_hint(sim, state)}."
    )


def instability_hint(sim, state) -> str:
    """A clause for `describe_failure` when the failure looks like a numerical instability:
    the first failure is a non-finite point, or by the state's step a point that never failed
    moves more than a cell per step (|v| dt > h), which physical motion within the CFL limit
    never does. Points that have left the grid are not judged: the grid no longer carries
    them, and their values after leaving mean nothing. When the others move within the limit
    (a body that simply flows off a free edge, say), the clause says so with their largest
    |v| dt / h; when no point is left to judge, it gives both readings."""
    flags = np.asarray(state.particles.flags)
    scene = sim.scene
    key, value = ("scene.dt", scene.dt) if scene.dt is not None else ("scene.cfl", scene.cfl)
    first_left = bool(flags[int(state.error_point)] & state_bits.LEFT_GRID)
    judged = flags == 0
    if first_left and not judged.any():
        return (f" (by the end of the output interval every point had failed: if the body should stay on the "
                f"grid, the step may be unstable, lower {key}; if it leaves through a free edge, enlarge grid.size)")
    speeds = np.hypot(*np.asarray(state.particles.v, np.float64)[judged].reshape(-1, 2).T)
    fine = np.all(np.isfinite(speeds)) and np.all(np.isfinite(np.asarray(state.particles.x)[judged]))
    per_step = np.max(speeds, initial=0.0) * sim.dt / scene.grid.cell     # the motion's Courant number
    if first_left and fine and per_step <= 1.0:
        return (f" (the points still on the grid move at most {per_step:.2g} of a cell per step: the body "
                f"flowed off the grid; if it should stay on it, enlarge grid.size or hold that edge)")
    numerics = scene.numerics
    seen = (f"points moved up to {per_step:.3g} cells per step" if fine
            else "points went non-finite")
    return (
        f" (by then {seen}: the step is unstable "
        f"with {key} = {value:g}, numerics.shape = {numerics.shape!r}, transfer = {scene.transfer!r}, "
        f"update = {numerics.update!r}; lower {key} or change the numerics, see docs/stability.md)"
    )
