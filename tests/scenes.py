"""Small scenes shared by the tests, as TOML text (the format users write)."""

BLOCK = """
[scene]
name = "block"
gravity = [0.0, -9.81]
duration = 0.01
output_every = 0.005

[grid]
size = [0.4, 0.3]
cell = 0.05
boundaries = { left = "slip", right = "slip", bottom = "fixed", top = "free" }

[numerics]
shape = "linear"
transfer = "flip"
ppc = 2
damping = 0.0

[materials.soil]
model = "linear_elastic"
density = 1800.0
young = 1.0e6
poisson = 0.3

[[bodies]]
name = "block"
material = "soil"
region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }

[[probes]]
name = "top"
kind = "displacement"
at = [0.2, 0.2]

[[probes]]
name = "block_move"
kind = "body_displacement"
body = "block"
"""


def reverse_mode_against_central_differences(sim, reduce, cases, rel, relative_step=1e-6):
    """One jitted reverse-mode gradient of the loss reduce(sim.probes(params)) (every leaf
    finite) and, for each (dotted name, value, path into the gradient) of `cases`, its
    derivative against central differences with relative step `relative_step` (1e-6 unless a
    switch lies within it, docs/validation.md §8): nonzero and within `rel`. The differences
    run on `sim.probes` itself, so the program that reads the probes is compiled once for the
    test's own reads and the differences. `reduce` takes the probes as JAX arrays (traced) or
    NumPy arrays (the differences)."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import pytest

    from jaxmpm import with_values

    params = sim.cast(sim.params)
    gradient = jax.jit(jax.grad(lambda values: reduce(sim.probes(values))))(params)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(gradient))
    for name, value, path in cases:
        derivative = gradient
        for key in path:
            derivative = derivative[key]
        step = relative_step * value
        moved = (with_values(params, {name: jnp.asarray(value + sign * step)}) for sign in (1, -1))
        above, below = (float(reduce(jax.tree_util.tree_map(np.asarray, sim.probes(values)))) for values in moved)
        reference = (above - below) / (2 * step)
        assert float(derivative) != 0.0
        assert float(derivative) == pytest.approx(reference, rel=rel), name


def jaxpr_equations(jaxpr):
    """Every equation of `jaxpr` and of the jaxprs nested in its equations (loops, conditionals,
    checkpoints, custom derivatives)."""
    for equation in jaxpr.eqns:
        yield equation
        for value in equation.params.values():
            for inner in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(inner, "jaxpr", inner)
                if hasattr(inner, "eqns"):
                    yield from jaxpr_equations(inner)
