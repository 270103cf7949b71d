"""Speed kernels: faster versions of parts of the plain step, kept only where they measured at
least 15 % faster on an example scene (docs/benchmarks.md, "Kernels"). Each sits beside the
plain code it replaces, which stays the reference, and tests/test_kernels.py checks that the
two agree to round-off in values and derivatives. Only public JAX APIs are used.

- `fusion.materialized`: computes a value into memory once, where XLA:CPU would recompute it
  inside every kernel that reads it.
- `scatter.batched_add_to_nodes`: the particle-to-grid scatter with a hand-written `vmap`, for
  programs differentiated in forward mode only (`Simulation.forward_only`).
- `transposes`: the transfers' reverse mode written as each other (scatter and gather, sum
  and broadcast), for programs differentiated in reverse mode only (`Simulation.reverse_only`).
"""
