"""The `jaxmpm` command.

    jaxmpm run SCENE.toml [-o OUT.h5] [--set sand.friction_angle=32 ...] [--resume] [--quiet]
               [--refine dt | cell | relaxation | stress ...]
    jaxmpm check SCENE.toml [--set ...] [--quick]
    jaxmpm calibrate CONFIG.toml [-o FIT.h5] [--resume] [--quiet]   (added by inverse.command)
    jaxmpm design DESIGN.toml [-o OUT.h5 | .csv | .png]             (added by inverse.design_command)
    jaxmpm plot OUT.h5 [-o OUT.png | .gif | .mp4] [--field q] [--snapshot -1] [--probes] [--mirror]
    jaxmpm plot FIT.h5 [-o FIT.png]                                  (drawn by inverse.fit_plot)
    jaxmpm export OUT.h5 [-o OUT.pvd] [--revolve N]

Exit status: 0 done; 1 the run stopped early (the output file keeps what was computed, marked
complete = false); 2 user error (one line naming the key and value, never a traceback);
130 interrupted (the output file keeps what was computed).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import math
import os
import signal
import sys
import threading
import tomllib
from pathlib import Path

from jaxmpm.errors import SceneError

USER_ERROR = 2


def parse_assignment(text):
    """'key=value' -> (key, value), the value read as a TOML value (a bare word is a string)."""
    key, separator, raw = text.partition("=")
    if not separator or not key.strip():
        raise SceneError(f"--set {text!r} must look like key=value (e.g. sand.friction_angle=32).")
    try:
        value = tomllib.loads(f"value = {raw.strip()}")["value"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return key.strip(), value


def installed_version() -> str:
    """The installed package's version (pyproject.toml), or "unknown" outside an install."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("jaxmpm")
    except PackageNotFoundError:
        return "unknown"


def build_parser():
    from jaxmpm.running.refinement import REFINEMENTS   # here, not at import: `import jaxmpm.cli` stays quick

    parser = argparse.ArgumentParser(prog="jaxmpm", description="Differentiable MPM for soil mechanics.")
    parser.add_argument("--version", action="version", version=f"jaxmpm {installed_version()}")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="run a scene and write its HDF5 output")
    run.add_argument("scene", help="scene file (TOML)")
    run.add_argument("-o", "--output", help="output HDF5 file (default: SCENE name with .h5)")
    run.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scene value, e.g. sand.friction_angle=32 or grid.cell=0.01")
    run.add_argument("--resume", action="store_true",
                     help="continue the interrupted run in OUTPUT (same scene and --set values)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--refine", action="append", default=[], choices=REFINEMENTS,
                     help="after the run, run the scene again with dt halved (or the cell halved, the "
                          "relaxation doubled, the stress substeps doubled), write it beside OUTPUT as "
                          "OUTPUT-dt.h5 (-cell, -relaxation, -stress) "
                          "and print how far each probe moved; repeatable")
    check = commands.add_parser("check", help="check a scene (points, steps, memory) and estimate its run time "
                                              "from a few timed steps")
    check.add_argument("scene", help="scene file (TOML)")
    check.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                       help="override a scene value, as for run")
    check.add_argument("--quick", action="store_true", help="no timed steps and no run-time estimate: nothing compiled")
    plot = commands.add_parser("plot", help="draw a run (points coloured by a field, or probe histories) "
                                            "or a calibration result")
    plot.add_argument("result", help="output HDF5 file of `jaxmpm run` (or of `jaxmpm calibrate`)")
    plot.add_argument("-o", "--output", help="PNG, GIF or MP4 file (default: RESULT name with .png)")
    plot.add_argument("--field", help="colour by this field (default q; e.g. p, plastic_strain, displacement, speed)")
    plot.add_argument("--snapshot", type=int, help="snapshot index for a PNG (default -1, the last)")
    plot.add_argument("--probes", action="store_true", help="plot the probe histories instead")
    plot.add_argument("--mirror", action="store_true",
                      help="axisymmetric runs: also draw the mirror image about the axis (the whole section)")
    export = commands.add_parser("export", help="write ParaView files (PVD + VTU) of a run's snapshots")
    export.add_argument("result", help="output HDF5 file of `jaxmpm run`")
    export.add_argument("-o", "--output", help="PVD file (default: RESULT name with .pvd)")
    export.add_argument("--revolve", type=int, metavar="N",
                        help="axisymmetric runs: write each point at N angles about the axis (a 3-D point cloud)")
    for name, command in plugged_commands().items():
        command.add_arguments(commands.add_parser(name, help=command.help))
    return parser


