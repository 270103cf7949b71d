"""How long a run takes: `jaxmpm check`'s estimate from timed steps, and the progress bar's
rate and time left, counted from after the compile."""

import io

import pytest

import jaxmpm
from jaxmpm.cli import main
from jaxmpm.running.progress import progress_bar, restart_clock
from jaxmpm.running.run_time import estimate_run_time, readable_seconds
from tests.scenes import BLOCK


def test_the_estimate_times_the_runs_own_chunks_within_the_scenes_steps():
    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK.replace("duration = 0.01", "duration = 0.1")))
    estimate = estimate_run_time(sim, seconds=0.0)         # one timed chunk after the compiling call
    assert estimate.timed_steps == sim.chunk and (estimate.steps, estimate.outputs) == (sim.steps, sim.outputs)
    assert estimate.step_seconds > 0 and estimate.snapshot_seconds > 0 and estimate.compile_seconds >= 0
    assert estimate.seconds == pytest.approx(sim.steps * estimate.step_seconds + sim.outputs * estimate.snapshot_seconds)
    longer = estimate_run_time(sim, seconds=1e9)           # never more steps than the scene's own
    assert longer.timed_steps == sim.steps - sim.chunk


def test_check_prints_the_estimate_and_its_basis(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("JAXMPM_CACHE_DIR", "off")
    path = tmp_path / "block.toml"
    path.write_text(BLOCK)
    assert main(["check", str(path)]) == 0
    ok, estimate = capsys.readouterr().out.strip().splitlines()
    assert ok.endswith(": ok")
    assert estimate.startswith("run time: about ") and "estimated from" in estimate and "compiling first took" in estimate
    assert main(["check", str(path), "--quick"]) == 0
    assert "run time" not in capsys.readouterr().out


def test_readable_seconds():
    assert [readable_seconds(s) for s in (4.2e-4, 0.012, 0.5, 3.44, 42.0, 150.0, 9000.0)] == [
        "0.42 ms", "12 ms", "500 ms", "3.4 s", "42 s", "2.5 min", "2.5 h"]


def test_the_bar_counts_its_rate_from_after_the_compile():
    now = [0.0]
    bar = progress_bar(True, total=1000, file=io.StringIO(), mininterval=0)
    bar._time = lambda: now[0]                 # a clock the test moves
    now[0] = 10.0                              # the first call: 10 s of compiling, 100 steps
    restart_clock(bar, 100)
    now[0] = 11.0                              # the next call: 100 steps in 1 s
    bar.update(100)
    shown = bar.format_dict
    assert shown["n"] == 200 and shown["elapsed"] == pytest.approx(1.0)
    assert shown["rate"] == pytest.approx(100.0)           # so the time left reads 8 s, not 80
    bar.close()
