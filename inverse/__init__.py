"""inverse: gradient-based calibration of jaxmpm parameters.

    import inverse
    observations = inverse.load_observations("measured.csv", sigma={"top": 1e-4})
    fit = inverse.calibrate(sim, observations, fit={"sand.friction_angle": (20, 45)})
    fit.params, fit.stderr, fit.correlation, fit.history, fit.cost, fit.plot(), fit.save("fit.h5")

Several experiments sharing parameters: inverse.calibrate([inverse.Experiment(sim, slow, set=...),
inverse.Experiment(sim, fast, set=...)], fit=...).

Experiment design before measuring (inverse/design.py): inverse.design([inverse.Experiment(sim,
inverse.planned_observations(sim, {"top": {"every": 0.01, "noise": 1e-4}}), set=...), ...],
parameters={"sand.friction_angle": {"guess": 30, "low": 20, "high": 40}}, k=2).summary().
"""

from inverse.calibrate import calibrate
from inverse.design import Design, design, planned_observations
from inverse.experiments import Experiment, as_observations
from inverse.fit import Fit
from inverse.observations import Channel, Observations, load_observations
from inverse.parameters import ParameterSpace

__all__ = ["Channel", "Design", "Experiment", "Fit", "Observations", "ParameterSpace", "as_observations", "calibrate",
           "design", "load_observations", "planned_observations"]