COMMAND_GROUP = "jaxmpm.commands"


def plugged_commands() -> dict:
    """{name: command} of the packages that add commands to `jaxmpm` (the entry points of group
    COMMAND_GROUP, e.g. `calibrate` from `inverse.command`): each command has `help`,
    `add_arguments(parser)` and `run(arguments) -> exit status`. jaxmpm imports none of them
    by name."""
    from importlib.metadata import entry_points

    return {point.name: point.load() for point in sorted(entry_points(group=COMMAND_GROUP), key=lambda p: p.name)}


FILE_KIND_GROUP = "jaxmpm.file_kinds"


def plugged_file_kind(path):
    """The kind of HDF5 file another package writes and draws (the entry points of group
    FILE_KIND_GROUP, e.g. the calibration result of `inverse.fit_plot`) that `path` is, or None.
    A kind has `description`, `how_to_open`, `claims(open h5py file) -> bool` and
    `plot(path, output)`."""
    import h5py
    from importlib.metadata import entry_points

    try:
        with h5py.File(path, "r") as file:
            for point in sorted(entry_points(group=FILE_KIND_GROUP), key=lambda p: p.name):
                kind = point.load()
                if kind.claims(file):
                    return kind
    except OSError:           # not HDF5, or damaged: read_result says which
        return None
    return None


def run_command(arguments):
    import jax

    jax.config.update("jax_enable_x64", True)   # a program chooses its precision; scenes pick dtype
    import jaxmpm

    jaxmpm.use_compilation_cache()

    output = output_path(arguments.output, arguments.scene)
    sim = checked_simulation(arguments)
    refined = refined_runs(sim, output, arguments.refine)      # every check before anything compiles
    if not arguments.resume:
        for path in [output, *(path for _, _, path in refined)]:
            refuse_unfinished(path)
    for refinement, refined_sim, path in refined if arguments.resume else ():
        refuse_other_scene(refinement, refined_sim, path)
    print(describe(sim), file=sys.stderr)
    print_notes(sim.scene)
    status, result = run_to_file(sim, output, arguments.quiet, arguments.resume)
    if status != 0:
        if refined:
            print("jaxmpm: the refined runs (--refine) were not started: the run itself did not finish", file=sys.stderr)
        return status
    return run_refinements(sim.scene, result, refined, arguments.quiet, arguments.resume)


def run_refinements(scene, result, refined, quiet, resume):
    """Each refined run of `refined_runs` after the run (`result`), written to its file (and
    continued with `resume` when its file holds an unfinished run), then compared with it:
    the exit status, 1 if a refined run stopped early (compared up to where it stopped)."""
    from jaxmpm.running.output import resumable_steps
    from jaxmpm.running.refinement import compare_results, describe_refinement

    status = 0
    for refinement, refined_sim, path in refined:
        change = describe_refinement(scene, refinement)
        print(f"refined run, {change}: {describe(refined_sim)}", file=sys.stderr)
        refined_status, refined_result = run_to_file(refined_sim, path, quiet, resume and resumable_steps(path) > 0)
        if refined_result is None:
            return refined_status
        print(f"refinement {refinement} ({change}), {compare_results(result, refined_result).describe()}")
        status = max(status, refined_status)
    return status


