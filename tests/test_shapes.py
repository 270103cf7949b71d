"""Shape functions `linear`, `gimp` (uGIMP) and `bspline2` (quadratic B-spline).

Sources: Bardenhagen & Kober (2004) define uGIMP as the tent function averaged over the point's
cell of half-width l; the quadratic B-spline is the tent averaged over a whole cell (Steffen,
Kirby & Berzins 2008). Both are checked against those integrals, computed numerically here.
Then the bar of docs/validation.md §1 (tests/test_elastic_validation.py) with each shape:
second-order convergence for small motion, and for large motion (points crossing cells) the
accuracy that linear shape functions lose.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm
from jaxmpm.physics.grid import GridLayout
from jaxmpm.physics.shapes import QuadraticBSpline, UniformGIMP
from tests.test_elastic_validation import (
    BAR_LENGTH,
    BAR_OMEGA,
    BAR_PERIOD,
    bar_dispersion,
    bar_scene,
    first_mode_state,
    fitted_period,
    loglog_slope,
)

SHAPES = ["linear", "gimp", "bspline2"]


def random_points(count, size, seed=0):
    """Points spread over the whole grid, the four corners and the edges included."""
    points = np.random.default_rng(seed).uniform([0.0, 0.0], size, size=(count, 2))
    points[:4] = [[0.0, 0.0], [size[0], size[1]], [0.0, size[1]], [size[0], 0.0]]
    points[4:8] = [[1e-9, 0.3], [size[0] - 1e-9, 0.3], [0.3, 1e-9], [0.3, size[1] - 1e-9]]
    return jnp.asarray(points)


@pytest.mark.parametrize("ppc", [1, 2, 3])
@pytest.mark.parametrize("shape", SHAPES)
def test_partition_of_unity_and_linear_completeness_up_to_the_edges(shape, ppc):
    layout = GridLayout((0.2, -0.1), 0.1, (10, 8), shape, ppc)
    points = random_points(500, (1.0, 0.8)) + jnp.asarray([0.2, -0.1])
    stencil = layout.stencil(points)
    offsets = jnp.stack(layout.node_offsets(stencil.base, points, stencil.weights.shape[1]))    # x_I - x_p
    gradients = jnp.stack(stencil.gradients)
    assert float(jnp.min(stencil.weights)) >= 0.0
    np.testing.assert_allclose(jnp.sum(stencil.weights, axis=(1, 2)), 1.0, atol=1e-14)
    np.testing.assert_allclose(jnp.sum(gradients, axis=(2, 3)), 0.0, atol=1e-12)
    # sum N_I x_I = x_p and sum x_I (x) grad N_I = I: linear fields are reproduced exactly
    np.testing.assert_allclose(jnp.sum(stencil.weights * offsets, axis=(2, 3)), 0.0, atol=1e-14)
    identity = jnp.einsum("inab,jnab->nij", offsets, gradients)
    np.testing.assert_allclose(identity, np.broadcast_to(np.eye(2), identity.shape), atol=1e-12)


@pytest.mark.parametrize("shape", SHAPES)
def test_gradients_are_the_derivatives_of_the_weights(shape):
    layout = GridLayout((0.0, 0.0), 0.1, (10, 8), shape, 2)
    points = random_points(200, (1.0, 0.8), seed=1)[8:]       # away from the kinks of the edges

    def weights(x):           # the stencil of one point, its base node held fixed
        stencil = layout.stencil(x[None])
        assert stencil.base.shape == (1, 2)
        return stencil.weights[0]

    checked = points[:40]
    jacobians = jax.jit(jax.vmap(jax.jacfwd(weights)))(checked)           # (40, s, s, 2), point by point
    stencil = layout.stencil(checked)
    np.testing.assert_allclose(jnp.stack(stencil.gradients, axis=-1), jacobians, atol=1e-12)



@pytest.mark.parametrize("shape", SHAPES)
def test_the_stencil_arithmetic_captures_no_array_constant(shape):
    # An array the step closes over becomes an operand of the loops around it, which XLA:CPU
    # does not fold back into a constant inside nested loops: with the grid's origin and sizes
    # captured as arrays, the segmented rollout's stencil kernels ran 2x slower
    # (docs/benchmarks.md, 2026-12-03). Every grid constant here must be a Python scalar.
    layout = GridLayout((0.2, -0.1), 0.1, (10, 8), shape, 2)
    points = random_points(50, (1.0, 0.8)) + jnp.asarray([0.2, -0.1])

    def stencil_work(x):
        stencil = layout.stencil(x)
        return stencil, layout.node_offsets(stencil.base, x, stencil.weights.shape[1]), layout.outside(x)

    closed = jax.make_jaxpr(stencil_work)(points)
    assert [np.shape(const) for const in closed.consts] == []


def test_stack_last_is_the_stack_along_a_new_last_axis_in_value_and_derivatives():
    # stack_last builds jnp.stack(values, axis=-1) another way (a leading-axis stack moved to
    # the end, which XLA:CPU lays out entry-major: docs/benchmarks.md, 2026-12-03); the stencil,
    # the transfers and the velocity gradient rely on it being exactly that array.
    from jaxmpm.tensors import from_entries, stack_last

    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    values = [jax.random.normal(key, (7, 3, 3)) for key in keys]
    tangents = [2.0 * value + 1.0 for value in values]
    weights = jax.random.normal(jax.random.PRNGKey(4), (7, 3, 3, 3))

    def plain(*parts):
        return jnp.stack(parts, axis=-1)

    assert stack_last(values).shape == (7, 3, 3, 3)
    np.testing.assert_array_equal(stack_last(values), plain(*values))
    np.testing.assert_array_equal(jax.jvp(lambda *v: stack_last(list(v)), values, tangents)[1],
                                  jax.jvp(plain, values, tangents)[1])
    ours = jax.grad(lambda *v: jnp.sum(weights * stack_last(list(v))), argnums=(0, 1, 2))(*values)
    theirs = jax.grad(lambda *v: jnp.sum(weights * plain(*v)), argnums=(0, 1, 2))(*values)
    for a, b in zip(ours, theirs):
        np.testing.assert_array_equal(a, b)
    entries = [value[:, 0, 0] for value in values] * 3
    np.testing.assert_array_equal(from_entries(entries), jnp.stack(entries, axis=-1).reshape(7, 3, 3))


def tent(r):
    return np.maximum(1.0 - np.abs(r), 0.0)


def cell_average_of_tent(r, half_width):
    """(1 / 2l) * integral of the tent over [r - l, r + l] (trapezoid rule, 20 001 nodes)."""
    s = np.linspace(r - half_width, r + half_width, 20_001)
    return np.trapezoid(tent(s), s) / (2.0 * half_width)


@pytest.mark.parametrize("shape, half_width", [(UniformGIMP(0.25), 0.25), (UniformGIMP(1 / 6), 1 / 6),
                                                (UniformGIMP(0.5), 0.5), (QuadraticBSpline(), 0.5)])
def test_1d_functions_are_the_tent_averaged_over_the_point_cell(shape, half_width):
    offsets = np.linspace(0.5, 1.5, 41, endpoint=False)        # point minus base node, in cells
    values, slopes = shape.along(jnp.asarray(offsets))
    for k in range(3):        # node k of the stencil sits at distance offset - k from the point
        expected = [cell_average_of_tent(offset - k, half_width) for offset in offsets]
        np.testing.assert_allclose(values[:, k], expected, atol=1e-8)
        # d/dr of the average is (tent(r + l) - tent(r - l)) / (2 l)
        r = offsets - k
        np.testing.assert_allclose(slopes[:, k], (tent(r + half_width) - tent(r - half_width)) / (2 * half_width), atol=1e-12)


def shaped_bar(cells, shape, duration, output_every):
    scene = bar_scene(cells, duration, output_every)
    return dataclasses.replace(scene, numerics=dataclasses.replace(scene.numerics, shape=shape))


def bar_errors(cells, shape, v0):
    """(history error / amplitude, period error, dt) of the bar's centre of mass over two periods."""
    sim = jaxmpm.Simulation(shaped_bar(cells, shape, 2.0 * BAR_PERIOD, 2.0 * BAR_PERIOD))
    t, u = sim.time, np.asarray(sim.probes(initial=first_mode_state(sim, v0))["centre_of_mass"][:, 0])
    amplitude = 2.0 * v0 / (math.pi * BAR_OMEGA)
    return np.max(np.abs(u - amplitude * np.sin(BAR_OMEGA * t))) / amplitude, fitted_period(t, u) / BAR_PERIOD - 1.0, sim.dt


