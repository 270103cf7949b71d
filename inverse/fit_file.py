"""The calibration's HDF5 file (docs/output_files.md): `save_fit` writes a `Fit` atomically,
`load_fit` reads back the keyword arguments that rebuild it, bit for bit (`Fit.save`,
`Fit.load`; this module reads and writes fields and knows no class of inverse.fit).

The file says what it is in its attribute `file_kind` = "calibration": `jaxmpm plot FIT.h5`
finds `inverse.command.CALIBRATION_FILE` among the entry points of group `jaxmpm.file_kinds`
(pyproject.toml), so that jaxmpm reads no calibration file itself. Files written before
these keys (no `file_kind`, `values`, `jacobian`, `starts/stopped`, observations or timing)
load too: what they lack is None, NaN or empty.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path

FILE_KIND = "calibration"


def save_fit(fit, path) -> Path:
    """Write `fit` to `path` (HDF5), atomically."""
    import h5py

    from jaxmpm import __version__

    path = Path(path)
    with atomic_path(path) as temporary, h5py.File(temporary, "w") as file:
        file.attrs.update(
            file_kind=FILE_KIND, jaxmpm_version=__version__,
            optimizer=fit.optimizer, loss=fit.loss, iterations=fit.iterations, evaluations=fit.evaluations,
            wall_time=fit.wall_time, compile_seconds=fit.compile_seconds,
            iteration_compile_seconds=fit.iteration_compile_seconds, earlier_seconds=fit.earlier_seconds,
            scene=fit.scene_toml, best_start=fit.best_start, stopped=fit.reasons[fit.best_start], warning=fit.warning,
        )
        file.create_dataset("names", data=np.array(fit.names, dtype="S"))
        file.create_dataset("values", data=fit.values)
        for group, values in (("params", fit.params), ("stderr", fit.stderr)):
            for name, value in values.items():
                file.create_dataset(f"{group}/{name}", data=value)
        file.create_dataset("covariance", data=fit.covariance)
        file.create_dataset("correlation", data=fit.correlation)
        if fit.jacobian is not None:
            file.create_dataset("jacobian", data=fit.jacobian)
        for name, values in fit.history.items():
            file.create_dataset(f"history/{name}", data=values)
        file.create_dataset("starts/initial", data=fit.start_values)
        file.create_dataset("starts/final", data=fit.final_values)
        file.create_dataset("starts/loss", data=fit.final_losses)
        file.create_dataset("starts/stopped", data=list(fit.reasons), dtype=h5py.string_dtype())
        file.create_dataset("time", data=fit.time)
        for name, values in fit.probes.items():
            file.create_dataset(f"probes/{name}", data=values)
        for refinement, shift in fit.numerical_shifts.items():
            for name, value in zip(fit.names, shift):
                file.create_dataset(f"numerical_shift/{refinement}/{name}", data=value)
        experiments = file.create_group("experiments", track_order=True)
        for run in fit.experiments:
            write_experiment(experiments.create_group(run.name, track_order=True), run)
    return path


def write_experiment(group, run):
    """/experiments/NAME: time, probes/PROBE at the fitted values, observations/PROBE, the fixed values."""
    group.attrs["fixed"] = json.dumps(run.fixed, default=lambda value: np.asarray(value).tolist())
    group.create_dataset("time", data=run.time)
    probes = group.create_group("probes", track_order=True)
    for name, values in run.probes.items():
        probes.create_dataset(name, data=values)
    if run.observations is None:
        return
    observations = group.create_group("observations", track_order=True)
    for name, channel in run.observations.channels.items():
        measured = observations.create_group(name)
        measured.attrs.update(components=np.array(channel.components, dtype=int), window=channel.window)
        measured.create_dataset("times", data=channel.times)
        measured.create_dataset("values", data=channel.values)
        if channel.sigma is not None:
            measured.create_dataset("sigma", data=channel.sigma)


def is_fit_file(file) -> bool:
    """Whether an open HDF5 file is a calibration's (older ones have no `file_kind`)."""
    return file.attrs.get("file_kind") == FILE_KIND or ("covariance" in file and "optimizer" in file.attrs)


