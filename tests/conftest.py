"""Tests run with 64-bit JAX (scenes choose float32 or float64 themselves) and strict dtype
promotion, so an accidental mix of dtypes inside the solver is an error, not a silent upcast.
The CLI's compilation cache is off (tests/test_cli_and_output.py tests it in its own
directory), so that no test reads programs another run left on disk."""

import os

import jax
import pytest

os.environ["JAXMPM_CACHE_DIR"] = "off"

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
