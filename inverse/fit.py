"""The result of a calibration: fitted values, their uncertainty, history, plots, HDF5 file;
`fit_from` makes it from the problem and the optimiser's run.

Uncertainty is the Gauss-Newton (linearised least-squares) covariance at the optimum,
    C = s^2 (J^T J)^-1,  J = dr/dtheta  (residuals r weighted by 1 / sigma),
with s^2 = 1 when every channel's noise sigma is given, and the residual variance
s^2 = r.r / (M - P) otherwise. Standard errors are sqrt(diag C); correlations C_ij / (se_i se_j).
A parameter the data do not identify shows as a large relative standard error or a
correlation near +-1 with another parameter.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from inverse.experiments import experiment_bases
from jaxmpm.errors import SimulationError
from jaxmpm.running.refinement import REFINEMENT_LABELS
from jaxmpm.running.runner import describe_failure
from jaxmpm.running.tracing import collector_paused

BEYOND_ONE_STEP = 0.5   # a numerical shift over this fraction of a fitted value: fit again, not read the step


@dataclasses.dataclass(frozen=True)
class NumericalError:
    """How far a fit's values would move at refined numerics (one refinement).

    shift: {name: shift}, the Gauss-Newton step of the refined problem from the fitted values
    (inverse/numerical_error.py); in_standard_errors: {name: |shift| / standard error} (NaN
    where the standard error is not finite or zero); dominant: "numerics" if any shift is at
    least one standard error, "noise" if none is, None if no standard error is finite;
    beyond_one_step: the names whose shift exceeds BEYOND_ONE_STEP of their fitted value. Such
    a shift is past what one Gauss-Newton step can be trusted for: fit again at the refined
    numerics instead (a fit of the wall twin at its cell to data made at half of it was biased
    by -4.2 deg in the friction angle, where the step said +34 deg; docs/calibration.md)."""

    shift: dict
    in_standard_errors: dict
    dominant: str | None
    beyond_one_step: tuple

    @property
    def trusted(self) -> bool:
        """Whether the shift can be read as the numerics' bias (no shift beyond one step)."""
        return not self.beyond_one_step


def numerical_verdict(names, values, stderr, shift) -> NumericalError:
    """The `NumericalError` of `shift` (P,) for parameters `names` with fitted `values` and
    standard errors `stderr` ({name: value})."""
    shifts = {name: float(s) for name, s in zip(names, shift, strict=True)}
    ratios = {name: abs(shifts[name]) / stderr[name] if 0.0 < stderr[name] < np.inf else float("nan") for name in names}
    finite = [ratio for ratio in ratios.values() if np.isfinite(ratio)]
    dominant = None if not finite else "numerics" if max(finite) >= 1.0 else "noise"
    beyond = tuple(name for name in names if abs(shifts[name]) > BEYOND_ONE_STEP * abs(values[name]))
    return NumericalError(shifts, ratios, dominant, beyond)


def gauss_newton(residuals, values, noise_known, linearization=None):
    """(covariance (P, P), jacobian (M, P)) of the residual function at `values` (or of its
    `linearization` (r (M,), jacobian (M, P)) there, when the optimiser already holds it).

    The Jacobian's columns are scaled by |theta| (so E ~ 1e7 and phi ~ 30 are comparable) and
    decomposed by SVD. A direction whose singular value is below sqrt(eps) of the largest is not
    constrained by the data: every parameter taking part in it gets an infinite variance (and
    NaN correlations), rather than the zero a pseudo-inverse would report.
    """
    values = jnp.asarray(values)
    if linearization is None:
        linearization = residuals(values), jax.jacfwd(residuals)(values)
    r, jacobian = (np.asarray(part) for part in linearization)
    count, size = jacobian.shape
    variance = 1.0 if noise_known else float(r @ r) / max(count - size, 1)
    scale = np.where(np.abs(np.asarray(values)) > 0, np.abs(np.asarray(values)), 1.0)
    _, singular, directions = np.linalg.svd(jacobian * scale, full_matrices=False)
    constrained = singular > np.sqrt(np.finfo(float).eps) * max(singular.max(initial=0.0), 1e-300)
    inverse_squares = np.where(constrained, 1.0 / np.where(constrained, singular, 1.0) ** 2, 0.0)
    covariance = variance * (directions.T * inverse_squares) @ directions * np.outer(scale, scale)
    free = np.any(np.abs(directions[~constrained]) > 1e-8, axis=0) if (~constrained).any() else np.zeros(size, bool)
    covariance[free, :] = np.nan
    covariance[:, free] = np.nan
    covariance[free, free] = np.inf
    return covariance, jacobian


