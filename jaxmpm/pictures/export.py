"""ParaView files of a run: one VTU file of points per snapshot and a PVD time collection.

    jaxmpm export OUT.h5 [-o OUT.pvd] [--revolve N]

The VTU files (written with meshio, zlib-compressed binary) go to a folder named after the
PVD file; ParaView opens the PVD file as one time series. Each point carries its body number,
every stored snapshot field (vectors padded to 3 components, stress as a 9-component tensor
ordered xx, xy, xz, yx, ...) and the derived p and q.

Axisymmetric runs are written as their section: points at (r, z, 0), vectors (v_r, v_z, 0),
stress in (r, z, theta) components, which are the (x, y, z) components of that picture.
`revolve=N` (N >= 3; `--revolve N`) writes instead a 3-D point cloud: every point N times, at
the angles theta_k = 2 pi k / N about the axis, at (r cos theta, r sin theta, z) so that VTK's z
is the axial direction (ParaView shows an upright cylinder). Vectors are turned with their
point, (v_r cos theta, v_r sin theta, v_z), and the stress is rotated to those Cartesian
components, sigma = Q sigma_(r, z, theta) Q^T with the columns of Q the unit vectors e_r, e_z,
e_theta. Scalars (body, p, q, plastic_strain, mass, volume) are repeated; mass and volume stay
per radian.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.pictures.snapshots import Snapshots


def turns(count):
    """(count,) angles 2 pi k / count [rad]."""
    return 2.0 * np.pi * np.arange(count) / count


def revolve_vectors(values, count):
    """(N, 2) vectors or points in (r, z) -> (count * N, 3) Cartesian (a_r cos, a_r sin, a_z),
    angle by angle: the first N rows are theta = 0, the next N theta = 2 pi / count, ..."""
    angles = turns(count)[:, None]
    radial, axial = values[:, 0][None, :], values[:, 1][None, :]
    return np.stack(
        [(np.cos(angles) * radial).ravel(), (np.sin(angles) * radial).ravel(),
         np.broadcast_to(axial, (count, len(values))).ravel()],
        axis=1,
    )


def revolve_tensors(values, count):
    """(N, 3, 3) tensors in (r, z, theta) components -> (count * N, 3, 3) Cartesian ones,
    Q sigma Q^T at each angle, in the order of `revolve_vectors`."""
    angles = turns(count)
    cos, sin, zero, one = np.cos(angles), np.sin(angles), np.zeros(count), np.ones(count)
    rotation = np.stack([np.stack([cos, zero, -sin], axis=1),      # columns: e_r, e_z, e_theta
                         np.stack([sin, zero, cos], axis=1),
                         np.stack([zero, one, zero], axis=1)], axis=1)
    return np.einsum("kia,nab,kjb->knij", rotation, values, rotation).reshape(-1, 3, 3)


def revolved(values, count):
    """One field of the section, repeated at `count` angles (vectors and tensors turned)."""
    if values.ndim == 2 and values.shape[1] == 2:
        return revolve_vectors(values, count)
    if values.ndim == 3:
        return revolve_tensors(values, count)
    return np.tile(values, (count,) + (1,) * (values.ndim - 1))


def point_data(snapshots, index, revolve=None):
    """{name: (N,) or (N, k)} arrays of one snapshot, shaped as VTK point data (N times
    `revolve` rows when revolved)."""
    count = revolve or 1
    data = {"body": np.tile(snapshots.body_number.astype(np.int32), count)}
    for name in snapshots.stored:
        values = snapshots.stored_field(name, index)
        if revolve:
            values = revolved(values, revolve)
        elif values.ndim == 2 and values.shape[1] == 2:
            values = np.pad(values, ((0, 0), (0, 1)))
        data[name] = values.reshape(len(values), -1) if values.ndim > 2 else values
    if "stress" in snapshots.stored:
        data["p"] = np.tile(snapshots.field("p", index), count)
        data["q"] = np.tile(snapshots.field("q", index), count)
    return data


def export_bytes(snapshots, revolve=None) -> int:
    """The VTU files' size before compression: per snapshot, the points (3 float64 each), their
    vertex cells (connectivity and offset, int64, and a type byte) and the point data. The
    files are zlib-compressed, so they are smaller, by how much depends on the fields."""
    points = len(snapshots.body_number) * (revolve or 1)
    data = sum(values.nbytes for values in point_data(snapshots, 0, revolve).values())
    return len(snapshots) * (points * (3 * 8 + 2 * 8 + 1) + data)


def write_vtu(path, positions, data):
    """One snapshot's points ((N, 2), placed at z = 0, or (N, 3)) as VTK vertex cells, written
    atomically."""
    import meshio

    points = np.pad(positions, ((0, 0), (0, 1))) if positions.shape[1] == 2 else positions
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


def check_revolve(snapshots, revolve):
    if revolve is None:
        return
    if not snapshots.axisymmetric:
        raise SceneError(f"--revolve {revolve} turns an axisymmetric section about its axis; this run is plane strain.")
    if isinstance(revolve, bool) or not isinstance(revolve, (int, np.integer)) or revolve < 3:
        raise SceneError(f"--revolve {revolve}: give a whole number of angles, at least 3.")


def export_paraview(result, path, revolve=None, report=None) -> Path:
    """Write `path` (.pvd) and its folder of VTU files for a `Result`; returns the PVD path.
    `revolve=N` (axisymmetric runs) writes each point at N angles about the axis (see above).
    `report(bytes, files)`, if given, is told before anything is written how large the export
    can be (`export_bytes`), so that a command can say so."""
    path = Path(path)
    snapshots = Snapshots(result)
    check_revolve(snapshots, revolve)
    folder = path.with_suffix("")
    if folder.exists() and not folder.is_dir():
        raise SceneError(f"-o {str(path)!r}: its VTU folder {str(folder)!r} exists and is not a folder.")
    if report is not None:
        report(export_bytes(snapshots, revolve), len(snapshots))
    folder.mkdir(exist_ok=True)
    entries = []
    for index, time in enumerate(snapshots.times):
        file = folder / f"{folder.name}_{index:05d}.vtu"
        positions = snapshots.positions(index)
        write_vtu(file, revolve_vectors(positions, revolve) if revolve else positions,
                  point_data(snapshots, index, revolve))
        entries.append((time, f"{folder.name}/{file.name}"))
    write_pvd(path, entries)
    written = {folder / Path(file).name for _, file in entries}
    for stale in folder.glob(f"{folder.name}_[0-9][0-9][0-9][0-9][0-9].vtu"):   # from an earlier, longer export
        if stale not in written:
            stale.unlink()
    return path
