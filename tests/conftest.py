"""Tests run with 64-bit JAX (scenes choose float32 or float64 themselves) and strict dtype
promotion, so an accidental mix of dtypes inside the solver is an error, not a silent upcast.

Compiled programs are shared between the tests of one session (both xdist workers, and the
CLI runs they start) through a compilation cache in a fresh temporary directory, removed at
the end: many tests compile the same scene, and no test reads programs another session left
on disk (tests/test_cli_and_output.py tests the cache itself in its own directory).

The suite spends most of its time compiling small scenes that then run for a second or two,
so it asks XLA:CPU for its classic fusion emitters (`--xla_cpu_use_fusion_emitters=false`),
which compile the step's programs in about two thirds of the time and run them 1.3-1.6 times
slower (docs/benchmarks.md); the values agree to round-off (tests/test_example_references.py holds them to
1e-9). Users' runs keep XLA's defaults. The flag is set only if this jaxlib accepts it (an
unknown XLA flag aborts the process), and not at all if XLA_FLAGS already names it."""

import os
import shutil
import subprocess
import sys
import tempfile

import jax
import pytest

SESSION_CACHE = "JAXMPM_TEST_SESSION_CACHE"
QUICK_COMPILING = "--xla_cpu_use_fusion_emitters=false"


def accepts_xla_flag(flag):
    """Whether a fresh process with `flag` in XLA_FLAGS compiles and runs a program."""
    environment = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip())
    probe = "import jax; jax.jit(lambda x: x + 1.0)(1.0).block_until_ready()"
    try:
        done = subprocess.run([sys.executable, "-c", probe], env=environment, capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def use_quick_compiling():
    """Add QUICK_COMPILING to XLA_FLAGS (before JAX's backend starts) unless XLA_FLAGS already
    names the option or this jaxlib refuses it."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags and accepts_xla_flag(QUICK_COMPILING):
        os.environ["XLA_FLAGS"] = f"{flags} {QUICK_COMPILING}".strip()


def pytest_configure(config):
    """The first process of the session (the xdist controller, or the only process) makes the
    cache directory and chooses the compiler flag; workers inherit both through the
    environment."""
    if SESSION_CACHE not in os.environ:
        os.environ[SESSION_CACHE] = tempfile.mkdtemp(prefix="jaxmpm-test-cache-")
        config._jaxmpm_owns_cache = True
        use_quick_compiling()
    os.environ["JAXMPM_CACHE_DIR"] = os.environ[SESSION_CACHE]
    jax.config.update("jax_compilation_cache_dir", os.environ[SESSION_CACHE])


def pytest_unconfigure(config):
    if getattr(config, "_jaxmpm_owns_cache", False):
        shutil.rmtree(os.environ.pop(SESSION_CACHE), ignore_errors=True)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def count_step_traces():
    """count_step_traces(sim) -> a list that grows by one each time `sim`'s step is traced
    (a guard against recompiling when only parameter values change)."""

    def install(sim):
        traces, step = [], sim.step

        def counting_step(params, state):
            traces.append(1)
            return step(params, state)

        sim.step = counting_step
        return traces

    return install
