"""Drucker-Prager sand: elastic-perfectly plastic, or elastic-viscoplastic (Perzyna).

The paper's model (Wieckowski, eq. 2 and the viscoplastic variant), non-cohesive:
  yield          f = q - m p,   m = 18 sin(phi) / (9 - sin^2 phi) by default ("paper" cone;
                 the mean of the triaxial compression and extension cones; see CONES);
  potential      g = q - m_psi p (g = q, no dilatancy, at the default psi = 0);
  plastic        d^p = lambda_dot dg/dsigma, lambda_dot >= 0 when f = 0;
  viscoplastic   d^vp = gamma <Phi> dg/dsigma, Phi = ((q - m p) / (m p))^N, when `fluidity`
                 (gamma [1/s]) is given, with `exponent` N > 0.

Stress update (one point, one step): rotate the stress with the step's spin (Jaumann,
Hughes-Winget), add the elastic trial increment, then correct. With a plastic multiplier
increment dl the trial state (p*, q*) moves to
  q = q* - 3 G dl,   p = p* + K m_psi dl,   f = f* - H dl,   H = 3 G + K m m_psi
(with psi = 0 the return is radial in the deviatoric plane at fixed p).
- rate-independent: dl = f* / H, which lands exactly on f = 0;
- Perzyna, backward Euler: dl = gamma dt Phi(p, q). Writing dl = x f*/H with x in [0, 1]
  turns it into one monotone scalar equation, solved in log form
      log x + log(f*/H) - log(gamma dt) - N [log(1 - x) + log(f* / (m p(x)))] = 0
  for t = log(x / (1 - x)), where it is nearly linear (slope 1 as x -> 0, N as x -> 1), by
  Newton steps kept inside a bracket (at most NEWTON_STEPS, fewer once every point has
  converged; stable for every gamma dt and N: x -> 1 is the plastic limit, x -> 0 the
  elastic one); its gradient comes from the implicit function theorem, not from the
  iteration.
- apex: sand carries no tension. If the return along the flow direction cannot reach the cone
  (q* K m_psi + 3 G p* <= 0, i.e. p* <= 0 for psi = 0), the stress returns to the apex,
  sigma = 0.
History variable: `plastic_strain`, the accumulated equivalent plastic strain (sum of dl).
"""

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from jaxmpm import tensors
from jaxmpm.errors import SceneError
from jaxmpm.keys import Key, is_concrete
from jaxmpm.materials.base import ELASTIC_KEYS, Law, Material, check_keys
from jaxmpm.kernels.checkpoint_names import KEPT_SOLVES
from jaxmpm.materials.linear_elastic import elastic_moduli, elastic_trial_voigt, p_wave_speed

CONES = {
    # m as a function of sin(angle); each matches Mohr-Coulomb in one stress state.
    "paper": lambda s: 18.0 * s / (9.0 - s * s),           # mean of compression and extension
    "compression": lambda s: 6.0 * s / (3.0 - s),          # triaxial compression corners
    "extension": lambda s: 6.0 * s / (3.0 + s),            # triaxial extension corners
    "plane_strain": lambda s: jnp.sqrt(3.0) * s,           # plane strain, zero dilatancy
}
NEWTON_STEPS = 8   # at most; 6 reach round-off (|x - x_bisection| < 1e-14) over E, phi, psi, p, f*,
                   # gamma dt, N swept over 6-20 decades (tests/test_drucker_prager.py); 2 more for margin
TINY = 1e-30


def cone_slope(cone, angle_degrees):
    """m of the chosen cone for a friction (or dilation) angle in degrees."""
    return CONES[cone](jnp.sin(jnp.deg2rad(angle_degrees)))


def perzyna_fraction(trial_overstress, hardening, pressure_trial, dilation_rate, m, rate, exponent):
    """x in [0, 1] with dl = x f*/H solving the backward-Euler Perzyna equation (see module).
    trial_overstress f* > 0; hardening H; pressure_trial p* > 0; dilation_rate K m_psi;
    m the cone slope; rate = gamma dt; exponent N. Value from bracketed Newton steps on
    t = logit(x) (`perzyna_root_of`), derivatives from the implicit function theorem
    (`fraction_at_root`). The root is named KEPT_SOLVES: a checkpointed step keeps it, and
    its recomputation in reverse mode does not solve again (`jaxmpm.running.rollout`).
    """
    arguments = (trial_overstress, hardening, pressure_trial, dilation_rate, m, rate, exponent)
    root = checkpoint_name(perzyna_root_of(*arguments), KEPT_SOLVES)
    return fraction_at_root(root, *arguments)


