"""Interrupting a run: Ctrl-C (SIGINT) or SIGTERM acts within a chunk of steps (well under a
second) at any scene size, even in the middle of a long output interval; the file keeps every
step done and resumes to the same result; a second signal stops at once and leaves a valid
file; a signal while JAX is still importing ends quietly."""

import dataclasses
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

import jaxmpm
from jaxmpm.running.output import resumable_steps
from jaxmpm.running.runner import chunk_length, interval_calls
from tests.scenes import BLOCK

# One output interval of 43,756 steps of 512 points (about 4.7 s of CPU, in chunks of 1,953
# steps): before runs were chunked, a signal was acted on only at the end of it. (The block at
# its own 128 points needed 137,000 steps for as long an interval, and the run file takes a
# row per step.)
LONG_INTERVAL = 16.0
LONG = (BLOCK.replace("cell = 0.05", "cell = 0.025").replace("duration = 0.01", f"duration = {LONG_INTERVAL}")
        .replace("output_every = 0.005", f"output_every = {LONG_INTERVAL}"))


def test_the_chunk_bounds_the_work_per_call_and_divides_the_interval_where_it_can():
    assert chunk_length(7644, 5_100_000) == 1          # the wall at cell 1 mm: one step per call
    assert chunk_length(7644, 32_640) == 28            # the largest divisor of 7644 within 1e6 point-steps
    assert chunk_length(100, 1_000) == 100             # small scenes: a whole interval per call
    assert chunk_length(97, 50_000) == 20              # a prime interval: chunks of the bound, then 17 steps
    assert chunk_length(2 * 101, 50_000) == 20         # its divisors within 20 are 1 and 2: too short


@pytest.mark.parametrize("length, calls", [(2, [2, 2, 2]), (4, [4, 2])])   # whole chunks; a remainder
def test_a_chunked_run_gives_the_same_numbers(tmp_path, length, calls):
    scene = jaxmpm.Scene.from_toml(BLOCK)
    scene = dataclasses.replace(scene, dt=0.5 * scene.stable_dt)
    whole = jaxmpm.Simulation(scene)
    assert whole.steps_per_output == 6 and [steps for _, steps in interval_calls(whole)] == [6]
    chunked = jaxmpm.Simulation(scene)
    chunked.chunk = length                     # (read when its programs are traced)
    assert [steps for _, steps in interval_calls(chunked)] == calls
    expected = whole.run(progress=False)
    found = chunked.run(progress=False, save_to=tmp_path / "chunked.h5")
    for name, values in expected.probes.items():
        np.testing.assert_array_equal(found.probes[name], values)
    for field, values in expected.snapshots["block"].items():
        np.testing.assert_array_equal(found.snapshots["block"][field], values)


def start_run(scene_path, output, *extra):
    """`jaxmpm run` in a subprocess. It loads the programs that the `long_scene` fixture compiled
    from the session's compilation cache (tests/conftest.py); every signal below comes after
    its first chunk, so after they are loaded."""
    command = [sys.executable, "-m", "jaxmpm.cli", "run", str(scene_path), "-o", str(output), "--quiet", *extra]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def steps_in(path) -> int:
    """steps_done of a run file that another process is writing (read without locking)."""
    try:
        with h5py.File(path, "r", locking=False) as file:
            return int(file.attrs["steps_done"])
    except (OSError, KeyError):
        return 0


def outputs_in(path) -> int:
    """The output intervals a run that another process is writing can resume from."""
    try:
        with h5py.File(path, "r", locking=False) as file:
            return int(file.attrs["resume_output"])
    except (OSError, KeyError):
        return 0


