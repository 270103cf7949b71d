"""Gradients of probe histories against central finite differences, and no recompiling.

docs/validation.md §8: every differentiable output is checked against central differences
in float64 with a relative step of about 1e-6 of the parameter.
"""

import functools
import gc
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm
from tests.scenes import BLOCK, jaxpr_equations

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


@functools.lru_cache
def shared_simulation(update="musl", shape="linear"):
    """One compiled simulation per update scheme and shape, shared by the tests that only read it."""
    return small_simulation(update, shape)


def small_simulation(update="musl", shape="linear"):
    scene = jaxmpm.Scene.from_toml(BLOCK.replace('shape = "linear"', f'update = "{update}"\nshape = "{shape}"'))
    return jaxmpm.Simulation(scene)


def settlement_measure(sim, params):
    """A scalar that depends on the whole history: the summed vertical top displacement."""
    return jnp.sum(sim.probes(params)["top"][:, 1])


def central_difference(function, params, material, name, relative_step=1e-6):
    value = params["materials"][material][name]
    step = relative_step * value

    def shifted(delta):
        moved = jaxmpm.with_values(params, {f"{material}.{name}": value + delta})
        return float(function(moved))

    return (shifted(step) - shifted(-step)) / (2.0 * step)


@pytest.mark.parametrize("update, shape", [("musl", "linear"), ("usl", "linear"), ("musl", "gimp"), ("musl", "bspline2")])
def test_probe_gradient_matches_central_differences(update, shape):
    # One reverse pass gives the gradient with respect to every material value; each is
    # checked against its own central difference.
    sim = shared_simulation(update, shape)
    params = sim.params
    gradients = jax.grad(lambda p: settlement_measure(sim, p))(params)["materials"]["soil"]
    for name in ("young", "density", "poisson"):
        reference = central_difference(lambda p: settlement_measure(sim, p), params, "soil", name)
        assert np.isfinite(gradients[name]) and abs(reference) > 0.0, name
        np.testing.assert_allclose(gradients[name], reference, rtol=1e-5, err_msg=name)


@pytest.mark.parametrize("shape", ["linear", "bspline2"])
def test_gradients_are_finite_with_empty_nodes_and_fixed_edges(shape):
    # Most of the grid is empty (zero-mass nodes) and two edges are constrained (with bspline2,
    # through mirrored ghost nodes): the guarded p / m must give finite gradients everywhere
    # (a published JAX MPM returned NaN gradients exactly here).
    sim = shared_simulation("musl", shape)
    gradient = jax.grad(lambda p: jnp.sum(sim.final_state(p).particles.v ** 2))(sim.params)
    assert all(np.all(np.isfinite(value)) for value in jax.tree_util.tree_leaves(gradient))


def test_changing_parameters_never_retraces(count_step_traces):
    sim = small_simulation()
    traces = count_step_traces(sim)
    for young in (1.0e6, 2.0e6, np.float64(3.0e6), jnp.asarray(4.0e6)):
        params = jaxmpm.with_values(sim.params, {"soil.young": young})
        sim.probes(params)["top"].block_until_ready()
    assert len(traces) == 1

    loss = jax.jit(jax.grad(lambda p: settlement_measure(sim, p)))
    loss(sim.params)
    traced_for_gradient = len(traces)
    for density in (1700.0, 1900.0):
        loss(jaxmpm.with_values(sim.params, {"soil.density": density}))
    assert len(traces) == traced_for_gradient

    batched = jax.vmap(lambda young: settlement_measure(sim, jaxmpm.with_values(sim.params, {"soil.young": young})))
    batched(jnp.array([1.0e6, 2.0e6]))
    traced_for_batch = len(traces)
    batched(jnp.array([3.0e6, 5.0e6]))
    assert len(traces) == traced_for_batch


def test_vmap_over_parameters_matches_single_runs():
    sim = shared_simulation()
    youngs = jnp.array([1.0e6, 3.0e6])
    batched = jax.vmap(lambda young: settlement_measure(sim, jaxmpm.with_values(sim.params, {"soil.young": young})))(youngs)
    singles = [settlement_measure(sim, jaxmpm.with_values(sim.params, {"soil.young": y})) for y in youngs]
    np.testing.assert_allclose(batched, singles, rtol=1e-12)


