"""XLA compiler options for jaxmpm's own jitted reverse-mode computations.

XLA:CPU (jaxlib 0.10) hands short reductions to YNNPACK library kernels. The backward pass of
the MPM step is full of them (the transposes of the stencil broadcasts, reductions over 2 to 5
entries), and it ran 15-17 % faster without them on the development VM (docs/benchmarks.md);
the forward step gains nothing, so forward runs keep XLA's defaults. Options are per `jax.jit`:
the user's own jits, and everything else in the process, are left alone.
"""

import functools

import jax

NO_YNNPACK = {"xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def reverse_mode_options() -> dict:
    """NO_YNNPACK on the CPU backend if this jax and jaxlib accept it, else {}."""
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=NO_YNNPACK).lower(1.0).compile()
    except (TypeError, ValueError, RuntimeError):     # older jax (no option) or unknown flag
        return {}
    return NO_YNNPACK


def jit_reverse_mode(function):
    """jax.jit for a function that differentiates a simulation (see the module docstring)."""
    options = reverse_mode_options()
    return jax.jit(function, compiler_options=options) if options else jax.jit(function)
