"""Long runs: output streamed to the file output by output, a run stopped by a signal and
resumed equal to one never stopped, and memory that does not grow with the snapshots."""

import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import h5py
import numpy as np
import pytest

import jaxmpm
from jaxmpm.cli import main
from tests.scenes import BLOCK

ROOT = Path(__file__).resolve().parents[1]
# The retaining wall of Więckowski's Fig. 1, coarsened: viscoplastic sand with plastic history,
# a rigid wall in frictional contact, geostatic start; every kind of state a run carries.
WALL = [str(ROOT / "examples" / "retaining_wall.toml"), "--set", "grid.cell=0.05", "--set", "scene.duration=0.2",
        "--set", "scene.output_every=0.02"]


def datasets(path):
    """{name: array} of every dataset outside /resume."""
    found = {}

    def keep(name, item):
        if isinstance(item, h5py.Dataset) and not name.startswith("resume"):
            found[name] = item[()]

    with h5py.File(path, "r") as file:
        file.visititems(keep)
        return found, dict(file.attrs)


def steps_written(path):
    try:
        with h5py.File(path, "r", locking=False) as file:
            return int(file.attrs["steps_done"])
    except (OSError, KeyError):
        return 0


def test_a_run_stopped_by_sigterm_and_resumed_equals_the_run_never_stopped(tmp_path, capsys):
    full, part = tmp_path / "full.h5", tmp_path / "part.h5"
    assert main(["run", *WALL, "-o", str(full), "--quiet"]) == 0
    reference, attributes = datasets(full)
    steps = len(reference["time"]) - 1

    command = [sys.executable, "-m", "jaxmpm.cli", "run", *WALL, "-o", str(part), "--quiet"]
    process = subprocess.Popen(command, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while steps_written(part) < 0.2 * steps and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    process.send_signal(signal.SIGTERM)
    _, error = process.communicate(timeout=120)
    assert process.returncode == 130, error            # stopped between outputs, like Ctrl-C
    assert "continue with --resume" in error and "Traceback" not in error
    stopped, stopped_attributes = datasets(part)
    assert not stopped_attributes["complete"]
    assert 0 < stopped_attributes["steps_done"] < steps   # it really stopped midway
    kept = stopped_attributes["steps_done"] + 1
    np.testing.assert_array_equal(stopped["probes/wall_move"], reference["probes/wall_move"][:kept])

    # run again without --resume: refused in one line, the computed steps kept
    capsys.readouterr()
    assert main(["run", *WALL, "-o", str(part), "--quiet"]) == 2
    assert f"holds {stopped_attributes['steps_done']} computed steps" in capsys.readouterr().err
    assert datasets(part)[1]["steps_done"] == stopped_attributes["steps_done"]

    assert main(["run", *WALL, "-o", str(part), "--quiet", "--resume"]) == 0
    resumed, resumed_attributes = datasets(part)
    assert resumed_attributes["complete"] and resumed.keys() == reference.keys()
    for name, values in reference.items():
        np.testing.assert_array_equal(resumed[name], values, err_msg=name)     # bit for bit

    # A different scene is refused, in one line, before anything runs.
    capsys.readouterr()
    assert main(["run", *WALL, "--set", "materials.sand.friction_angle=31", "-o", str(part), "--resume"]) == 2
    message = capsys.readouterr().err.splitlines()[-1]
    assert "the scene differs from the one" in message and "part.h5" in message


def test_resume_refuses_what_it_cannot_continue(tmp_path):
    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK))
    with pytest.raises(jaxmpm.SceneError, match="does not exist: there is no run to continue"):
        sim.run(progress=False, save_to=tmp_path / "none.h5", resume=True)
    with pytest.raises(jaxmpm.SceneError, match="resume=True needs save_to"):
        sim.run(progress=False, resume=True)
    done = sim.run(progress=False, save_to=tmp_path / "done.h5")
    other = jaxmpm.with_values(sim.params, {"soil.young": 0.9 * sim.params["materials"]["soil"]["young"]})
    with pytest.raises(jaxmpm.SceneError, match="the parameters differ"):
        sim.run(other, progress=False, save_to=tmp_path / "done.h5", resume=True)
    again = sim.run(progress=False, save_to=tmp_path / "done.h5", resume=True)     # complete: nothing to add
    np.testing.assert_array_equal(again.probes["top"], done.probes["top"])
    # a state laid out as an earlier build stored it: the stress as (N, 3, 3) tensors
    with h5py.File(tmp_path / "done.h5", "r+") as file:
        slot = file["resume"][str(file.attrs["resume_slot"])]
        index = next(key for key in slot if slot[key].attrs["path"] == ".particles.stress_voigt")
        del slot[index]
        slot.create_dataset(index, data=np.zeros((sim.point_count, 3, 3)))
        slot[index].attrs["path"] = ".particles.stress"
    with pytest.raises(jaxmpm.SceneError, match="laid out unlike this jaxmpm's .at .particles.stress_voigt"):
        sim.run(progress=False, save_to=tmp_path / "done.h5", resume=True)


def test_a_streamed_run_holds_no_snapshot_in_memory_and_equals_the_in_memory_run(tmp_path):
    # 2,000-point block, a snapshot (x, v, stress: 240 bytes a point) after every step: the
    # in-memory run holds them all, the streamed run none, so its peak Python memory (numpy
    # allocations, as tracemalloc counts them) does not grow with the number of snapshots.
    text = BLOCK.replace("cell = 0.05", "cell = 0.0125").replace(
        "[scene]", '[scene]\nsnapshot_fields = ["x", "v", "stress"]')
    peaks = {}
    for outputs in (20, 60):
        scene = jaxmpm.Scene.from_toml(text)
        sim = jaxmpm.Simulation(scene)
        scene = scene.with_value("scene.output_every", sim.dt).with_value("scene.duration", outputs * sim.dt)
        sim = jaxmpm.Simulation(scene)
        sim.run(progress=False, save_to=tmp_path / "warm.h5")          # compile outside the measurement
        for mode in ("memory", "file"):
            tracemalloc.start()
            result = sim.run(progress=False, save_to=None if mode == "memory" else tmp_path / f"{outputs}.h5")
            peaks[mode, outputs] = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        snapshot_bytes = sim.point_count * (2 + 2 + 9) * 8
        if outputs == 60:
            in_memory = sim.run(progress=False)
            for field in ("x", "v", "stress"):
                np.testing.assert_array_equal(result.snapshots["block"][field], in_memory.snapshots["block"][field])
    extra = 40 * snapshot_bytes          # what 40 more snapshots hold
    assert peaks["memory", 60] - peaks["memory", 20] > 0.8 * extra          # the measure sees them
    assert peaks["file", 60] - peaks["file", 20] < 0.1 * extra              # the streamed run holds none
    assert isinstance(result.snapshots, jaxmpm.running.results.FileSnapshots)