def time_line(cost: dict) -> str:
    """Where a calibration's time went, from `Fit.cost`: compiling apart from the iterations."""
    whole = f"{cost['wall_time']:.1f} s in all"
    if cost["before_resume"] > 0:
        whole += f" ({cost['before_resume']:.1f} s of it before the resume)"
    count = cost["iterations"]
    if not np.isfinite(cost["compiling"]):           # a file written before compiling was timed
        later = cost["seconds_per_iteration"]
        return (f"{whole}; {cost['first_iteration']:.1f} s first iteration"
                + (f", {later:.2f} s per later one" if np.isfinite(later) else ""))
    rest = cost["wall_time"] - cost["compiling"] - cost["iterating"]
    return (f"{whole}: compiled in {cost['compiling']:.1f} s; {count} iterations in {cost['iterating']:.1f} s, "
            f"{cost['iterating'] / max(count, 1):.2f} s per iteration; {max(rest, 0.0):.1f} s evaluating the "
            "starts, covariance and best fit")


@dataclasses.dataclass
class ExperimentFit:
    """One experiment of a calibration: its measurements and the best fit's probe histories."""

    name: str
    observations: object
    time: np.ndarray            # (T,) [s]
    probes: dict                # {probe: (T, k)} at the fitted values
    fixed: dict                 # the experiment's own fixed values ({dotted name: value})