def refined_runs(sim, output, refinements):
    """(refinement, Simulation, output file) for each `--refine` (each once, in the order
    given), every one checked now: SceneError if a refinement cannot be made on the scene."""
    import jaxmpm
    from jaxmpm.running.refinement import refinement_refused

    runs = []
    for refinement in dict.fromkeys(refinements):
        reason = refinement_refused(sim.scene, refinement)
        if reason:
            raise SceneError(f"--refine {refinement}: {reason}.")
        path = output.with_name(f"{output.stem}-{refinement}{output.suffix}")
        try:
            refined = jaxmpm.Simulation(jaxmpm.refined_scene(sim.scene, refinement))
        except SceneError as error:
            raise SceneError(f"--refine {refinement}: {error}") from None
        runs.append((refinement, refined, path))
    return runs


def refuse_unfinished(path):
    """SceneError if `path` holds an unfinished run that --resume could continue."""
    from jaxmpm.running.output import resumable_steps

    done = resumable_steps(path)
    if done:
        raise SceneError(f"{str(path)!r} holds {done} computed steps of an unfinished run: continue it with "
                         "--resume, or give another -o (or remove the file) to start again.")


def refuse_other_scene(refinement, sim, path):
    """SceneError, before anything runs, if `--resume` would continue a refined run in `path`
    that was run with another scene (another --set, or an edited scene file)."""
    import h5py

    from jaxmpm.running.output import resumable_steps

    if resumable_steps(path):
        with h5py.File(path, "r") as file:
            if str(file.attrs["scene"]) != sim.scene.to_toml():
                raise SceneError(f"--refine {refinement} --resume: {str(path)!r} holds an unfinished run of another "
                                 "scene: resume with the same scene file and --set values, or remove the file.")


def run_to_file(sim, output, quiet, resume):
    """(exit status, Result or None) of a run written to `output`: 1 and the part computed
    if it stopped early, INTERRUPTED and None if interrupted."""
    import jaxmpm

    try:
        with second_signal_ends_at_once(output):
            result = sim.run(progress=not quiet, save_to=output, resume=resume)
    except jaxmpm.SimulationError as error:
        print(f"jaxmpm: {error}", file=sys.stderr)
        print(f"partial output written to {output}", file=sys.stderr)
        return 1, error.result
    except KeyboardInterrupt:
        print(f"jaxmpm: interrupted; partial output written to {output} (continue with --resume)", file=sys.stderr)
        return INTERRUPTED, None
    print(f"wrote {output}")
    return 0, result


@contextlib.contextmanager
def second_signal_ends_at_once(output):
    """A run takes the first Ctrl-C or SIGTERM itself and stops after the chunk of steps being
    computed (`output.deferred_interrupts`); here a second signal ends the program at once,
    even inside a long compiled call (a large scene's step, the first call's compile): its
    file is marked interrupted at the last step written and closed, after any write in
    progress (`output.abandon_open_runs`), so it stays valid and resumable; status 130. A
    thread does it, woken through Python's signal wakeup pipe: the main thread runs no Python
    until a compiled call returns, so no signal handler could act before."""
    read, write = os.pipe()
    os.set_blocking(write, False)
    previous = signal.set_wakeup_fd(write, warn_on_full_buffer=False)

    def watch():
        seen = 0
        while data := os.read(read, 64):
            seen += sum(byte in (signal.SIGINT, signal.SIGTERM) for byte in data)
            if seen >= 2:
                from jaxmpm.running.output import abandon_open_runs

                abandon_open_runs()
                os.write(2, f"jaxmpm: interrupted at once; partial output written to {output} "
                            "(continue with --resume)\n".encode())
                os._exit(INTERRUPTED)

    watcher = threading.Thread(target=watch, name="jaxmpm-second-signal", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous)
        os.close(write)                     # the watcher reads the end of the pipe and returns
        watcher.join()
        os.close(read)


def checked_simulation(arguments):
    """The Simulation of the scene file with its --set values: every check, nothing compiled."""
    import jaxmpm

    scene = jaxmpm.load_scene(arguments.scene)
    for assignment in arguments.assignments:
        key, value = parse_assignment(assignment)
        scene = scene.with_value(key, value)
    return jaxmpm.Simulation(scene)


