"""How much a fit's parameters owe to the discretisation: the shift at refined numerics.

A model whose predictions depend on the time step or the cell returns fitted parameters that
depend on them too. At the fitted values theta*, the weighted residuals r (M,) and their
Jacobian J (M, P) are known. Refining the numerics (the time step halved, or the cell) changes
the predictions, and so the residuals, by d = r_refined(theta*) - r(theta*). To first order
the refined model's best fit is then theta* + delta,

    delta = -J^+ d,

the Gauss-Newton step of the refined problem from theta* (J^+ the pseudo-inverse, with the
directions the data do not constrain left out, as in `fit.gauss_newton`). Each refinement
costs one forward run of every experiment at the refined numerics and one compilation. When
|delta| is well below the noise standard errors the numerics are fine enough for this fit;
when it is comparable or larger, the discretisation, not the noise, limits the result.

"relaxation" is not a refinement but a sensitivity: the relaxation kappa (numerics.relaxation,
the time over which the points' own velocity fades into the grid's) doubled. kappa is a
numerical parameter whose effect vanishes neither with dt nor with the cell: between kappa
= 10 and 1000 the examples' headline results move by 10-65 % (docs/convergence.md); the shift
says how much of the fit rests on its choice.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from inverse.experiments import group_experiments, problem_arguments, problem_residuals
from jaxmpm.running.refinement import refined_scene


def refined_experiments(experiments, refinement: str):
    """The experiments with their simulations rebuilt at the refined numerics; experiments
    that shared one Simulation share one refined Simulation."""
    from jaxmpm import Simulation

    rebuilt = {}
    for experiment in experiments:
        if id(experiment.sim) not in rebuilt:
            sim = experiment.sim
            rebuilt[id(sim)] = Simulation(refined_scene(sim.scene, refinement), checkpointing=sim.checkpointing)
    return [dataclasses.replace(e, sim=rebuilt[id(e.sim)]) for e in experiments]


def residuals_at(experiments, space, values):
    """Every experiment's weighted residuals (M,) at the physical `values` (P,)."""
    groups = group_experiments(experiments, space)
    data, bases = problem_arguments(experiments, groups)
    return np.asarray(jax.jit(problem_residuals(groups))(values, data, bases))


def parameter_shift(jacobian, difference):
    """-J^+ d: the Gauss-Newton step (P,) that a change `difference` (M,) of the residuals
    asks for, with the directions whose singular value is below sqrt(eps) of the largest
    (unconstrained by the data) left out. The columns are scaled to unit norm first, so that
    parameters of different units weigh alike."""
    jacobian = np.asarray(jacobian, float)
    norms = np.linalg.norm(jacobian, axis=0)
    scale = np.where(norms > 0.0, norms, 1.0)
    left, singular, right = np.linalg.svd(jacobian / scale, full_matrices=False)
    kept = singular > np.sqrt(np.finfo(float).eps) * max(singular.max(initial=0.0), 1e-300)
    inverse = np.where(kept, 1.0 / np.where(kept, singular, 1.0), 0.0)
    return -(right.T @ (inverse * (left.T @ np.asarray(difference, float)))) / scale


def numerical_shifts(experiments, space, values, residuals, jacobian, refinements):
    """{refinement: (P,) shift of the fitted values} for each of `refinements` (`REFINEMENTS`)."""
    shifts = {}
    for refinement in refinements:
        refined = residuals_at(refined_experiments(experiments, refinement), space, values)
        shifts[refinement] = parameter_shift(jacobian, refined - np.asarray(residuals))
    return shifts
