"""The `jaxmpm run` command and the HDF5 output schema of jaxmpm.running.results."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

import jaxmpm
from jaxmpm.cli import main
from jaxmpm.running.output import ROWS_PER_CHUNK
from tests.scenes import BLOCK


# A block thrown at 40 m/s leaves a 0.4 m grid through its free edge within a few steps.
FLYING = BLOCK.replace('right = "slip"', 'right = "free"').replace(
    'region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }',
    'region = { rectangle = [[0.0, 0.0], [0.2, 0.2]] }\nvelocity = [40.0, 0.0]',
)


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
        # histories in chunks of many rows (one a step made a long run's file four times larger),
        # a snapshot compressed in a chunk of its own (docs/output_files.md)
        assert file["time"].chunks == (ROWS_PER_CHUNK,) and file["probes/top"].chunks == (ROWS_PER_CHUNK, 2)
        assert file["snapshots/block/x"].chunks == (1, sim.point_count, 2)
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
    path = tmp_path / "flying.toml"
    path.write_text(FLYING)
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


def test_a_second_run_loads_every_program_from_the_compilation_cache(block_file, tmp_path):
    # Every compilation is stored (no minimum compile time): the first run fills the cache; a
    # second run of the same scene writes no new entry, so each of its programs was found
    # there (a miss would have compiled and stored one), and its output is the same.
    import os

    cache = tmp_path / "cache"
    environment = dict(os.environ, JAXMPM_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    entries = []
    for name in ("first.h5", "second.h5"):
        done = subprocess.run([sys.executable, "-m", "jaxmpm.cli", "run", str(block_file), "-o", str(tmp_path / name),
                               "--quiet"], capture_output=True, text=True, cwd=tmp_path, env=environment)
        assert done.returncode == 0, done.stderr[-2000:]
        entries.append(sorted(path.name for path in cache.iterdir()))
    assert entries[0] and entries[1] == entries[0]
    first, second = jaxmpm.Result.load(tmp_path / "first.h5"), jaxmpm.Result.load(tmp_path / "second.h5")
    for name in first.probes:
        assert np.array_equal(first.probes[name], second.probes[name])


def test_the_compilation_cache_directory_follows_the_environment(tmp_path):
    from jaxmpm.running.compilation_cache import cache_directory

    assert cache_directory({"JAXMPM_CACHE_DIR": "off", "HOME": str(tmp_path)}) is None
    assert cache_directory({"JAXMPM_CACHE_DIR": str(tmp_path / "c")}) == tmp_path / "c"
    assert cache_directory({"XDG_CACHE_HOME": str(tmp_path / "x")}) == tmp_path / "x" / "jaxmpm" / "xla"
    assert cache_directory({"HOME": str(tmp_path)}) == tmp_path / ".cache" / "jaxmpm" / "xla"


def test_the_library_imports_nothing_of_inverse_and_the_command_still_calibrates():
    # inverse adds `calibrate` to the command through the entry point group jaxmpm.commands:
    # importing jaxmpm (and its command) loads no module of inverse, and the parser offers it.
    code = ("import sys, jaxmpm, jaxmpm.cli, jaxmpm.scene, jaxmpm.pictures.plotting, jaxmpm.pictures.export; "
            "assert not [m for m in sys.modules if m == 'inverse' or m.startswith('inverse.')], 'inverse imported'; "
            "parser = jaxmpm.cli.build_parser(); print(parser.parse_args(['calibrate', 'x.toml']).config)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "x.toml"


def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as stopped:
        main(["--version"])
    assert stopped.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxmpm {version('jaxmpm')}"


def test_run_refine_dt_writes_the_refined_run_and_prints_each_probes_largest_change(block_file, tmp_path, capsys):
    output = tmp_path / "out.h5"
    assert main(["run", str(block_file), "-o", str(output), "--quiet", "--refine", "dt"]) == 0
    printed = capsys.readouterr().out
    refined_file = tmp_path / "out-dt.h5"
    assert "scene.cfl 0.4 -> 0.2" in printed and str(refined_file) in printed
    run, refined = jaxmpm.Result.load(output), jaxmpm.Result.load(refined_file)
    scene = jaxmpm.Scene.from_toml(refined.scene_toml)
    assert scene.cfl == 0.2 and len(refined.time) == 2 * len(run.time) - 1
    # the printed change of the top's vertical displacement, read independently from the two
    # files: its time averages over each output interval (0.005 s), trapezoidal rule
    def means(result):
        values = []
        for start, stop in ((0.0, 0.005), (0.005, 0.01)):
            inside = (result.time >= start - 1e-12) & (result.time <= stop + 1e-12)
            t, v = result.time[inside], result.probes["top"][inside, 1]
            values.append(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)) / (t[-1] - t[0]))
        return np.array(values)

    ours, theirs = means(run), means(refined)
    difference = np.abs(ours - theirs)
    row = next(line.split() for line in printed.splitlines() if line.split()[:2] == ["top", "y"])
    assert float(row[2]) == pytest.approx(difference.max(), rel=1e-3)
    largest = max(np.abs(ours).max(), np.abs(theirs).max())
    assert float(row[3]) == pytest.approx(100 * difference.max() / largest, rel=1e-2)
    assert float(row[5]) == pytest.approx([0.0025, 0.0075][np.argmax(difference)])


def test_run_refine_refuses_a_relaxation_the_scene_does_not_have_before_running(block_file, tmp_path, capsys):
    output = tmp_path / "out.h5"
    assert main(["run", str(block_file), "-o", str(output), "--quiet", "--refine", "relaxation"]) == 2
    message = capsys.readouterr().err
    assert "--refine relaxation" in message and "numerics.transfer = 'flip'" in message
    assert not output.exists()


def test_compare_results_compares_interval_means_up_to_the_time_both_runs_reached():
    scene = jaxmpm.Scene.from_toml(BLOCK).with_value("scene.output_every", 0.01)   # one output interval
    time = np.linspace(0.0, 0.01, 11)
    fine = np.linspace(0.0, 0.006, 13)               # a refined run that stopped at 6 ms
    ripple = np.where(np.arange(11) % 2 == 0, 1.0, -1.0)   # a force flipping sign each step
    run = jaxmpm.Result(scene.to_toml(), time, {"top": np.stack([time, -time**2], axis=1), "still": 0 * time[:, None],
                                                "appears": 0 * time[:, None], "ripple": ripple[:, None]}, {})
    refined = jaxmpm.Result(scene.to_toml(), fine, {"top": np.stack([fine + fine**2, -fine**2], axis=1),
                                                    "still": 0 * fine[:, None], "appears": fine[:, None],
                                                    "ripple": 0 * fine[:, None]}, {}, complete=False)
    comparison = jaxmpm.compare_results(run, refined)
    assert comparison.end == pytest.approx(0.006)
    by_label = {change.label: change for change in comparison.changes}
    # over [0, 6 ms]: the mean of t is 3 ms in both; t^2 adds 6^2 / 3 = 12 (mm)^2 / ms, plus the
    # trapezoidal rule's h^2 / 6 on the refined run's 0.5 ms steps
    top_x = by_label["top x"]
    assert top_x.change == pytest.approx(0.006**2 / 3 + 0.0005**2 / 6, rel=1e-9) and top_x.at == pytest.approx(0.003)
    assert top_x.relative == pytest.approx(top_x.change / (0.003 + top_x.change))
    assert by_label["top y"].change == pytest.approx((0.001**2 - 0.0005**2) / 6, rel=1e-9)   # the two rules on -t^2
    assert np.isnan(by_label["still"].relative)
    # zero in the run, not in the refined one: a full change, not hidden as "-"
    assert by_label["appears"].relative == pytest.approx(1.0)
    # a step-to-step ripple averages out: +1 -1 ... over 0-6 ms (7 samples) is 0 by the trapezoid
    assert by_label["ripple"].change == pytest.approx(0.0, abs=1e-12)
    assert comparison.largest_change() is by_label["appears"]
    described = comparison.describe().splitlines()
    assert "the refined run stopped there" in described[0]
    assert [line.split()[0] for line in described[2:5]] == ["appears", "top", "top"]


def test_refined_scene_halves_the_step_or_the_cell_and_doubles_the_relaxation_or_the_stress_substeps():
    scene = jaxmpm.Scene.from_toml(BLOCK)                    # cfl 0.4 (the default), cell 0.05
    assert jaxmpm.refined_scene(scene, "dt").cfl == pytest.approx(scene.cfl / 2)
    given = scene.with_value("scene.dt", 1e-4)
    assert jaxmpm.refined_scene(given, "dt").dt == pytest.approx(5e-5)
    finer = jaxmpm.refined_scene(given, "cell")
    assert finer.grid.cell == pytest.approx(0.025) and finer.dt == pytest.approx(5e-5)
    assert jaxmpm.Simulation(finer).point_count == 4 * jaxmpm.Simulation(given).point_count
    relaxed = scene.with_value("numerics.transfer", "apic").with_value("numerics.relaxation", 10.0)
    assert jaxmpm.refined_scene(relaxed, "relaxation").numerics.relaxation == 20.0
    # "stress": the stress update's substeps doubled, on a scene whose body can yield; refused
    # with one sentence on the elastic block, whose update has nothing to refine
    from jaxmpm.running.refinement import describe_refinement, refinement_refused

    sand = jaxmpm.Scene.from_toml(BLOCK.replace('model = "linear_elastic"', 'model = "drucker_prager"\nfriction_angle = 30.0'))
    assert jaxmpm.refined_scene(sand.with_value("numerics.stress_substeps", 2), "stress").numerics.stress_substeps == 4
    assert describe_refinement(sand, "stress") == "numerics.stress_substeps 1 -> 2"
    assert refinement_refused(sand, "stress") is None
    assert "no free body that can yield" in refinement_refused(scene, "stress")
    assert "64 is the largest" in refinement_refused(sand.with_value("numerics.stress_substeps", 64), "stress")


def test_run_refine_keeps_an_unfinished_refined_file_and_resumes_only_its_own_scene(block_file, tmp_path, capsys):
    # an unfinished run of another scene (a thrown block that leaves the grid) where the refined
    # run would be written
    (tmp_path / "flying.toml").write_text(FLYING)
    refined_file = tmp_path / "out-dt.h5"
    assert main(["run", str(tmp_path / "flying.toml"), "-o", str(refined_file), "--quiet"]) == 1
    before = refined_file.read_bytes()
    output = tmp_path / "out.h5"
    assert main(["run", str(block_file), "-o", str(output), "--quiet", "--refine", "dt"]) == 2
    assert "unfinished run" in capsys.readouterr().err and not output.exists()
    assert main(["run", str(block_file), "-o", str(output), "--quiet", "--refine", "dt", "--resume"]) == 2
    assert "--refine dt --resume" in capsys.readouterr().err and not output.exists()
    assert refined_file.read_bytes() == before