def test_programs_are_traced_with_the_garbage_collector_paused():
    # jaxmpm.running.tracing: Python's cyclic collector is paused while jaxmpm traces its programs
    # (a fifth of a gradient's tracing and lowering went to its collections), and left as it
    # was after, also when the call fails.
    from jaxmpm.running.tracing import collector_paused

    sim = small_simulation()
    collecting = []
    step = sim.step
    sim.step = lambda params, state: collecting.append(gc.isenabled()) or step(params, state)
    sim.probes()
    assert collecting == [False] and gc.isenabled()

    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
    with pytest.raises(ZeroDivisionError):
        with collector_paused():
            1 / 0
    assert gc.isenabled()


@pytest.fixture(scope="module")
def one_step_segments():
    """Value and gradient of the settlement with one step per segment (the plain rollout)."""
    reference = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK), jaxmpm.Checkpointing(segment=1))
    return jax.value_and_grad(lambda p: settlement_measure(reference, p))(reference.params)


# 14 steps: segments of 3 (the last one shorter), the default (7, a divisor), one segment
# (what "auto" picks for this small block, or a segment longer than the run), against one step
# per segment; each step recomputed but for its node arrays (what "auto" picks), its elementwise
# arithmetic recomputed in the backward pass, the whole step recomputed, or all its
# intermediates stored.
@pytest.mark.parametrize("segment, step", [
    (3, "auto"), (None, "auto"), (10_000, "auto"), (None, "recompute_grid"), (None, "recompute_arithmetic"),
    (None, "store"), (None, "recompute"),
])
def test_checkpoint_segments_do_not_change_values_or_gradients(segment, step, one_step_segments):
    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK), jaxmpm.Checkpointing(segment=segment, step=step))
    value, gradient = jax.value_and_grad(lambda p: settlement_measure(sim, p))(sim.params)
    value_ref, gradient_ref = one_step_segments
    np.testing.assert_allclose(value, value_ref, rtol=1e-12)
    np.testing.assert_allclose(gradient["materials"]["soil"]["young"], gradient_ref["materials"]["soil"]["young"], rtol=1e-10)


VISCOPLASTIC_BLOCK = BLOCK.replace(
    'model = "linear_elastic"', 'model = "drucker_prager"\nfriction_angle = 20.0\nfluidity = 20.0\nexponent = 2.0',
).replace("duration = 0.01", "duration = 0.03")


def test_recomputed_steps_keep_the_perzyna_roots_instead_of_solving_again():
    # rollout.KEPT_SOLVES: "recompute" and "recompute_grid" keep each point's Perzyna root
    # from the forward pass, so the gradient's program holds the Newton loop of the forward
    # pass only, not a second one in the step its backward pass runs again. The gradient is that of the rollout storing everything.
    # The released block yields at every point, so the viscoplastic return is what is
    # differentiated.
    results = {}
    for step in ("store", "recompute", "recompute_grid"):
        sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(VISCOPLASTIC_BLOCK), jaxmpm.Checkpointing(segment=10**6, step=step))
        # traced once: the jaxpr read here is the one compiled and run (tracing it again for
        # make_jaxpr took a fifth of the test's time)
        traced = jax.jit(jax.value_and_grad(lambda p, sim=sim: settlement_measure(sim, p))).trace(sim.params)
        newton_loops = [e for e in jaxpr_equations(traced.jaxpr.jaxpr) if e.primitive.name == "while"]
        assert len(newton_loops) == 1, (step, len(newton_loops))
        results[step] = traced.lower().compile()(sim.params)
    assert np.all(np.asarray(sim.final_state().particles.history[0]["plastic_strain"]) > 0.0)
    # "auto"'s budget counts the kept roots (one value a point and step) with the states
    from jaxmpm.running.rollout import state_bytes
    from jaxmpm.physics.solver import kept_grid_bytes, kept_solve_bytes

    initial = sim.initial_state()
    itemsize = initial.particles.x.dtype.itemsize
    assert kept_solve_bytes(sim.structure, initial.particles.x.dtype) == sim.point_count * itemsize
    without_roots = sim.steps * (state_bytes(initial) + kept_grid_bytes(sim.structure, sim.point_count, itemsize))
    for budget, chosen in ((without_roots + sim.steps * sim.point_count * itemsize, "recompute_grid"), (without_roots, "recompute")):
        tight = jaxmpm.Simulation(sim.scene, jaxmpm.Checkpointing(budget=budget))
        assert tight.checkpointing_for(initial).step == chosen
    value_ref, gradient_ref = results["store"]
    for step in ("recompute", "recompute_grid"):
        value, gradient = results[step]
        np.testing.assert_allclose(value, value_ref, rtol=1e-12)
        for name in ("fluidity", "friction_angle", "exponent"):
            np.testing.assert_allclose(gradient["materials"]["soil"][name], gradient_ref["materials"]["soil"][name], rtol=1e-10)


