"""The parameters being fitted, and the unconstrained coordinates the optimiser works in.

A fitted parameter is named by its dotted name in `sim.params` ("sand.friction_angle",
"materials.sand.friction_angle", "contacts.backfill/wall.friction"; see `jaxmpm.scene.parameters`)
and keeps the name it was given in the results. Bounds decide the transform:
  (low, high)   scaled logit:  x = low + (high - low) sigmoid(z)
  (low, None)   log shift:     x = low + exp(z)          (e.g. (0, None) for a positive value)
  (None, high)  log shift:     x = high - exp(z)
  (None, None)  identity:      x = z
Everything not named stays at its value in the simulation's parameters.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.scene.parameters import location_name, resolve, value_at, with_values


@dataclasses.dataclass(frozen=True)
class Bounded:
    """One fitted parameter: its path, bounds (either may be None) and start value."""

    path: str
    low: float | None
    high: float | None
    start: float

    def to_unconstrained(self, x):
        if self.low is not None and self.high is not None:
            fraction = (x - self.low) / (self.high - self.low)
            return jnp.log(fraction) - jnp.log1p(-fraction)
        if self.low is not None:
            return jnp.log(x - self.low)
        if self.high is not None:
            return jnp.log(self.high - x)
        return x

    def to_physical(self, z):
        if self.low is not None and self.high is not None:
            return self.low + (self.high - self.low) * jax.nn.sigmoid(z)
        if self.low is not None:
            return self.low + jnp.exp(z)
        if self.high is not None:
            return self.high - jnp.exp(z)
        return z


def _bounds(path, spec):
    """(low, high, start) from (low, high) or {"low": .., "high": .., "start": ..}."""
    start = None
    if isinstance(spec, dict):
        unknown = set(spec) - {"low", "high", "start"}
        if unknown:
            raise SceneError(f"fit.{path} has unknown key {sorted(unknown)[0]!r} (use low, high, start).")
        low, high, start = spec.get("low"), spec.get("high"), spec.get("start")
    elif isinstance(spec, (tuple, list)) and len(spec) == 2:
        low, high = spec
    else:
        raise SceneError(f"fit.{path} = {spec!r} must be (low, high) or {{low, high, start}}.")
    for name, value in (("low", low), ("high", high), ("start", start)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)):
            raise SceneError(f"fit.{path}.{name} = {value!r} must be a finite number.")
    if low is not None and high is not None and not low < high:
        raise SceneError(f"fit.{path} = ({low}, {high}): the lower bound must be below the upper bound.")
    return low, high, start


class ParameterSpace:
    """The fitted subset of one or several simulations' parameters, with transforms to
    unconstrained z. `params` is one parameter pytree, or a list of them (one per experiment):
    a fitted name then applies to every experiment whose parameters have it, and must exist
    in at least one; its start value is taken from the first that has it."""

    def __init__(self, params, fit: dict):
        if not fit:
            raise SceneError("fit is empty: name at least one parameter, e.g. 'sand.friction_angle'.")
        templates = list(params) if isinstance(params, (list, tuple)) else [params]
        self.templates = templates
        self.template = templates[0]
        self.entries = []
        self.placements = [[] for _ in templates]   # per experiment: (entry index, location from `resolve`)
        for path, spec in fit.items():
            found, first_error, value = [], None, None
            for experiment, template in enumerate(templates):
                try:
                    location = resolve(template, path)
                except SceneError as error:
                    first_error = first_error or error
                    continue
                if any(location == placed for _, placed in self.placements[experiment]):
                    raise SceneError(f"fit names {path!r} twice (as {location_name(location)}).")
                here = np.asarray(value_at(template, location))
                if here.shape != ():
                    raise SceneError(f"fit names {path!r}, which is not a single number (shape {here.shape}): "
                                     f"name one component, e.g. '{path}[0]'.")
                value = here if value is None else value
                found.append((experiment, location))
            if not found:
                prefix = "fit: " if len(templates) == 1 else "fit: in every experiment, "
                raise SceneError(f"{prefix}{first_error}") from None
            for experiment, location in found:
                self.placements[experiment].append((len(self.entries), location))
            low, high, start = _bounds(path, spec)
            start = float(value) if start is None else float(start)
            inside = (low is None or start > low) and (high is None or start < high)
            if not inside:
                raise SceneError(
                    f"fit.{path}: the initial value {start:g} is not strictly inside the bounds "
                    f"({low}, {high})."
                )
            self.entries.append(Bounded(path, None if low is None else float(low), None if high is None else float(high), start))
        self.names = tuple(entry.path for entry in self.entries)
        self.locations = [location for _, location in self.placements[0]]

    def fitted_in(self, experiment=0):
        """[(entry, (namespace, owner, key))] of the fitted parameters one experiment has."""
        return [(self.entries[index], location) for index, location in self.placements[experiment]]

    @property
    def size(self):
        return len(self.entries)

    def start_values(self):
        return np.array([entry.start for entry in self.entries])

    def to_unconstrained(self, values):
        return jnp.stack([e.to_unconstrained(values[i]) for i, e in enumerate(self.entries)])

    def to_physical(self, z):
        return jnp.stack([e.to_physical(z[i]) for i, e in enumerate(self.entries)])

    def insert(self, values, params=None, experiment=0):
        """A copy of an experiment's parameter pytree with the fitted values (P,) it has
        replaced (differentiable)."""
        params = self.templates[experiment] if params is None else params
        return with_values(params, {location_name(location): values[index] for index, location in self.placements[experiment]})

    def random_values(self, count, seed):
        """`count` start vectors drawn uniformly inside the bounds (1-99 % of the range;
        log-uniform beyond a single
        bound: within a factor 10 of the start's distance to it); the first is the configured start."""
        rng = np.random.default_rng(seed)
        draws = [self.start_values()]
        for _ in range(count - 1):
            row = []
            for entry in self.entries:
                if entry.low is not None and entry.high is not None:
                    row.append(entry.low + (entry.high - entry.low) * rng.uniform(0.01, 0.99))
                elif entry.low is not None:
                    row.append(entry.low + (entry.start - entry.low) * 10.0 ** rng.uniform(-1.0, 1.0))
                elif entry.high is not None:
                    row.append(entry.high - (entry.high - entry.start) * 10.0 ** rng.uniform(-1.0, 1.0))
                else:
                    row.append(entry.start + rng.normal() * max(1.0, abs(entry.start)))
            draws.append(np.array(row))
        return np.stack(draws)

    def fingerprint(self):
        """What must match for a checkpoint to be resumed."""
        return repr([(e.path, e.low, e.high) for e in self.entries])
