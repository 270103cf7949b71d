"""The figure of a calibration (`Fit.plot`, `jaxmpm plot FIT.h5`): the loss and every
parameter over the iterations, the error ellipses of every pair of parameters from the
Gauss-Newton covariance, the fitted against the observed probes of every experiment, and each
experiment's weighted residuals r_j = (y_fit(t_j) - y_j) / s_j (s: the noise sigma, or the
channel's RMS when none is given, as in the loss).

An ellipse is the region {d : d^T C2^-1 d <= k} about the fitted values, C2 the pair's block
of the covariance: k = 1 is the 1-sigma ellipse (its shadow on each axis is +- one standard
error), k = 5.991 the 95 % confidence region of the pair (chi-square, two degrees of freedom).
"""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np

from inverse.experiments import window_mean, window_steps
from inverse.observations import default_scale

ELLIPSES = ((1.0, "1 σ"), (-2.0 * math.log(0.05), "95 %"))     # (k, label); chi2(2) quantile: -2 ln(1 - p)
COLUMNS = 4


def ellipse(center, covariance, k=1.0, points=121):
    """(2, points) outline of {center + d : d^T covariance^-1 d = k}; None if the 2x2
    covariance is not finite (a pair the data do not constrain)."""
    covariance = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(covariance)):
        return None
    eigenvalues, vectors = np.linalg.eigh(covariance)
    angle = np.linspace(0.0, 2.0 * np.pi, points)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    return np.asarray(center, dtype=float)[:, None] + vectors @ (np.sqrt(k * np.clip(eigenvalues, 0.0, None))[:, None] * circle)


def fit_figure(fit):
    """The figure: one panel per drawing (each a function of the axis), COLUMNS to a row."""
    import matplotlib.pyplot as plt

    panels = [functools.partial(draw_loss, fit)]
    panels += [functools.partial(draw_parameter, fit, index) for index in range(len(fit.names))]
    panels += [functools.partial(draw_ellipses, fit, i, j) for i, j in itertools.combinations(range(len(fit.names)), 2)]
    panels += [functools.partial(draw_channel, fit, run, name, component, index)
               for run in fit.experiments if run.observations is not None
               for name, channel in run.observations.channels.items()
               for index, component in enumerate(channel.components)]
    panels += [functools.partial(draw_residuals, fit, run) for run in fit.experiments if run.observations is not None]
    columns = min(COLUMNS, len(panels))
    rows = math.ceil(len(panels) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(3.9 * columns, 3.2 * rows), squeeze=False)
    for axis, draw in itertools.zip_longest(axes.ravel(), panels):
        if draw is None:
            axis.set_visible(False)
        else:
            draw(axis)
    figure.tight_layout()
    return figure


def draw_loss(fit, axis):
    from matplotlib.ticker import MaxNLocator

    axis.semilogy(fit.history_loss, lw=1)
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.set_xlabel("iteration")
    axis.set_title(f"loss ({fit.optimizer}, each start)", fontsize=9)


def draw_parameter(fit, index, axis):
    """The parameter at the start of every iteration, each start; the fitted value +- 1 sigma."""
    from matplotlib.ticker import MaxNLocator

    name, value = fit.names[index], float(fit.values[index])
    error = math.sqrt(fit.covariance[index, index]) if fit.covariance[index, index] >= 0 else math.nan
    axis.plot(fit.history_values[:, :, index], lw=1, marker=".", ms=3)
    axis.axhline(value, color="k", lw=0.8)
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    if math.isfinite(error):
        axis.axhspan(value - error, value + error, color="C3", alpha=0.15, lw=0, label="fitted ± 1 σ")
        axis.legend(fontsize=7)
    axis.set_xlabel("iteration")
    axis.set_title(f"{name} = {value:.4g} ± {error:.2g}", fontsize=9)


def draw_ellipses(fit, i, j, axis):
    """The 1-sigma and 95 % ellipses of parameters i and j about the fitted values."""
    center = np.asarray(fit.values)[[i, j]]
    block = np.asarray(fit.covariance)[np.ix_([i, j], [i, j])]
    outlines = [(ellipse(center, block, k), label) for k, label in ELLIPSES]
    if outlines[0][0] is None:
        axis.text(0.5, 0.5, "the data do not constrain this pair:\nno ellipse", ha="center", va="center",
                  transform=axis.transAxes, fontsize=8)
    else:
        for (outline, label), style in zip(outlines, ("-", "--")):
            axis.plot(outline[0], outline[1], style, color="C0", lw=1.2, label=label)
        axis.legend(fontsize=7)
    axis.plot(*center, "+", color="k", ms=8)
    axis.set_xlabel(fit.names[i])
    axis.set_ylabel(fit.names[j])
    correlation = fit.correlation[i, j]
    axis.set_title(f"ρ = {correlation:.3f}" if np.isfinite(correlation) else "not identified", fontsize=9)


def fitted_history(run, name, channel):
    """(T, k) the best fit of probe `name` as the channel observes it: its mean over the
    channel's averaging window, if any."""
    simulated = run.probes[name]
    if channel.window > 0 and len(run.time) > 1:
        simulated = np.asarray(window_mean(simulated, window_steps(channel.window, run.time[1] - run.time[0])))
    return simulated


def fitted_at_observations(run, name, channel):
    """(N, c) `fitted_history` interpolated to the observation times, at the observed components."""
    simulated = fitted_history(run, name, channel)
    return np.stack([np.interp(channel.times, run.time, simulated[:, k]) for k in channel.components], axis=1)


def draw_residuals(fit, run, axis):
    """The weighted residuals of every observed component of one experiment against time."""
    known = all(channel.sigma is not None for channel in run.observations.channels.values())
    for name, channel in run.observations.channels.items():
        scale = channel.sigma if channel.sigma is not None else default_scale(channel)
        residuals = (fitted_at_observations(run, name, channel) - channel.values) / scale
        for index, component in enumerate(channel.components):
            axis.plot(channel.times, residuals[:, index], ".", ms=3, label=f"{name}[{component}]")
    axis.axhline(0.0, color="k", lw=0.8)
    if known:
        for bound in (-2.0, 2.0):
            axis.axhline(bound, color="0.6", lw=0.8, ls="--")
    several = len(fit.experiments) > 1
    axis.set_title(("residuals / σ (±2 dashed)" if known else "residuals / channel RMS")
                   + (f": {run.name}" if several else ""), fontsize=9)
    axis.set_xlabel("t [s]")
    axis.legend(fontsize=7)


def draw_channel(fit, run, name, component, index, axis):
    """Observed values of one probe component against the best fit (its window mean when the
    observation averages over a window)."""
    channel = run.observations.channels[name]
    simulated = fitted_history(run, name, channel)
    axis.plot(channel.times, channel.values[:, index], ".", ms=3, color="0.4", label="observed")
    axis.plot(run.time, simulated[:, component], "-", color="C3",
              label=f"fit (mean over {channel.window:g} s)" if channel.window > 0 else "fit")
    several = len(fit.experiments) > 1
    axis.set_title(f"{run.name}: {name}[{component}]" if several else f"{name}[{component}]", fontsize=9)
    axis.set_xlabel("t [s]")
    axis.legend(fontsize=7)
