"""Drucker-Prager sand at one material point, against closed-form answers.

docs/validation.md §0, §3 and §8. The model (Wieckowski, eq. 2 and its
Perzyna variant): f = q - m p, g = q, non-cohesive; tension positive, p = -tr(sigma)/3,
q = sqrt(3/2 s:s). Every expected number is re-derived in a comment next to its test.

Strain-controlled paths go through `jaxmpm.drive`. Where a stress must be held (the cell
pressure of a drained test), `lateral_stress_control` below calls the material's `update` and
solves each step for the lateral strain rate by Newton's method. Compiling dominates the run
time here, so each helper is jitted once per dtype and shape and vmapped over parameter sets
(the rate-independent mixed-control runs over the four cones as well).

Tolerances are a stated number of round-off units (ULPS * eps of the dtype) unless a derived
truncation bound applies; the bound is then computed in the test.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm
from jaxmpm import SceneError
from jaxmpm.materials import DruckerPrager, LinearElastic, material_parameters

DENSITY = 2000.0        # kg/m^3 (not used by a point update, but the table needs it)
YOUNG = 1.0e8           # Pa
SIGMA_C = 1.0e5         # Pa: cell pressure, or initial mean pressure
ULPS = 64               # round-off allowance in units of the dtype's eps
FRICTION_ANGLES = (20.0, 30.0, 40.0)
POISSON_RATIOS = (0.2, 0.3, 0.45)
DTYPES = (jnp.float32, jnp.float64)
DTYPE_IDS = ("float32", "float64")
WEIGHTS = np.array([[1.0, 0.3, 0.1], [0.3, -0.7, 0.2], [0.1, 0.2, 0.5]])


def round_off(dtype):
    return ULPS * float(jnp.finfo(dtype).eps)


def assert_close(actual, desired, rtol=0.0, atol=0.0, err_msg=""):
    """np.testing.assert_allclose with `desired` broadcast to the shape of `actual`."""
    actual = np.asarray(actual, np.float64)
    desired = np.broadcast_to(np.asarray(desired, np.float64), actual.shape)
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=atol, err_msg=err_msg)


def cone_slope(cone, friction_angle):
    """m(phi), written out independently of the package (docs/validation.md §0)."""
    s = np.sin(np.deg2rad(friction_angle))
    return {
        "paper": 18.0 * s / (9.0 - s * s),
        "compression": 6.0 * s / (3.0 - s),
        "extension": 6.0 * s / (3.0 + s),
        "plane_strain": np.sqrt(3.0) * s,
    }[cone]


def invariants(stress):
    """(p, q) in float64 of a (..., 3, 3) stress, tension positive."""
    stress = np.asarray(stress, np.float64)
    pressure = -np.trace(stress, axis1=-2, axis2=-1) / 3.0
    deviator = stress + pressure[..., None, None] * np.eye(3)
    return pressure, np.sqrt(1.5 * np.sum(deviator * deviator, axis=(-2, -1)))


def grid(*axes):
    """The flattened Cartesian product of parameter axes."""
    return [axis.ravel() for axis in np.meshgrid(*map(np.asarray, axes), indexing="ij")]


def parameter_batch(dtype, viscoplastic=False, **values):
    """Material parameters as a dict of (B,) arrays, broadcast from scalars or arrays."""
    table = dict(density=DENSITY, young=YOUNG, poisson=0.3, friction_angle=30.0, dilation_angle=0.0)
    if viscoplastic:
        table.update(fluidity=0.1, exponent=2.0)
    table.update(values)
    arrays = np.broadcast_arrays(*(np.asarray(value, np.float64) for value in table.values()))
    return {name: jnp.asarray(array.ravel(), dtype) for name, array in zip(table, arrays)}


def template(cone="paper", viscoplastic=False):
    """A material object for its static choices; physical values come from `params`."""
    return DruckerPrager(
        density=DENSITY, young=YOUNG, poisson=0.3, friction_angle=30.0, cone=cone,
        fluidity=0.1 if viscoplastic else None, exponent=2.0 if viscoplastic else 1.0,
    )


def set_diagonal(tensors, diagonal):
    """Write diagonal (..., 3) into the diagonals of tensors (..., 3, 3), in place."""
    for i in range(3):
        tensors[..., i, i] = diagonal[..., i]


def hydrostatic(count, pressure, dtype):
    """(count, 3, 3) copies of -pressure I."""
    return jnp.asarray(np.broadcast_to(-pressure * np.eye(3), (count, 3, 3)), dtype)


@functools.partial(jax.jit, static_argnames="cone")
def drive_points(params, velocity_gradient, dt, stress0, cone="paper"):
    """jaxmpm.drive vmapped over parameter sets: (B,) params, (B, T, 3, 3) L, (B,) dt."""

    def one(params, velocity_gradient, dt, stress0):
        return jaxmpm.drive(dict(model="drucker_prager", cone=cone, **params), velocity_gradient, dt, stress0)

    return jax.vmap(one)(params, velocity_gradient, dt, stress0)


@jax.jit
def drive_elastic(params, velocity_gradient, dt, stress0):
    """The linear_elastic model with the same E, nu, vmapped like `drive_points`."""

    def one(params, velocity_gradient, dt, stress0):
        table = dict(model="linear_elastic", density=params["density"], young=params["young"],
                     poisson=params["poisson"])
        return jaxmpm.drive(table, velocity_gradient, dt, stress0)

    return jax.vmap(one)(params, velocity_gradient, dt, stress0)


def weighted_mean(history):
    """A scalar read-out of a whole stress history: mean_t sum_ij W_ij sigma_ij / sigma_c."""
    return jnp.mean(jnp.sum(jnp.asarray(WEIGHTS, history.dtype) * history, axis=(-2, -1))) / SIGMA_C


@jax.jit
def drive_gradients(params, velocity_gradient, dt, stress0):
    """d weighted_mean(drive(...)) / d params by reverse mode, vmapped like `drive_points`."""

    def one(params, velocity_gradient, dt, stress0):
        def read_out(params):
            table = dict(model="drucker_prager", **params)
            return weighted_mean(jaxmpm.drive(table, velocity_gradient, dt, stress0))

        return jax.grad(read_out)(params)

    return jax.vmap(one)(params, velocity_gradient, dt, stress0)


# ---------------------------------------------------------------------------------------------
# Mixed stress/strain control
# ---------------------------------------------------------------------------------------------

CONES = ("paper", "compression", "extension", "plane_strain")
NEWTON_STEPS = 8


class EveryCone:
    """The rate-independent Drucker-Prager update with the cone CONES[params["cone"]]: one
    compiled mixed-control run then serves every cone (under vmap all four updates are
    evaluated and one is selected, which costs far less than compiling each)."""

    materials = tuple(template(cone) for cone in CONES)

    def init_state(self, count, dtype):
        return self.materials[0].init_state(count, dtype)

    def update(self, params, stress, velocity_gradient, dt, state):
        values = {name: value for name, value in params.items() if name != "cone"}
        updates = [functools.partial(material.update, values) for material in self.materials]
        return jax.lax.switch(params["cone"], updates, stress, velocity_gradient, dt, state)


EVERY_CONE = EveryCone()


@functools.partial(jax.jit, static_argnames=("material", "steps"))
def lateral_stress_control(material, params, axial, lateral, dt, sigma_c, steps):
    """Mixed control: sigma_xx held at -sigma_c while the rest of L is prescribed.

    Each step L = axial + x lateral: `axial` (B, 3, 3) is the prescribed part, `lateral`
    (B, 3, 3) a 0/1 diagonal mask of the stress-controlled directions (x always; x and z for a
    triaxial test, x only for plane strain with d_zz = 0), and x [1/s] is found by Newton's
    method (NEWTON_STEPS iterations warm-started from the previous step: the lateral stress is
    monotone in x, piecewise linear for the rate-independent model, so a few iterations reach
    round-off; the tests check sigma_xx afterwards). dt (B,) [s]. The point starts at
    -sigma_c I. Returns the stress history (B, steps + 1, 3, 3), the rates x (B, steps) and the
    accumulated plastic strain (B, steps).
    """

    def one(params, axial, lateral, dt):
        dtype = axial.dtype
        stress = -sigma_c * jnp.eye(3, dtype=dtype)
        state = jax.tree_util.tree_map(lambda h: h[0], material.init_state(1, dtype))

        def one_step(carry, _):
            stress, state, rate = carry

            def lateral_residual(x):
                new, _ = material.update(params, stress, axial + x * lateral, dt, state)
                return new[0, 0] + sigma_c

            def newton(_, x):
                residual, slope = jax.jvp(lateral_residual, (x,), (jnp.ones_like(x),))
                return x - residual / jnp.where(slope > 0.0, slope, 1.0)

            rate = jax.lax.fori_loop(0, NEWTON_STEPS, newton, rate)
            stress, state = material.update(params, stress, axial + rate * lateral, dt, state)
            return (stress, state, rate), (stress, rate, state["plastic_strain"])

        guess = -params["poisson"] * axial[1, 1]
        _, (history, rates, plastic) = jax.lax.scan(one_step, (stress, state, guess), None, length=steps)
        return jnp.concatenate([stress[None], history]), rates, plastic

    return jax.vmap(one)(params, axial, lateral, dt)


MIXED_STEPS = 400
TRIAXIAL_STRAIN_STEP = 1.0e-4   # axial strain per step, triaxial (dt = 1 s)
BIAXIAL_STRAIN_STEP = 1.0e-3    # axial strain per step, plane strain (converges slowly)
LOADINGS = ("triaxial_compression", "triaxial_extension", "plane_strain_compression", "perzyna_triaxial")
STEADY_DT = 0.1                 # s, the Perzyna triaxial run; its steady state does not depend on dt
STEADY_STEPS = 100
FLUIDITY = 0.1                  # 1/s
AXIAL_RATE = 0.01               # 1/s


@functools.lru_cache
def mixed_runs(dtype):
    """All mixed-control runs of one dtype, axial direction y, as two tables of rows:

    - rate-independent, each cone x phi x nu x {triaxial compression, triaxial extension,
      plane-strain compression}, MIXED_STEPS steps of dt = 1 s (rates = strain increments);
    - viscoplastic (paper cone) drained triaxial compression at AXIAL_RATE, phi x nu x N,
      STEADY_STEPS steps of STEADY_DT.
    Triaxial: the cell pressure acts on x and z; plane strain: on x only, with d_zz = 0.
    """
    cone, phi, nu, loading = grid(np.arange(len(CONES)), FRICTION_ANGLES, POISSON_RATIOS, range(3))
    step = np.choose(loading, [-TRIAXIAL_STRAIN_STEP, TRIAXIAL_STRAIN_STEP, -BIAXIAL_STRAIN_STEP])
    params = parameter_batch(dtype, friction_angle=phi, poisson=nu)
    assert set(params) == set(material_parameters(template()))
    params["cone"] = jnp.asarray(cone, jnp.int32)
    plastic_run = run_mixed(EVERY_CONE, params, step, np.ones_like(step), loading == 2, dtype, MIXED_STEPS)
    plastic_run.update(cone=np.asarray(CONES)[cone], loading=loading, phi=phi, nu=nu,
                       exponent=np.full_like(phi, np.nan))

    phi, nu, exponent = grid(FRICTION_ANGLES, POISSON_RATIOS, (1.0, 2.0))
    params = parameter_batch(dtype, True, friction_angle=phi, poisson=nu, fluidity=FLUIDITY, exponent=exponent)
    assert set(params) == set(material_parameters(template(viscoplastic=True)))
    step = np.full(phi.size, -AXIAL_RATE * STEADY_DT)
    viscous_run = run_mixed(template(viscoplastic=True), params, step, np.full_like(step, STEADY_DT),
                            np.zeros(phi.size, bool), dtype, STEADY_STEPS)
    viscous_run.update(cone=np.full(phi.size, "paper"), loading=np.full(phi.size, 3), phi=phi, nu=nu,
                       exponent=exponent)
    for run in (plastic_run, viscous_run):
        run["m"] = np.array([cone_slope(c, f) for c, f in zip(run["cone"], run["phi"])])
    return {"rate_independent": plastic_run, "viscoplastic": viscous_run}


def run_mixed(material, params, step, dt, plane_strain, dtype, steps):
    """`lateral_stress_control` with axial strain increments `step` (B,) per time step dt (B,)."""
    axial = np.zeros((step.size, 3, 3))
    axial[:, 1, 1] = step / dt
    lateral = np.zeros((step.size, 3, 3))
    lateral[:, 0, 0] = 1.0
    lateral[:, 2, 2] = np.where(plane_strain, 0.0, 1.0)
    history, rates, plastic = lateral_stress_control(
        material, params, jnp.asarray(axial, dtype), jnp.asarray(lateral, dtype), jnp.asarray(dt, dtype),
        jnp.asarray(SIGMA_C, dtype), steps,
    )
    return dict(step=step, stress=np.asarray(history, np.float64),
                rates=np.asarray(rates, np.float64) * dt[:, None], plastic=np.asarray(plastic, np.float64))


def select(run, **where):
    """The rows of a mixed run matching every `column=value`."""
    chosen = np.ones(run["phi"].size, bool)
    for column, value in where.items():
        chosen &= run[column] == (LOADINGS.index(value) if column == "loading" else value)
    return {name: column[chosen] for name, column in run.items()}


# ---------------------------------------------------------------------------------------------
# 1, 2. Drained triaxial compression / extension, plane-strain biaxial compression
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("cone", CONES)
@pytest.mark.parametrize("loading", LOADINGS[:2])
def test_drained_triaxial_peak_yield_strain_and_no_dilation(loading, cone, dtype):
    # Drained triaxial test at cell pressure sigma_c (compression magnitudes in this comment):
    # sigma_r = sigma_c held, q = |sigma_a - sigma_r|.
    # Elastic: with d sigma_r = 0, Hooke gives d sigma_a = E d eps_a exactly (d eps_r =
    #   -nu d eps_a), so q = E |eps_a| until yield: yield at |eps_a| = q_peak / E.
    # Compression: p = sigma_c + q/3 and q = m p give q_peak = 3 m sigma_c / (3 - m),
    #   p = 3 sigma_c / (3 - m), sigma_1/sigma_3 = (sigma_c + q)/sigma_c = (3 + 2m)/(3 - m).
    #   phi = 30, paper cone: m = 9/8.75 = 1.028571 -> q = 156.52 kPa, p = 152.17 kPa.
    #   Compression cone m = 6 s/(3 - s): (3 + 2m)/(3 - m) = (1 + s)/(1 - s), Mohr-Coulomb.
    # Extension (axial unloading): p = sigma_c - q/3 gives q_peak = 3 m sigma_c / (3 + m),
    #   sigma_r/sigma_a = sigma_c/(sigma_c - q) = (3 + m)/(3 - 2m); extension cone
    #   m = 6 s/(3 + s): (1 + s)/(1 - s) again (for m > 3/2, sigma_a ends in tension, p > 0).
    # After yield, g = q: the flow is deviatoric and p, q are constant, so no elastic strain
    #   either: d eps_v = d eps_a + 2 d eps_r = 0. The flow direction dq/dsigma = 3s/(2q) is
    #   diag(1/2, -1, 1/2) (compression), whose equivalent strain sqrt(2/3 e:e) is 1: the
    #   accumulated plastic strain ends at |eps_a| - q_peak / E.
    run = select(mixed_runs(dtype)["rate_independent"], cone=cone, loading=loading)
    tol = round_off(dtype)
    m, nu, step = run["m"], run["nu"], run["step"][0]
    stress, rates, plastic = run["stress"], run["rates"], run["plastic"]
    assert stress.shape[1] == MIXED_STEPS + 1
    sign = 1.0 if loading == "triaxial_compression" else -1.0

    q_peak = 3.0 * m * SIGMA_C / (3.0 - sign * m)
    p_peak = 3.0 * SIGMA_C / (3.0 - sign * m)
    pressure, deviatoric = invariants(stress)
    assert_close(stress[:, :, 0, 0], -SIGMA_C, rtol=tol)    # the helper did hold sigma_r
    assert_close(stress[:, :, 2, 2], -SIGMA_C, rtol=tol)
    axial_strain = np.abs(step) * np.arange(MIXED_STEPS + 1)
    expected_q = np.minimum(YOUNG * axial_strain, q_peak[:, None])
    assert_close(deviatoric / q_peak[:, None], expected_q / q_peak[:, None], atol=tol)
    assert_close(deviatoric[:, -1], q_peak, rtol=tol)
    assert_close(pressure[:, -1], p_peak, rtol=tol)
    if sign > 0:
        ratio, expected_ratio = stress[:, -1, 1, 1] / stress[:, -1, 0, 0], (3 + 2 * m) / (3 - m)
    else:
        ratio, expected_ratio = stress[:, -1, 0, 0] / stress[:, -1, 1, 1], (3 + m) / (3 - 2 * m)
    assert_close(ratio, expected_ratio, rtol=tol)
    sine = np.sin(np.deg2rad(run["phi"]))
    if (cone, loading) in {("compression", "triaxial_compression"), ("extension", "triaxial_extension")}:
        assert_close(ratio, (1 + sine) / (1 - sine), rtol=tol)
    if cone == "paper" and loading == "triaxial_compression":
        at_30 = run["phi"] == 30.0
        assert_close(deviatoric[at_30, -1], 156.52e3, atol=0.005e3)
        assert_close(pressure[at_30, -1], 152.17e3, atol=0.005e3)

    # Lateral strain increment: -nu d eps_a before yield, -d eps_a / 2 after it. It is only as
    # exact as sigma_r: a stress error tol sigma_c is a strain error below tol sigma_c / E.
    yield_step = np.ceil(q_peak / (YOUNG * np.abs(step))).astype(int)     # the step that yields
    steps = np.arange(1, MIXED_STEPS + 1)
    rate_tol = tol * (1.0 + SIGMA_C / (YOUNG * np.abs(step)))
    elastic = steps[None, :] < yield_step[:, None]
    flowing = steps[None, :] > yield_step[:, None]
    assert_close((rates / step)[elastic], np.broadcast_to(-nu[:, None], rates.shape)[elastic], atol=rate_tol)
    assert_close(((step + 2 * rates) / step)[flowing], 0.0, atol=rate_tol)
    assert np.all(plastic[elastic] == 0.0)
    assert_close(plastic[:, -1], axial_strain[-1] - q_peak / YOUNG, atol=rate_tol * axial_strain[-1])


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("cone", ["paper", "plane_strain"])
def test_plane_strain_biaxial_stress_ratio(cone, dtype):
    # docs/validation.md §0 / §3: in plane strain (d_zz = 0) with g = q the plastic strain rate has
    # e^p_zz ~ s_zz, and d_zz = 0 makes the elastic strain absorb it until s_zz = 0, i.e.
    # sigma_zz = (sigma_1 + sigma_3)/2 (an exponential approach in the plastic strain, at a rate
    # ~ G/q per unit strain: hence 400 steps of 1e-3 at E/sigma_c = 1000). Then
    # s_1 = -s_3 = (sigma_1 - sigma_3)/2, q = sqrt(3)(sigma_1 - sigma_3)/2, p = (sigma_1 + sigma_3)/2,
    # and q = m p gives sigma_1/sigma_3 = (1 + m/sqrt3)/(1 - m/sqrt3): 3.924 at phi = 30 (paper
    # cone, sin phi_eq = m/sqrt3); the plane_strain cone m = sqrt3 sin phi gives Mohr-Coulomb's
    # (1 + sin phi)/(1 - sin phi).
    run = select(mixed_runs(dtype)["rate_independent"], cone=cone, loading="plane_strain_compression")
    tol = round_off(dtype)
    m, stress = run["m"], run["stress"]
    final = stress[:, -1]
    ratio = final[:, 1, 1] / final[:, 0, 0]
    assert_close(ratio, (1 + m / np.sqrt(3)) / (1 - m / np.sqrt(3)), rtol=tol)
    assert_close(final[:, 2, 2], (final[:, 0, 0] + final[:, 1, 1]) / 2, rtol=tol)
    assert_close(final[:, 0, 0], -SIGMA_C, rtol=tol)
    if cone == "plane_strain":
        sine = np.sin(np.deg2rad(run["phi"]))
        assert_close(ratio, (1 + sine) / (1 - sine), rtol=tol)
    else:
        assert_close(ratio[run["phi"] == 30.0], 3.924, atol=5e-4)
    # Never past the cone, and on it at the end.
    pressure, deviatoric = invariants(stress)
    assert np.all(deviatoric <= m[:, None] * pressure * (1 + tol))
    assert_close(deviatoric[:, -1], m * pressure[:, -1], rtol=tol)


# ---------------------------------------------------------------------------------------------
# 3, 4. Perzyna: steady overstress and relaxation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_perzyna_steady_overstress_at_constant_pressure(dtype):
    # Isochoric axisymmetric compression L = diag(r/2, -r, r/2) from -p0 I: tr d = 0 and g = q
    # keep p = p0. Steady state: q constant, so the deviatoric strain rate is all viscoplastic,
    # e^vp = gamma Phi dq/dsigma = gamma Phi (3/2) s/q, whose equivalent rate
    # sqrt(2/3 e^vp:e^vp) = gamma Phi. The applied equivalent rate is sqrt(2/3 e:e) = r
    # (e:e = (1/4 + 1 + 1/4) r^2). Hence Phi = r/gamma: (q - m p)/(m p) = (r/gamma)^(1/N).
    # Backward Euler has the same fixed point (dl = r dt = gamma dt Phi(q_ss)) for every dt.
    phi, nu, exponent = grid(FRICTION_ANGLES, POISSON_RATIOS, (1.0, 2.0, 5.0))
    steps = 100
    params = parameter_batch(dtype, True, friction_angle=phi, poisson=nu, fluidity=FLUIDITY, exponent=exponent)
    rate = np.zeros((phi.size, steps, 3, 3))
    set_diagonal(rate, np.array([AXIAL_RATE / 2, -AXIAL_RATE, AXIAL_RATE / 2]))
    history = drive_points(params, jnp.asarray(rate, dtype), jnp.full(phi.size, STEADY_DT, dtype),
                           hydrostatic(phi.size, SIGMA_C, dtype))
    pressure, deviatoric = invariants(history)
    m = cone_slope("paper", phi)
    expected = m * SIGMA_C * (1.0 + (AXIAL_RATE / FLUIDITY) ** (1.0 / exponent))
    tol = round_off(dtype)
    assert_close(pressure, SIGMA_C, rtol=tol)
    assert_close(deviatoric[:, -1], expected, rtol=tol)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_perzyna_steady_state_in_drained_triaxial(dtype):
    # Drained triaxial at constant sigma_c and axial rate r (docs/validation.md §3). Steady state: all
    # stresses constant, so all strain rates are viscoplastic and (g = q) isochoric: lateral
    # rates -r/2 and, exactly as above, an equivalent deviatoric rate r, so
    # (q - m p)/(m p) = rho = (r/gamma)^(1/N). With p = sigma_c + q/3:
    # q = m (1 + rho)(sigma_c + q/3), i.e. q_ss = m sigma_c (1 + rho) / (1 - m (1 + rho)/3).
    # phi = 30, gamma = 0.1/s, N = 2, r = 0.01/s: rho = 0.31623, m (1 + rho) = 1.35384,
    # q_ss = 135.384 kPa / 0.54872 = 246.73 kPa.
    run = select(mixed_runs(dtype)["viscoplastic"], loading="perzyna_triaxial")
    stress, rates, m = run["stress"], run["rates"], run["m"]
    rho = (AXIAL_RATE / FLUIDITY) ** (1.0 / run["exponent"])
    expected = m * SIGMA_C * (1.0 + rho) / (1.0 - m * (1.0 + rho) / 3.0)
    pressure, deviatoric = invariants(stress)
    tol = round_off(dtype)
    assert_close(stress[:, :, 0, 0], -SIGMA_C, rtol=tol)
    assert_close(deviatoric[:, -1], expected, rtol=tol)
    assert_close(pressure[:, -1], SIGMA_C + expected / 3.0, rtol=tol)
    reference = (run["phi"] == 30.0) & (run["exponent"] == 2.0)
    assert_close(deviatoric[reference, -1], 246.7e3, atol=0.05e3)
    # Isochoric in the steady state: lateral increment -r dt/2 (as exact as sigma_r).
    step = AXIAL_RATE * STEADY_DT
    assert_close(rates[:, -1] / step, 0.5, atol=tol * (1.0 + SIGMA_C / (YOUNG * step)))


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_perzyna_relaxation_with_strain_held(dtype):
    # N = 1, L = 0 after one isochoric loading step past yield. With L = 0 the trial is the old
    # stress and the return (g = q) is at fixed p: q_dot = -3G gamma (q - m p)/(m p), so the
    # overstress q - m p decays as exp(-3 G gamma t/(m p)).
    # Backward Euler: (q_{n+1} - m p)(1 + a) = q_n - m p with a = 3 G gamma dt/(m p): a factor
    # 1/(1 + a) per step, exactly. Its distance to the exponential after n steps is
    # e^{-n a}(e^{n a^2/2 + O(n a^3)} - 1) of the overstress (log(1 + a) = a - a^2/2 + ...).
    phi, nu = grid(FRICTION_ANGLES, POISSON_RATIOS)
    m = cone_slope("paper", phi)
    shear = YOUNG / (2.0 * (1.0 + nu))
    a, hold_steps = 1.0e-3, 2000
    dt = a * m * SIGMA_C / (3.0 * shear * FLUIDITY)
    params = parameter_batch(dtype, True, friction_angle=phi, poisson=nu, fluidity=FLUIDITY, exponent=1.0)
    # Loading step e = diag(-k/2, k, -k/2): the elastic trial q* = 3 G k = 3 m p.
    strain = m * SIGMA_C / shear
    path = np.zeros((phi.size, hold_steps + 1, 3, 3))
    set_diagonal(path[:, 0], np.stack([-strain / 2, strain, -strain / 2], axis=1) / dt[:, None])
    history = drive_points(params, jnp.asarray(path, dtype), jnp.asarray(dt, dtype),
                           hydrostatic(phi.size, SIGMA_C, dtype))
    pressure, deviatoric = invariants(history)
    tol = round_off(dtype)
    assert_close(pressure, SIGMA_C, rtol=tol)
    overstress = deviatoric[:, 1:] - m[:, None] * SIGMA_C
    assert np.all(overstress > 0.0)
    # The discrete factor, step by step (local round-off only).
    assert_close((overstress[:, 1:] * (1.0 + a) - overstress[:, :-1]) / SIGMA_C, 0.0, atol=tol)
    # The exponential, within the derived time-discretisation bound plus the round-off carried
    # through the damped recursion (tol sigma_c per step, summed over at most 1/a steps).
    n = np.arange(hold_steps + 1)
    continuous = overstress[:, :1] * np.exp(-n * a)
    bound = np.exp(-n * a) * np.expm1(n * a * a / 2 * (1 + a)) * overstress[:, :1]
    carried = tol * SIGMA_C * np.minimum(n + 1, 1.0 / a + 1.0)
    error = np.abs(overstress - continuous)
    assert np.all(error <= bound + carried), (error / (bound + carried)).max()
    if dtype == jnp.float64:
        assert np.all(error[:, -1] > 0.5 * bound[:, -1])      # the O(dt) error is really there


# ---------------------------------------------------------------------------------------------
# 5. The limits gamma dt -> infinity (rate-independent) and gamma dt -> 0 (elastic)
# ---------------------------------------------------------------------------------------------

SHORT_STEPS = 20
SHORT_DT = 1.0e-3


def bisected_perzyna_fraction(overstress, hardening, pressure, dilation_rate, m, rate, exponent, steps=60):
    """Reference root x in [0, 1] of the module's Perzyna equation (log form in x), by
    bisection in float64 numpy: 60 halvings put it within 2^-60 of the root."""
    largest = overstress / hardening
    constant = np.log(largest) - np.log(rate) - exponent * np.log(overstress)
    low, high = np.zeros_like(overstress), np.ones_like(overstress)
    with np.errstate(divide="ignore"):
        for _ in range(steps):
            x = 0.5 * (low + high)
            value = np.log(x) - exponent * (np.log1p(-x) - np.log(m * (pressure + dilation_rate * largest * x))) + constant
            low, high = np.where(value > 0, low, x), np.where(value > 0, x, high)
    return 0.5 * (low + high)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_perzyna_newton_solve_matches_bisection_over_extremes(dtype):
    # 100,000 physically consistent trial states: E 1e4..1e10 Pa, nu 0..0.49, phi 1..60 deg,
    # psi 0..phi (half of them 0), p* 1e-3..1e7 Pa, overstress ratio f*/(m p*) 1e-8..1e3,
    # gamma dt 1e-10..1e10, N 0.1..10. The bracketed Newton solve must land on the
    # bisection's root: measured max |dx| 2.9e-15 in float64 after 6 of its 8 steps (1.5e-4 after
    # 3, 6.7e-8 after 4), 1.1e-6 in float32.
    from jaxmpm.materials.drucker_prager import perzyna_fraction
    rng = np.random.default_rng(7)
    n = 100_000
    young, poisson = 10 ** rng.uniform(4, 10, n), rng.uniform(0.0, 0.49, n)
    bulk, shear = young / (3 * (1 - 2 * poisson)), young / (2 * (1 + poisson))
    phi = np.radians(rng.uniform(1, 60, n))
    psi = phi * rng.uniform(0, 1, n) * (rng.uniform(size=n) < 0.5)
    m = 18 * np.sin(phi) / (9 - np.sin(phi) ** 2)
    dilation_rate = bulk * 18 * np.sin(psi) / (9 - np.sin(psi) ** 2)
    pressure = 10 ** rng.uniform(-3, 7, n)
    overstress = 10 ** rng.uniform(-8, 3, n) * m * pressure
    hardening = 3 * shear + m * dilation_rate
    rate, exponent = 10 ** rng.uniform(-10, 10, n), 10 ** rng.uniform(-1, 1, n)
    arguments = (overstress, hardening, pressure, dilation_rate, m, rate, exponent)
    expected = bisected_perzyna_fraction(*arguments)
    solved = np.asarray(jax.jit(jax.vmap(perzyna_fraction))(*(a.astype(dtype) for a in arguments)))
    assert np.all(np.isfinite(solved)) and np.all((solved >= 0) & (solved <= 1))
    # float32: rounding the inputs to 6e-8 relative moves the root by that times the
    # residual's sensitivity (N log of the inputs, up to ~10 log 1e10): 1e-5 covers it.
    assert np.max(np.abs(solved - expected)) < (1e-12 if dtype == "float64" else 1e-5)


def test_perzyna_fraction_at_its_root_skips_the_residual_but_keeps_its_derivatives():
    # Undifferentiated, x = sigmoid(t) at the solved root (no logarithm: the residual and its
    # slope are not evaluated); its first and second derivatives are those of the implicit
    # function expression sigmoid(t - (R - R) / R') with t and R' held.
    from jaxmpm.materials.drucker_prager import fraction_at_root, fraction_by_implicit_function, perzyna_root_of
    arguments = tuple(jnp.float64(v) for v in (2.0e3, 3.0e6, 1.0e4, 0.0, 1.2, 5e-4, 2.0))
    root = perzyna_root_of(*arguments)
    plain = jax.make_jaxpr(fraction_at_root)(root, *arguments).jaxpr
    assert not any(e.primitive.name in ("log", "log1p", "exp") for e in plain.eqns)

    def of_overstress(function, overstress):
        return function(root, overstress, *arguments[1:])

    for derivative in (jax.grad, lambda f: jax.grad(jax.grad(f))):
        np.testing.assert_allclose(derivative(functools.partial(of_overstress, fraction_at_root))(arguments[0]),
                                   derivative(functools.partial(of_overstress, fraction_by_implicit_function))(arguments[0]),
                                   rtol=1e-14)
    assert float(jax.grad(functools.partial(of_overstress, fraction_at_root))(arguments[0])) > 0.0


def test_perzyna_residual_and_slope_written_out_match_the_log_sigmoid_form():
    # The Newton steps use R(t) and dR/dt written with one exponential; they must be the
    # residual of perzyna_fraction, log sigmoid(t) - N log sigmoid(-t) + N log(m p(x)) + c,
    # and its derivative (JAX's jvp of that form), over t from -700 to 700 (the exponential's
    # float64 range), pressure growth from 0 to 1e8 times p*, and m down to 0 (the TINY clamp).
    from jaxmpm.materials.drucker_prager import TINY, perzyna_residual_and_slope
    rng = np.random.default_rng(11)
    n = 20_000
    t = np.concatenate([rng.uniform(-700, 700, n // 2), rng.normal(0, 3, n // 2)])
    t[:5] = [0.0, -0.0, 1e-300, -700.0, 700.0]
    pressure = 10 ** rng.uniform(-3, 7, n)
    growth = pressure * np.where(rng.uniform(size=n) < 0.3, 0.0, 10 ** rng.uniform(-8, 8, n))
    m = np.where(rng.uniform(size=n) < 0.05, 0.0, rng.uniform(0.01, 2.0, n))
    exponent, constant = 10 ** rng.uniform(-1, 1, n), rng.uniform(-50, 50, n)

    def log_sigmoid_form(t, pressure, growth, m, exponent, constant):
        p = pressure + growth * jax.nn.sigmoid(t)
        return (jax.nn.log_sigmoid(t) - exponent * jax.nn.log_sigmoid(-t)
                + exponent * jnp.log(jnp.maximum(m * p, TINY)) + constant)

    arguments = (t, pressure, growth, m, exponent, constant)
    value, slope = jax.jit(perzyna_residual_and_slope)(*arguments)
    expected, expected_slope = jax.jit(lambda *a: jax.jvp(lambda t: log_sigmoid_form(t, *a[1:]), (a[0],), (jnp.ones_like(a[0]),)))(*arguments)
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(slope)) and np.all(slope > 0.0)
    scale = 1.0 + np.abs(expected)
    assert np.max(np.abs(value - expected) / scale) < 1e-13
    np.testing.assert_allclose(slope, expected_slope, rtol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_viscoplastic_limits(dtype):
    # Backward Euler on one step: q = q* - 3G dl with dl = gamma dt Phi(q), so after every step
    #   (q - m p)/(m p) = (dl/(gamma dt))^(1/N)   and   dl <= f*/(3G).
    # Isochoric loading keeps p = p0, and f*/(3G) <= de (the equivalent strain increment
    # sqrt(2/3 e:e) dt) + (the previous overstress)/(3G). So
    # - gamma dt = 1e8: |q - q_rate_independent| / (m p) <= (2 de/(gamma dt))^(1/N);
    # - gamma dt = 1e-8: each step moves q by 3G dl = 3G gamma dt Phi(q), and q stays below
    #   the elastic q, so |sigma - sigma_elastic| <= sum_n 3G gamma dt Phi(q_elastic,n).
    phi, nu, exponent = grid(FRICTION_ANGLES, POISSON_RATIOS, (1.0, 2.0))
    m = cone_slope("paper", phi)
    shear = YOUNG / (2.0 * (1.0 + nu))
    strain_step = 0.5 * m * SIGMA_C / (3.0 * shear)     # yields after about two steps
    rate = np.zeros((phi.size, SHORT_STEPS, 3, 3))
    rate[..., 0, 1] = 2.0 * strain_step[:, None] / SHORT_DT      # simple shear (with spin)
    set_diagonal(rate, np.array([0.5, -1.0, 0.5]) * strain_step[:, None, None] / SHORT_DT)
    deviator = 0.5 * (rate[:, 0] + np.swapaxes(rate[:, 0], -1, -2))   # tr d = 0
    strain_per_step = np.sqrt(2.0 / 3.0 * np.sum(deviator ** 2, axis=(-2, -1))) * SHORT_DT
    path = jnp.asarray(rate, dtype)
    stress0 = hydrostatic(phi.size, SIGMA_C, dtype)
    dt = jnp.full(phi.size, SHORT_DT, dtype)
    tol = round_off(dtype)
    rate_independent = drive_points(parameter_batch(dtype, friction_angle=phi, poisson=nu), path, dt, stress0)
    _, q_plastic = invariants(rate_independent)
    assert np.all(q_plastic[:, -1] >= m * SIGMA_C * (1 - tol))        # the path does yield

    stiff = parameter_batch(dtype, True, friction_angle=phi, poisson=nu, exponent=exponent,
                            fluidity=1.0e8 / SHORT_DT)
    _, q_stiff = invariants(drive_points(stiff, path, dt, stress0))
    assert np.all(np.isfinite(q_stiff)), f"NaN in {np.mean(~np.isfinite(q_stiff[:, -1])):.0%} of the runs"
    bound = (2.0 * strain_per_step / 1.0e8) ** (1.0 / exponent)
    error = np.abs(q_stiff - q_plastic).max(axis=1) / (m * SIGMA_C)
    assert np.all(error <= bound + tol), (error.max(), bound.max())

    soft = parameter_batch(dtype, True, friction_angle=phi, poisson=nu, exponent=exponent,
                           fluidity=1.0e-8 / SHORT_DT)
    elastic = np.asarray(drive_elastic(soft, path, dt, stress0), np.float64)
    p_elastic, q_elastic = invariants(elastic)
    overstress = np.maximum(q_elastic - m[:, None] * p_elastic, 0.0) / (m[:, None] * p_elastic)
    drift = np.cumsum(3.0 * shear[:, None] * 1.0e-8 * overstress ** exponent[:, None], axis=1)
    viscous = np.asarray(drive_points(soft, path, dt, stress0), np.float64)
    assert np.all(np.isfinite(viscous))
    error = np.abs(viscous - elastic).max(axis=(-2, -1))
    assert np.all(error <= drift + tol * np.abs(elastic).max(axis=(-2, -1))), (error.max(), drift.max())


# ---------------------------------------------------------------------------------------------
# 6. A sweep over the extremes: finite values and gradients, no overshoot
# ---------------------------------------------------------------------------------------------

SWEEP_STEPS = 12
SWEEP_DT = 1.0e-3
SWEEP_PATHS = ("compression", "simple_shear", "expansion", "zero", "hydrostatic_tension",
               "zero_deviator", "on_surface", "on_surface_loaded")


@functools.partial(jax.jit, static_argnames="viscoplastic")
def sweep_histories(params, velocity_gradient, stress0, viscoplastic):
    """Per set: the stress after each step, its elastic trial (the linear_elastic update of the
    same stress), the plastic strain, and d(read-out)/d params. All vmapped."""
    material = template(viscoplastic=viscoplastic)
    elastic = LinearElastic(density=DENSITY, young=YOUNG, poisson=0.3)

    def one(params, velocity_gradient, stress0):
        def read_out(params):
            state = {"plastic_strain": jnp.zeros((), stress0.dtype)}

            def one_step(carry, gradient):
                stress, state = carry
                trial, _ = elastic.update(params, stress, gradient, SWEEP_DT, state)
                stress, state = material.update(params, stress, gradient, SWEEP_DT, state)
                return (stress, state), (stress, trial, state["plastic_strain"])

            _, (history, trials, plastic) = jax.lax.scan(one_step, (stress0, state), velocity_gradient)
            scale = jnp.maximum(jnp.max(jnp.abs(trials)), 1.0)
            value = jnp.sum(jnp.asarray(WEIGHTS, history.dtype) * history) / scale + jnp.sum(plastic)
            return value, (history, trials, plastic)

        (_, outputs), gradient = jax.value_and_grad(read_out, has_aux=True)(params)
        return outputs, gradient

    return jax.vmap(one)(params, velocity_gradient, stress0)


def sweep_cases(viscoplastic):
    """Parameter extremes x paths: (parameter columns, path names, L (B, T, 3, 3), stress0)."""
    axes = dict(friction_angle=(0.0, 1.0, 10.0, 30.0, 50.0), poisson=(0.0, 0.25, 0.49),
                young=(1.0e5, 1.0e7, 1.0e9))
    if viscoplastic:
        gamma_dt = (1e-8, 1e-3, 1.0, 1e3, 1e8)
        axes.update(fluidity=tuple(g / SWEEP_DT for g in gamma_dt), exponent=(1.0, 4.0, 20.0))
    *columns, path_index = grid(*axes.values(), np.arange(len(SWEEP_PATHS)))
    values = dict(zip(axes, columns))
    m = cone_slope("paper", values["friction_angle"])
    k = SIGMA_C / values["young"]        # strain steps scaled so that stress steps ~ sigma_c
    rate = np.zeros((path_index.size, SWEEP_STEPS, 3, 3))
    stress0 = np.broadcast_to(-SIGMA_C * np.eye(3), (path_index.size, 3, 3)).copy()
    half = SWEEP_STEPS // 2
    for index, name in enumerate(SWEEP_PATHS):
        rows = path_index == index
        kk = k[rows, None]
        if name == "compression":
            rate[rows, :, 0, 0] = rate[rows, :, 2, 2] = 0.1 * kk
            rate[rows, :, 1, 1] = -0.6 * kk
        elif name == "simple_shear":
            rate[rows, :, 0, 1] = 1.5 * kk
        elif name == "expansion":                 # into tension (the apex) and back, sheared
            for i in range(3):
                rate[rows, :half, i, i] = 0.5 * kk
                rate[rows, half:, i, i] = -0.3 * kk
            rate[rows, :, 0, 1] = 0.2 * kk
        elif name == "zero":
            stress0[rows] = 0.0
        elif name == "hydrostatic_tension":
            stress0[rows] = SIGMA_C * np.eye(3)
        elif name.startswith("on_surface"):       # q of q0 diag(1/3, -2/3, 1/3) is q0 = m p0
            on_cone = m[rows, None, None] * SIGMA_C * np.diag([1 / 3, -2 / 3, 1 / 3])
            stress0[rows] = -SIGMA_C * np.eye(3) + on_cone
            if name == "on_surface_loaded":
                for i, value in enumerate((0.05, -0.1, 0.05)):
                    rate[rows, :, i, i] = value * kk
    return values, np.asarray(SWEEP_PATHS)[path_index], rate / SWEEP_DT, stress0


@pytest.mark.parametrize("viscoplastic", [False, True], ids=["rate_independent", "viscoplastic"])
@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_sweep_over_extremes_is_finite_and_never_overshoots(dtype, viscoplastic):
    # phi 0..50 deg, nu 0..0.49, E 1e5..1e9, gamma dt 1e-8..1e8, N 1..20, times paths through
    # zero stress, hydrostatic tension, zero deviator, the apex and the yield surface.
    # After every step, with (p*, q*) the elastic trial and f* = q* - m p*:
    # - values and gradients (friction_angle, young, poisson, fluidity, exponent) are finite;
    # - p* < 0: the apex, sigma = 0 exactly (non-cohesive);
    # - f* < 0, p* > 0: elastic, sigma = trial;
    # - f* > 0, p* > 0: p = p* (g = q), the deviatoric direction kept, and rate-independent
    #   q = m p*; viscoplastic m p* <= q <= q* (never inside the elastic region, never beyond
    #   the trial).
    # Classes are decided with a round-off margin; on the boundaries only the checks that
    # hold on both sides apply.
    values, names, rate, stress0 = sweep_cases(viscoplastic)
    params = parameter_batch(dtype, viscoplastic, **values)
    (history, trials, plastic), gradient = sweep_histories(
        params, jnp.asarray(rate, dtype), jnp.asarray(stress0, dtype), viscoplastic)
    history, trials = np.asarray(history, np.float64), np.asarray(trials, np.float64)

    bad_value = ~np.isfinite(history).all(axis=(1, 2, 3)) | ~np.isfinite(np.asarray(plastic)).all(axis=1)
    bad_gradient = np.zeros_like(bad_value)
    for value in gradient.values():
        bad_gradient |= ~np.isfinite(np.asarray(value))
    bad = bad_value | bad_gradient
    if bad.any():
        first = np.flatnonzero(bad)[0]
        case = {key: float(column[first]) for key, column in values.items()}
        pytest.fail(f"NaN/Inf values in {bad_value.sum()} and gradients in {bad_gradient.sum()} of "
                    f"{bad.size} runs; e.g. path {names[first]!r} with {case}")

    m = cone_slope("paper", values["friction_angle"])[:, None]
    tol = round_off(dtype)
    margin = tol * (np.abs(trials).max(axis=(-2, -1)) + np.abs(history).max(axis=(-2, -1)))
    p_trial, q_trial = invariants(trials)
    pressure, deviatoric = invariants(history)
    overstress_trial = q_trial - m * p_trial
    apex = p_trial < -margin
    elastic = (overstress_trial < -margin) & (p_trial > margin)
    cone = (overstress_trial > margin) & (p_trial > margin)
    assert np.all(history[apex] == 0.0)
    assert np.all(np.abs(history - trials).max(axis=(-2, -1))[elastic] <= margin[elastic])
    assert np.all(np.abs(pressure - p_trial)[cone] <= margin[cone])
    excess = (deviatoric - m * pressure)[cone]
    if viscoplastic:
        assert np.all(excess >= -margin[cone])
        assert np.all(deviatoric[cone] <= q_trial[cone] + margin[cone])
    else:
        assert np.all(np.abs(excess) <= margin[cone])
    # p* ~ 0 with f* > 0: round-off decides between the apex (sigma = 0) and the cone, where
    # rate-independent sigma ~ 0 (q = m p* ~ 0) and viscoplastic m p* <= q <= q*.
    near_apex = (np.abs(p_trial) <= margin) & (overstress_trial > margin)
    at_apex = np.all(history == 0.0, axis=(-2, -1))
    if viscoplastic:
        between = (deviatoric >= m * pressure - margin) & (deviatoric <= q_trial + margin)
        assert np.all((at_apex | between)[near_apex])
    else:
        assert np.all(np.abs(history).max(axis=(-2, -1))[near_apex] <= ((1.0 + m) * margin)[near_apex])
    # Everywhere: no tension, and (rate-independent) nothing outside the cone.
    assert np.all(pressure >= -margin)
    if not viscoplastic:
        assert np.all(deviatoric - m * pressure <= margin)
    # The return keeps the deviatoric direction: s / q = s* / q*.
    moving = cone & (deviatoric > margin)
    unit = (history + pressure[..., None, None] * np.eye(3)) / np.maximum(deviatoric, 1e-300)[..., None, None]
    unit_trial = (trials + p_trial[..., None, None] * np.eye(3)) / np.maximum(q_trial, 1e-300)[..., None, None]
    turned = np.abs(unit - unit_trial).max(axis=(-2, -1))
    assert np.all(turned[moving] <= margin[moving] / deviatoric[moving])
    # Every class occurred, so the sweep tested what it claims.
    assert apex.any() and elastic.any() and cone.any() and near_apex.any()


# ---------------------------------------------------------------------------------------------
# 7. Gradients against central differences (float64)
# ---------------------------------------------------------------------------------------------

GRADIENT_STEPS = 30
GRADIENT_DT = 1.0e-2
GRADIENT_STATES = ("elastic", "plastic", "starts_on_surface", "on_surface_rotated", "apex")
RELATIVE_STEP = 1.0e-6


def gradient_path(state):
    """(L (T, 3, 3), stress0 (3, 3)) of a named state at phi = 30 deg, paper cone."""
    m = cone_slope("paper", 30.0)
    k = SIGMA_C / YOUNG / GRADIENT_DT           # a strain rate giving stress steps ~ sigma_c
    rate = np.zeros((GRADIENT_STEPS, 3, 3))
    stress0 = -SIGMA_C * np.eye(3)
    if state == "elastic":                      # q stays well below m p
        set_diagonal(rate, np.array([0.005, -0.01, 0.002]) * k)
        rate[:, 0, 1] = 0.002 * k
    elif state == "plastic":                    # compression with shear and spin, past yield
        set_diagonal(rate, np.array([0.05, -0.2, 0.03]) * k)
        rate[:, 0, 1] = 0.08 * k
    elif state == "starts_on_surface":          # sigma0 exactly on the cone, loaded further
        stress0 = stress0 + m * SIGMA_C * np.diag([1 / 3, -2 / 3, 1 / 3])
        set_diagonal(rate, np.array([0.02, -0.05, 0.02]) * k)
    elif state == "on_surface_rotated":         # loaded onto the cone, then spun rigidly
        third = GRADIENT_STEPS // 3
        set_diagonal(rate[:third], np.array([0.05, -0.2, 0.05]) * k)
        rate[third:, 0, 1], rate[third:, 1, 0] = 5.0, -5.0
    elif state == "apex":                       # sheared, then expanded into tension
        stress0 = stress0 + 0.5 * m * SIGMA_C * np.diag([1 / 3, -2 / 3, 1 / 3])
        set_diagonal(rate, np.full(3, 0.15) * k)
        rate[:, 0, 1] = 0.05 * k
    return rate, stress0


@functools.lru_cache
def gradient_comparison(viscoplastic):
    """{state: ({name: (reverse-mode, central difference, its round-off noise)}, final
    q/(m p), final stress)}."""
    base = dict(friction_angle=30.0, young=YOUNG, poisson=0.3)
    if viscoplastic:
        base.update(fluidity=20.0, exponent=2.0)       # gamma dt = 0.2: a large overstress
    names = list(base)
    shifts = [(None, 0.0)] + [(name, sign) for name in names for sign in (1.0, -1.0)]
    sets = []
    for state in GRADIENT_STATES:
        for name, sign in shifts:
            values = dict(base)
            if name is not None:
                values[name] = base[name] * (1.0 + sign * RELATIVE_STEP)
            sets.append((state, values))
    paths = [gradient_path(state) for state, _ in sets]
    columns = {key: np.array([values[key] for _, values in sets]) for key in base}
    params = parameter_batch(jnp.float64, viscoplastic, **columns)
    rate = jnp.asarray(np.stack([path for path, _ in paths]))
    stress0 = jnp.asarray(np.stack([start for _, start in paths]))
    dt = jnp.full(len(sets), GRADIENT_DT)
    histories = drive_points(params, rate, dt, stress0)
    read_outs = np.asarray(jax.vmap(weighted_mean)(histories))
    centres = np.arange(len(GRADIENT_STATES)) * len(shifts)
    pick = lambda tree: jax.tree_util.tree_map(lambda v: v[centres], tree)   # noqa: E731
    gradients = drive_gradients(pick(params), rate[centres], dt[centres], stress0[centres])
    pressure, deviatoric = invariants(histories[centres, -1])
    results = {}
    for row, state in enumerate(GRADIENT_STATES):
        compared = {}
        for i, name in enumerate(names):
            plus, minus = read_outs[centres[row] + 1 + 2 * i], read_outs[centres[row] + 2 + 2 * i]
            step = base[name] * RELATIVE_STEP
            central = (plus - minus) / (2.0 * step)
            # Round-off in J (ULPS eps |J|) divided by the step: the cancellation noise of `central`.
            noise = round_off(jnp.float64) * max(abs(plus), abs(minus)) / step
            compared[name] = (float(gradients[name][row]), central, noise)
        ratio = deviatoric[row] / (cone_slope("paper", 30.0) * pressure[row]) if pressure[row] > 0 else np.nan
        results[state] = (compared, ratio, np.asarray(histories[centres[row], -1]))
    return results


@pytest.mark.parametrize("viscoplastic", [False, True], ids=["rate_independent", "viscoplastic"])
@pytest.mark.parametrize("state", GRADIENT_STATES)
def test_gradients_match_central_differences(state, viscoplastic):
    # docs/validation.md §8: reverse-mode d(read-out)/d(parameter) against (J(t + h) - J(t - h))/2h with
    # h = 1e-6 t, float64; J = mean over the history of sum_ij W_ij sigma_ij / sigma_c.
    # Truncation O(h^2) ~ 1e-12 relative; cancellation ULPS eps |J| / h absolute (it dominates
    # where t dJ/dt << J, e.g. the fluidity once the overstress has relaxed). Tolerance: 1e-6
    # relative plus that noise. The Perzyna return is solved to round-off and differentiated
    # by the implicit function theorem, so it must agree just as well.
    # Elastic state: the friction angle, fluidity and exponent cannot matter: both exactly 0.
    # Apex state: the history ends at sigma = 0, its earlier steps depend on the parameters.
    compared, ratio, final = gradient_comparison(viscoplastic)[state]
    if state == "elastic":
        assert ratio < 0.5
    elif state == "apex":
        assert np.all(final == 0.0)
    elif state == "on_surface_rotated" and not viscoplastic:
        assert_close(ratio, 1.0, rtol=1e-12)
    else:
        assert ratio >= 1.0 - 1e-12          # plastic: on (or, viscoplastic, above) the cone
    for name, (gradient, central, noise) in compared.items():
        assert np.isfinite(gradient), name
        if state == "elastic" and name in ("friction_angle", "fluidity", "exponent"):
            assert gradient == 0.0 and central == 0.0, name
            continue
        assert abs(central) > 100.0 * noise, name     # a derivative well above the noise
        assert_close(gradient, central, rtol=1e-6, atol=noise, err_msg=name)


# ---------------------------------------------------------------------------------------------
# 8, 9. Objectivity and the apex
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_rigid_rotation_of_a_plastic_state_keeps_invariants(dtype):
    # docs/validation.md §4: load onto the cone (isochoric compression with shear), then spin
    # (L = W, d = 0) through 2 rad. A rigid rotation must keep p and q (the state stays on the
    # cone: f* = 0 to round-off, so the return does nothing), and the stress must turn with the
    # body: sigma = R sigma0 R^T with R the rotation by omega t, up to the error of the
    # incremental rotation (second order: at most (omega dt)^3/12 rad per step).
    phi, nu = grid(FRICTION_ANGLES, POISSON_RATIOS)
    m = cone_slope("paper", phi)
    load_steps, spin_steps, omega, dt = 10, 200, 1.0, 1.0e-2
    k = SIGMA_C / YOUNG / dt
    path = np.zeros((phi.size, load_steps + spin_steps, 3, 3))
    set_diagonal(path[:, :load_steps], np.array([0.1, -0.2, 0.1]) * k)
    path[:, :load_steps, 0, 1] = 0.1 * k
    path[:, load_steps:, 1, 0] = omega          # v_y,x = omega, v_x,y = -omega: spin omega about z
    path[:, load_steps:, 0, 1] = -omega
    params = parameter_batch(dtype, friction_angle=phi, poisson=nu)
    history = drive_points(params, jnp.asarray(path, dtype), jnp.full(phi.size, dt, dtype),
                           hydrostatic(phi.size, SIGMA_C, dtype))
    history = np.asarray(history, np.float64)
    pressure, deviatoric = invariants(history)
    tol = round_off(dtype) * np.sqrt(spin_steps)      # round-off of 200 rotations (random walk)
    assert_close(deviatoric[:, load_steps], m * pressure[:, load_steps], rtol=tol)   # on the cone
    assert_close(pressure[:, load_steps:], pressure[:, load_steps:load_steps + 1], rtol=tol)
    assert_close(deviatoric[:, load_steps:], deviatoric[:, load_steps:load_steps + 1], rtol=tol)
    angle = omega * dt * spin_steps
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    expected = rotation @ history[:, load_steps] @ rotation.T
    angle_error = spin_steps * (omega * dt) ** 3 / 12.0
    size = np.abs(history[:, load_steps]).max(axis=(-2, -1))[:, None, None]
    assert np.all(np.abs(history[:, -1] - expected) <= 2.0 * size * (angle_error + tol))
    assert np.abs(history[:, -1] - history[:, load_steps]).max() > 0.1 * size.min()   # it did turn


@pytest.mark.parametrize("viscoplastic", [False, True], ids=["rate_independent", "viscoplastic"])
@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tension_returns_to_the_apex(dtype, viscoplastic):
    # Non-cohesive sand carries no tension: a trial with p* < 0 returns to sigma = 0.
    # Path 1, from -sigma_c I: expansion d = e I with 3 K e dt = 0.3 sigma_c, so the trial
    #   p* = sigma_c (1 - 0.3 n) (hydrostatic, q = 0: elastic) until n = 4 where p* < 0: the
    #   apex; then compression from sigma = 0, elastic again: sigma = -0.3 sigma_c j I.
    # Path 2, from a sheared state, expansion with shear throughout: at the apex from n = 4
    #   (trial p* < 0 whatever q*) to the end.
    # (Finite gradients at the apex: test_gradients_match_central_differences[apex-*] and the
    # sweep's expansion and hydrostatic-tension paths.)
    phi, nu, sheared = grid(FRICTION_ANGLES, POISSON_RATIOS, (0, 1))
    bulk = YOUNG / (3.0 * (1.0 - 2.0 * nu))
    expansion = 0.3 * SIGMA_C / (3.0 * bulk) / SHORT_DT
    expand_steps = 6
    rate = np.zeros((phi.size, SHORT_STEPS, 3, 3))
    expanding = (sheared[:, None] == 1) | (np.arange(SHORT_STEPS) < expand_steps)[None, :]
    set_diagonal(rate, np.where(expanding, 1.0, -1.0)[..., None] * expansion[:, None, None] * np.ones(3))
    rate[sheared == 1, :, 0, 1] = 0.2 * SIGMA_C / YOUNG / SHORT_DT
    stress0 = np.broadcast_to(-SIGMA_C * np.eye(3), (phi.size, 3, 3)).copy()
    stress0[sheared == 1] += 0.3 * SIGMA_C * np.diag([1 / 3, -2 / 3, 1 / 3])
    values = dict(friction_angle=phi, poisson=nu)
    if viscoplastic:
        values.update(fluidity=1.0, exponent=2.0)
    params = parameter_batch(dtype, viscoplastic, **values)
    history = drive_points(params, jnp.asarray(rate, dtype), jnp.full(phi.size, SHORT_DT, dtype),
                           jnp.asarray(stress0, dtype))
    history = np.asarray(history, np.float64)
    tol = round_off(dtype)
    plain = sheared == 0
    expected = (1.0 - 0.3 * np.arange(1, 4))[None, :, None, None] * np.eye(3)
    assert_close(-history[plain, 1:4] / SIGMA_C, expected, atol=tol)
    assert np.all(history[:, 4:expand_steps + 1] == 0.0)
    recompressed = 0.3 * np.arange(1, SHORT_STEPS - expand_steps + 1)[None, :, None, None] * np.eye(3)
    assert_close(-history[plain, expand_steps + 1:] / SIGMA_C, recompressed, atol=tol)
    assert np.all(history[sheared == 1, 4:] == 0.0)


def test_the_driver_refuses_out_of_plane_shear_and_an_asymmetric_stress():
    # The stress updates work on [xx, yy, zz, xy] (plane strain, axisymmetry): an input they
    # would silently ignore is refused, naming it.
    table = dict(model="linear_elastic", density=1000.0, young=1e6, poisson=0.3)
    gradient = np.zeros((4, 3, 3))
    gradient[:, 0, 1] = 1.0
    assert np.isfinite(np.asarray(jaxmpm.drive(table, gradient, 1e-3))).all()
    gradient[2, 1, 2] = 0.5
    with pytest.raises(SceneError, match=r"velocity_gradient has out-of-plane shear .* up to 0\.5"):
        jaxmpm.drive(table, gradient, 1e-3)
    stress0 = -1e3 * np.eye(3)
    stress0[0, 1] = 10.0
    with pytest.raises(SceneError, match=r"stress0 is not symmetric: .* up to 10"):
        jaxmpm.drive(table, np.zeros((4, 3, 3)), 1e-3, stress0)


def test_stress_substeps_make_the_perzyna_update_converge_at_first_order_within_a_step():
    # numerics.stress_substeps = K: each step's update is K updates of dt / K with the step's L
    # (materials.base.points_update; Sloan 1987's substepping at a fixed count). The Perzyna
    # backward Euler is first order in its own step, and in a flow a point's strain rate changes
    # from step to step, so the update never reaches the steady state where backward Euler is
    # exact. Here: the sand of examples/retaining_wall.toml (E = 5 MPa, fluidity 5 1/s) with
    # N = 3, at p = 5 kPa, sheared at a rate that changes every step (1 +- 0.8 1/s) at that
    # example's step; the shear stress after 200 steps against 256 updates a step (each step's
    # L repeated at dt / 256). The error must shrink about K-fold.
    from jaxmpm.materials.base import points_update

    material = DruckerPrager(density=1800.0, young=5e6, poisson=0.3, friction_angle=30.0, fluidity=5.0, exponent=3.0)
    law, dt, steps = material.law, 8.17e-5, 200
    params = jax.tree_util.tree_map(jnp.asarray, material_parameters(material))
    gradients = np.zeros((steps, 1, 3, 3))
    gradients[:, 0, 0, 1] = 1.0 + 0.8 * np.sin(2.0 * np.arange(steps))       # 1/s, a new value every step

    @functools.partial(jax.jit, static_argnums=(1, 2))
    def final_shear(gradients, step, substeps):
        update = points_update(law, step, substeps)
        start = (-5e3 * jnp.eye(3)[None], law.init_state(1, jnp.float64))
        (stress, _), _ = jax.lax.scan(lambda carry, g: (update(params, carry[0], g, carry[1]), None), start, gradients)
        return stress[0, 0, 1]

    def repeated(times):
        return float(final_shear(np.repeat(gradients, times, axis=0), dt / times, 1))

    reference = repeated(256)
    substepped = np.array([float(final_shear(gradients, dt, k)) for k in (1, 2, 4, 8)])
    assert substepped[2] == pytest.approx(repeated(4), rel=1e-12)       # K substeps: K updates of dt / K
    errors = np.abs(substepped - reference)
    assert errors[0] > 1e-3 * abs(reference), errors                     # one update a step is off
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all((orders > 0.8) & (orders < 1.3)), (errors, orders)