@dataclasses.dataclass
class Fit:
    """A calibration's outcome. `params` {path: value} are the best start's values.

    Cost: `evaluations` counts simulations (for "lm" one forward pass carrying P tangents;
    for "lbfgs" and "adam" one forward and one reverse pass), `history_seconds`,
    `history_memory` (peak resident memory so far, MB) and `history_simulations` give them
    per iteration. `wall_time` is the whole calibration's, the sessions before a resume
    (`earlier_seconds` of it) included; `compile_seconds` of it went into compiling (NaN:
    not measured), `iteration_compile_seconds` of that inside the iterations."""

    names: tuple
    values: np.ndarray
    loss: float
    covariance: np.ndarray
    jacobian: np.ndarray
    start_values: np.ndarray
    final_values: np.ndarray
    final_losses: np.ndarray
    best_start: int
    reasons: list
    history_loss: np.ndarray        # (iterations, starts)
    history_values: np.ndarray      # (iterations, starts, P)
    history_gradient: np.ndarray    # (iterations, starts)
    history_seconds: np.ndarray     # (iterations,)
    history_memory: np.ndarray      # (iterations,)
    history_simulations: np.ndarray  # (iterations,)
    iterations: int
    evaluations: int
    wall_time: float
    optimizer: str
    experiments: list               # [ExperimentFit]
    scene_toml: str
    warning: str = ""
    numerical_shifts: dict = dataclasses.field(default_factory=dict)   # {refinement: (P,)}
    compile_seconds: float = float("nan")
    iteration_compile_seconds: float = 0.0
    earlier_seconds: float = 0.0

    @property
    def observations(self):
        """The first experiment's observations."""
        return self.experiments[0].observations

    @property
    def time(self) -> np.ndarray:
        """The first experiment's simulated times."""
        return self.experiments[0].time

    @property
    def probes(self) -> dict:
        """The first experiment's best-fit probe histories."""
        return self.experiments[0].probes

    @property
    def params(self) -> dict:
        return {name: float(value) for name, value in zip(self.names, self.values)}

    @property
    def stderr(self) -> dict:
        return {name: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, name in enumerate(self.names)}

    @property
    def correlation(self) -> np.ndarray:
        """(P, P) correlation matrix, ordered as `names`."""
        scale = np.sqrt(np.clip(np.diag(self.covariance), 1e-300, None))
        return self.covariance / np.outer(scale, scale)

    @property
    def history(self) -> dict:
        """Per iteration: loss (I, S), parameter values (I, S, P), gradient norm (I, S), wall
        seconds (I,), peak memory [MB] (I,), simulations so far (I,)."""
        return {"loss": self.history_loss, "values": self.history_values, "gradient_norm": self.history_gradient,
                "seconds": self.history_seconds, "memory_mb": self.history_memory,
                "simulations": self.history_simulations}

    @property
    def cost(self) -> dict:
        """What the calibration cost: iterations, simulations, wall time [s] (`before_resume`
        of it in the sessions before a resume), `compiling` [s] of it, the iterations' seconds
        less their compiling (`iterating`), the first iteration's seconds and the mean of the
        later ones (both with any compiling in them), peak memory [MB]."""
        later = self.history_seconds[1:]
        return {
            "iterations": self.iterations,
            "simulations": self.evaluations,
            "wall_time": self.wall_time,
            "before_resume": self.earlier_seconds,
            "compiling": self.compile_seconds,
            "iterating": float(np.sum(self.history_seconds)) - self.iteration_compile_seconds,
            "first_iteration": float(self.history_seconds[0]) if len(self.history_seconds) else 0.0,
            "seconds_per_iteration": float(np.mean(later)) if len(later) else float("nan"),
            "peak_memory_mb": float(np.max(self.history_memory)) if len(self.history_memory) else float("nan"),
        }

    def identifiability(self, relative=0.1, correlated=0.95) -> dict:
        """{path: verdict}: "identified" if its relative standard error is below `relative`,
        "poorly identified" if above, "not identified" if the data do not constrain it; and,
        on the line of each of them, the parameters it is correlated with beyond `correlated`."""
        verdicts = {}
        correlation = self.correlation
        for i, name in enumerate(self.names):
            error = self.stderr[name] / max(abs(self.values[i]), 1e-300)
            partners = [self.names[j] for j in range(len(self.names)) if j != i and abs(correlation[i, j]) > correlated]
            if not np.isfinite(error):
                verdicts[name] = "not identified: the data do not constrain it"
                continue
            if error > relative:
                verdicts[name] = f"poorly identified (relative standard error {error:.1%})"
            else:
                verdicts[name] = f"identified (relative standard error {error:.2%})"
            if partners:            # said on the line of each parameter of a correlated pair
                verdicts[name] += f"; correlated with {', '.join(partners)} (|rho| > {correlated})"
        return verdicts

    def summary(self) -> str:
        cost = self.cost
        kind = "forward passes with tangents" if self.optimizer == "lm" else "forward + reverse passes"
        lines = [f"{self.optimizer}: loss {self.loss:.6g} after {self.iterations} iterations, "
                 f"{self.evaluations} simulations ({kind}), peak memory {cost['peak_memory_mb']:.0f} MB",
                 f"  time: {time_line(cost)}"]
        if len(self.experiments) > 1:
            lines.append(f"  experiments: {', '.join(e.name for e in self.experiments)}")
        verdicts = self.identifiability()
        lines.append("  value +- one standard error (Gauss-Newton, at the fitted values):")
        for name in self.names:
            lines.append(f"  {name} = {self.params[name]:.6g} +- {self.stderr[name]:.3g}   {verdicts[name]}")
        lines.extend(self.numerical_error_lines())
        lines.append(f"  stopped: {self.reasons[self.best_start]}")
        if self.warning:
            lines.append(f"  warning: {self.warning}")
        return "\n".join(lines)

    def numerical_error(self) -> dict:
        """{refinement: NumericalError} for each refinement checked (`calibrate(numerical_check=...)`):
        the shifts, their size in standard errors, which dominates, and the parameters whose
        shift is beyond one Gauss-Newton step (`numerical_verdict`)."""
        return {refinement: numerical_verdict(self.names, self.params, self.stderr, shift)
                for refinement, shift in self.numerical_shifts.items()}

    def numerical_error_lines(self) -> list[str]:
        """One line per refinement checked: how far each value would move at the refined
        numerics, in standard errors, and which dominates (`numerical_verdict`)."""
        lines = []
        for refinement, shift in self.numerical_shifts.items():
            verdict = numerical_verdict(self.names, self.params, self.stderr, shift)
            moves = ", ".join(f"{name} {verdict.shift[name]:+.3g} "
                              f"({f'{ratio:.2g} se' if np.isfinite(ratio) else 'no standard error'})"
                              for name, ratio in verdict.in_standard_errors.items())
            words = {"numerics": "the numerics dominate the noise", "noise": "the noise dominates",
                     None: "no parameter has a finite standard error to compare with"}[verdict.dominant]
            if verdict.beyond_one_step:
                words += (f"; the shift is over half the value of {', '.join(verdict.beyond_one_step)}, beyond "
                          "what one Gauss-Newton step can say: fit again at the refined numerics")
            lines.append(f"  numerical error ({REFINEMENT_LABELS[refinement]}): {moves}; {words}")
        return lines

    def plot(self, path=None):
        """The calibration's figure (inverse/fit_plot.py): the loss and each parameter over the
        iterations, the error ellipses of each pair, and data against fit for every observed
        component of every experiment. Returns the figure (and writes it to `path` if given)."""
        from inverse.fit_plot import fit_figure

        figure = fit_figure(self)
        if path is not None:
            figure.savefig(path, dpi=130)
        return figure

    def save(self, path) -> Path:
        """HDF5, written atomically (inverse/fit_file.py; every key: docs/output_files.md):
        values, standard errors, covariance, correlation, the Jacobian at the fitted values,
        the history, the starts, every experiment's observations and best-fit probes."""
        from inverse.fit_file import save_fit

        return save_fit(self, path)

    @classmethod
    def load(cls, path) -> Fit:
        """The Fit a calibration wrote with `save` (or `jaxmpm calibrate`); one SceneError
        sentence if `path` is no calibration file."""
        from inverse.fit_file import load_fit

        fields = load_fit(path)
        return cls(**{**fields, "experiments": [ExperimentFit(**run) for run in fields["experiments"]]})


