"""Experiment design: which experiments would identify the parameters, before any is run.

A candidate experiment is an `inverse.Experiment` whose observations are planned, not
measured: which probe components are read at which times, with which noise sigma
(`planned_observations`; the values are never used). At a prior guess theta_0 of the
parameters, the Fisher information of candidate e is

    F_e = J_e^T J_e,    J_e = dr_e/dtheta (theta_0),    r_j = (y_sim(t_j) - y_j) / sigma_j,

the Jacobian of the weighted residuals the Levenberg-Marquardt calibration linearises
(`inverse.experiments.residual_function`, forward mode: one pass carrying P tangents).
Independent experiments add: F = sum_e F_e. If the model is right, the noise Gaussian and
independent with the stated sigma, and the residuals nearly linear in theta over the
uncertainty, a calibration's covariance is C = F^-1 (`inverse.fit.gauss_newton` at the optimum).

Each design (one candidate, or a set) is reported in coordinates scaled by s_i = |theta_0_i|
(relative changes; the prior range's width for a zero guess): F~ = S F S, S = diag(s), with
eigenvalues lambda_1 >= ... >= lambda_P and unit eigenvectors v_k:
  - a direction v_k with lambda_k < threshold lambda_1 is not identified (the data cannot see
    it; e.g. "0.71 gamma - 0.70 N": raising gamma by 1 % and N by 1 % changes nothing); every
    parameter taking part in one gets an infinite standard error;
  - standard errors sqrt(diag C), C = S (sum over identified k of v_k v_k^T / lambda_k) S;
  - correlations C_ij / (se_i se_j);
  - D-optimality log det F~ = sum_k log lambda_k (-inf when a direction is not identified);
    a larger value is a smaller confidence ellipsoid (its volume goes as exp(-log det / 2)).
Over several guesses (the prior range's corners, or samples in it) each candidate's worst
case is reported, and the greedy selection maximises the worst case.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import time as clock
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from inverse.problem import over_starts
from inverse.experiments import (
    check_observations, experiments_from, group_experiments, layout_of, problem_arguments, problem_residuals,
)
from inverse.levenberg_marquardt import residuals_and_jacobian
from inverse.observations import Observations, check_against
from inverse.parameters import ParameterSpace
from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.kernels.xla_options import jit_with_options
from jaxmpm.scene.parameters import resolve

THRESHOLD = 1e-8        # a scaled eigenvalue below THRESHOLD * the largest: a direction not identified
TAKES_PART = 1e-6       # a parameter whose weight in such a direction exceeds this is not identified
SHOWN_WEIGHT = 0.005    # weights below this are left out of a direction's description
MAX_CORNERS = 16        # beyond this many corners of the prior range, guesses="corners" samples instead


# --------------------------------------------------------------------------- one design


@dataclasses.dataclass(frozen=True)
class Direction:
    """A direction of parameter space the data cannot see: `weights` (P,) a unit vector of
    relative changes d theta_i / s_i, `ratio` its eigenvalue over the largest."""

    weights: np.ndarray
    ratio: float

    def describe(self, names) -> str:
        """"0.71·sand.fluidity − 0.70·sand.exponent" (sign chosen so the largest weight is positive)."""
        weights = self.weights * np.sign(self.weights[np.argmax(np.abs(self.weights))])
        terms = [(w, n) for w, n in zip(weights, names) if abs(w) >= SHOWN_WEIGHT]
        text = "".join(f"{' − ' if w < 0 else ' + '}{abs(w):.2f}·{n}" for w, n in terms)
        return text[3:] if text.startswith(" + ") else "−" + text[3:]


@dataclasses.dataclass(frozen=True)
class Information:
    """What one design predicts at one guess: `fisher` (P, P) in the parameters' units,
    `scale` (P,) the s_i of the scaled coordinates (see the module docstring)."""

    names: tuple
    values: np.ndarray
    fisher: np.ndarray
    scale: np.ndarray
    threshold: float = THRESHOLD

    @functools.cached_property
    def eigen(self):
        """(lambda (P,) descending, v (P, P) columns) of the scaled Fisher matrix S F S."""
        scaled = self.fisher * np.outer(self.scale, self.scale)
        eigenvalues, vectors = np.linalg.eigh(0.5 * (scaled + scaled.T))
        return eigenvalues[::-1], vectors[:, ::-1]

    @functools.cached_property
    def identified(self) -> np.ndarray:
        """(P,) bool per eigen-direction: lambda_k > threshold lambda_1 (and lambda_1 > 0)."""
        eigenvalues = self.eigen[0]
        return eigenvalues > self.threshold * max(eigenvalues[0], 0.0) if eigenvalues[0] > 0 else np.zeros(len(eigenvalues), bool)

    @property
    def unidentified(self) -> list[Direction]:
        """The directions the data cannot see: first each parameter that alone has no visible
        effect ((S F S)_ii below threshold lambda_1), then the eigenvectors of the others'
        block below it (so a parameter without effect never mixes into another direction of
        the same null space, where eigenvectors are arbitrary)."""
        scaled = self.fisher * np.outer(self.scale, self.scale)
        largest = max(self.eigen[0][0], 1e-300)
        silent = np.diag(scaled) <= self.threshold * largest
        directions = [Direction(np.eye(len(silent))[i], max(scaled[i, i], 0.0) / largest) for i in np.flatnonzero(silent)]
        rest = np.flatnonzero(~silent)
        if rest.size:
            eigenvalues, vectors = np.linalg.eigh(scaled[np.ix_(rest, rest)])
            for k in np.flatnonzero(eigenvalues <= self.threshold * largest):
                weights = np.zeros(len(silent))
                weights[rest] = vectors[:, k]
                directions.append(Direction(weights, max(eigenvalues[k], 0.0) / largest))
        return directions

    @functools.cached_property
    def covariance(self) -> np.ndarray:
        """(P, P) F^-1 on the identified directions; inf variance (NaN covariances) for every
        parameter taking part in an unidentified one."""
        eigenvalues, vectors = self.eigen
        kept = self.identified
        inverse = np.where(kept, 1.0 / np.where(kept, eigenvalues, 1.0), 0.0)
        covariance = (vectors * inverse) @ vectors.T * np.outer(self.scale, self.scale)
        free = np.any(np.abs(vectors[:, ~kept]) > TAKES_PART, axis=1)
        covariance[free, :] = np.nan
        covariance[:, free] = np.nan
        covariance[free, free] = np.inf
        return covariance

    @property
    def stderr(self) -> np.ndarray:
        """(P,) predicted standard errors sqrt(diag F^-1) [the parameters' units]."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def relative_stderr(self) -> np.ndarray:
        """(P,) standard errors over s_i (over |guess|, unless the guess is 0)."""
        return self.stderr / self.scale

    @property
    def correlation(self) -> np.ndarray:
        error = self.stderr
        with np.errstate(invalid="ignore"):
            return self.covariance / np.outer(error, error)

    @property
    def log_det(self) -> float:
        """D-optimality log det S F S (-inf if a direction is not identified)."""
        if not self.identified.all():
            return -math.inf
        return float(np.sum(np.log(self.eigen[0])))

    @property
    def rank_and_log_det(self) -> tuple:
        """(identified directions, sum of their log lambda): what the greedy selection
        maximises, so that it still ranks designs that leave a direction unidentified."""
        kept = self.identified
        return int(kept.sum()), float(np.sum(np.log(self.eigen[0][kept])))


def information(fisher, names, values, scale=None, threshold=THRESHOLD) -> Information:
    """The `Information` of a Fisher matrix (P, P) at `values` (P,), scaled by `scale`
    (default |values|, 1 where a value is 0)."""
    values = np.asarray(values, float)
    scale = default_scale(values) if scale is None else np.asarray(scale, float)
    return Information(tuple(names), values, np.asarray(fisher, float), scale, threshold)


def default_scale(values, low=None, high=None) -> np.ndarray:
    """s_i = |theta_i|; for a zero value the prior range's width, or 1."""
    values = np.asarray(values, float)
    width = np.ones_like(values) if low is None else np.where(np.isfinite(high - low), high - low, 1.0)
    return np.where(values != 0.0, np.abs(values), width)


def fisher_matrix(jacobian) -> np.ndarray:
    """F = J^T J of a Jacobian of residuals already weighted by 1 / sigma (M, P)."""
    jacobian = np.asarray(jacobian, float)
    return jacobian.T @ jacobian


# --------------------------------------------------------------------------- selection


@dataclasses.dataclass(frozen=True)
class Step:
    """One addition of the greedy selection: the candidate added, the set so far, and the
    worst case over the guesses of the set's information."""

    added: str
    chosen: tuple
    worst: Information          # the information at the guess where the set is weakest


def greedy_selection(fishers: dict, k: int, names, guesses, scales, threshold=THRESHOLD) -> list[Step]:
    """The k candidates chosen one at a time, each maximising the worst case over the guesses
    of (identified directions, log det S F S) of the set with it (Fisher matrices of
    independent experiments add). fishers: {candidate: (G, P, P)}, guesses and scales (G, P)."""
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= len(fishers):
        raise SceneError(f"k = {k!r} must be a whole number from 1 to the number of candidates ({len(fishers)}).")
    total = np.zeros_like(next(iter(fishers.values())))
    chosen, steps = [], []
    for _ in range(k):
        scores = {}
        for name in fishers:
            if name not in chosen:
                scores[name] = worst_information(total + fishers[name], names, guesses, scales, threshold)
        best = max(scores, key=lambda name: scores[name].rank_and_log_det)
        chosen.append(best)
        total = total + fishers[best]
        steps.append(Step(best, tuple(chosen), scores[best]))
    return steps


def worst_information(fisher, names, guesses, scales, threshold=THRESHOLD) -> Information:
    """Of the Information at each guess (fisher (G, P, P), each scaled by its row of scales
    (G, P)), the one of least (identified directions, log det)."""
    each = [Information(tuple(names), np.asarray(g, float), f, s, threshold) for g, f, s in zip(guesses, fisher, scales)]
    return min(each, key=lambda info: info.rank_and_log_det)


# --------------------------------------------------------------------------- candidates


def planned_observations(sim, probes: dict, label="probes") -> Observations:
    """Observations to plan with: probes {name: {"times": (M,) [s] or "every": dt [s],
    "noise": sigma (one, or one per component), "components": [k, ...] (default all),
    "window": [s] (default 0)}}; the values are zeros (the Fisher information never reads
    them). `every` samples t = dt, 2 dt, ... up to the simulation's end."""
    if not isinstance(probes, dict) or not probes:
        raise SceneError(f"{label} = {probes!r} must name at least one probe: {{name: {{times, noise}}}}.")
    widths = {name: value.shape[0] for name, value in sim.observe_start(sim.initial_state()).items()}
    data, sigma, window = {}, {}, {}
    for name, plan in probes.items():
        where = f"{label}.{name}"
        if name not in widths:
            raise SceneError(f"{where} is not a probe of the scene (probes: {', '.join(map(repr, widths))}).")
        if not isinstance(plan, dict):
            raise SceneError(f"{where} = {plan!r} must be a table with times (or every) and noise.")
        unknown = sorted(set(plan) - {"times", "every", "noise", "components", "window"})
        if unknown:
            raise SceneError(f"{where}.{unknown[0]} is not a known key (use times, every, noise, components, window).")
        times = sampling_times(plan, float(sim.time[-1]), where)
        components = plan.get("components")
        components = list(range(widths[name])) if components is None else components
        if plan.get("noise") is None:
            raise SceneError(f"{where}.noise is missing: a design needs the noise sigma of every observed probe.")
        data[name] = (times, np.zeros((len(times), len(components))), components)
        sigma[name] = plan["noise"]
        window[name] = plan.get("window")
    try:
        observations = Observations.from_arrays(data, sigma, {k: v for k, v in window.items() if v is not None})
        check_against(observations, widths, (float(sim.time[0]), float(sim.time[-1])))
        return observations
    except SceneError as error:
        raise SceneError(str(error).replace("observations.", f"{label}.", 1)) from None


def sampling_times(plan: dict, end: float, where: str) -> np.ndarray:
    """The times of a plan: its `times`, or every `every` seconds from `every` to `end`."""
    if ("times" in plan) == ("every" in plan):
        raise SceneError(f"{where} must give exactly one of times (a list) or every (a sampling interval).")
    if "times" in plan:
        return np.asarray(plan["times"], float)
    every = plan["every"]
    if isinstance(every, bool) or not isinstance(every, (int, float)) or not (math.isfinite(every) and 0 < every <= end):
        raise SceneError(f"{where}.every = {every!r} must be a time in (0, {end:g}] s.")
    return every * np.arange(1, int(math.floor(end / every * (1 + 1e-9))) + 1)


def parameter_space(templates, parameters: dict) -> ParameterSpace:
    """The ParameterSpace of `parameters` {dotted name: guess | {"guess", "low", "high"}}
    (its start values are the guesses)."""
    if not isinstance(parameters, dict) or not parameters:
        raise SceneError(f"parameters = {parameters!r} must name at least one parameter with its guess.")
    fit = {}
    for name, spec in parameters.items():
        if isinstance(spec, dict):
            unknown = sorted(set(spec) - {"guess", "low", "high"})
            if unknown:
                raise SceneError(f"parameters.{name}.{unknown[0]} is not a known key (use guess, low, high).")
            fit[name] = {"start": spec.get("guess"), "low": spec.get("low"), "high": spec.get("high")}
        elif isinstance(spec, bool) or not isinstance(spec, (int, float)):
            raise SceneError(f"parameters.{name} = {spec!r} must be a guess (a number) or {{guess, low, high}}.")
        else:
            fit[name] = {"start": spec}
    try:
        return ParameterSpace(templates, fit)
    except SceneError as error:
        message = str(error).replace("fit: in every experiment, ", "fit: ", 1)
        raise SceneError("parameters" + message[3:] if message.startswith("fit") else message) from None


def guess_values(space: ParameterSpace, guesses="guess", seed=0) -> np.ndarray:
    """(G, P) points to evaluate the design at, the guess first: "guess" (only it), "corners"
    (and every corner of the prior range: a parameter without both bounds stays at its guess;
    beyond MAX_CORNERS corners, that many samples instead), a count (and count - 1 samples
    drawn uniformly in the prior range), or a list of {name: value} dicts."""
    guess = space.start_values()
    bounded = [e.low is not None and e.high is not None for e in space.entries]
    if isinstance(guesses, str) and guesses in ("guess", "corners"):
        if guesses == "guess" or not any(bounded):
            return guess[None]
        if 2 ** sum(bounded) > MAX_CORNERS:
            return guess_values(space, MAX_CORNERS + 1, seed)
        spans = [(e.low, e.high) if both else (value,) for e, value, both in zip(space.entries, guess, bounded)]
        return np.vstack([guess, np.array(list(itertools.product(*spans)), float)])
    if isinstance(guesses, int) and not isinstance(guesses, bool) and guesses >= 1:
        rng = np.random.default_rng(seed)
        draws = [np.array([rng.uniform(e.low, e.high) if both else value
                           for e, value, both in zip(space.entries, guess, bounded)]) for _ in range(guesses - 1)]
        return np.vstack([guess] + draws)
    if isinstance(guesses, (list, tuple)) and guesses and all(isinstance(g, dict) for g in guesses):
        rows = [guess]
        for index, point in enumerate(guesses):
            unknown = sorted(set(point) - set(space.names))
            if unknown:
                raise SceneError(f"guesses[{index}] names {unknown[0]!r}, which is not among the parameters.")
            rows.append(np.array([float(point.get(name, value)) for name, value in zip(space.names, guess)]))
        return np.vstack(rows)
    raise SceneError(f"guesses = {guesses!r} must be 'guess', 'corners', a number of points, or a list of {{name: value}}.")


def check_candidates(experiments, space: ParameterSpace, guesses):
    """SceneError, before anything compiles, for a candidate without noise on every probe,
    a fixed value that is also a design parameter, observations outside the scene, or a
    guess that makes the scene's fixed time step unstable."""
    from inverse.experiments import base_parameters

    dtypes = {e.sim.dtype for e in experiments}
    if len(dtypes) > 1:
        raise SceneError(f"candidates: every scene must have the same numerics.dtype (they have "
                         f"{', '.join(sorted(map(str, dtypes)))}).")
    for index, experiment in enumerate(experiments):
        label = f"candidates.{experiment.name}"
        missing = [name for name, c in experiment.observations.channels.items() if c.sigma is None]
        if missing:
            raise SceneError(f"{label}.probes.{missing[0]}.noise is missing: a design needs the noise of every probe.")
        base = base_parameters(experiment)          # names a bad set value first
        parameters = {location for _, location in space.fitted_in(index)}
        for name in experiment.set:
            if resolve(experiment.sim.params, name) in parameters:
                raise SceneError(f"{label}.set.{name} is also a design parameter: a value cannot be both fixed and sought.")
        check_observations(experiment)
        for values in guesses:
            try:
                experiment.sim.check_time_step(space.insert(jnp.asarray(values, experiment.sim.dtype), base, index))
            except SceneError as error:
                point = ", ".join(f"{n} = {v:g}" for n, v in zip(space.names, values))
                raise SceneError(f"{label} at the guess ({point}): {error}") from None


# --------------------------------------------------------------------------- the computation


def jacobians_at(experiments, space: ParameterSpace, guesses) -> list[np.ndarray]:
    """[(G, M_e, P)]: each experiment's weighted residual Jacobian dr_e/dtheta at each guess,
    in forward mode, the guesses under jax.vmap (a single guess runs unbatched)."""
    groups = group_experiments(experiments, space)
    data, bases = problem_arguments(experiments, groups)
    linearize = compiled_linearization(experiments, groups, space)
    _, jacobian = linearize(jnp.asarray(guesses, experiments[0].sim.dtype), data, bases)
    jacobian = np.asarray(jacobian)
    parts, row = {}, 0
    for group in groups:                     # rows in group order, a group's members one after another
        for index in group.members:
            count = experiments[index].observations.count
            parts[index] = jacobian[:, row:row + count]
            row += count
    return [parts[index] for index in range(len(experiments))]


def compiled_linearization(experiments, groups, space):
    """linearize(values (G, P), data, bases) -> (r (G, M), J (G, M, P)), jitted once per
    simulation, parameters and observation layouts (cached on the first simulation)."""
    key = (space.fingerprint(), tuple((id(e.sim), layout_of(e.observations)) for e in experiments))
    cache = experiments[0].sim.compiled_cache.setdefault("design", {})
    if key not in cache:
        residuals = problem_residuals(groups, derivatives="forward")

        def linearize(values, data, bases):
            return residuals_and_jacobian(functools.partial(residuals, data=data, bases=bases), values)

        several_fields = any(e.sim.several_fields for e in experiments)
        cache[key] = jit_with_options(over_starts(linearize, in_axes=(0, None, None)), several_fields=several_fields)
    return cache[key]


@dataclasses.dataclass
class Design:
    """The Fisher information of every candidate at every guess, and what it predicts.

    names: the parameters; candidates: the candidates' names; guesses (G, P), the guess first;
    fishers (G, C, P, P); scales (G, P) of each point's scaled coordinates (relative changes
    at that point); selection: the greedy steps (empty without k)."""

    names: tuple
    candidates: tuple
    guesses: np.ndarray
    fishers: np.ndarray
    scales: np.ndarray
    threshold: float
    selection: list
    seconds: float
    counts: tuple = ()          # observed values per candidate

    def fisher(self, chosen=None, guess=0) -> np.ndarray:
        """(P, P) the summed Fisher matrix of `chosen` (candidate names; default all) at one guess."""
        return self.fishers[guess, self.indices(chosen)].sum(axis=0)

    def indices(self, chosen=None) -> list[int]:
        chosen = self.candidates if chosen is None else ((chosen,) if isinstance(chosen, str) else tuple(chosen))
        unknown = [name for name in chosen if name not in self.candidates]
        if unknown:
            raise SceneError(f"{unknown[0]!r} is not a candidate (candidates: {', '.join(self.candidates)}).")
        return [self.candidates.index(name) for name in chosen]

    def information(self, chosen=None, guess=0) -> Information:
        """What `chosen` (a candidate's name, or several; default all) predicts at guess index `guess`."""
        return Information(self.names, self.guesses[guess], self.fisher(chosen, guess), self.scales[guess], self.threshold)

    def worst(self, chosen=None) -> Information:
        """The Information of `chosen` at the guess where it is weakest."""
        fisher = self.fishers[:, self.indices(chosen)].sum(axis=1)
        return worst_information(fisher, self.names, self.guesses, self.scales, self.threshold)

    def worst_stderr(self, chosen=None) -> np.ndarray:
        """(P,) the largest relative standard error of each parameter over the guesses."""
        return np.max([self.information(chosen, g).relative_stderr for g in range(len(self.guesses))], axis=0)

    def rows(self) -> list[tuple]:
        """(label, candidate names) of the designs reported: each candidate, the greedy
        sets, and all candidates together."""
        rows = [(name, (name,)) for name in self.candidates]
        rows += [(" + ".join(step.chosen), step.chosen) for step in self.selection if len(step.chosen) > 1]
        every = len(self.selection) == len(self.candidates)
        if len(self.candidates) > 1 and not every:
            rows.append(("all candidates", tuple(self.candidates)))
        return rows

    def summary(self) -> str:
        """The table: per design, relative standard error of each parameter at the guess (and,
        with several guesses, the worst over them), log det of the scaled Fisher matrix, the
        unidentified directions; then the greedy selection."""
        several = len(self.guesses) > 1
        guess = ", ".join(f"{n} = {v:g}" for n, v in zip(self.names, self.guesses[0]))
        lines = [f"Fisher information of {len(self.candidates)} candidates at the guess ({guess})"
                 + (f" and {len(self.guesses) - 1} more points of the prior range" if several else "")
                 + f", {self.seconds:.1f} s.",
                 "Predicted standard errors relative to |guess|" + (" (worst over the points in brackets)" if several else "")
                 + "; log det of the scaled Fisher matrix (D-optimality, larger is better):"]
        table, notes = [], []
        for label, chosen in self.rows():
            info, worst = self.information(chosen), self.worst(chosen)
            cells = [percent(e) + (f" ({percent(w)})" if several else "")
                     for e, w in zip(info.relative_stderr, self.worst_stderr(chosen))]
            table.append([label] + cells + [f"{worst.log_det if several else info.log_det:.4g}"])
            for direction in worst.unidentified:
                notes.append(f"  {label}: {direction.describe(self.names)} is not identified "
                             f"(eigenvalue ratio {direction.ratio:.2g})")
        header = ["design", *self.names, "log det"]
        widths = [max(len(row[c]) for row in [header] + table) for c in range(len(header))]
        for row in [header] + table:
            lines.append("  " + row[0].ljust(widths[0]) + "".join(f"  {cell:>{w}}" for cell, w in zip(row[1:], widths[1:])))
        lines += notes
        if self.selection:
            lines.append(f"Greedy selection of {len(self.selection)} by D-optimality"
                         + (" (worst case over the points)" if several else "") + ":")
            for number, step in enumerate(self.selection, start=1):
                errors = ", ".join(f"{n} {percent(e)}" for n, e in zip(self.names, self.worst_stderr(step.chosen)))
                lines.append(f"  {number}. + {step.added}: log det {step.worst.log_det:.4g}; {errors}")
        return "\n".join(lines)

    def save(self, path) -> Path:
        """By suffix: .csv (one row per design and point: its log det and each parameter's
        value and standard error) or HDF5 (.h5, .hdf5), written atomically: attrs threshold,
        seconds; /names, /candidates, /guesses (G, P), /scale, /fishers (G, C, P, P),
        /designs/LABEL/{candidates, stderr (G, P), log_det (G,), correlation (G, P, P)},
        /selection/{order, log_det, relative_stderr (k, P)} (worst over the points)."""
        path = Path(path)
        if path.suffix.lower() == ".csv":
            return self.save_csv(path)
        import h5py

        with atomic_path(path) as temporary, h5py.File(temporary, "w") as file:
            file.attrs.update(threshold=self.threshold, seconds=self.seconds)
            file.create_dataset("names", data=np.array(self.names, dtype="S"))
            file.create_dataset("candidates", data=np.array(self.candidates, dtype="S"))
            file.create_dataset("counts", data=np.array(self.counts, dtype=int))
            for name in ("guesses", "scales", "fishers"):
                file.create_dataset(name, data=getattr(self, name))
            for label, chosen in self.rows():
                group = file.create_group(f"designs/{label.replace('/', '_')}")
                each = [self.information(chosen, g) for g in range(len(self.guesses))]
                group.create_dataset("candidates", data=np.array(chosen, dtype="S"))
                group.create_dataset("stderr", data=np.array([i.stderr for i in each]))
                group.create_dataset("log_det", data=np.array([i.log_det for i in each]))
                group.create_dataset("correlation", data=np.array([i.correlation for i in each]))
            if self.selection:
                file.create_dataset("selection/order", data=np.array([s.added for s in self.selection], dtype="S"))
                file.create_dataset("selection/log_det", data=np.array([s.worst.log_det for s in self.selection]))
                file.create_dataset("selection/relative_stderr", data=np.array([self.worst_stderr(s.chosen)
                                                                                for s in self.selection]))
        return path

    def save_csv(self, path) -> Path:
        header = ["design", "point", "log_det"] + [f"{n}{suffix}" for n in self.names for suffix in ("", "_stderr")]
        lines = [",".join(header)]
        for label, chosen in self.rows():
            for g in range(len(self.guesses)):
                info = self.information(chosen, g)
                cells = [f"{v!r},{e!r}" for v, e in zip(info.values.tolist(), info.stderr.tolist())]
                lines.append(",".join([f'"{label}"', str(g), repr(info.log_det)] + cells))
        with atomic_path(path) as temporary:
            temporary.write_text("\n".join(lines) + "\n")
        return path

    def plot(self, path=None):
        """Predicted one-standard-error ellipses at the guess, in relative changes of each pair
        of parameters (a bar per design for one parameter); a design that leaves a pair
        unidentified is left out of its panel. Returns the figure (written to `path` if given)."""
        import matplotlib.pyplot as plt

        pairs = list(itertools.combinations(range(len(self.names)), 2)) or [(0, 0)]
        figure, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 4.0), squeeze=False)
        for axis, (i, j) in zip(axes[0], pairs):
            for number, (label, chosen) in enumerate(self.rows()):
                relative = self.information(chosen).covariance / np.outer(self.scales[0], self.scales[0])
                block = relative[np.ix_([i, j], [i, j])]
                if not np.all(np.isfinite(block)):
                    continue
                if i == j:
                    axis.errorbar([number], [0.0], yerr=[math.sqrt(block[0, 0])], fmt="o", capsize=4, label=label)
                    continue
                eigenvalues, vectors = np.linalg.eigh(block)
                angle = np.linspace(0.0, 2.0 * np.pi, 121)
                ellipse = vectors @ (np.sqrt(np.clip(eigenvalues, 0.0, None))[:, None] * np.stack([np.cos(angle), np.sin(angle)]))
                axis.plot(100 * ellipse[0], 100 * ellipse[1], lw=1.3, label=label)
            axis.set_xlabel(f"{self.names[i]} [% of guess]")
            axis.set_ylabel(f"{self.names[j]} [% of guess]" if i != j else "relative error [% of guess]")
            axis.axhline(0.0, color="0.85", lw=0.8)
            axis.axvline(0.0, color="0.85", lw=0.8)
            if axis.get_legend_handles_labels()[0]:
                axis.legend(fontsize=7)
            else:
                axis.text(0.5, 0.5, "not identified by any design", ha="center", transform=axis.transAxes)
        figure.suptitle("predicted 1-standard-error regions at the guess", fontsize=10)
        figure.tight_layout()
        if path is not None:
            figure.savefig(path, dpi=130)
        return figure


