"""Observations: measured probe histories to calibrate against.

A `Channel` is one probe's measured history: times (M,) [s], values (M, c) for the probe
components it covers (e.g. only the vertical displacement, component 1), an optional noise
standard deviation per component (c,), and an optional averaging window [s]: a measurement
that is the mean of the probe over the window centred on each time (a load cell's bandwidth;
a contact force rings with the soil's waves from step to step). Sources: numpy
arrays, CSV files, HDF5 files (including a jaxmpm output file).

CSV layout: a header `time, top[0], top[1], thrust[0]`; each column after `time` is one
component (`name[k]`) of a probe; rows are observation times.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import re
from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError

COLUMN = re.compile(r"^\s*([A-Za-z_][\w\-]*)\[(\d+)\]\s*$")


@dataclasses.dataclass(frozen=True)
class Channel:
    """times: (M,) strictly increasing [s]; values: (M, c); components: the c probe components
    observed; sigma: (c,) noise standard deviation per component, or None (unknown); window:
    the averaging window [s] of each value (0: the probe's value at that time)."""

    times: np.ndarray
    values: np.ndarray
    components: tuple[int, ...]
    sigma: np.ndarray | None = None
    window: float = 0.0


def make_channel(name, times, values, components=None, sigma=None, window=None) -> Channel:
    """A checked Channel; raises SceneError naming the probe and the bad value."""
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    if times.ndim != 1 or len(times) != len(values) or len(times) == 0:
        raise SceneError(
            f"observations.{name}: times {times.shape} and values {values.shape} must have one row per time."
        )
    components = tuple(range(values.shape[1])) if components is None else tuple(int(c) for c in components)
    if len(components) != values.shape[1]:
        raise SceneError(f"observations.{name}: {len(components)} components named for {values.shape[1]} columns.")
    for label, array in (("times", times), ("values", values)):
        bad = np.argwhere(~np.isfinite(array))
        if len(bad):
            raise SceneError(f"observations.{name}.{label} has a non-finite value ({array[tuple(bad[0])]}) at row {bad[0][0]}.")
    if np.any(np.diff(times) <= 0.0):
        raise SceneError(f"observations.{name}.times must be strictly increasing.")
    if sigma is not None:
        try:
            sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (len(components),)).copy()
        except (TypeError, ValueError):
            raise SceneError(f"observations.{name}.sigma = {sigma!r} must be one number or one per observed "
                             f"component ({len(components)}).") from None
        if not np.all(np.isfinite(sigma) & (sigma > 0.0)):
            raise SceneError(f"observations.{name}.sigma = {sigma.tolist()} must be positive.")
    window = 0.0 if window is None else window
    if isinstance(window, bool) or not isinstance(window, (int, float)) or not (np.isfinite(window) and window >= 0):
        raise SceneError(f"observations.{name}.window = {window!r} must be a time >= 0 [s].")
    return Channel(times, values, components, sigma, float(window))


