"""The result of a calibration: fitted values, their uncertainty, history, plots, HDF5 file.

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

from inverse.experiments import window_mean, window_steps
from jaxmpm.files import atomic_path


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
    per iteration (the first iteration's seconds include compiling)."""

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
    numerical_shifts: dict = dataclasses.field(default_factory=dict)   # {"dt" | "cell": (P,)}

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
        """What the calibration cost: iterations, simulations, wall time [s] (and the part
        spent in the first iteration, which includes compiling), seconds per later iteration,
        peak memory [MB]."""
        later = self.history_seconds[1:]
        return {
            "iterations": self.iterations,
            "simulations": self.evaluations,
            "wall_time": self.wall_time,
            "first_iteration": float(self.history_seconds[0]) if len(self.history_seconds) else 0.0,
            "seconds_per_iteration": float(np.mean(later)) if len(later) else float("nan"),
            "peak_memory_mb": float(np.max(self.history_memory)) if len(self.history_memory) else float("nan"),
        }

    def identifiability(self, relative=0.1, correlated=0.95) -> dict:
        """{path: verdict}: "identified" if its relative standard error is below `relative` and
        it is not correlated beyond `correlated` with another; otherwise why not."""
        verdicts = {}
        correlation = self.correlation
        for i, name in enumerate(self.names):
            error = self.stderr[name] / max(abs(self.values[i]), 1e-300)
            partners = [self.names[j] for j in range(len(self.names)) if j != i and abs(correlation[i, j]) > correlated]
            if not np.isfinite(error):
                verdicts[name] = "not identified: the data do not constrain it"
            elif error > relative:
                verdicts[name] = f"poorly identified (relative standard error {error:.1%})"
            elif partners:
                verdicts[name] = f"correlated with {', '.join(partners)} (|rho| > {correlated})"
            else:
                verdicts[name] = f"identified (relative standard error {error:.2%})"
        return verdicts

    def summary(self) -> str:
        cost = self.cost
        kind = "forward passes with tangents" if self.optimizer == "lm" else "forward + reverse passes"
        later = cost["seconds_per_iteration"]
        timing = (f"{cost['first_iteration']:.1f} s first iteration with compiling"
                  + (f", {later:.2f} s per later one" if np.isfinite(later) else ""))
        lines = [f"{self.optimizer}: loss {self.loss:.6g} after {self.iterations} iterations, "
                 f"{self.evaluations} simulations ({kind}), {self.wall_time:.1f} s "
                 f"({timing}), peak memory {cost['peak_memory_mb']:.0f} MB"]
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

    def numerical_error_lines(self) -> list[str]:
        """One line per refinement checked (`calibrate(numerical_check=...)`): how far each
        value would move at the refined numerics, in standard errors, and which dominates."""
        labels = {"dt": "time step halved", "cell": "cell halved"}
        lines = []
        for refinement, shift in self.numerical_shifts.items():
            errors = [self.stderr[n] for n in self.names]
            ratios = [abs(s) / e if 0.0 < e < np.inf else np.nan for s, e in zip(shift, errors)]
            moves = ", ".join(f"{n} {s:+.3g} ({f'{r:.2g} se' if np.isfinite(r) else 'no standard error'})"
                              for n, s, r in zip(self.names, shift, ratios))
            finite = [r for r in ratios if np.isfinite(r)]
            verdict = ("no parameter has a finite standard error to compare with" if not finite
                       else "the discretisation dominates the noise" if max(finite) >= 1.0
                       else "the noise dominates")
            lines.append(f"  numerical error ({labels[refinement]}): {moves}; {verdict}")
        return lines

    def plot(self, path=None):
        """Data vs fit for every observed component of every experiment, and the loss
        history. Returns the figure (and writes it to `path` if given)."""
        import matplotlib.pyplot as plt

        several = len(self.experiments) > 1
        channels = [(run, name, k, index) for run in self.experiments
                    for name, channel in run.observations.channels.items()
                    for index, k in enumerate(channel.components)]
        figure, axes = plt.subplots(1, len(channels) + 1, figsize=(4 * (len(channels) + 1), 3.2))
        for axis, (run, name, component, index) in zip(axes, channels):
            channel = run.observations.channels[name]
            simulated = run.probes[name]
            if channel.window > 0 and len(run.time) > 1:      # what the observation measures
                simulated = np.asarray(window_mean(simulated, window_steps(channel.window, run.time[1] - run.time[0])))
            axis.plot(channel.times, channel.values[:, index], ".", ms=3, color="0.4", label="observed")
            axis.plot(run.time, simulated[:, component], "-", color="C3",
                      label=f"fit (mean over {channel.window:g} s)" if channel.window > 0 else "fit")
            axis.set_title(f"{run.name}: {name}[{component}]" if several else f"{name}[{component}]")
            axis.set_xlabel("t [s]")
            axis.legend(fontsize=7)
        history = axes[-1]
        history.semilogy(self.history_loss, lw=1)
        history.set_xlabel("iteration")
        history.set_title("loss (each start)")
        figure.tight_layout()
        if path is not None:
            figure.savefig(path, dpi=130)
        return figure

    def save(self, path) -> Path:
        """HDF5, written atomically: attrs (optimizer, loss, iterations, evaluations, wall
        time, scene of the first experiment); /params, /stderr (one dataset per parameter),
        /correlation, /covariance, /names, /history/{loss, values, gradient_norm, seconds,
        memory_mb, simulations}, /starts/{initial, final, loss}; /time and /probes/NAME of the
        first experiment, and /experiments/NAME/{time, probes/PROBE} of each; with a numerical
        check, /numerical_shift/REFINEMENT/PARAMETER."""
        import h5py

        path = Path(path)
        with atomic_path(path) as temporary, h5py.File(temporary, "w") as file:
            file.attrs.update(
                optimizer=self.optimizer, loss=self.loss, iterations=self.iterations,
                evaluations=self.evaluations, wall_time=self.wall_time, scene=self.scene_toml,
                best_start=self.best_start, stopped=self.reasons[self.best_start], warning=self.warning,
            )
            file.create_dataset("names", data=np.array(self.names, dtype="S"))
            for group, values in (("params", self.params), ("stderr", self.stderr)):
                for name, value in values.items():
                    file.create_dataset(f"{group}/{name}", data=value)
            file.create_dataset("covariance", data=self.covariance)
            file.create_dataset("correlation", data=self.correlation)
            for name, values in self.history.items():
                file.create_dataset(f"history/{name}", data=values)
            file.create_dataset("starts/initial", data=self.start_values)
            file.create_dataset("starts/final", data=self.final_values)
            file.create_dataset("starts/loss", data=self.final_losses)
            file.create_dataset("time", data=self.time)
            for name, values in self.probes.items():
                file.create_dataset(f"probes/{name}", data=values)
            for refinement, shift in self.numerical_shifts.items():
                for name, value in zip(self.names, shift):
                    file.create_dataset(f"numerical_shift/{refinement}/{name}", data=value)
            for run in self.experiments:
                file.create_dataset(f"experiments/{run.name}/time", data=run.time)
                for name, values in run.probes.items():
                    file.create_dataset(f"experiments/{run.name}/probes/{name}", data=values)
        return path
