"""Every example scene's first steps against stored values (tests/reference/examples.npz), with
its own settings: they stay finite, inside the grid, and move something.

The stored values were computed before the step was rewritten as plain JAX (commit 6904040,
with hand-written adjoints, paired transposes and compiler barriers); a change meant to keep
the physics must reproduce them to round-off. A change meant to change the numbers
regenerates the file (tests/reference/make_example_references.py) and says so in its commit.
"""

import jax
import numpy as np
import pytest

from tests.reference.make_example_references import OUTPUT, example_run, example_scenes

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def stored():
    with np.load(OUTPUT) as data:
        return dict(data)


@pytest.mark.parametrize("path", example_scenes(), ids=lambda path: path.stem)
def test_example_reproduces_its_stored_values(path, stored):
    computed, final = example_run(path)
    particles = final.particles
    assert int(np.max(np.asarray(particles.flags))) == 0, "a point left the grid or went non-finite"
    # gravity, a prescribed body or an initial velocity acts in every example
    assert np.max(np.abs(np.asarray(particles.v))) > 0.0
    assert set(computed) == {key for key in stored if key.startswith(path.stem + "/")}
    for key, value in computed.items():
        reference = stored[key]
        scale = float(np.max(np.abs(reference))) or 1.0
        # round-off: XLA may sum in another order after a change of the program's shape
        np.testing.assert_allclose(value, reference, rtol=1e-9, atol=1e-9 * scale, err_msg=key)