def describe(sim) -> str:
    scene = sim.scene
    subcycled = "".join(f", {block.name} in {block.substeps} substeps of each"
                        for block in sim.structure.bodies if block.substeps > 1)
    return (f"{scene.name}: {sim.point_count} points, {sim.steps} steps of {sim.dt:.4g} s{subcycled}, "
            f"{scene.numerics.dtype}{describe_relaxation(scene)}{describe_corners(sim.structure)}"
            f"{describe_structure_hold(sim.structure)}{describe_stress_substeps(scene)}")


def describe_relaxation(scene) -> str:
    """', relaxation 25 (tau = 5.1 ms)' for a relaxed APIC transfer, '' otherwise: a numerical
    choice that moves results (docs/convergence.md), so said with them."""
    from jaxmpm.running.simulation import slowest_crossing_time

    relaxation, crossing = scene.numerics.relaxation, slowest_crossing_time(scene)
    if scene.numerics.transfer != "apic" or relaxation <= 0.0 or not math.isfinite(crossing):
        return ""
    return f", relaxation {relaxation:g} (tau = {1e3 * relaxation * crossing:.3g} ms)"


def describe_corners(structure) -> str:
    """', corner radius 1 cell (pile 12.5 mm)' when prescribed bodies meet the sand with their
    outline (`bodies.prescribed_outline_normals`), '' otherwise: the rounding moves a pile's
    resistance by several per cent (docs/convergence.md), so it is said with the run."""
    import numpy as np

    from jaxmpm.physics.bodies import corner_radius

    outlined = [block for block in structure.bodies if block.kinematics == "prescribed" and block.outline is not None]
    if not outlined:
        return ""
    cells = structure.corner_radius
    if cells == 0.0:
        return ", prescribed bodies' corners sharp (corner radius 0)"
    radii = ", ".join(f"{block.name} {1e3 * float(corner_radius(np.asarray(block.outline), structure.layout.cell, cells)):.3g} mm"
                      for block in outlined)
    return f", corner radius {cells:g} cell{'' if cells == 1.0 else 's'} ({radii})"


def describe_structure_hold(structure) -> str:
    """', structures hold the nodes where they have mass (numerics.structure_hold = "mass")'
    when the scene has structures (`bodies.held_structures`), '' otherwise: the hold moves a
    structure's result by up to ten times (docs/convergence.md), so it is said with the run."""
    from jaxmpm.physics.bodies import held_structures

    if not held_structures(structure):
        return ""
    how = {"mass": "structures hold the nodes where they have mass",
           "outline": "structures hold the nodes whose cell meets their outline",
           "points": "prescribed and rigid structures push the points that reach into their outline"}[structure.structure_hold]
    return f', {how} (numerics.structure_hold = "{structure.structure_hold}")'


def describe_stress_substeps(scene) -> str:
    """', stress update in 4 substeps' when numerics.stress_substeps > 1, '' otherwise."""
    substeps = scene.numerics.stress_substeps
    return f", stress update in {substeps} substeps" if substeps > 1 else ""


def print_notes(scene):
    """The choices made for the scene that its file does not state (`Scene.notes`), on stderr."""
    for note in scene.notes:
        print(f"note: {note}", file=sys.stderr)


def check_command(arguments):
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxmpm.running.budget import estimate_bytes

    sim = checked_simulation(arguments)
    print_notes(sim.scene)
    parts = estimate_bytes(sim.scene, sim.steps)
    parts.pop("counts")
    print(f"{describe(sim)}, {sim.outputs} outputs; about {sum(parts.values()) / 1e6:.3g} MB of arrays for a forward run; "
          f"{describe_reverse_mode(*sim.reverse_mode_memory(), sim.steps)}: ok", flush=True)
    if not arguments.quick:
        import jaxmpm
        from jaxmpm.running.run_time import estimate_run_time

        jaxmpm.use_compilation_cache()          # the program compiled here is the one `run` loads
        print("compiling and timing a few steps for the run-time estimate (--quick skips it)", file=sys.stderr)
        print(estimate_run_time(sim).describe())
    return 0


