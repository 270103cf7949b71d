"""Tests run with 64-bit JAX (scenes choose float32 or float64 themselves) and strict dtype
promotion, so an accidental mix of dtypes inside the solver is an error, not a silent upcast."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