def test_auto_checkpointing_keeps_states_and_node_arrays_only_within_its_memory_budget():
    from jaxmpm.running.rollout import STORE_BUDGET_BYTES as budget

    auto, grid = jaxmpm.Checkpointing(), "recompute_grid"
    # 200 steps whose states and node arrays fill the budget exactly: one segment, each step run
    # again in the backward pass but for its particle-to-grid transfers
    assert auto.resolved(200, budget // 400, budget // 400) == jaxmpm.Checkpointing(200, grid)
    # a byte more: the states alone still fit, so one segment of steps run again whole
    assert auto.resolved(200, budget // 400, budget // 400 + 1) == jaxmpm.Checkpointing(200, "recompute")
    # the states alone do not fit: segments, still keeping each step's node arrays
    assert auto.resolved(200, budget // 200 + 1, 0) == jaxmpm.Checkpointing(None, grid)
    assert auto.resolved(10_000, 16_384 * 16 * 4, 17_689 * 7 * 4) == jaxmpm.Checkpointing(None, grid)
    # rollouts run together (a calibration's starts) share the budget: the same one in segments
    assert jaxmpm.Checkpointing(budget=budget // 4).resolved(200, budget // 400, 0).segment is None
    # what the user chose stays
    assert jaxmpm.Checkpointing(step="recompute_arithmetic").resolved(200, 1, 1) == jaxmpm.Checkpointing(None, "recompute_arithmetic")
    assert jaxmpm.Checkpointing(segment=10).resolved(200, 1, 1) == jaxmpm.Checkpointing(10, grid)
    with pytest.raises(ValueError, match=r"Checkpointing.budget = '256 MB': give a number of bytes"):
        jaxmpm.Checkpointing(budget="256 MB")


def test_the_default_budget_is_two_gib_or_an_eighth_of_a_smaller_machine():
    from jaxmpm.running.rollout import STORE_BUDGET_BYTES, default_budget
    from jaxmpm.running.budget import physical_bytes

    gib = 1024**3
    assert default_budget(24 * gib) == 2 * gib            # the development VM
    assert default_budget(16 * gib) == 2 * gib
    assert default_budget(8 * gib) == gib                 # a smaller machine keeps less
    assert default_budget(gib) == gib // 4                # never under 256 MiB
    assert default_budget(float("inf")) == 2 * gib        # the system does not say
    assert STORE_BUDGET_BYTES == default_budget(physical_bytes())
    assert jaxmpm.Checkpointing().budget == STORE_BUDGET_BYTES


def test_a_rollout_in_one_segment_keeps_its_states_and_node_arrays_and_nothing_more():
    # "auto" on a small scene: one segment whose forward pass keeps each step's state and the
    # node arrays of its particle-to-grid transfers, and whose backward pass runs the rest of
    # each step again. The gradient's XLA temporaries are then those (steps x (state + node
    # array bytes), the memory the budget rule counts), not the steps' intermediates (~5x
    # more), and not a few segment states.
    from jaxmpm.running.rollout import state_bytes
    from jaxmpm.physics.solver import kept_grid_bytes

    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK.replace("duration = 0.01", "duration = 0.1")))   # 140 steps
    initial = sim.initial_state()
    assert sim.checkpointing_for(initial) == jaxmpm.Checkpointing(sim.steps, "recompute_grid")
    states = sim.steps * (state_bytes(initial) + kept_grid_bytes(sim.structure, sim.point_count, initial.particles.x.dtype.itemsize))
    temp = {}
    for step in ("auto", "recompute_arithmetic"):
        kept = jaxmpm.Simulation(sim.scene, jaxmpm.Checkpointing(segment=sim.steps if step != "auto" else None, step=step))
        compiled = jax.jit(jax.grad(lambda p, kept=kept: settlement_measure(kept, p))).lower(sim.params).compile()
        temp[step] = compiled.memory_analysis().temp_size_in_bytes
    assert 0.5 * states <= temp["auto"] <= 1.5 * states, (temp, states)
    assert temp["recompute_arithmetic"] > 3 * temp["auto"], temp
    # what `jaxmpm check` reports, counted from shapes alone
    assert sim.reverse_mode_memory() == (jaxmpm.Checkpointing(sim.steps, "recompute_grid"), states)
    assert kept_for("recompute_arithmetic", sim)[1] is None


def kept_for(step, sim, segment=None, budget=None):
    more = {} if budget is None else {"budget": budget}
    return jaxmpm.Simulation(sim.scene, jaxmpm.Checkpointing(segment=segment, step=step, **more)).reverse_mode_memory()


def test_reverse_mode_memory_counts_what_each_checkpointing_keeps():
    # Simulation.reverse_mode_memory: one segment keeps every step's state (and, with
    # "recompute_grid", its node arrays); segments keep one state a segment and that for the
    # steps of one segment. The gradient's XLA temporaries hold that and the step's own.
    from jaxmpm.running.rollout import state_bytes
    from jaxmpm.physics.solver import kept_grid_bytes

    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK.replace("duration = 0.01", "duration = 0.1")))   # 140 steps
    initial = sim.initial_state()
    state = state_bytes(initial)
    grid = kept_grid_bytes(sim.structure, sim.point_count, initial.particles.x.dtype.itemsize)
    assert kept_for("recompute", sim, segment=sim.steps)[1] == sim.steps * state
    # a budget under the whole rollout's states: "auto" runs it in segments of 14 (140 = 10 x 14)
    checkpointing, kept = kept_for("auto", sim, budget=sim.steps * state - 1)
    assert checkpointing == jaxmpm.Checkpointing(None, "recompute_grid", budget=sim.steps * state - 1)
    assert checkpointing.segment_length(sim.steps) == 14
    assert kept == 10 * state + 14 * (state + grid)
    segmented = jaxmpm.Simulation(sim.scene, checkpointing)
    compiled = jax.jit(jax.grad(lambda p: settlement_measure(segmented, p))).lower(sim.params).compile()
    assert 0.5 * kept <= compiled.memory_analysis().temp_size_in_bytes <= 1.5 * kept


