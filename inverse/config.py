"""Calibration configuration files, for `jaxmpm calibrate CONFIG.toml -o FIT.h5`.

    scene = "twin_scene.toml"                  # paths are relative to this file
    observations = "twin_observations.csv"     # .csv or .h5 (e.g. a jaxmpm output file)

    [fit]                                      # parameters to fit, with bounds
    "sand.friction_angle" = [15.0, 40.0]
    "sand.fluidity" = { low = 0.1, high = 100.0, start = 3.0 }

    [noise]                                    # optional: noise std of each probe, its units
    footing = 1.0e-5

    [optimizer]                                # all optional
    name = "lbfgs"                             # or "adam" (then learning_rate, default 0.05)
    max_iterations = 50
    starts = 1
    gtol = 1e-8
    ftol = 1e-10
    seed = 0
    checkpoint_every = 5
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

from jaxmpm.errors import SceneError
from jaxmpm.scene import _Table, load_scene
from inverse.observations import load_observations

OPTIONS = {"name": ("str", "lbfgs"), "max_iterations": ("int", 50), "starts": ("int", 1),
           "learning_rate": ("float", None), "gtol": ("float", 1e-8), "ftol": ("float", 1e-10),
           "seed": ("int", 0), "checkpoint_every": ("int", 5)}


@dataclasses.dataclass
class CalibrationConfig:
    scene: object
    observations: object
    fit: dict
    options: dict


def load_calibration(path) -> CalibrationConfig:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as error:
        raise SceneError(f"cannot read calibration file {str(path)!r}: {error.strerror}.") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path} is not valid TOML: {error}.") from None
    root = _Table(data, "")
    root.known = ["scene", "observations", "fit", "noise", "optimizer"]
    scene = load_scene(path.parent / root.get("scene", "str"))
    noise_table = root.table("noise", {})
    noise_table.known = list(noise_table.data)
    noise = {name: noise_table.get(name, "float") for name in noise_table.data}
    observations = load_observations(path.parent / root.get("observations", "str"), sigma=noise)
    fit = root.get("fit", "any")
    if not isinstance(fit, dict) or not fit:
        raise SceneError("fit must be a table naming at least one parameter, e.g. \"sand.friction_angle\" = [20, 45].")
    optimizer = root.table("optimizer", {})
    optimizer.known = list(OPTIONS)
    options = {key: optimizer.get(key, kind, default) for key, (kind, default) in OPTIONS.items()}
    optimizer.finish()
    root.finish()
    return CalibrationConfig(scene, observations, fit, options)