def wait_for_steps(process, path, timeout=60.0):
    """Until the running process has written some steps to `path`."""
    deadline = time.monotonic() + timeout
    while steps_in(path) == 0:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the run wrote no steps"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def long_scene(tmp_path_factory):
    """(scene file, the uninterrupted run's probes) of the long-interval scene."""
    folder = tmp_path_factory.mktemp("long")
    path = folder / "long.toml"
    path.write_text(LONG)
    reference = jaxmpm.Simulation(jaxmpm.Scene.from_toml(LONG)).run(progress=False)
    return path, reference.probes


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_a_long_interval_at_once_and_the_run_resumes_to_the_same_result(long_scene, tmp_path, signum):
    scene_path, expected = long_scene
    output = tmp_path / "run.h5"
    process = start_run(scene_path, output)
    wait_for_steps(process, output)
    signalled = time.monotonic()
    process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    assert time.monotonic() - signalled < 3.0            # a chunk, not the rest of the interval
    assert process.returncode == 130 and "continue with --resume" in err
    assert "Traceback" not in err
    with h5py.File(output, "r") as file:
        done = int(file.attrs["steps_done"])
        assert not file.attrs["complete"] and "interrupted" in file.attrs["message"]
        assert 0 < done < len(expected["top"]) - 1
        assert len(file["probes/top"]) == done + 1        # every step done is in the file
    if signum == signal.SIGINT:                           # (one resume is enough)
        resumed = start_run(scene_path, output, "--resume")
        _, err = resumed.communicate(timeout=120)
        assert resumed.returncode == 0, err
        result = jaxmpm.Result.load(output)
        assert result.complete
        for name, values in expected.items():
            np.testing.assert_array_equal(result.probes[name], values)


def test_a_second_signal_stops_at_once_and_leaves_a_valid_file(long_scene, tmp_path):
    scene_path, expected = long_scene
    output = tmp_path / "twice.h5"
    process = start_run(scene_path, output)
    wait_for_steps(process, output)
    process.send_signal(signal.SIGINT)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130 and "Traceback" not in err
    result = jaxmpm.Result.load(output)                  # a valid file, marked incomplete
    assert not result.complete
    rows = len(result.probes["top"])
    np.testing.assert_array_equal(result.probes["top"], expected["top"][:rows])


def test_a_second_signal_stops_at_once_inside_a_long_compiled_call(tmp_path):
    # Calls of a whole interval of the long scene (43,756 steps, about 4.7 s here), as one step
    # of a scene of millions of points takes: the first signal waits for the call to end, the
    # second does not.
    scene_path = tmp_path / "two_calls.toml"
    scene_path.write_text(LONG.replace(f"duration = {LONG_INTERVAL}", f"duration = {2 * LONG_INTERVAL}"))
    output = tmp_path / "two_calls.h5"
    driver = ("import sys, jaxmpm.running.runner; jaxmpm.running.runner.CHUNK_POINT_STEPS = 1e12; "
              "from jaxmpm.cli import main; sys.exit(main(sys.argv[1:]))")
    process = subprocess.Popen([sys.executable, "-c", driver, "run", str(scene_path), "-o", str(output), "--quiet"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "JAXMPM_CACHE_DIR": "off"})
    wait_for_steps(process, output)                      # the first call is done
    while outputs_in(output) == 0:                       # and its snapshot written:
        time.sleep(0.05)
    time.sleep(0.5)                                      # the second call has begun
    process.send_signal(signal.SIGINT)
    process.send_signal(signal.SIGTERM)
    signalled = time.monotonic()
    _, err = process.communicate(timeout=60)
    assert time.monotonic() - signalled < 1.5            # not the rest of the call (3 s or more)
    assert process.returncode == 130 and "interrupted at once" in err and "Traceback" not in err, err
    result = jaxmpm.Result.load(output)                  # valid, marked interrupted at its last step written
    assert not result.complete and result.message == f"interrupted at t = {LONG_INTERVAL:g} s"
    assert len(result.snapshots["time"]) == 2            # t = 0 and the end of the first call
    assert resumable_steps(output) == len(result.probes["top"]) - 1 > 40_000


def wait_for_handler(process, timeout=30.0):
    """Until the process handles SIGTERM (the command's first line installs the handler; a
    signal before it, while Python itself starts, is not the command's). Linux's /proc shows
    it; elsewhere, a pause."""
    status = f"/proc/{process.pid}/status"
    if not os.path.exists(status):
        time.sleep(0.3)
        return
    deadline = time.monotonic() + timeout
    while True:
        with open(status) as file:
            caught = next(int(line.split()[1], 16) for line in file if line.startswith("SigCgt:"))
        if caught & (1 << (signal.SIGTERM - 1)):
            return
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.005)


def test_an_interrupt_while_jax_imports_ends_quietly(tmp_path):
    scene = tmp_path / "block.toml"
    scene.write_text(BLOCK)
    process = start_run(scene, tmp_path / "early.h5")
    wait_for_handler(process)                            # main has begun; jax takes a second more to import
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
