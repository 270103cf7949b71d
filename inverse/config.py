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
from jaxmpm.keys import Key, Section, convert, read_section
from jaxmpm.scene import load_scene
from inverse.problem import OPTIMIZERS
from inverse.observations import load_observations

NOISE = Key("noise", "mapping", "noise standard deviation of each observed probe, in the probe's units: "
            "one number, or one per observed component (absent: each channel weighted by its RMS)", default={})
WINDOW = Key("window", "mapping", "each listed probe's value is its mean over this window, centred on "
             "its time", unit="s", default={})
EXPERIMENT = Section((
    Key("name", "str", "the experiment's name in outputs", default=None),
    Key("scene", "str", "the scene file, relative to the calibration file"),
    Key("observations", "str", "the observations, .csv or .h5 (a jaxmpm output file works), relative to "
        "the calibration file"),
    Key("set", "mapping", "this experiment's own values: dotted name = value (e.g. a pile velocity)", default={}),
    NOISE,
    WINDOW,
), "one experiment: a scene, its observations, its own values")
OPTIMIZER = Section((
    Key("name", "str", "'lm' (Levenberg-Marquardt, forward-mode Jacobians), 'lbfgs' or 'adam' (optax)",
        default="lm", choices=tuple(OPTIMIZERS)),
    Key("max_iterations", "int", "iteration limit", default=50, low=1, low_inclusive=True),
    Key("starts", "int", "start points: the configured start plus random draws inside the bounds, run "
        "together under vmap", default=1, low=1, low_inclusive=True),
    Key("learning_rate", "float", "step size of 'adam' (absent: 0.05) and of 'lbfgs' (absent: its line "
        "search sets it); unused by 'lm'", default=None, low=0.0),
    Key("gtol", "float", "stop when the largest gradient component ||dL/dz||_inf, in the unconstrained "
        "coordinates z of the bounded parameters, falls below this", default=1e-8, low=0.0, low_inclusive=True),
    Key("ftol", "float", "stop when an accepted step changes the loss L by at most ftol max(|L|, tiny)",
        default=1e-10, low=0.0, low_inclusive=True),
    Key("seed", "int", "seed of the random start points", default=0),
    Key("checkpoint_every", "int", "iterations between checkpoints (OUT.h5.checkpoint.npz, removed "
        "once OUT.h5 is written unless --keep-checkpoint; --resume continues from it)", default=5, low=1, low_inclusive=True),
), "the optimiser; every key is optional")
CALIBRATION_FILE = Section((
    Key("scene", "str", "one experiment: its scene file, relative to this file (or give [[experiments]])",
        default=None),
    Key("observations", "str", "one experiment: its observations, .csv or .h5", default=None),
    NOISE,
    WINDOW,
    Key("experiments", "tables", "several experiments sharing the fitted parameters, instead of scene and "
        "observations", default=None, section=EXPERIMENT),
    Key("fit", "mapping", "the parameters to fit: \"dotted.name\" = [low, high] or { low, high, start }"),
    Key("optimizer", "table", "the optimiser", default={}, section=OPTIMIZER),
    Key("numerical_check", "strings", "refinements after the fit: 'dt' (time step halved), 'cell' (cell "
        "halved), 'relaxation' (numerics.relaxation doubled); for each, how far the fitted values would move "
        "at those numerics, beside the noise standard errors (one forward run of every experiment each)",
        default=[], choices=("dt", "cell", "relaxation")),
))


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
        same file share it, so they run together under vmap, for every start). With a
        reverse-mode optimizer, each of the rollouts run together gets its share of the memory
        reverse mode may keep (`jaxmpm.Checkpointing.budget`); Levenberg-Marquardt's forward
        mode keeps none."""
        import jaxmpm
        from jaxmpm.running.rollout import STORE_BUDGET_BYTES
        from inverse.experiments import Experiment

        sharing = {}
        for experiment in self.experiments:
            key = experiment.scene_path.resolve()
            sharing[key] = sharing.get(key, 0) + 1
        sims = {}
        experiments = []
        for experiment in self.experiments:
            key = experiment.scene_path.resolve()
            if key not in sims:
                reverse = self.options.get("name", "lm") != "lm"
                together = sharing[key] * self.options.get("starts", 1) if reverse else 1
                sims[key] = jaxmpm.Simulation(experiment.scene, jaxmpm.Checkpointing(budget=STORE_BUDGET_BYTES // together))
            experiments.append(Experiment(sims[key], experiment.observations, experiment.set, experiment.name))
        return experiments


def _per_probe(values: dict, path: str, per_component=False) -> dict:
    """{probe: number} of a [window] table, or of a [noise] table (per_component: a number or
    one number per observed component)."""
    checked = {}
    for name, value in values.items():
        key = f"{path}.{name}" if path else name
        if per_component and isinstance(value, list) and value:
            checked[name] = [convert(f"{key}[{k}]", item, "float") for k, item in enumerate(value)]
        else:
            checked[name] = convert(key, value, "float")
    return checked


def _experiment(values: dict, path: str, folder: Path) -> ExperimentConfig:
    scene_path = folder / values["scene"]
    scene = load_scene(scene_path)
    prefix = f"{path}." if path else ""
    noise = _per_probe(values["noise"], prefix + "noise", per_component=True)
    window = _per_probe(values["window"], prefix + "window")
    observations = load_observations(folder / values["observations"], sigma=noise, window=window)
    return ExperimentConfig(values.get("name"), scene, scene_path, observations, values.get("set", {}))


def read_toml(path: Path, kind: str = "calibration file") -> dict:
    """The TOML table of a file (a calibration or design file), or one SceneError sentence."""
    try:
        return tomllib.loads(path.read_text())
    except OSError as error:
        raise SceneError(f"cannot read {kind} {str(path)!r}: {error.strerror}.") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path} is not valid TOML: {error}.") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path} is not UTF-8 text.") from None


def load_calibration(path) -> CalibrationConfig:
    path = Path(path)
    data = read_toml(path)
    if "grid" in data and "fit" not in data:
        raise SceneError(f"{str(path)!r} is a scene file (it has [grid]), not a calibration file: give it to "
                         "`jaxmpm run`, or name it as the scene of a calibration file (scene = \"...\").")
    values = read_section(CALIBRATION_FILE, data, "")
    if values["experiments"] is not None:
        for key in ("scene", "observations", "noise", "window"):
            if key in data:
                raise SceneError(f"{key} is given beside [[experiments]]: put it inside each experiment.")
        if not values["experiments"]:
            raise SceneError("experiments must be a non-empty array of tables ([[experiments]]).")
        experiments = [_experiment(entry, f"experiments[{index}]", path.parent)
                       for index, entry in enumerate(values["experiments"])]
    else:
        for key in ("scene", "observations"):
            if values[key] is None:
                raise SceneError(f"{key} is missing: give scene and observations, or [[experiments]] tables.")
        experiments = [_experiment(values, "", path.parent)]
    if not values["fit"]:
        raise SceneError("fit must be a table naming at least one parameter, e.g. \"sand.friction_angle\" = [20, 45].")
    options = dict(values["optimizer"], numerical_check=tuple(values["numerical_check"]))
    return CalibrationConfig(experiments, values["fit"], options)