def load_fit(path) -> dict:
    """The fields of the `Fit` in `path` (its experiments as dicts of the fields of
    `ExperimentFit`); one SceneError sentence if it is no calibration file or is damaged."""
    import h5py

    if not Path(path).is_file():
        raise SceneError(f"{str(path)!r} does not exist.")
    if not h5py.is_hdf5(path):
        raise SceneError(f"{str(path)!r} is not an HDF5 file.")
    try:
        with h5py.File(path, "r") as file:
            if not is_fit_file(file):
                raise SceneError(not_a_fit(str(path), file))
            return read_fit(file)
    except OSError:
        raise SceneError(f"{str(path)!r} is damaged (HDF5 cannot read it, e.g. a copy cut short): "
                         "calibrate again, or copy the whole file.") from None
    except KeyError as error:
        raise SceneError(f"{str(path)!r} is a calibration file with parts missing or damaged ({error}).") from None


def not_a_fit(path, file) -> str:
    """Why an HDF5 file that is not a calibration's cannot be loaded as one, in one sentence."""
    if "complete" in file.attrs and "scene" in file.attrs:
        return (f"{path!r} is the output of a run (`jaxmpm run`), not a calibration result: "
                "open it with jaxmpm.Result.load.")
    return f"{path!r} is not a calibration result (written by `jaxmpm calibrate` or Fit.save)."


def read_fit(file) -> dict:
    """The fields of the Fit in an open calibration file."""
    attrs = file.attrs
    names = tuple(name.decode() for name in file["names"][()])
    history = {name: data[()] for name, data in file["history"].items()}
    starts = file["starts"]
    best = int(attrs["best_start"])
    if "stopped" in starts:
        reasons = list(starts["stopped"].asstr()[()])
    else:
        reasons = [""] * len(starts["loss"])
        reasons[best] = str(attrs["stopped"])
    shifts = {refinement: np.array([group[name][()] for name in names])
              for refinement, group in file.get("numerical_shift", {}).items()}
    return dict(
        names=names,
        values=file["values"][()] if "values" in file else np.array([file[f"params/{name}"][()] for name in names]),
        loss=float(attrs["loss"]),
        covariance=file["covariance"][()],
        jacobian=file["jacobian"][()] if "jacobian" in file else None,
        start_values=starts["initial"][()],
        final_values=starts["final"][()],
        final_losses=starts["loss"][()],
        best_start=best,
        reasons=reasons,
        history_loss=history["loss"],
        history_values=history["values"],
        history_gradient=history["gradient_norm"],
        history_seconds=history["seconds"],
        history_memory=history["memory_mb"],
        history_simulations=history["simulations"],
        iterations=int(attrs["iterations"]),
        evaluations=int(attrs["evaluations"]),
        wall_time=float(attrs["wall_time"]),
        optimizer=str(attrs["optimizer"]),
        experiments=[read_experiment(name, group) for name, group in file["experiments"].items()],
        scene_toml=str(attrs["scene"]),
        warning=str(attrs.get("warning", "")),
        numerical_shifts=shifts,
        compile_seconds=float(attrs.get("compile_seconds", np.nan)),
        iteration_compile_seconds=float(attrs.get("iteration_compile_seconds", 0.0)),
        earlier_seconds=float(attrs.get("earlier_seconds", 0.0)),
    )


def read_experiment(name, group) -> dict:
    """The fields of an ExperimentFit from /experiments/NAME (observations None in files written
    before them)."""
    from inverse.observations import Channel, Observations

    observations = None
    if "observations" in group:
        observations = Observations({
            probe: Channel(times=measured["times"][()], values=measured["values"][()],
                           components=tuple(int(k) for k in measured.attrs["components"]),
                           sigma=measured["sigma"][()] if "sigma" in measured else None,
                           window=float(measured.attrs["window"]))
            for probe, measured in group["observations"].items()
        })
    return dict(name=name, observations=observations, time=group["time"][()],
                         probes={probe: data[()] for probe, data in group["probes"].items()},
                         fixed=json.loads(group.attrs.get("fixed", "{}")))