def percent(relative) -> str:
    """12.3 %, 0.041 %, or "not identified" for an infinite error."""
    return f"{100 * relative:.3g} %" if np.isfinite(relative) else "not identified"


def design(candidates, parameters: dict, k: int | None = None, guesses="guess", seed: int = 0,
           threshold: float = THRESHOLD) -> Design:
    """The `Design` of `candidates` (a list of inverse.Experiment, observations planned with
    `planned_observations`; or one) for `parameters` {dotted name: guess | {"guess", "low",
    "high"}}, evaluated at `guesses` (see `guess_values`), with the greedy selection of `k`
    candidates when k is given. Every check runs before anything compiles."""
    started = clock.monotonic()
    experiments = experiments_from(candidates if isinstance(candidates, (list, tuple)) else [candidates], None)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0.0 < threshold < 1.0:
        raise SceneError(f"threshold = {threshold!r} must be a number in (0, 1).")
    if k is not None and (isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= len(experiments)):
        raise SceneError(f"k = {k!r} must be a whole number from 1 to the number of candidates ({len(experiments)}).")
    space = parameter_space([e.sim.params for e in experiments], parameters)
    points = guess_values(space, guesses, seed)
    check_candidates(experiments, space, points)
    jacobians = jacobians_at(experiments, space, points)
    fishers = np.stack([np.einsum("gmp,gmq->gpq", j, j) for j in jacobians], axis=1)     # (G, C, P, P)
    low = np.array([np.nan if e.low is None else e.low for e in space.entries])
    high = np.array([np.nan if e.high is None else e.high for e in space.entries])
    scales = np.stack([default_scale(point, low, high) for point in points])
    names = tuple(e.name for e in experiments)
    selection = [] if k is None else greedy_selection(
        {name: fishers[:, index] for index, name in enumerate(names)}, k, space.names, points, scales, threshold)
    return Design(space.names, names, points, fishers, scales, threshold, selection, clock.monotonic() - started,
                  tuple(e.observations.count for e in experiments))