def bspline_dispersion(cells, dt):
    """Leading-order period error for quadratic B-splines, derived as `bar_dispersion` is: the
    consistent B-spline mass, (66 + 52 cos kh + 2 cos 2kh) / 120 h = h (1 - (kh)^2 / 4 + ...),
    is lumped to h, which lowers the frequency by (kh)^2 / 8 (the B-spline stiffness itself is
    O(kh)^4 accurate); the MUSL re-projection (eigenvalue 1 - (kh)^2 / 4) lowers it by another
    (kh)^2 / 8; the time step raises it by (omega dt)^2 / 24."""
    kh = math.pi / (2.0 * BAR_LENGTH) * (BAR_LENGTH / cells)
    return kh**2 / 4.0 - (BAR_OMEGA * dt) ** 2 / 24.0


@pytest.mark.parametrize("shape", ["gimp", "bspline2"])
def test_bar_small_motion_converges_at_second_order(shape):
    """v0 = 1e-3 (no cell crossing), 10, 20, 40 cells (80 measured too), fixed end through mirrored ghosts.
    Measured: gimp history errors 3.99e-2 ... 6.33e-4, period 3.14e-3 ... 5.51e-5 (like linear,
    whose 1-D function it equals away from cell edges for ppc = 2); bspline2 history errors
    7.79e-2, 1.96e-2, 4.93e-3, 1.23e-3, period 6.18e-3, 1.55e-3, 3.95e-4, 1.03e-4 (the estimate
    6.00e-3 ... 9.38e-5). Zeroing the ghost nodes instead of mirroring them, or not folding the
    ghosts' mass back, made bspline2 first order (period error 3.7e-2 at 10 cells)."""
    cell_counts = [10, 20, 40]
    history, period = [], []
    for cells in cell_counts:
        history_error, period_error, dt = bar_errors(cells, shape, 1e-3)
        estimate = bspline_dispersion(cells, dt) if shape == "bspline2" else bar_dispersion(cells, dt)
        assert 0.0 < period_error <= 1.3 * estimate
        history.append(history_error)
        period.append(period_error)
    sizes = BAR_LENGTH / np.asarray(cell_counts)
    assert 1.8 <= loglog_slope(sizes, history) <= 2.2, history
    assert 1.8 <= loglog_slope(sizes, period) <= 2.2, period