@jax.custom_jvp
def fraction_at_root(root, *arguments):
    """x = sigmoid(t) at the root t of the Perzyna equation with these `arguments`; its
    derivatives are those of the implicit function (`fraction_by_implicit_function`)."""
    return jax.nn.sigmoid(root)


def fraction_by_implicit_function(root, *arguments):
    """sigmoid(t - (R(t) - R(t)) / (dR/dt)) with the root t and the slope held: the value
    sigmoid(t), and the derivative with respect to the arguments -(dR/dtheta) / (dR/dt), the
    implicit function theorem's."""
    residual = perzyna_equation(*arguments)["residual"]
    slope = jax.lax.stop_gradient(jax.grad(residual)(root))
    value = residual(root)
    return jax.nn.sigmoid(root - (value - jax.lax.stop_gradient(value)) / slope)


fraction_at_root.defjvp(lambda primals, tangents: jax.jvp(fraction_by_implicit_function, primals, tangents))


def perzyna_root_of(trial_overstress, hardening, pressure_trial, dilation_rate, m, rate, exponent):
    """t = logit(x) of `perzyna_fraction`, by bracketed Newton steps from the asymptote (no
    derivative)."""
    equation = perzyna_equation(trial_overstress, hardening, pressure_trial, dilation_rate, m, rate, exponent)
    terms = [equation[name] for name in ("pressure_trial", "growth", "m", "exponent", "constant")]
    bracket = perzyna_bracket(equation["residual"], equation["constant"], exponent, m, pressure_trial, equation["growth"])
    return jax.lax.stop_gradient(bracketed_newton(lambda t: perzyna_residual_and_slope(t, *terms), *bracket))


def perzyna_equation(trial_overstress, hardening, pressure_trial, dilation_rate, m, rate, exponent):
    """The residual R(t) of the Perzyna equation in t = logit(x) (see the module docstring),
    with the terms the Newton steps read."""
    largest = trial_overstress / hardening
    constant = jnp.log(largest) - jnp.log(rate) - exponent * jnp.log(trial_overstress)
    growth = dilation_rate * largest            # p(x) = p* + growth x

    def residual(t):
        # log x - N log(1 - x) + N log(m p(x)) + constant, with x = sigmoid(t)
        pressure = pressure_trial + growth * jax.nn.sigmoid(t)
        return (jax.nn.log_sigmoid(t) - exponent * jax.nn.log_sigmoid(-t)
                + exponent * jnp.log(jnp.maximum(m * pressure, TINY)) + constant)

    return {"residual": residual, "constant": constant, "growth": growth, "pressure_trial": pressure_trial,
            "m": m, "exponent": exponent}


def perzyna_residual_and_slope(t, pressure_trial, growth, m, exponent, constant):
    """(R(t), dR/dt) of the Perzyna residual of `perzyna_fraction` (no derivative through
    them: they steer the Newton steps only), written with one exponential, e = exp(-|t|):
    log sigmoid(+-t) = -max(-+t, 0) - log1p(e), sigmoid(t) = 1 / (1 + e) for t >= 0, e / (1 + e)
    below, and dR/dt = (1 - x) + N x + N growth x (1 - x) / p(x) (cheaper than JAX's jvp of
    the log-sigmoids, a log-add-exp with its special cases)."""
    e = jnp.exp(-jnp.abs(t))
    tail = jnp.log1p(e)
    x = jnp.where(t >= 0.0, 1.0, e) / (1.0 + e)
    pressure = pressure_trial + growth * x
    scaled = m * pressure
    kept = scaled > TINY
    value = (-jnp.maximum(-t, 0.0) - tail + exponent * (jnp.maximum(t, 0.0) + tail)
             + exponent * jnp.log(jnp.maximum(scaled, TINY)) + constant)
    pressure_slope = jnp.where(kept, growth * x * (1.0 - x) / jnp.where(kept, pressure, 1.0), 0.0)
    return value, (1.0 - x) + exponent * (x + pressure_slope)


def perzyna_bracket(residual, constant, exponent, m, pressure_trial, growth):
    """(low, high, start) around the root of the Perzyna residual R(t). With
    R_0 = N log(m p*) + c and R_1 = N log(m (p* + growth)) + c, and log 2 bounding the
    log-sigmoid terms: a root t < 0 (R(0) > 0) lies in [-(R_1 + N log 2), min(0, log 2 - R_0)],
    a root t >= 0 in [max(0, -R_1 / N - log 2), max(0, (log 2 - R_0) / N)]. The start is
    the asymptote of its side (R ~ t + R_0 for t -> -inf, R ~ N t + R_1 for t -> inf)."""
    log2 = jnp.log(2.0)
    at_least = exponent * jnp.log(jnp.maximum(m * pressure_trial, TINY)) + constant
    at_most = exponent * jnp.log(jnp.maximum(m * (pressure_trial + growth), TINY)) + constant
    negative = residual(jnp.zeros_like(constant)) > 0.0
    low = jnp.where(negative, -(at_most + exponent * log2), jnp.maximum(0.0, -at_most / exponent - log2))
    high = jnp.where(negative, jnp.minimum(0.0, log2 - at_least), jnp.maximum(0.0, (log2 - at_least) / exponent))
    start = jnp.clip(jnp.where(negative, -at_least, -at_most / exponent), low, high)
    return low, high, start


