"""Results of a forward run and their HDF5 file.

File layout: root attributes `jaxmpm_version`, `scene` (TOML text), `complete` (bool),
`message`, `geometry` ("plane_strain" or "axisymmetric") and `extent` ("per metre of
thickness" or "per radian": what the stored mass and volume are per); datasets /time (T,),
/probes/NAME (T, k), /snapshots/time (S,), /snapshots/BODY/FIELD (S, N_body, ...). Tensor
components are ordered (x, y, z), so stress[..., 2, 2] is sigma_zz; in axisymmetry (r, z,
theta), so it is the hoop stress. `geometry` and `extent` repeat what the scene says, for
other readers; `load` reads files written before they existed. `save` writes to a temporary
name and renames, so a reader never sees half a file; a run with `save_to` streams the same
layout output by output (jaxmpm/running/output.py), plus `steps_done` and a `/resume` group.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np

from jaxmpm.files import atomic_path
from jaxmpm.running.output import EXTENTS


class FileSnapshots(Mapping):
    """A run's snapshots left in its HDF5 file, read when asked for: `["time"]` is (S,),
    `[body][field]` is (S, N_body, ...), as in an in-memory Result. A long run's Result holds
    these, so its memory does not grow with the number of snapshots."""

    def __init__(self, path, group="snapshots"):
        self.path, self.group = Path(path), group

    def _names(self):
        with h5py.File(self.path, "r") as file:
            return list(file[self.group])

    def __getitem__(self, name):
        with h5py.File(self.path, "r") as file:
            item = file[self.group][name]
            if isinstance(item, h5py.Dataset):
                return item[()]
        return FileSnapshots(self.path, f"{self.group}/{name}")

    def __iter__(self):
        return iter(self._names())

    def __len__(self):
        return len(self._names())


@dataclasses.dataclass
class Result:
    """A forward run: time (T,) [s]; probes {name: (T, k)}; snapshots {"time": (S,),
    body: {field: (S, N_body, ...)}}; complete: False if the run stopped early (see message)."""

    scene_toml: str
    time: np.ndarray
    probes: dict
    snapshots: dict
    complete: bool = True
    message: str = ""

    @property
    def geometry(self) -> str:
        """"plane_strain" or "axisymmetric", as the scene says."""
        from jaxmpm.scene import Scene

        return Scene.from_toml(self.scene_toml).geometry

    @classmethod
    def from_run(cls, sim, probes, snapshots, steps_done, complete, message):
        """Assemble the Result of `steps_done` steps from per-output pieces of a run."""
        probes = {name: np.concatenate(parts)[: steps_done + 1] for name, parts in probes.items()}
        kept = snapshots[: steps_done // sim.steps_per_output + 1]
        by_body = {
            body.name: {
                field: np.stack([snap[field][start:stop] for snap in kept])
                for field in sim.scene.snapshot_fields
            }
            for body, (start, stop) in zip(sim.scene.bodies, sim.body_slices)
        }
        times = np.arange(len(kept)) * sim.steps_per_output * sim.dt
        return cls(
            scene_toml=sim.scene.to_toml(),
            time=sim.time[: steps_done + 1],
            probes=probes,
            snapshots={"time": times, **by_body},
            complete=complete,
            message=message,
        )

    def save(self, path) -> Path:
        """Write the HDF5 file atomically (temporary file, then rename); returns the path."""
        from jaxmpm import __version__

        path, geometry = Path(path), self.geometry
        with atomic_path(path) as temporary, h5py.File(temporary, "w") as file:
            file.attrs["jaxmpm_version"] = __version__
            file.attrs["scene"] = self.scene_toml
            file.attrs["complete"] = bool(self.complete)
            file.attrs["message"] = self.message
            file.attrs["geometry"] = geometry
            file.attrs["extent"] = EXTENTS[geometry]
            file.create_dataset("time", data=self.time)
            probes = file.create_group("probes")
            for name, values in self.probes.items():
                probes.create_dataset(name, data=values)
            snapshots = file.create_group("snapshots")
            snapshots.create_dataset("time", data=self.snapshots["time"])
            for body, fields in self.snapshots.items():
                if body == "time":
                    continue
                group = snapshots.create_group(body)
                for field, values in fields.items():
                    group.create_dataset(field, data=values, compression="gzip", compression_opts=4)
        return path

    def plot(self, field=None, snapshot=-1, mirror=False, ax=None):
        """A matplotlib figure of one snapshot, points coloured by `field` (default q); see
        `jaxmpm.pictures.plotting` (in Jupyter the returned figure shows itself). `mirror=True`
        (axisymmetric runs) also draws the mirror image about the axis. `ax`: draw into these
        matplotlib axes (one panel of a larger figure)."""
        from jaxmpm.pictures.plotting import snapshot_figure

        return snapshot_figure(self, field, snapshot, mirror, ax)

    def plot_probes(self):
        """A matplotlib figure of every probe history against time."""
        from jaxmpm.pictures.plotting import probes_figure

        return probes_figure(self)

    def export(self, path, revolve=None) -> Path:
        """ParaView files: `path` (.pvd) and a folder of one VTU file per snapshot.
        `revolve=N` (axisymmetric runs) writes every point at N angles about the axis, a 3-D
        point cloud (see `jaxmpm.pictures.export`)."""
        from jaxmpm.pictures.export import export_paraview

        return export_paraview(self, path, revolve)

    @classmethod
    def load(cls, path) -> Result:
        """Read a file written by `save`."""
        with h5py.File(path, "r") as file:
            snapshots = {"time": file["snapshots/time"][()]}
            for body, group in file["snapshots"].items():
                if isinstance(group, h5py.Group):
                    snapshots[body] = {field: data[()] for field, data in group.items()}
            return cls(
                scene_toml=str(file.attrs["scene"]),
                time=file["time"][()],
                probes={name: data[()] for name, data in file["probes"].items()},
                snapshots=snapshots,
                complete=bool(file.attrs["complete"]),
                message=str(file.attrs.get("message", "")),
            )
