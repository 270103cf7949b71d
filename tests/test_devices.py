"""Several devices: ensembles sharded over a batch axis, on two forced host devices.

Each check runs in a subprocess started with XLA_FLAGS=--xla_force_host_platform_device_count=2
(the device count is fixed when JAX starts, so it cannot change inside the test process). The
children keep the suite's own XLA flags (tests/conftest.py) and compile with LLVM's
optimisations off (--xla_backend_optimization_level=0): their scenes run a few dozen steps, so
compiling is nearly all their time, and it takes less than half as long; each comparison is
between programs of the same child, compiled alike."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
QUICK_TO_COMPILE = "--xla_backend_optimization_level=0"

CHILD = r"""
import json
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jaxmpm
from jaxmpm.running.ensembles import stack
from tests.scenes import BLOCK

sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK))
members = [jaxmpm.with_values(sim.params, {"soil.young": young, "soil.density": density})
           for young, density in ((0.6e6, 1700.0), (0.8e6, 1800.0), (1.0e6, 1900.0), (1.2e6, 2000.0))]
report = {"devices": len(jax.devices())}
for count in (4, 3):                      # even, and padded to a multiple of the devices
    batch = stack(members[:count])
    probes = jaxmpm.ensemble(sim, batch)
    again = jaxmpm.ensemble(sim, batch)
    worst = 0.0
    for index, params in enumerate(members[:count]):
        alone = sim.probes(params)
        for name in alone:
            scale = float(np.max(np.abs(np.asarray(alone[name])))) or 1.0
            worst = max(worst, float(np.max(np.abs(np.asarray(probes[name][index]) - np.asarray(alone[name])))) / scale)
    values = probes["top"]
    report[str(count)] = {
        "shape": list(values.shape),
        "worst_relative": worst,
        "repeatable": all(np.array_equal(np.asarray(probes[n]), np.asarray(again[n])) for n in probes),
        "devices_holding": len(values.sharding.device_set),
        "shard_rows": sorted({shard.data.shape[0] for shard in values.addressable_shards}),
    }
from inverse.optimise import over_devices
report["holding_starts"] = len(over_devices(jax.numpy.zeros((2, 1))).sharding.device_set)

# A calibration of one start and two experiments of the same scene (twins: noise-free
# synthetic data at young = 0.8e6, each with its own density): the experiments are laid over
# the devices, and the fit recovers the value the data came from.
import inverse
from inverse.experiments import experiments_from, group_experiments, members_over_devices, problem_arguments
truths = {density: jaxmpm.with_values(sim.params, {"soil.young": 0.8e6, "soil.density": density})
          for density in (1700.0, 1900.0)}
experiments = experiments_from([inverse.Experiment(sim, sim.run(truth, progress=False), set={"soil.density": density})
                                for density, truth in truths.items()], None)
fit_keys = {"soil.young": (0.3e6, 3.0e6)}
groups = group_experiments(experiments, inverse.ParameterSpace([sim.params], fit_keys))
data, bases = members_over_devices(groups, *problem_arguments(experiments, groups))
report["holding_experiments"] = len(jax.tree_util.tree_leaves(data)[0].sharding.device_set)
fit = inverse.calibrate(experiments, fit=fit_keys, max_iterations=10, progress=False)
report["fitted_young"] = float(fit.params["soil.young"])
print(json.dumps(report))
"""


SHARDED_SCENE = r"""
import json
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jaxmpm
from pathlib import Path

# The heap of the calibration example: Perzyna sand slumping over several cells (large
# deformation: the first cells of its slump; plastic history, geostatic start), made 33 x 17 points so that their count is
# odd and the sharded state is padded with one inert point.
scene = jaxmpm.load_scene(Path("examples/calibrate_heap_scene.toml"))
scene = scene.with_value("bodies.heap.region.rectangle", [[0.0, 0.0], [0.165, 0.085]]).with_value("scene.duration", 0.06)
alone = jaxmpm.Simulation(scene)
sharded = jaxmpm.Simulation(scene, devices=jax.devices())
one, two = alone.run(progress=False), sharded.run(progress=False)
state = sharded.initial_state()
worst = 0.0
for name in one.probes:
    scale = float(np.max(np.abs(one.probes[name]))) or 1.0
    worst = max(worst, float(np.max(np.abs(two.probes[name] - one.probes[name]))) / scale)
for body in scene.bodies:
    for field in scene.snapshot_fields:
        a, b = one.snapshots[body.name][field], two.snapshots[body.name][field]
        assert a.shape == b.shape, (field, a.shape, b.shape)
        scale = float(np.max(np.abs(a))) or 1.0
        worst = max(worst, float(np.max(np.abs(b - a))) / scale)
print(json.dumps({"points": alone.point_count, "padded_points": int(state.particles.x.shape[0]),
                  "devices_holding": len(state.particles.x.sharding.device_set),
                  "shard_rows": sorted({s.data.shape[0] for s in state.particles.x.addressable_shards}),
                  "worst_relative": worst}))
"""


def run_on_devices(code, count=2):
    flags = f"{os.environ.get('XLA_FLAGS', '')} {QUICK_TO_COMPILE} --xla_force_host_platform_device_count={count}"
    environment = dict(os.environ, XLA_FLAGS=flags.strip(),
                       PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=environment,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_an_ensemble_on_two_devices_is_sharded_and_equals_its_members_run_alone():
    report = run_on_devices(CHILD)
    assert report["devices"] == 2
    assert report["holding_starts"] == 2              # calibration lays two starts over both devices
    assert report["holding_experiments"] == 2         # ... and one start's two experiments
    assert abs(report["fitted_young"] / 0.8e6 - 1) < 1e-6
    even, padded = report["4"], report["3"]
    # Four members on two devices: two rows on each, the result left where it was computed.
    assert even["shape"][0] == 4 and even["devices_holding"] == 2 and even["shard_rows"] == [2]
    assert padded["shape"][0] == 3                          # the padding member is dropped
    for case in (even, padded):
        # Each member equals the same parameters run alone to round-off (the batched program
        # may sum in another order: docs/devices.md), and the same call repeats bit for bit.
        assert case["worst_relative"] < 1e-12
        assert case["repeatable"]


def test_one_scene_sharded_over_two_devices_equals_the_single_device_run():
    report = run_on_devices(SHARDED_SCENE)
    assert report["points"] % 2 == 1 and report["padded_points"] == report["points"] + 1
    assert report["devices_holding"] == 2 and report["shard_rows"] == [report["padded_points"] // 2]
    # Probes and every snapshot field to round-off (the sums are split between devices and
    # added in another order: docs/devices.md). (A gradient through the sharded run matched
    # the one-device gradient to 1e-16 when measured; it is left out of the suite for time.)
    assert report["worst_relative"] < 1e-9