def bracketed_newton(residual_and_slope, low, high, start):
    """Newton steps on an increasing R(t) from `start`, a step that leaves the bracket
    [low, high] (shrunk at every step) replaced by the bracket's midpoint;
    residual_and_slope(t) -> (R(t), dR/dt).

    At most NEWTON_STEPS steps; the loop ends early once every point's last step was a
    Newton step shorter than sqrt(eps) (1 + |t|): convergence is quadratic there, so the
    next step would move t by round-off only."""
    tolerance = float(np.finfo(start.dtype).eps) ** 0.5

    def newton_step(carry):
        taken, t, low, high, _ = carry
        value, slope = residual_and_slope(t)
        low = jnp.where(value < 0.0, t, low)
        high = jnp.where(value > 0.0, t, high)
        step = t - value / slope
        inside = (step >= low) & (step <= high)
        converged = inside & (jnp.abs(step - t) <= tolerance * (1.0 + jnp.abs(t)))
        return taken + 1, jnp.where(inside, step, 0.5 * (low + high)), low, high, converged

    def unfinished(carry):
        taken, *_, converged = carry
        return (taken < NEWTON_STEPS) & ~converged

    carry = (0, start, low, high, jnp.zeros(jnp.shape(start), bool))
    return jax.lax.while_loop(unfinished, newton_step, carry)[1]


@dataclasses.dataclass(frozen=True)
class DruckerPrager(Material):
    """Non-cohesive Drucker-Prager sand (see the module docstring for the equations).

    Attributes:
      density: rho [kg/m^3]; young: E [Pa]; poisson: nu.
      friction_angle: phi [degrees], 0 <= phi < 90.
      dilation_angle: psi [degrees], 0 <= psi <= phi (0: the paper's g = q).
      cone: which m(phi): "paper" | "compression" | "extension" | "plane_strain" (static).
      fluidity: Perzyna gamma [1/s]; None = rate-independent (static: present or not).
      exponent: Perzyna N > 0 (used only with fluidity).
    """

    density: float
    young: float
    poisson: float
    friction_angle: float
    dilation_angle: float = 0.0
    cone: str = "paper"
    fluidity: float | None = None
    exponent: float = 1.0

    model: ClassVar[str] = "drucker_prager"
    option_names: ClassVar[tuple[str, ...]] = ("cone",)
    keys: ClassVar[tuple] = ELASTIC_KEYS + (
        Key("friction_angle", "float", "friction angle phi of the yield cone", unit="degree",
            low=0.0, high=90.0, low_inclusive=True),
        Key("dilation_angle", "float", "dilation angle psi of the plastic potential g = q - m(psi) p; "
            "0 is the paper's g = q (no dilatancy); at most the friction angle", unit="degree",
            default=0.0, low=0.0, high=90.0, low_inclusive=True),
        Key("cone", "str", "which Drucker-Prager cone matches Mohr-Coulomb: 'paper' "
            "m = 18 sin(phi) / (9 - sin^2 phi), 'compression' 6 sin / (3 - sin), 'extension' "
            "6 sin / (3 + sin), 'plane_strain' sqrt(3) sin (static: changing it recompiles)",
            default="paper", choices=tuple(CONES)),
        Key("fluidity", "float", "Perzyna fluidity gamma; given, the model is viscoplastic "
            "(d_vp = gamma <Phi> dg/dsigma, Phi = ((q - m p) / (m p))^N); absent, rate-independent",
            unit="1/s", default=None, low=0.0),
        Key("exponent", "float", "Perzyna exponent N (only with fluidity)", default=1.0, low=0.0),
    )

    @property
    def parameter_names(self):
        base = ("density", "young", "poisson", "friction_angle", "dilation_angle")
        return base + (("fluidity", "exponent") if self.viscoplastic else ())

    @property
    def viscoplastic(self):
        return self.fluidity is not None

    def check(self, where):
        check_keys(self, where)
        concrete = is_concrete(self.dilation_angle) and is_concrete(self.friction_angle)
        if concrete and self.dilation_angle > self.friction_angle:
            raise SceneError(
                f"{where}.dilation_angle = {self.dilation_angle!r} exceeds the friction angle "
                f"{self.friction_angle!r}."
            )
        if not self.viscoplastic and self.exponent != 1.0:
            raise SceneError(
                f"{where}.exponent = {self.exponent!r} is given without fluidity: give "
                "fluidity (1/s) for the viscoplastic model, or remove exponent."
            )

    @property
    def law(self):
        """The static constitutive law (what the solver compiles; values come from params)."""
        return DruckerPragerLaw(self.cone, self.viscoplastic)