@dataclasses.dataclass(frozen=True)
class Observations:
    """The measured histories by probe name."""

    channels: dict[str, Channel]

    @classmethod
    def from_arrays(cls, data: dict, sigma: dict | None = None, window: dict | None = None) -> Observations:
        """data: {probe: (times, values)} or {probe: (times, values, components)};
        sigma: optional {probe: noise std (scalar or per component)}; window: optional
        {probe: averaging window [s]}."""
        sigma, window = sigma or {}, window or {}
        for label, table in (("sigma", sigma), ("window", window)):
            unknown = sorted(set(table) - set(data))
            if unknown:
                close = difflib.get_close_matches(unknown[0], list(data), n=1)
                hint = f"; is the observations' {close[0]!r} a misspelling of it?" if close else ""
                raise SceneError(f"{label}.{unknown[0]} names no observed probe (observed: {', '.join(data)}){hint}.")
        channels = {}
        for name, entry in data.items():
            times, values, *rest = entry
            channels[name] = make_channel(name, times, values, rest[0] if rest else None, sigma.get(name),
                                          window.get(name))
        return cls(channels)

    @classmethod
    def from_csv(cls, path, sigma: dict | None = None, window: dict | None = None) -> Observations:
        path = Path(path)
        with open(path, newline="") as stream:
            rows = [(number, row) for number, row in enumerate(csv.reader(stream), start=1)
                    if row and not row[0].lstrip().startswith("#")]
        if not rows or rows[0][1][0].strip() != "time":
            raise SceneError(f"{path}: the first column must be headed 'time'.")
        header = rows[0][1]
        columns = []
        for name in header[1:]:
            match = COLUMN.match(name)
            if not match:
                raise SceneError(f"{path}: column {name!r} must be named like probe[k] (e.g. top[1]).")
            columns.append((match.group(1), int(match.group(2))))
        if len(rows) == 1:
            raise SceneError(f"{path}: the file has a header but no rows of measurements.")
        values = []
        for line, row in rows[1:]:
            if len(row) != len(header):
                raise SceneError(f"{path}, line {line}: {len(row)} values, but the header names {len(header)} columns.")
            try:
                values.append([float(cell) for cell in row])
            except ValueError:
                column = next(index for index, cell in enumerate(row) if not _is_number(cell))
                raise SceneError(f"{path}, line {line}, column {header[column]!r}: {row[column]!r} is not a number.") from None
        table = np.array(values)
        grouped = {}
        for index, (name, component) in enumerate(columns, start=1):
            grouped.setdefault(name, []).append((component, index))
        data = {
            name: (table[:, 0], table[:, [index for _, index in pairs]], [c for c, _ in pairs])
            for name, pairs in grouped.items()
        }
        return cls.from_arrays(data, sigma, window)

    @classmethod
    def from_hdf5(cls, path, sigma: dict | None = None, probes=None, window: dict | None = None) -> Observations:
        """A jaxmpm output file (or any file with /time and /probes/NAME (T, k))."""
        import h5py

        try:
            with h5py.File(path, "r") as file:
                if "time" not in file or "probes" not in file:
                    raise SceneError(f"{path}: an observation file needs /time and /probes/NAME datasets.")
                times = file["time"][()]
                names = list(file["probes"]) if probes is None else list(probes)
                missing = [name for name in names if name not in file["probes"]]
                if missing:
                    raise SceneError(f"{path} has no probe {missing[0]!r} (it has: {', '.join(file['probes'])}).")
                data = {name: (times, file["probes"][name][()]) for name in names}
        except OSError as error:
            raise SceneError(f"{path} is not a readable HDF5 file ({error}).") from None
        return cls.from_arrays(data, sigma, window)

    def to_csv(self, path):
        """Write channels that share their times as one CSV file (see the module docstring)."""
        times = next(iter(self.channels.values())).times
        if any(len(c.times) != len(times) or np.any(c.times != times) for c in self.channels.values()):
            raise ValueError("to_csv needs every channel at the same times.")
        header = ["time"] + [f"{name}[{k}]" for name, c in self.channels.items() for k in c.components]
        table = np.column_stack([times] + [c.values for c in self.channels.values()])
        with open(path, "w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(header)
            writer.writerows([[repr(float(x)) for x in row] for row in table])

    @property
    def count(self) -> int:
        """Number of observed scalar values."""
        return sum(c.values.size for c in self.channels.values())

    @property
    def noise_known(self) -> bool:
        return all(c.sigma is not None for c in self.channels.values())


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_observations(path, sigma: dict | None = None, window: dict | None = None) -> Observations:
    """Read observations from a .csv or .h5/.hdf5 file."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"observations file {str(path)!r} does not exist.")
    if path.suffix.lower() == ".csv":
        return Observations.from_csv(path, sigma, window)
    if path.suffix.lower() in (".h5", ".hdf5"):
        return Observations.from_hdf5(path, sigma, window=window)
    raise SceneError(f"observations file {str(path)!r} must be .csv, .h5 or .hdf5.")


def default_scale(channel: Channel) -> np.ndarray:
    """Per-component weight when the noise is unknown: the RMS of the observed values (so
    channels of different units weigh alike), floored to avoid division by zero."""
    rms = np.sqrt(np.mean(channel.values**2, axis=0))
    return np.where(rms > 0.0, rms, 1.0)


def check_against(observations: Observations, probe_names, time_span):
    """SceneError if a channel names an unknown probe or lies outside the simulated time."""
    start, end = time_span
    for name, channel in observations.channels.items():
        if name not in probe_names:
            known = ", ".join(repr(n) for n in probe_names)
            raise SceneError(f"observations.{name} is not a probe of the scene (probes: {known}).")
        tolerance = 1e-9 * max(1.0, abs(end))
        if channel.times[0] < start - tolerance or channel.times[-1] > end + tolerance:
            bad = channel.times[0] if channel.times[0] < start else channel.times[-1]
            raise SceneError(
                f"observations.{name}.times has t = {bad:g} s outside the simulated span "
                f"[{start:g}, {end:g}] s."
            )