def fit_from(problem, run, state, start_values, warning="") -> Fit:
    """The Fit of a calibration's `problem` (inverse/problem.py) after the optimiser's `run`
    and `state` (inverse/optimise.py): each start's answer is the better of its last point and
    the best finite point it passed through (the last one unless it went astray); the best
    start's covariance and every experiment's best-fit probes. Levenberg–Marquardt's state
    holds the residuals and Jacobian of its last point, and its history the loss of every
    point it passed through, so nothing is simulated again for them (each costs a compilation
    of the whole problem)."""
    experiments, groups, space = problem.experiments, problem.groups, problem.space
    programs, data, bases, optimizer = problem.programs, problem.data, problem.bases, problem.optimizer
    dtype = problem.dtype
    last_z, best_z = jnp.asarray(run.z, dtype), jnp.asarray(run.best_z, dtype)
    if optimizer == "lm":
        last_losses = 0.5 * np.sum(np.asarray(state.residuals) ** 2, axis=1) / problem.count
        passed_losses = np.asarray(run.best_loss)
    else:
        with collector_paused():
            last_losses = np.asarray(programs.losses(last_z, data, bases))
            passed_losses = np.asarray(programs.losses(best_z, data, bases))
    at_best = np.all(np.asarray(run.best_z) == np.asarray(run.z), axis=1)    # the same point: no rounding decides
    take_last = np.isfinite(last_losses) & (at_best | ~(passed_losses < last_losses))
    final_z = jnp.where(jnp.asarray(take_last)[:, None], last_z, best_z)
    final_losses = np.where(take_last, last_losses, passed_losses)
    if not np.any(np.isfinite(final_losses)):
        raise SimulationError("every start of the calibration went non-finite; narrow the bounds or change the starts.")
    best = int(np.nanargmin(np.where(np.isfinite(final_losses), final_losses, np.nan)))
    values = np.asarray(space.to_physical(final_z[best]))
    linearization = None
    if optimizer == "lm" and take_last[best]:
        linearization = physical_linearization(space, final_z[best], state.residuals[best], state.jacobian[best])
    if linearization is None:             # another optimiser, a passed point, or a value pinned at a bound
        with collector_paused():
            linearization = programs.linearization(jnp.asarray(values, dtype), data, bases)
    covariance, jacobian = gauss_newton(
        programs.residuals, values, noise_known=all(e.observations.noise_known for e in experiments),
        linearization=linearization,
    )
    runs, warnings_found = [], [warning] if warning else []
    for index, (experiment, base) in enumerate(zip(experiments, experiment_bases(groups, bases, len(experiments)))):
        sim = experiment.sim
        params = space.insert(jnp.asarray(values, dtype), base, experiment=index)
        probes, final_state = sim.probes_and_final_state(params)
        if int(final_state.error_step) >= 0:
            warnings_found.append(f"best-fit run of {experiment.name}: " + describe_failure(sim, final_state))
        runs.append(ExperimentFit(experiment.name, experiment.observations, np.asarray(sim.time),
                                  {name: np.asarray(v) for name, v in probes.items()}, dict(experiment.set)))
    # + two losses of every start, the covariance's Jacobian and the best-fit probes, per experiment
    evaluations = run.evaluations + (2 * len(start_values) + 2) * len(experiments)
    return Fit(
        names=space.names,
        values=values,
        loss=float(final_losses[best]),
        covariance=covariance,
        jacobian=jacobian,
        start_values=np.asarray(start_values),
        final_values=np.asarray(jax.vmap(space.to_physical)(final_z)),
        final_losses=final_losses,
        best_start=best,
        reasons=list(run.reason),
        history_loss=np.array(run.history_loss),
        history_values=np.array(run.history_values),
        history_gradient=np.array(run.history_gradient),
        history_seconds=np.array(run.history_seconds),
        history_memory=np.array(run.history_memory),
        history_simulations=np.array(run.history_simulations),
        iterations=run.iteration,
        evaluations=evaluations,
        wall_time=float("nan"),           # set by the caller, who holds the clock
        optimizer=optimizer,
        experiments=runs,
        scene_toml=experiments[0].sim.scene.to_toml(),
        warning="; ".join(warnings_found),
    )


def physical_linearization(space, z, residuals, jacobian):
    """(r, dr/dtheta) from Levenberg–Marquardt's (r, dr/dz) at z: the bounds' transforms act
    on each parameter alone, so dr/dtheta_k = (dr/dz_k) / (dtheta_k/dz_k); None where that
    derivative vanishes (a value pinned at a bound), and the Jacobian is then taken afresh."""
    slopes = np.diag(np.asarray(jax.jacfwd(space.to_physical)(z)))
    if not np.all(np.isfinite(slopes) & (np.abs(slopes) > np.finfo(slopes.dtype).tiny)):   # no subnormal divisor
        return None
    return np.asarray(residuals), np.asarray(jacobian) / slopes[None, :]
