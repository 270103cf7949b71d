"""inverse: gradient-based calibration of jaxmpm parameters.

    import inverse
    observations = inverse.load_observations("measured.csv", sigma={"top": 1e-4})
    fit = inverse.calibrate(sim, observations, fit={"sand.friction_angle": (20, 45)})
    fit.params, fit.stderr, fit.correlation, fit.history, fit.cost, fit.plot(), fit.save("fit.h5")

Several experiments sharing parameters: inverse.calibrate([inverse.Experiment(sim, slow, set=...),
inverse.Experiment(sim, fast, set=...)], fit=...).
"""

from inverse.calibrate import calibrate
from inverse.experiments import Experiment, as_observations
from inverse.fit import Fit
from inverse.observations import Channel, Observations, load_observations
from inverse.parameters import ParameterSpace

__all__ = ["Channel", "Experiment", "Fit", "Observations", "ParameterSpace", "as_observations", "calibrate",
           "load_observations"]
