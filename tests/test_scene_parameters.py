"""Gravity and damping are parameters like the materials' (params["scene"], params["numerics"]):
dynamic, differentiable, addressable by name and by component, fitted like any other."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxmpm
from jaxmpm.scene.parameters import resolve, value_at
from tests.scenes import BLOCK

FALL = BLOCK.replace('bottom = "fixed"', 'bottom = "free"').replace("size = [0.4, 0.3]", "size = [0.4, 0.6]").replace(
    "region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }", "region = { rectangle = [[0.1, 0.3], [0.3, 0.5]] }")


def free_fall():
    """A block falling freely (no edge touched in 0.01 s)."""
    return jaxmpm.Simulation(jaxmpm.Scene.from_toml(FALL))


def fallen(sim, params):
    """The block's mean vertical displacement at the end [m]."""
    return sim.probes(params)["block_move"][-1, 1]


def test_gravity_is_a_parameter_of_every_scene_and_damping_of_damped_ones():
    sim = free_fall()
    np.testing.assert_array_equal(sim.params["scene"]["gravity"], [0.0, -9.81])
    assert "numerics" not in sim.params          # undamped: no damping is compiled, so no coefficient
    with pytest.raises(jaxmpm.SceneError, match="'numerics.damping' is not a parameter"):
        jaxmpm.with_values(sim.params, {"numerics.damping": 0.1})
    damped = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK.replace("damping = 0.0", "damping = 0.2")))
    assert damped.params["numerics"] == {"damping": 0.2}


def test_a_free_fall_follows_the_gravity_parameter_exactly_and_its_derivative():
    # Symplectic Euler on a free body: v_n = n g dt, x_N = g dt^2 N (N + 1) / 2, exactly
    # (no stress: the block starts unstressed and every point falls alike).
    sim = free_fall()
    steps, dt = sim.steps, sim.dt
    expected = lambda g: g * dt * dt * steps * (steps + 1) / 2
    gravities = jnp.asarray([-9.81, -98.1])      # 1 g and a centrifuge's 10 g, one compiled program
    batched = jax.vmap(lambda g: fallen(sim, jaxmpm.with_values(sim.params, {"scene.gravity[1]": g})))(gravities)
    np.testing.assert_allclose(batched, expected(gravities), rtol=1e-10)
    slope = jax.grad(lambda g: fallen(sim, jaxmpm.with_values(sim.params, {"scene.gravity[1]": g})))(-9.81)
    np.testing.assert_allclose(slope, expected(1.0), rtol=1e-10)
    sideways = jaxmpm.with_values(sim.params, {"scene.gravity[0]": 2.0})
    np.testing.assert_array_equal(sideways["scene"]["gravity"], [2.0, -9.81])
    np.testing.assert_array_equal(sim.params["scene"]["gravity"], [0.0, -9.81])    # the template is untouched


def test_the_geostatic_stress_follows_the_gravity_parameter():
    scene = jaxmpm.Scene.from_toml(BLOCK.replace(
        'region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }',
        'region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }\ninitial_stress = { geostatic = { k0 = 0.5 } }'))
    sim = jaxmpm.Simulation(scene)
    once = sim.initial_state().particles.stress_voigt
    twice = sim.initial_state(jaxmpm.with_values(sim.params, {"scene.gravity": [0.0, -2 * 9.81]})).particles.stress_voigt
    assert float(jnp.min(once[:, 1])) < 0.0
    np.testing.assert_allclose(twice, 2 * once, rtol=1e-12)


def test_the_damping_gradient_matches_central_differences():
    sim = jaxmpm.Simulation(jaxmpm.Scene.from_toml(BLOCK.replace("damping = 0.0", "damping = 0.2")))
    settle = jax.jit(lambda alpha: sim.probes(jaxmpm.with_values(sim.params, {"numerics.damping": alpha}))["top"][-1, 1])
    slope = jax.grad(settle)(0.2)
    step = 1e-6
    central = (settle(0.2 + step) - settle(0.2 - step)) / (2 * step)
    assert abs(float(central)) > 0.0
    np.testing.assert_allclose(slope, central, rtol=1e-5)


def test_component_names_resolve_and_are_refused_out_of_range():
    sim = free_fall()
    location = resolve(sim.params, "scene.gravity[1]")
    assert location == ("scene", "gravity", 1)
    assert value_at(sim.params, location) == -9.81
    with pytest.raises(jaxmpm.SceneError, match=r"'scene.gravity\[2\]': 'scene.gravity' has no component 2"):
        resolve(sim.params, "scene.gravity[2]")
    with pytest.raises(jaxmpm.SceneError, match="must be a whole number"):
        resolve(sim.params, "scene.gravity[y]")
    with pytest.raises(jaxmpm.SceneError, match="did you mean 'scene.gravity'"):
        resolve(sim.params, "scene.gravty")


def test_a_gravity_component_is_fitted_like_a_material_value():
    sim = free_fall()
    space = inverse.ParameterSpace(sim.params, {"scene.gravity[1]": (-200.0, -1.0)})
    assert space.names == ("scene.gravity[1]",)
    np.testing.assert_array_equal(space.start_values(), [-9.81])
    placed = space.insert(jnp.asarray([-50.0]))
    np.testing.assert_array_equal(placed["scene"]["gravity"], [0.0, -50.0])
    with pytest.raises(jaxmpm.SceneError, match=r"not a single number \(shape \(2,\)\): name one component, e.g. 'scene.gravity\[0\]'"):
        inverse.ParameterSpace(sim.params, {"scene.gravity": (-200.0, -1.0)})


def test_values_put_into_cast_parameters_keep_their_dtype_so_a_jitted_function_traces_once():
    # A jitted function of the parameters is traced again whenever a leaf's dtype or weak type
    # changes: central differences over several names then compiled the whole rollout once
    # per name (three times in a three-parameter gradient check) until with_values kept them.
    sim = free_fall()
    params = sim.cast(sim.params)
    traces = []

    @jax.jit
    def young_times_gravity(p):
        traces.append(1)
        return p["materials"]["soil"]["young"] * p["scene"]["gravity"][1]

    for values in ({"soil.young": 2.0e6}, {"soil.density": 1700.0}, {"scene.gravity[1]": -5.0},
                   {"soil.young": jnp.asarray(3.0e6, jnp.float32)}):
        changed = jaxmpm.with_values(params, values)
        assert all(leaf.dtype == sim.dtype and not leaf.weak_type for leaf in jax.tree_util.tree_leaves(changed))
        young_times_gravity(changed)
    assert len(traces) == 1
    assert float(young_times_gravity(jaxmpm.with_values(params, {"scene.gravity[1]": -5.0}))) == pytest.approx(-5.0e6)
