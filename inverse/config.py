"""Calibration configuration files, for `jaxmpm calibrate CONFIG.toml -o FIT.h5`.

One experiment:

    scene = "twin_scene.toml"                  # paths are relative to this file
    observations = "twin_observations.csv"     # .csv or .h5 (e.g. a jaxmpm output file)

    [noise]                                    # optional: noise std of each probe, its units
    footing = 1.0e-5                           # (or one value per observed component: [1e-5, 2e-5])

    [window]                                   # optional: each value is the probe's mean over
    thrust = 0.01                              # this window [s] centred on its time

Several experiments sharing the fitted parameters (instead of scene/observations/noise):

    [[experiments]]
    name = "slow"
    scene = "footing.toml"
    observations = "slow.csv"
    set = { "bodies.footing.velocity" = [0.0, -0.02] }   # optional: this experiment's own values
    noise = { footing = 1.0e-5 }                         # optional
    window = { footing = 0.01 }                          # optional

    [[experiments]]
    name = "fast"
    scene = "footing.toml"                     # the same scene file: one Simulation, vmapped
    observations = "fast.csv"
    set = { "bodies.footing.velocity" = [0.0, -0.08] }

Then, for both forms:

    [fit]                                      # parameters to fit, with bounds
    "sand.friction_angle" = [15.0, 40.0]
    "sand.fluidity" = { low = 0.1, high = 100.0, start = 3.0 }

    [optimizer]                                # all optional
    name = "lm"                                # or "lbfgs", "adam" (then learning_rate, default 0.05)
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
from jaxmpm.scene import _Table, convert, load_scene
from inverse.observations import load_observations

OPTIONS = {"name": ("str", "lm"), "max_iterations": ("int", 50), "starts": ("int", 1),
           "learning_rate": ("float", None), "gtol": ("float", 1e-8), "ftol": ("float", 1e-10),
           "seed": ("int", 0), "checkpoint_every": ("int", 5)}


@dataclasses.dataclass
class ExperimentConfig:
    name: str | None
    scene: object
    scene_path: Path
    observations: object
    set: dict


@dataclasses.dataclass
class CalibrationConfig:
    experiments: list
    fit: dict
    options: dict

    def simulations(self):
        """inverse.Experiments with one jaxmpm.Simulation per scene file (experiments of the
        same file share it, so they run together under vmap)."""
        import jaxmpm
        from inverse.experiments import Experiment

        sims = {}
        experiments = []
        for experiment in self.experiments:
            key = experiment.scene_path.resolve()
            if key not in sims:
                sims[key] = jaxmpm.Simulation(experiment.scene)
            experiments.append(Experiment(sims[key], experiment.observations, experiment.set, experiment.name))
        return experiments


def _per_probe(table: _Table, per_component=False) -> dict:
    """{probe: number} of a [window] table, or of a [noise] table (per_component: a number or
    one number per observed component)."""
    table.known = list(table.data)
    values = {}
    for name in table.data:
        value = table.get(name, "any")
        if per_component and isinstance(value, list) and value:
            values[name] = [convert(f"{table.key(name)}[{k}]", item, "float") for k, item in enumerate(value)]
        else:
            values[name] = convert(table.key(name), value, "float")
    return values


def _experiment(table: _Table, folder: Path, name=None) -> ExperimentConfig:
    scene_path = folder / table.get("scene", "str")
    scene = load_scene(scene_path)
    noise = _per_probe(table.table("noise", {}), per_component=True)
    window = _per_probe(table.table("window", {}))
    observations = load_observations(folder / table.get("observations", "str"), sigma=noise, window=window)
    fixed = table.get("set", "any", {})
    if not isinstance(fixed, dict):
        raise SceneError(f"{table.key('set')} = {fixed!r} must be a table of dotted names and values.")
    return ExperimentConfig(name, scene, scene_path, observations, fixed)


def load_calibration(path) -> CalibrationConfig:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as error:
        raise SceneError(f"cannot read calibration file {str(path)!r}: {error.strerror}.") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path} is not valid TOML: {error}.") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path} is not UTF-8 text.") from None
    root = _Table(data, "")
    root.known = ["scene", "observations", "fit", "noise", "window", "optimizer", "experiments"]
    if "experiments" in data:
        for key in ("scene", "observations", "noise", "window"):
            if key in data:
                raise SceneError(f"{key} is given beside [[experiments]]: put it inside each experiment.")
        entries = root.get("experiments", "any")
        if not isinstance(entries, list) or not entries:
            raise SceneError("experiments must be a non-empty array of tables ([[experiments]]).")
        experiments = []
        for index, entry in enumerate(entries):
            table = _Table(entry, f"experiments[{index}]")
            table.known = ["name", "scene", "observations", "set", "noise", "window"]
            experiments.append(_experiment(table, path.parent, table.get("name", "str", None)))
            table.finish()
    else:
        experiments = [_experiment(root, path.parent)]
    fit = root.get("fit", "any")
    if not isinstance(fit, dict) or not fit:
        raise SceneError("fit must be a table naming at least one parameter, e.g. \"sand.friction_angle\" = [20, 45].")
    optimizer = root.table("optimizer", {})
    optimizer.known = list(OPTIONS)
    options = {key: optimizer.get(key, kind, default) for key, (kind, default) in OPTIONS.items()}
    optimizer.finish()
    root.finish()
    return CalibrationConfig(experiments, fit, options)