@pytest.mark.parametrize("shape", ["linear", "bspline2"])
def test_recompute_grid_keeps_the_velocity_gradients_of_3x3_stencils_and_counts_them(shape):
    # solver.keeps_velocity_gradient: with a 3 x 3 stencil "recompute_grid" keeps each point's
    # four in-plane velocity-gradient entries (KEPT_RATE) on top of the node arrays; with 2 x 2
    # stencils it does not. The XLA temporaries beyond those of the same rollout keeping only
    # the node arrays are what the budget rule counts for them (kept_grid_bytes).
    from jaxmpm.physics.solver import kept_grid_bytes

    scene = jaxmpm.Scene.from_toml(BLOCK.replace("duration = 0.01", "duration = 0.1").replace('shape = "linear"', f'shape = "{shape}"'))
    temp = {}
    for step in ("recompute_grid", "names:grid+solve"):
        sim = jaxmpm.Simulation(scene, jaxmpm.Checkpointing(segment=10**6, step=step))
        compiled = jax.jit(jax.grad(lambda p, sim=sim: settlement_measure(sim, p))).lower(sim.params).compile()
        temp[step] = compiled.memory_analysis().temp_size_in_bytes
    itemsize = sim.initial_state().particles.x.dtype.itemsize
    counted = sim.steps * (kept_grid_bytes(sim.structure, sim.point_count, itemsize) - kept_grid_bytes(sim.structure, 0, itemsize))
    assert counted == (sim.steps * sim.point_count * 4 * itemsize if shape == "bspline2" else 0)
    assert temp["recompute_grid"] - temp["names:grid+solve"] == pytest.approx(counted, rel=0.01, abs=1024)


def test_reverse_mode_compiler_options_keep_the_gradient():
    # jaxmpm.kernels.xla_options: calibration gradients are compiled without XLA:CPU's YNNPACK
    # reduction kernels (docs/benchmarks.md measures the gain); the numbers must not change
    # beyond round-off. XLA uses those kernels only for large enough arrays, hence a block of
    # 1,600 points. (Whether the option reaches the program is not asserted on the compiled
    # text, which changes with every jaxlib.)
    from jaxmpm.kernels.xla_options import jit_reverse_mode

    finer = {"cell = 0.05": "cell = 0.01", "duration = 0.01": "duration = 0.001", "output_every = 0.005": "output_every = 0.001"}
    text = BLOCK
    for old, new in finer.items():
        text = text.replace(old, new)
    scene = jaxmpm.Scene.from_toml(text)
    sim = jaxmpm.Simulation(scene)
    young = sim.params["materials"]["soil"]["young"]

    def loss(value):
        return settlement_measure(sim, jaxmpm.with_values(sim.params, {"soil.young": value}))

    plain, tuned = jax.jit(jax.grad(loss)), jit_reverse_mode(jax.grad(loss))
    np.testing.assert_allclose(tuned(young), plain(young), rtol=1e-12)