def describe_reverse_mode(checkpointing, kept, steps) -> str:
    """What a gradient keeps for its backward pass (`Simulation.reverse_mode_memory`), in words."""
    segment = checkpointing.segment_length(steps)
    if segment < steps:
        how = f"segments of {segment} steps"
    else:
        how = {"recompute_grid": "one segment, its node arrays kept",
               "recompute": "one segment, each step run again whole"}.get(checkpointing.step, "one segment")
    if kept is None:
        return f'a gradient runs in {how} (step = "{checkpointing.step}")'
    return f"a gradient keeps about {readable_bytes(kept)} for its backward pass ({how})"


def readable_bytes(count) -> str:
    """1.88 GB, 370 MB, 8.26 MB, 12 kB."""
    if count >= 1e9:
        return f"{count / 1e9:.3g} GB"
    return f"{count / 1e6:.3g} MB" if count >= 1e6 else f"{count / 1e3:.3g} kB"


def output_path(argument, source, suffix=".h5"):
    output = Path(argument or Path(source).with_suffix(suffix).name)
    if not output.parent.is_dir():
        raise SceneError(f"-o {str(output)!r}: the folder {str(output.parent)!r} does not exist.")
    if not os.access(output.parent, os.W_OK):
        raise SceneError(f"-o {str(output)!r}: the folder {str(output.parent)!r} is not writable.")
    return output


def read_result(path):
    """The Result in `path`, or one SceneError line if it is not a jaxmpm output file."""
    import h5py

    from jaxmpm.running.results import Result

    if not Path(path).is_file():
        raise SceneError(f"{path!r} does not exist.")
    try:
        return Result.load(path)
    except (OSError, KeyError) as error:
        if isinstance(error, OSError) and not h5py.is_hdf5(path):
            raise SceneError(f"{path!r} is not an HDF5 file.") from None
        try:
            with h5py.File(path, "r") as file:
                written_by_jaxmpm = "jaxmpm_version" in file.attrs
        except OSError:
            raise SceneError(f"{path!r} is damaged (HDF5 cannot open it, e.g. a copy cut short): "
                             "run the scene again, or with --resume if a full copy of the file exists.") from None
        kind = plugged_file_kind(path)
        if kind is not None:
            raise SceneError(f"{path!r} is {kind.description}, not a run: draw it with `jaxmpm plot`, "
                             f"{kind.how_to_open}.") from None
        if written_by_jaxmpm:
            raise SceneError(f"{path!r} is a jaxmpm output file with parts missing or damaged ({error}).") from None
        raise SceneError(f"{path!r} is not a jaxmpm output file (written by `jaxmpm run`).") from None


def plot_command(arguments):
    import matplotlib

    matplotlib.use("Agg")
    from jaxmpm.pictures import plotting

    output = output_path(arguments.output, arguments.result, ".png")
    if Path(arguments.result).is_file():
        kind = plugged_file_kind(arguments.result)
        if kind is not None:
            return plot_other_kind(kind, arguments, output)
    allowed = (".png",) if arguments.probes else plotting.FORMATS
    plotting.check_output(output, allowed)        # before the file is read: name every type -o takes
    animation = output.suffix.lower() in (".gif", ".mp4")
    if arguments.probes and arguments.field is not None:
        raise SceneError(f"--field {arguments.field} colours snapshots; it does not apply to --probes.")
    if arguments.probes and arguments.mirror:
        raise SceneError("--mirror draws snapshots; it does not apply to --probes.")
    if (arguments.probes or animation) and arguments.snapshot is not None:
        raise SceneError(f"--snapshot {arguments.snapshot} picks the snapshot of a PNG; it does not apply to "
                         f"{'--probes' if arguments.probes else output.suffix}.")
    result = read_result(arguments.result)
    if arguments.probes:
        plotting.save_probes(result, output)
    elif animation:
        plotting.save_animation(result, output, arguments.field, mirror=arguments.mirror)
    else:
        count, snapshot = len(result.snapshots["time"]), -1 if arguments.snapshot is None else arguments.snapshot
        if not -count <= snapshot < count:
            raise SceneError(f"--snapshot {snapshot} is out of range: the file has {count} snapshots.")
        plotting.save_snapshot(result, output, arguments.field, snapshot, arguments.mirror)
    print(f"wrote {output}")
    return 0


