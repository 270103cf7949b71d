"""XLA compiler options for the programs jaxmpm compiles, chosen by what they compute.

Two options, each measured on the development VM (docs/benchmarks.md) and each applied only
where it measured faster; values are the same to round-off (the sums' order) without YNNPACK,
and bit for bit with region analysis:

- Reverse mode: XLA:CPU (jaxlib 0.10) hands short reductions to YNNPACK library kernels. The
  backward pass of the MPM step is full of them (the transposes of the stencil broadcasts,
  reductions over 2 to 5 entries), and it ran 15-17 % faster without them; the forward step
  gains nothing, so forward programs keep XLA's defaults.
- Scenes with several velocity fields (contact, prescribed and rigid bodies): XLA's copy
  insertion with region analysis, which proves more in-place updates safe across loop and
  conditional boundaries and so drops copies of the node arrays that the per-field updates
  (impulses, edge conditions) made every step. The wall twin's gradient ran 8-20 % faster
  and its forward pass 4-5 %, with about 4 % fewer kernels to compile; the one-field heap's
  gradient lost up to 9 % with it (there it removed copies of the state's per-point arrays),
  so one-field programs keep XLA's defaults.

Options are per `jax.jit`: the user's own jits, and everything else in the process, are left
alone (`Simulation.compiler_options` gives them the same choice for their own programs). An
option this jax or jaxlib does not accept is left out.
"""

import functools

import jax

NO_YNNPACK = {"xla_cpu_experimental_ynn_fusion_type": ""}
REGION_ANALYSIS = {"xla_cpu_copy_insertion_use_region_analysis": True}


@functools.cache
def accepted(name: str) -> dict:
    """The option set `name` ("no_ynnpack" or "region_analysis") on the CPU backend if this
    jax and jaxlib accept it, else {}."""
    options = {"no_ynnpack": NO_YNNPACK, "region_analysis": REGION_ANALYSIS}[name]
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=options).lower(1.0).compile()
    except (TypeError, ValueError, RuntimeError):     # older jax (no option) or unknown flag
        return {}
    return options


def compiler_options(*, reverse_mode: bool = False, several_fields: bool = False) -> dict:
    """The options of a program that differentiates in reverse mode (or not) a scene with
    several velocity fields (or one)."""
    options = {}
    if reverse_mode:
        options.update(accepted("no_ynnpack"))
    if several_fields:
        options.update(accepted("region_analysis"))
    return options


def jit_with_options(function, *, reverse_mode: bool = False, several_fields: bool = False, **jit_arguments):
    """jax.jit(function, **jit_arguments) with the `compiler_options` of such a program."""
    options = compiler_options(reverse_mode=reverse_mode, several_fields=several_fields)
    return jax.jit(function, compiler_options=options or None, **jit_arguments)


def jit_reverse_mode(function, several_fields: bool = False):
    """jax.jit for a function that differentiates a simulation in reverse mode."""
    return jit_with_options(function, reverse_mode=True, several_fields=several_fields)