@dataclasses.dataclass(frozen=True)
class DruckerPragerLaw(Law):
    """The static side of `DruckerPrager`: the cone and whether the Perzyna solve exists.

    Changing either recompiles; every value (phi, E, gamma, N, ...) comes from `params`.
    """

    cone: str = "paper"
    viscoplastic: bool = False

    @property
    def kept_solves_per_point(self):
        """Values a point's update solves for and a checkpointed step keeps: the Perzyna root."""
        return 1 if self.viscoplastic else 0

    def init_state(self, count, dtype):
        return {"plastic_strain": jnp.zeros((count,), dtype)}

    def wave_speed(self, params):
        return p_wave_speed(params)

    def update(self, params, stress, velocity_gradient, dt, state):
        """One point: Jaumann rotation, elastic trial, plastic / viscoplastic correction."""
        constants = self.constants(params)
        trial = elastic_trial_voigt(constants, stress, velocity_gradient, dt)
        returned = self.return_state(constants, trial, dt)
        return (tensors.from_voigt(returned["stress"]),
                {"plastic_strain": state["plastic_strain"] + returned["increment"]})

    def correct(self, params, trial, dt):
        """Return the trial stress to the admissible set: (stress, plastic multiplier dl)."""
        state = self.return_state(self.constants(params), tensors.voigt(trial), dt)
        return tensors.from_voigt(state["stress"]), state["increment"]

    def constants(self, params):
        """The scalars the return reads: K, G, m, K m_psi, and gamma, N when viscoplastic."""
        constants = elastic_moduli(params)
        constants["slope"] = cone_slope(self.cone, params["friction_angle"])
        constants["dilation_rate"] = constants["bulk"] * cone_slope(self.cone, params["dilation_angle"])
        if self.viscoplastic:
            constants.update(fluidity=params["fluidity"], exponent=params["exponent"])
        return constants

    def return_state(self, constants, trial, dt):
        """The return of the trial stress [xx, yy, zz, xy] (`tensors.voigt`) to the admissible
        set: {"stress": [xx, yy, zz, xy], "increment": dl} (see the module docstring)."""
        shear, m, dilation_rate = constants["shear"], constants["slope"], constants["dilation_rate"]
        pressure = -(trial[0] + trial[1] + trial[2]) / 3.0
        trial_deviator = tensors.voigt_deviator(trial)
        deviatoric = tensors.voigt_von_mises_of_deviator(trial_deviator)
        overstress = deviatoric - m * pressure
        hardening = 3.0 * shear + m * dilation_rate

        yielding = (overstress > 0.0) | (pressure < 0.0)
        to_apex = yielding & (deviatoric * dilation_rate + 3.0 * shear * pressure <= 0.0)
        to_cone = yielding & ~to_apex
        # Safe stand-ins where a branch is not taken, so no branch makes NaN (double where).
        safe_overstress = jnp.where(to_cone, overstress, 1.0)
        safe_pressure = jnp.where(to_cone, pressure, 1.0)
        safe_deviatoric = jnp.where(to_cone, deviatoric, 1.0)

        fraction = 1.0
        if self.viscoplastic:
            safe_rate = jnp.where(to_cone, constants["fluidity"] * dt, 1.0)
            fraction = perzyna_fraction(safe_overstress, hardening, safe_pressure, dilation_rate, m, safe_rate,
                                        constants["exponent"])
        multiplier = fraction * safe_overstress / hardening
        ratio = (safe_deviatoric - 3.0 * shear * multiplier) / safe_deviatoric      # q' / q
        new_pressure = safe_pressure + dilation_rate * multiplier                     # p'
        returned = [value * ratio - (new_pressure if index < 3 else 0.0) for index, value in enumerate(trial_deviator)]
        stress = [jnp.where(to_cone, r, jnp.where(to_apex, jnp.zeros_like(t), t)) for r, t in zip(returned, trial)]
        apex_multiplier = deviatoric / (3.0 * shear)
        increment = jnp.where(to_cone, multiplier, jnp.where(to_apex, apex_multiplier, 0.0))
        return {"stress": stress, "increment": increment}
