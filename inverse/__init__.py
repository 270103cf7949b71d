"""inverse: gradient-based calibration of jaxmpm material parameters.

    import inverse
    observations = inverse.load_observations("measured.csv", sigma={"top": 1e-4})
    fit = inverse.calibrate(sim, observations, fit={"sand.friction_angle": (20, 45)})
    fit.params, fit.stderr, fit.correlation, fit.history, fit.plot(), fit.save("fit.h5")
"""

from inverse.calibrate import calibrate
from inverse.fit import Fit
from inverse.observations import Channel, Observations, load_observations
from inverse.parameters import ParameterSpace

__all__ = ["Channel", "Fit", "Observations", "ParameterSpace", "calibrate", "load_observations"]