RUN_PLOT_OPTIONS = ("field", "snapshot", "probes", "mirror")


def plot_other_kind(kind, arguments, output):
    """`jaxmpm plot` of a file another package drew (`plugged_file_kind`): one PNG."""
    from jaxmpm.pictures import plotting

    plotting.check_output(output, (".png",))
    for option in RUN_PLOT_OPTIONS:
        value = getattr(arguments, option)
        if value not in (None, False):
            raise SceneError(f"--{option} draws the output of a run; {str(arguments.result)!r} is {kind.description}.")
    kind.plot(arguments.result, output)
    print(f"wrote {output}")
    return 0


def export_command(arguments):
    from jaxmpm.pictures.export import export_paraview

    result = read_result(arguments.result)
    output = output_path(arguments.output, arguments.result, ".pvd")
    if output.suffix.lower() != ".pvd":
        raise SceneError(f"-o {str(output)!r}: the file type must be .pvd.")
    export_paraview(result, output, arguments.revolve, report=say_large_export)
    print(f"wrote {output} and its VTU files in {output.with_suffix('')}")
    return 0


LARGE_EXPORT = 100e6      # bytes: an export this large is announced before it is written


def say_large_export(size, files):
    """On stderr, before anything is written: how large an export of `files` VTU files can be
    (`export.export_bytes`: before compression)."""
    if size >= LARGE_EXPORT:
        print(f"jaxmpm: writing up to {readable_bytes(size)} in {files} VTU files (before compression; "
              "fewer snapshots or a smaller --revolve write less)", file=sys.stderr)


COMMANDS = {"run": run_command, "check": check_command, "plot": plot_command, "export": export_command}


INTERRUPTED = 130


@contextlib.contextmanager
def interrupts_end_quietly():
    """Ctrl-C or SIGTERM ends the program at once with one line and status 130: while JAX
    imports, and through the built-in commands except where a run takes the signals itself
    to keep what it computed (`output.deferred_interrupts`). Python's own KeyboardInterrupt
    is no use there: raised inside one of JAX's garbage-collector callbacks it is swallowed,
    and the program goes on."""
    def leave(signum, frame):
        os.write(2, b"jaxmpm: interrupted\n")
        os._exit(INTERRUPTED)

    previous = {sig: signal.signal(sig, leave) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main(argv=None):
    with interrupts_end_quietly():
        importlib.import_module("jax")      # the slow part of starting (the plugged commands import it too)
        arguments = build_parser().parse_args(argv)
        if arguments.command in COMMANDS:
            return run_reporting_errors(COMMANDS[arguments.command], arguments)
        command = plugged_commands()[arguments.command].run
    return run_reporting_errors(command, arguments)       # a plugged command handles its own interrupts


def run_reporting_errors(command, arguments) -> int:
    """The command's exit status; a user error is one line and status 2."""
    try:
        return command(arguments)
    except KeyboardInterrupt:
        print("jaxmpm: interrupted", file=sys.stderr)
        return INTERRUPTED
    except SceneError as error:
        print(f"jaxmpm: error: {one_line(str(error))}", file=sys.stderr)
        return USER_ERROR
    except OSError as error:
        print(f"jaxmpm: error: {one_line(f'{error.strerror}: {error.filename}')}", file=sys.stderr)
        return USER_ERROR


def one_line(text: str) -> str:
    """The message with every unprintable character (line breaks, controls) escaped, so that
    names and values the user wrote can never break it over lines."""
    return "".join(char if char.isprintable() else repr(char)[1:-1] for char in text)


if __name__ == "__main__":
    sys.exit(main())
