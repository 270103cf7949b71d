"""How long a scene's forward run will take here, from a few timed steps (`jaxmpm check`).

`estimate_run_time` compiles the run's own program (a chunk of `Simulation.chunk` steps and
their probe rows, `runner.run_forward`'s compiled unit), runs it once, then times further
chunks from the scene's initial state for about TIMED_SECONDS, each with its rows appended to
a run file in a temporary folder, and one output's snapshot and resumable state written there.
The run time is the time per step times the scene's steps, plus an output's writing per
output: an estimate, good while the cost of a step stays what it was over the first steps (it
does for a fixed grid and a fixed number of points; contact that spreads and plasticity that
needs more iterations can make later steps dearer). The compile is not in it.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from jaxmpm.running.output import RunFile
from jaxmpm.running.runner import snapshot_fields
from jaxmpm.physics.state import counters_at_start
from jaxmpm.running.tracing import collector_paused

TIMED_SECONDS = 1.0      # wall time of the timed chunks (at least one chunk is timed)


@dataclasses.dataclass(frozen=True)
class RunTimeEstimate:
    """Seconds measured here, and what they were measured over."""

    compile_seconds: float       # the first call less one chunk: compiling (or loading from the cache)
    step_seconds: float          # wall time per step over the timed chunks, their probe rows written
    timed_steps: int
    snapshot_seconds: float      # one output's snapshot and resumable state written
    steps: int                   # the scene's steps and outputs
    outputs: int

    @property
    def seconds(self) -> float:
        """The run's estimated time, without the compile: every step and every output."""
        return self.steps * self.step_seconds + self.outputs * self.snapshot_seconds

    def describe(self) -> str:
        """One line: the estimate and its basis."""
        steps = f"{self.timed_steps} step{'s' if self.timed_steps > 1 else ''}"
        return (f"run time: about {readable_seconds(self.seconds)} here, estimated from {steps} "
                f"timed from the start ({readable_seconds(self.step_seconds)} a step, {self.steps} steps, "
                f"{self.outputs} snapshots); compiling first took {readable_seconds(self.compile_seconds)} "
                "(less when the compilation cache holds the program)")


def readable_seconds(seconds: float) -> str:
    """0.42 ms, 12 ms, 3.4 s, 12 min, 2.5 h."""
    if seconds < 1.0:
        return f"{seconds * 1e3:.2g} ms" if seconds < 0.01 else f"{seconds * 1e3:.0f} ms"
    if seconds < 60.0:
        return f"{seconds:.2g} s" if seconds < 10.0 else f"{seconds:.0f} s"
    if seconds < 3600.0:
        return f"{seconds / 60:.2g} min"
    return f"{seconds / 3600:.2g} h"


def estimate_run_time(sim, params=None, seconds: float = TIMED_SECONDS) -> RunTimeEstimate:
    """The run time of `sim` (a Simulation) with `params` (default its own), from chunks of
    its run timed here with their file writes (see the module docstring). At most the
    scene's own steps are run, and at least one chunk after the first."""
    params = sim.cast(sim.params if params is None else params)
    state = sim.initial_state(params).replace(**counters_at_start())
    initial_x = state.particles.x
    fields = sim.scene.snapshot_fields
    first = {name: np.asarray(value) for name, value in sim.observe_start(state).items()}
    with tempfile.TemporaryDirectory() as folder:
        writer = RunFile.create(Path(folder) / "timed.h5", sim, params, state, first,
                                snapshot_fields(state.particles, initial_x, fields))

        def chunk(state):
            with collector_paused():
                state, values = sim._advance(params, state, initial_x)
            writer.append_rows(values, sim.chunk)           # as the run does: the rows to the file
            return state

        start = time.perf_counter()
        state = chunk(state)
        compiled = time.perf_counter() - start
        most = max(1, sim.steps // sim.chunk - 1)
        timed, start = 0, time.perf_counter()
        while timed == 0 or (timed < most and time.perf_counter() - start < seconds):
            state = chunk(state)
            timed += 1
        per_chunk = (time.perf_counter() - start) / timed
        snapshot_fields(state.particles, initial_x, fields)        # its first call compiles too
        start = time.perf_counter()
        writer.append_snapshot(snapshot_fields(state.particles, initial_x, fields), state, 1)
        snapshot = time.perf_counter() - start
        writer.finish(False, "timed steps")
    return RunTimeEstimate(compile_seconds=max(compiled - per_chunk, 0.0), step_seconds=per_chunk / sim.chunk,
                           timed_steps=timed * sim.chunk, snapshot_seconds=snapshot, steps=sim.steps,
                           outputs=sim.outputs)
