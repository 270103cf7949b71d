"""Tests run with 64-bit JAX (scenes choose float32 or float64 themselves) and strict dtype
promotion, so an accidental mix of dtypes inside the solver is an error, not a silent upcast.
Compiled programs are shared between the tests of one session (both xdist workers, and the
CLI runs they start) through a compilation cache in a fresh temporary directory, removed at
the end: many tests compile the same scene, and no test reads programs another session left
on disk (tests/test_cli_and_output.py tests the cache itself in its own directory)."""

import os
import shutil
import tempfile

import jax
import pytest

SESSION_CACHE = "JAXMPM_TEST_SESSION_CACHE"


def pytest_configure(config):
    """The first process of the session (the xdist controller, or the only process) makes the
    cache directory; workers inherit it through the environment."""
    if SESSION_CACHE not in os.environ:
        os.environ[SESSION_CACHE] = tempfile.mkdtemp(prefix="jaxmpm-test-cache-")
        config._jaxmpm_owns_cache = True
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
