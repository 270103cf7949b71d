"""The `jaxmpm run` command and the HDF5 output schema of jaxmpm.results."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

import jaxmpm
from jaxmpm.cli import main
from tests.scenes import BLOCK


@pytest.fixture
def block_file(tmp_path):
    path = tmp_path / "block.toml"
    path.write_text(BLOCK)
    return path


def test_run_writes_the_documented_schema(block_file, tmp_path, capsys):
    output = tmp_path / "out.h5"
    assert main(["run", str(block_file), "-o", str(output), "--quiet", "--set", "soil.young=2e6"]) == 0
    assert str(output) in capsys.readouterr().out
    with h5py.File(output) as file:
        assert file.attrs["complete"] == True  # noqa: E712 (numpy bool)
        assert file.attrs["jaxmpm_version"] == jaxmpm.__version__
        scene = jaxmpm.Scene.from_toml(file.attrs["scene"])
        assert scene.materials["soil"].young == 2e6
        sim = jaxmpm.Simulation(scene)
        steps = len(file["time"])
        assert steps == sim.steps + 1
        assert file["probes/top"].shape == (steps, 2)
        assert file["probes/block_move"].shape == (steps, 2)
        snapshots = len(file["snapshots/time"])
        assert snapshots == sim.outputs + 1
        assert file["snapshots/block/stress"].shape == (snapshots, sim.point_count, 3, 3)
        assert file["snapshots/block/x"].shape == (snapshots, sim.point_count, 2)
        assert file["snapshots/block/plastic_strain"].shape == (snapshots, sim.point_count)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_result_load_round_trip(tmp_path):
    scene = jaxmpm.Scene.from_toml(BLOCK)
    result = jaxmpm.simulate(scene, progress=False)
    loaded = jaxmpm.Result.load(result.save(tmp_path / "r.h5"))
    np.testing.assert_array_equal(loaded.probes["top"], result.probes["top"])
    np.testing.assert_array_equal(loaded.snapshots["block"]["stress"], result.snapshots["block"]["stress"])
    assert loaded.complete and jaxmpm.Scene.from_toml(loaded.scene_toml) == scene


@pytest.mark.parametrize(
    "arguments, words",
    [
        (["--set", "soil.poisson=0.7"], ["materials.soil.poisson = 0.7"]),
        (["--set", "grid.cel=0.1"], ["grid.cel"]),
        (["--set", "nonsense"], ["key=value"]),
        (["-o", "/no/such/folder/out.h5"], ["/no/such/folder"]),
    ],
)
def test_user_errors_exit_2_with_one_line(block_file, capsys, arguments, words):
    assert main(["run", str(block_file), "--quiet", *arguments]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error
    for word in words:
        assert word in error


def test_cli_process_exits_2_without_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(BLOCK.replace("cell = 0.05", "cell = -0.05"))
    done = subprocess.run(
        [sys.executable, "-m", "jaxmpm.cli", "run", str(bad)], capture_output=True, text=True, cwd=tmp_path
    )
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert "grid.cell = -0.05" in done.stderr


def test_failed_run_keeps_what_it_computed(tmp_path, capsys):
    # A block thrown at 40 m/s leaves a 0.4 m grid through its free edge within a few steps.
    flying = BLOCK.replace('right = "slip"', 'right = "free"').replace(
        'region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }',
        'region = { rectangle = [[0.0, 0.0], [0.2, 0.2]] }\nvelocity = [40.0, 0.0]',
    )
    path = tmp_path / "flying.toml"
    path.write_text(flying)
    output = tmp_path / "flying.h5"
    assert main(["run", str(path), "-o", str(output), "--quiet"]) == 1
    message = capsys.readouterr().err
    assert "left the grid" in message and "body 'block'" in message and "step" in message
    with h5py.File(output) as file:
        assert file.attrs["complete"] == False  # noqa: E712
        assert "left the grid" in file.attrs["message"]
        time, top = file["time"][()], file["probes/top"][()]
    assert len(time) == len(top) >= 1
    assert np.all(np.isfinite(top))
    # the part kept is the true history: the point moved at the thrown speed until it left
    np.testing.assert_allclose(top[-1, 0], 40.0 * time[-1], rtol=0.05)
