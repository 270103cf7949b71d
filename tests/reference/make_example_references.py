"""Write tests/reference/examples.npz: every example scene's probes and final state after its
first STEPS steps (float64), the values tests/test_example_references.py holds the code to.

    python tests/reference/make_example_references.py

Run it only when a change is meant to change the numbers of the examples, and say so in the
commit; a refactoring must leave them as they are (to round-off). It compiles with the XLA
flag the tests use (tests/conftest.py): an example at rest (retaining_wall_active's first
steps) has velocities that are round-off alone, which another compilation does not repeat.
"""

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

if __name__ == "__main__":
    from tests.conftest import use_quick_compiling

    use_quick_compiling()
STEPS = 40
OUTPUT = Path(__file__).with_name("examples.npz")


def example_scenes():
    return sorted(path for path in (ROOT / "examples").glob("*.toml") if not path.name.endswith((".calibration.toml", ".design.toml")))


def shortened(scene, dt):
    """The scene run for STEPS steps of its own time step dt (given as scene.dt, which the
    duration then cannot trim), one output at the end."""
    return dataclasses.replace(scene, dt=dt, duration=STEPS * dt, output_every=STEPS * dt)


def example_run(path):
    """({key: array}, final state) of one example after STEPS steps: the values are each
    probe's history and the final positions, velocities and stresses of its points."""
    import jaxmpm

    scene = jaxmpm.load_scene(path)
    dt = jaxmpm.Simulation(scene).dt
    sim = jaxmpm.Simulation(shortened(scene, dt))
    assert abs(sim.dt - dt) <= 1e-12 * dt and sim.steps == STEPS
    probes, final = sim.probes_and_final_state()
    values = {f"probe/{name}": np.asarray(history) for name, history in probes.items()}
    values.update(x=np.asarray(final.particles.x), v=np.asarray(final.particles.v),
                  stress=np.asarray(final.particles.stress))
    return {f"{path.stem}/{key}": value for key, value in values.items()}, final


def example_values(path):
    """{key: array} of one example after STEPS steps (`example_run`)."""
    return example_run(path)[0]


if __name__ == "__main__":
    stored = {}
    for path in example_scenes():
        stored.update(example_values(path))
        print(path.name, "done", flush=True)
    np.savez_compressed(OUTPUT, **stored)
    print(f"wrote {OUTPUT} ({len(stored)} arrays)")
