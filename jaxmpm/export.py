"""ParaView files of a run: one VTU file of points per snapshot and a PVD time collection.

    jaxmpm export OUT.h5 [-o OUT.pvd]

The VTU files (written with meshio, zlib-compressed binary) go to a folder named after the
PVD file; ParaView opens the PVD file as one time series. Each point carries its body number,
every stored snapshot field (vectors padded to 3 components, stress as a 9-component tensor
ordered xx, xy, xz, yx, ...) and the derived p and q.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.snapshots import Snapshots


def point_data(snapshots, index):
    """{name: (N,) or (N, k)} arrays of one snapshot, shaped as VTK point data."""
    data = {"body": snapshots.body_number.astype(np.int32)}
    for name in snapshots.stored:
        values = snapshots.stored_field(name, index)
        if values.ndim == 2 and values.shape[1] == 2:
            values = np.pad(values, ((0, 0), (0, 1)))
        data[name] = values.reshape(len(values), -1) if values.ndim > 2 else values
    if "stress" in snapshots.stored:
        data["p"] = snapshots.field("p", index)
        data["q"] = snapshots.field("q", index)
    return data


def write_vtu(path, positions, data):
    """One snapshot's points as VTK vertex cells, written atomically."""
    import meshio

    points = np.pad(positions, ((0, 0), (0, 1)))
    cells = [("vertex", np.arange(len(points))[:, None])]
    with atomic_path(path) as temporary:
        meshio.Mesh(points, cells, point_data=data).write(temporary, file_format="vtu")


def write_pvd(path, entries):
    """The time collection: entries [(time, vtu path relative to the PVD file)]."""
    root = ElementTree.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ElementTree.SubElement(root, "Collection")
    for time, file in entries:
        ElementTree.SubElement(collection, "DataSet", timestep=repr(float(time)), group="", part="0", file=file)
    with atomic_path(path) as temporary:
        ElementTree.ElementTree(root).write(temporary, xml_declaration=True, encoding="utf-8")


def export_paraview(result, path) -> Path:
    """Write `path` (.pvd) and its folder of VTU files for a `Result`; returns the PVD path."""
    path = Path(path)
    snapshots = Snapshots(result)
    folder = path.with_suffix("")
    if folder.exists() and not folder.is_dir():
        raise SceneError(f"-o {str(path)!r}: its VTU folder {str(folder)!r} exists and is not a folder.")
    folder.mkdir(exist_ok=True)
    entries = []
    for index, time in enumerate(snapshots.times):
        file = folder / f"{folder.name}_{index:05d}.vtu"
        write_vtu(file, snapshots.positions(index), point_data(snapshots, index))
        entries.append((time, f"{folder.name}/{file.name}"))
    write_pvd(path, entries)
    written = {folder / Path(file).name for _, file in entries}
    for stale in folder.glob(f"{folder.name}_[0-9][0-9][0-9][0-9][0-9].vtu"):   # from an earlier, longer export
        if stale not in written:
            stale.unlink()
    return path