def test_smooth_shapes_keep_a_bar_accurate_where_points_cross_cells():
    """v0 = 0.1 at 80 cells: the tip moves 0.16 m, half a cell, so points cross cell edges.
    Linear shape functions then lose the solution (measured: 22.6 % history error); uGIMP and
    B-splines stay under 1 % (measured 0.60 % and 0.63 %, the size of the finite-strain
    effects the linear analytical solution leaves out at 1 % strain)."""
    errors = {shape: bar_errors(80, shape, 0.1)[0] for shape in SHAPES}
    assert errors["linear"] > 0.1
    assert errors["gimp"] < 0.01 and errors["bspline2"] < 0.01


def column_errors(poisson, cell, shape):
    """(max pointwise sigma_yy error / rho g H, relative settlement error, max |v|, lateral
    ratio error / rho g H) of the settled confined column (examples/elastic_column.toml, the
    CB-Geo benchmark of docs/validation.md §2), with the exact sigma_yy = -rho g (H - y)."""
    from tests.test_elastic_validation import (
        COLUMN_HEIGHT, COLUMN_RHO, COLUMN_YOUNG, GRAVITY, constrained_modulus, settled_confined_column,
    )

    positions, stress, velocity, settlement, top = settled_confined_column(poisson, cell, shape)
    rho_g = COLUMN_RHO * GRAVITY
    base = rho_g * COLUMN_HEIGHT
    exact = -rho_g * (COLUMN_HEIGHT - positions[:, 1])
    settled = rho_g / constrained_modulus(COLUMN_YOUNG, poisson) * (COLUMN_HEIGHT * top[1] - top[1] ** 2 / 2.0)
    ratio = poisson / (1.0 - poisson)
    return (
        np.max(np.abs(stress[:, 1, 1] - exact)) / base,
        -settlement / settled - 1.0,
        np.max(np.abs(velocity)),
        np.max(np.abs(stress[:, 0, 0] - ratio * stress[:, 1, 1])) / base,
        cell / (4.0 * COLUMN_HEIGHT),          # rho g h / 4 over rho g H: linear MPM's point error
    )


# bspline2, the default, settles the column in
# test_elastic_validation.py::test_default_numerics_settle_the_confined_column_to_the_exact_stress.
@pytest.mark.parametrize("shape", ["gimp"])
def test_confined_column_settles_to_the_geostatic_stress(shape):
    """nu = 0.3 at h = 0.01 and 0.005, fixed base and slip sides through mirrored ghost nodes.
    Measured (h = 0.01 | 0.005): bspline2 point error 0.0139 | 0.0069 rho g H (half of linear's
    rho g h / 4 = 0.025 | 0.0125: first order, smooth), settlement error 0.07 % | -0.01 %;
    gimp 0.0252 | 0.0127 (as linear), settlement -0.22 % | -0.09 %. Lateral stress
    sigma_xx = nu / (1 - nu) sigma_yy to 1e-6 rho g H or better in all four runs."""
    errors = [column_errors(0.3, cell, shape) for cell in (0.01, 0.005)]
    for point, settlement, velocity, lateral, linear_bound in errors:
        assert velocity < 1e-5                                  # at rest
        assert point <= linear_bound + 5e-3                     # the bound linear MPM meets
        assert abs(settlement) < 5e-3
        assert lateral < 1e-5
    assert 1.8 <= errors[0][0] / errors[1][0] <= 2.2            # first order in h
    if shape == "bspline2":
        assert errors[0][0] < 0.6 * errors[0][4] and errors[1][0] < 0.6 * errors[1][4]
