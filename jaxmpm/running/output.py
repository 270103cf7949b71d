"""A forward run's HDF5 file, written output by output as the run goes, and resumed from.

The layout is `Result.save`'s (jaxmpm/running/results.py) with resizable datasets: after every chunk
of steps (`Simulation.chunk`, well under a second of work) its probe rows are appended, after
every output interval the new snapshot, and the file is flushed each time, so it is valid and
readable while the run goes (`complete = false` until the end) and memory does not grow with
the run. Beside them `/resume` holds what continuing needs: the full state
(points, material history, rigid motions, counters) of the last output written, in two slots
written in turn (`resume_slot` names the valid one, so a write cut short never spoils it),
the parameters and the initial positions. `steps_done` counts the steps whose probe rows are
in the file; a failed or interrupted run may hold rows past the resumable state (up to the
step before the failure, or the last chunk done), which a resumed run drops before
continuing (and computes again, to the same numbers).

The file is first written under a temporary name and renamed once it holds the first
snapshot and state: an existing file of the same name is replaced only by a valid one.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import weakref
from pathlib import Path

import h5py
import jax
import numpy as np

from jaxmpm.errors import SceneError

EXTENTS = {"plane_strain": "per metre of thickness", "axisymmetric": "per radian"}
SLOTS = ("a", "b")
WRITING = threading.RLock()     # held while a run file is written to (`uninterrupted`, `RunFile.finish`)
_open_runs = weakref.WeakSet()  # the RunFiles being written (`abandon_open_runs`)


def leaves_with_names(tree):
    """[(name, leaf)] of a pytree, names from its key paths (e.g. ".particles.x")."""
    flat, _ = jax.tree_util.tree_flatten_with_path(tree)
    return [(jax.tree_util.keystr(path), leaf) for path, leaf in flat]


def _append(dataset, rows):
    """Grow `dataset` along its first axis by `rows`."""
    start = dataset.shape[0]
    dataset.resize(start + len(rows), axis=0)
    dataset[start:] = rows


ROWS_PER_CHUNK = 1024       # rows of a probe history stored together (a snapshot is its own chunk)


def _growing(group, name, first_rows, compress=False):
    """A dataset holding `first_rows`, resizable along its first axis, in chunks of one
    compressed snapshot or of ROWS_PER_CHUNK rows of a history."""
    first_rows = np.asarray(first_rows)
    options = dict(compression="gzip", compression_opts=4) if compress else {}
    return group.create_dataset(name, data=first_rows, maxshape=(None, *first_rows.shape[1:]),
                                chunks=(1 if compress else ROWS_PER_CHUNK, *first_rows.shape[1:]), **options)


def resumable_steps(path) -> int:
    """Steps done by the interrupted or failed run held in `path` that `--resume` could
    continue (0: no file, a complete run, or not a run file)."""
    path = Path(path)
    if not path.is_file() or not h5py.is_hdf5(path):
        return 0
    try:
        with h5py.File(path, "r") as file:
            attrs = file.attrs
            if "resume" not in file or bool(attrs.get("complete", True)):
                return 0
            return int(attrs.get("steps_done", 0))
    except (OSError, KeyError):
        return 0


class RunFile:
    """The open HDF5 file of a run in progress (see the module docstring)."""

    def __init__(self, path: Path, file: h5py.File, sim):
        self.path, self.file, self.sim = path, file, sim
        _open_runs.add(self)

    # ------------------------------------------------------------------ starting

    @classmethod
    def create(cls, path, sim, params, state, first_probes: dict, first_snapshot: dict) -> RunFile:
        """A new file holding t = 0: the first probe values and snapshot, and `state`."""
        from jaxmpm import __version__

        path = Path(path)
        temporary = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
        file = h5py.File(temporary, "w")
        try:
            geometry = sim.scene.geometry
            file.attrs.update({
                "jaxmpm_version": __version__, "scene": sim.scene.to_toml(), "complete": False,
                "message": "run in progress", "geometry": geometry, "extent": EXTENTS[geometry], "steps_done": 0,
            })
            _growing(file, "time", sim.time[:1])
            probes = file.create_group("probes")
            for name, value in first_probes.items():
                _growing(probes, name, np.asarray(value)[None])
            snapshots = file.create_group("snapshots")
            _growing(snapshots, "time", np.zeros(1))
            for body, (start, stop) in zip(sim.scene.bodies, sim.body_slices):
                group = snapshots.create_group(body.name)
                for field, values in first_snapshot.items():
                    _growing(group, field, values[start:stop][None], compress=True)
            resume = file.create_group("resume")
            resume.create_dataset("initial_x", data=np.asarray(state.particles.x))
            for group_name, tree in (("params", params), *((slot, state) for slot in SLOTS)):
                group = resume.create_group(group_name)
                for index, (name, leaf) in enumerate(leaves_with_names(tree)):
                    group.create_dataset(str(index), data=np.asarray(leaf)).attrs["path"] = name
            file.attrs.update({"resume_slot": SLOTS[0], "resume_output": 0})
            file.flush()
            os.replace(temporary, path)
        except BaseException:
            file.close()
            temporary.unlink(missing_ok=True)
            raise
        return cls(path, file, sim)

    @classmethod
    def reopen(cls, path, sim, params, template):
        """(file, state, outputs done, probe rows so far) of an interrupted run of the same
        scene, version and parameters; `template` is a state of the right structure."""
        from jaxmpm import __version__

        path = Path(path)
        if not path.is_file():
            raise SceneError(f"--resume: {str(path)!r} does not exist: there is no run to continue.")
        if not h5py.is_hdf5(path):
            raise SceneError(f"--resume: {str(path)!r} is not an HDF5 file.")
        file = h5py.File(path, "r+")
        try:
            attrs = file.attrs
            if "resume" not in file:
                raise SceneError(f"--resume: {str(path)!r} holds no resumable state (not written by a streaming run).")
            if str(attrs["jaxmpm_version"]) != __version__:
                raise SceneError(f"--resume: {str(path)!r} was written by jaxmpm {attrs['jaxmpm_version']}, "
                                 f"this is {__version__}: run it again from the start.")
            if str(attrs["scene"]) != sim.scene.to_toml():
                raise SceneError(f"--resume: the scene differs from the one {str(path)!r} was run with: "
                                 "resume with the same scene file and --set values, or run it from the start.")
            stored = [file["resume/params"][str(i)][()] for i in range(len(file["resume/params"]))]
            given = [np.asarray(leaf) for _, leaf in leaves_with_names(params)]
            if len(stored) != len(given) or not all(np.array_equal(a, b) for a, b in zip(stored, given)):
                raise SceneError(f"--resume: the parameters differ from those {str(path)!r} was run with.")
            slot = file["resume"][str(attrs["resume_slot"])]
            leaves = []
            for index, (name, leaf) in enumerate(leaves_with_names(template)):
                stored_leaf = slot[str(index)] if str(index) in slot else None
                if stored_leaf is None or stored_leaf.attrs["path"] != name or stored_leaf.shape != np.shape(leaf):
                    raise SceneError(f"--resume: {str(path)!r} holds a state laid out unlike this jaxmpm's "
                                     f"(at {name}, shape {np.shape(leaf)}): it was written by another build; "
                                     "run it again from the start.")
                leaves.append(jax.numpy.asarray(stored_leaf[()], dtype=leaf.dtype))
            state = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), leaves)
            outputs = int(attrs["resume_output"])
            run = cls(path, file, sim)
            run.truncate(outputs)
            probes = {name: data[()] for name, data in file["probes"].items()}
            initial_x = jax.numpy.asarray(file["resume/initial_x"][()], dtype=template.particles.x.dtype)
        except BaseException:
            file.close()
            raise
        return run, state, outputs, probes, initial_x

    def truncate(self, outputs: int):
        """Drop rows past `outputs` output intervals (a failed chunk's rows)."""
        rows = outputs * self.sim.steps_per_output + 1
        self.file["time"].resize(rows, axis=0)
        for data in self.file["probes"].values():
            data.resize(rows, axis=0)
        snapshots = self.file["snapshots"]
        snapshots["time"].resize(outputs + 1, axis=0)
        for body in self.sim.scene.bodies:
            for data in snapshots[body.name].values():
                data.resize(outputs + 1, axis=0)
        self.file.attrs["steps_done"] = rows - 1
        self.file.flush()

    # ------------------------------------------------------------------ during the run

    def append_rows(self, values: dict, rows: int | None = None):
        """Probe rows of the steps just run (the first `rows` of them, default all of an
        output interval's)."""
        done = int(self.file.attrs["steps_done"])
        rows = self.sim.steps_per_output if rows is None else rows
        for name, value in values.items():
            _append(self.file["probes"][name], np.asarray(value)[:rows])
        _append(self.file["time"], self.sim.time[done + 1 : done + 1 + rows])
        self.file.attrs["steps_done"] = done + rows
        self.file.flush()                   # on disk: what an interrupt or a reader finds

    def append_output(self, values: dict, snapshot: dict, state, outputs: int):
        """One output interval: its probe rows, its snapshot, and the state to resume from."""
        self.append_rows(values)
        self.append_snapshot(snapshot, state, outputs)

    def append_snapshot(self, snapshot: dict, state, outputs: int):
        """The snapshot at the end of output interval `outputs` (its rows already appended),
        and the state to resume from."""
        snapshots = self.file["snapshots"]
        _append(snapshots["time"], [outputs * self.sim.steps_per_output * self.sim.dt])
        for body, (start, stop) in zip(self.sim.scene.bodies, self.sim.body_slices):
            for field, data in snapshot.items():
                _append(snapshots[body.name][field], data[start:stop][None])
        slot = SLOTS[1 - SLOTS.index(str(self.file.attrs["resume_slot"]))]
        group = self.file["resume"][slot]
        for index, (_, leaf) in enumerate(leaves_with_names(state)):
            group[str(index)][...] = np.asarray(leaf)
        self.file.flush()                   # the rows and the new slot are on disk before
        self.file.attrs.update({"resume_slot": slot, "resume_output": outputs})
        self.file.flush()                   # the file says to resume from them

    def finish(self, complete: bool, message: str):
        with WRITING:
            _open_runs.discard(self)
            self.file.attrs.update({"complete": bool(complete), "message": message})
            self.file.close()


def abandon_open_runs():
    """Mark every run file still being written as interrupted at its last step written, and
    close it: for a program that ends at once, from any thread (the `jaxmpm` command at a
    second signal). Waits for a write in progress (WRITING), so every file stays valid and
    resumable."""
    with WRITING:
        for run in [run for run in _open_runs if run.file.id.valid]:
            done = int(run.file.attrs["steps_done"])
            run.finish(False, f"interrupted at t = {done * run.sim.dt:.6g} s")


@contextlib.contextmanager
def deferred_interrupts():
    """Ctrl-C (SIGINT) and SIGTERM during a run set `stop["requested"]`, which the run checks
    after each compiled chunk of steps (`Simulation.chunk`, well under a second); a second
    signal interrupts at once, except while the file is being appended to (`uninterrupted`),
    which it waits for, so a file is never left half-written. Outside the main thread signals
    cannot be caught: no change there."""
    stop = {"requested": False, "writing": False, "pending": False}
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if not stop["requested"]:
            stop["requested"] = True
        elif stop["writing"]:
            stop["pending"] = True
        else:
            raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def uninterrupted(stop):
    """A block (appending to the output file) that a second signal does not cut short: it
    interrupts as soon as the block is done (`deferred_interrupts`)."""
    stop["writing"] = True
    try:
        with WRITING:
            yield
    finally:
        stop["writing"] = False
    if stop["pending"]:
        raise KeyboardInterrupt
