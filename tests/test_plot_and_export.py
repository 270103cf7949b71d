"""`jaxmpm plot` and `jaxmpm export`: the pictures and ParaView files show what the run stored.

The VTU files are read back with meshio, a reader independent of how we wrote them, and
compared point by point with the HDF5 output; p and q are checked against the solver's own
invariants (jaxmpm.tensors), a second implementation of the p and q formulas. An axisymmetric
run (x is the radius r, y the axial z) has its own stress names and units, a mirrored plot and
a revolved export, whose rotated vectors and stresses are projected back on e_r, e_z, e_theta.
"""

import xml.etree.ElementTree as ElementTree

import matplotlib

matplotlib.use("Agg")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm import tensors  # noqa: E402
from jaxmpm.pictures import plotting  # noqa: E402
from jaxmpm.cli import main  # noqa: E402
from jaxmpm.pictures.snapshots import Snapshots  # noqa: E402
from tests.scenes import BLOCK  # noqa: E402

# Two bodies of one material: a slab and a cap resting on it (lattice centres never sit on
# y = 0.1, so the regions share no point); every stored field is asked for.
TWO_BODIES = BLOCK.replace(
    'region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }',
    'region = { rectangle = [[0.0, 0.0], [0.4, 0.1]] }\n\n'
    '[[bodies]]\nname = "cap"\nmaterial = "soil"\nregion = { rectangle = [[0.1, 0.1], [0.3, 0.2]] }',
).replace('output_every = 0.005', 'output_every = 0.005\nsnapshot_fields = ["x", "v", "stress", "plastic_strain"]')


@pytest.fixture(scope="module")
def two_bodies(tmp_path_factory):
    """(Result, path of its HDF5 file) of the two-body scene."""
    result = jaxmpm.simulate(jaxmpm.Scene.from_toml(TWO_BODIES), progress=False)
    return result, result.save(tmp_path_factory.mktemp("run") / "two.h5")


# A 0.1 m x 0.1 m soil cylinder on the axis, under a held (prescribed) cap, for a few steps.
CYLINDER = """
[scene]
name = "cylinder"
geometry = "axisymmetric"
gravity = [0.0, -9.81]
duration = 0.004
output_every = 0.002
snapshot_fields = ["x", "v", "stress", "plastic_strain", "volume", "mass"]

[grid]
origin = [0.0, 0.0]
size = [0.2, 0.2]
cell = 0.025
boundaries = { left = "slip", right = "free", bottom = "fixed", top = "free" }

[numerics]
shape = "linear"
transfer = "flip"
ppc = 2
damping = 0.0

[materials.soil]
model = "linear_elastic"
density = 1800.0
young = 1.0e6
poisson = 0.3

[[bodies]]
name = "cylinder"
material = "soil"
region = { rectangle = [[0.0, 0.0], [0.1, 0.1]] }

[[bodies]]
name = "cap"
material = "soil"
kinematics = { type = "prescribed", velocity = [0.0, 0.0] }
region = { rectangle = [[0.0, 0.1], [0.1, 0.125]] }

[[probes]]
name = "top"
kind = "displacement"
at = [0.05, 0.1]

[[probes]]
name = "hold"
kind = "reaction"
body = "cap"
"""
RING = ("cylinder", "cap")


@pytest.fixture(scope="module")
def axisymmetric(tmp_path_factory):
    """(Result, path of its HDF5 file) of the axisymmetric cylinder."""
    result = jaxmpm.Simulation(jaxmpm.Scene.from_toml(CYLINDER)).run(progress=False)
    return result, result.save(tmp_path_factory.mktemp("axi") / "cylinder.h5")


def joined(result, field, index, bodies=("block", "cap")):
    """A stored field at a snapshot, the bodies joined in scene order (block, then cap)."""
    return np.concatenate([result.snapshots[body][field][index] for body in bodies])


def test_export_writes_a_vtu_per_snapshot_that_meshio_reads_back(two_bodies, tmp_path, capsys):
    meshio = pytest.importorskip("meshio")
    result, path = two_bodies
    pvd = tmp_path / "two.pvd"
    assert main(["export", str(path), "-o", str(pvd)]) == 0
    assert str(pvd) in capsys.readouterr().out
    same = result.export(tmp_path / "again.pvd")            # the Python route writes the same data
    assert same == tmp_path / "again.pvd" and same.is_file()
    direct, via_file = meshio.read(tmp_path / "again" / "again_00002.vtu"), meshio.read(tmp_path / "two" / "two_00002.vtu")
    assert sorted(direct.point_data) == sorted(via_file.point_data)
    for name in direct.point_data:
        np.testing.assert_array_equal(direct.point_data[name], via_file.point_data[name])
    datasets = ElementTree.parse(pvd).getroot().findall("Collection/DataSet")
    times = result.snapshots["time"]
    assert len(datasets) == len(times) == 3
    np.testing.assert_allclose([float(d.get("timestep")) for d in datasets], times, rtol=1e-15)
    for index, dataset in enumerate(datasets):
        mesh = meshio.read(tmp_path / dataset.get("file"))
        np.testing.assert_allclose(mesh.points[:, :2], joined(result, "x", index), rtol=1e-15)
        assert np.all(mesh.points[:, 2] == 0.0)
        count = len(result.snapshots["block"]["x"][index])
        np.testing.assert_array_equal(mesh.point_data["body"], np.repeat([0, 1], [count, len(mesh.points) - count]))
        stress = joined(result, "stress", index)
        np.testing.assert_allclose(mesh.point_data["stress"].reshape(-1, 3, 3), stress, rtol=1e-15)
        np.testing.assert_allclose(mesh.point_data["v"][:, :2], joined(result, "v", index), rtol=1e-15)
        np.testing.assert_allclose(mesh.point_data["p"], tensors.pressure(jnp.asarray(stress)), rtol=1e-12)
        np.testing.assert_allclose(mesh.point_data["q"], tensors.von_mises(jnp.asarray(stress)), rtol=1e-10)
    assert [p.name for p in tmp_path.rglob(".*")] == []      # no temporary file left behind


def test_points_placed_from_displacement_when_x_is_not_stored():
    # Same run twice: once storing x, once only the displacement; the positions must agree.
    with_x = jaxmpm.simulate(jaxmpm.Scene.from_toml(TWO_BODIES), progress=False)
    only_u = jaxmpm.simulate(
        jaxmpm.Scene.from_toml(TWO_BODIES.replace('["x", "v", "stress", "plastic_strain"]', '["displacement"]')),
        progress=False,
    )
    first, second = Snapshots(with_x), Snapshots(only_u)
    for index in range(len(first)):
        np.testing.assert_allclose(second.positions(index), first.positions(index), rtol=0, atol=1e-14)
    np.testing.assert_allclose(second.field("displacement", 2), first.field("displacement", 2), atol=1e-14)


def test_snapshot_figure_draws_the_stored_points_and_values(two_bodies):
    result, _ = two_bodies
    figure = result.plot()                                # default: the last snapshot, coloured by q
    points = figure.axes[0].collections[0]
    np.testing.assert_allclose(points.get_offsets(), joined(result, "x", -1), rtol=1e-15)
    np.testing.assert_allclose(points.get_array(), tensors.von_mises(jnp.asarray(joined(result, "stress", -1))), rtol=1e-10)
    figure = plotting.snapshot_figure(result, field="sigma_yy", snapshot=1)
    np.testing.assert_allclose(figure.axes[0].collections[0].get_array(), joined(result, "stress", 1)[:, 1, 1])
    # Panels of one figure (a notebook's side-by-side snapshots): each drawn into its own axes.
    import matplotlib.pyplot as plt

    panels, (first, last) = plt.subplots(1, 2)
    assert result.plot(snapshot=0, ax=first) is panels and result.plot(ax=last) is panels
    np.testing.assert_allclose(first.collections[0].get_offsets(), joined(result, "x", 0), rtol=1e-15)
    np.testing.assert_allclose(last.collections[0].get_offsets(), joined(result, "x", -1), rtol=1e-15)
    plt.close(panels)


def test_cli_writes_png_gif_and_probe_plots(two_bodies, tmp_path):
    from PIL import Image

    result, path = two_bodies
    assert main(["plot", str(path), "-o", str(tmp_path / "last.png"), "--field", "p"]) == 0
    assert Image.open(tmp_path / "last.png").size[0] > 100
    assert main(["plot", str(path), "-o", str(tmp_path / "run.gif")]) == 0
    assert Image.open(tmp_path / "run.gif").n_frames == len(result.snapshots["time"])
    figure = result.plot_probes()
    assert [axes.get_ylabel() for axes in figure.axes] == [f"{name} [m]" for name in result.probes]
    np.testing.assert_allclose(figure.axes[0].lines[1].get_ydata(), result.probes["top"][:, 1])
    assert main(["plot", str(path), "--probes", "-o", str(tmp_path / "probes.png")]) == 0
    assert (tmp_path / "probes.png").stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize(
    "arguments, words",
    [
        (["plot", "{missing}"], ["does not exist"]),
        (["plot", "{not_hdf5}"], ["not an HDF5 file"]),
        (["export", "{not_jaxmpm}"], ["not a jaxmpm output file"]),
        (["plot", "{cut}"], ["cut.h5", "is damaged"]),
        (["plot", "{run}", "--field", "porosity"], ["field 'porosity'", "choose one of"]),
        (["plot", "{run}", "--field", "v"], ["field 'v'", "speed"]),
        (["plot", "{run}", "--field", "stress"], ["field 'stress'", "sigma_xx"]),
        (["plot", "{run}", "--probes", "--field", "q"], ["--field q", "--probes"]),
        (["plot", "{run}", "-o", "{tmp}/run.gif", "--snapshot", "1"], ["--snapshot 1", ".gif"]),
        (["export", "{run}", "-o", "{tmp}/clash.pvd"], ["clash", "not a folder"]),
        (["plot", "{run}", "--snapshot", "7"], ["--snapshot 7", "3 snapshots"]),
        (["plot", "{run}", "-o", "{tmp}/picture.jpg"], ["picture.jpg", ".png"]),
        (["export", "{run}", "-o", "{tmp}/out.vtk"], ["out.vtk", ".pvd"]),
        (["plot", "{run}", "--mirror", "-o", "{tmp}/m.png"], ["--mirror", "plane strain"]),
        (["plot", "{run}", "--mirror", "-o", "{tmp}/m.gif"], ["--mirror", "plane strain"]),
        (["plot", "{axi}", "--probes", "--mirror", "-o", "{tmp}/p.png"], ["--mirror", "--probes"]),
        (["export", "{run}", "--revolve", "8", "-o", "{tmp}/r.pvd"], ["--revolve 8", "plane strain"]),
        (["export", "{axi}", "--revolve", "2", "-o", "{tmp}/r.pvd"], ["--revolve 2", "at least 3"]),
        (["plot", "{axi}", "--field", "sigma_xx"], ["field 'sigma_xx'", "plane-strain", "sigma_rr, sigma_rz"]),
        (["plot", "{run}", "--field", "sigma_tt"], ["field 'sigma_tt'", "axisymmetric", "sigma_xx, sigma_xy"]),
    ],
)
def test_plot_and_export_user_errors_exit_2_with_one_line(two_bodies, axisymmetric, tmp_path, capsys, arguments, words):
    import h5py

    (tmp_path / "notes.h5").write_text("not hdf5")
    (tmp_path / "clash").write_text("a file where the VTU folder would go")
    with h5py.File(tmp_path / "other.h5", "w") as file:
        file["data"] = np.zeros(3)
    whole = two_bodies[1].read_bytes()
    (tmp_path / "cut.h5").write_bytes(whole[: len(whole) // 2])      # a copy cut short
    names = {"missing": tmp_path / "missing.h5", "not_hdf5": tmp_path / "notes.h5", "cut": tmp_path / "cut.h5",
             "not_jaxmpm": tmp_path / "other.h5", "run": two_bodies[1], "axi": axisymmetric[1], "tmp": tmp_path}
    assert main([argument.format(**names) for argument in arguments]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error
    for word in words:
        assert word in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clash", "cut.h5", "notes.h5", "other.h5"]   # nothing written


def test_a_large_export_is_announced_with_its_size_before_it_is_written(two_bodies, tmp_path, capsys, monkeypatch):
    # `export --revolve 24` wrote 928 MB without a word. The bound said first is the files'
    # size before compression: above what is written, and exact with compression turned off.
    from jaxmpm import cli

    _, path = two_bodies
    assert main(["export", str(path), "-o", str(tmp_path / "small.pvd")]) == 0
    assert "writing up to" not in capsys.readouterr().err          # below the threshold: quiet
    monkeypatch.setattr(cli, "LARGE_EXPORT", 1.0)
    assert main(["export", str(path), "-o", str(tmp_path / "big.pvd")]) == 0
    said = capsys.readouterr().err
    files = sorted((tmp_path / "big").glob("*.vtu"))
    assert f"in {len(files)} VTU files" in said
    number, unit = said.split("writing up to ")[1].split()[:2]
    announced = float(number) * {"kB": 1e3, "MB": 1e6, "GB": 1e9}[unit]
    assert announced >= sum(file.stat().st_size for file in files)
    import meshio

    raw = [meshio.read(file) for file in files]
    uncompressed = sum(mesh.points.nbytes + sum(c.data.nbytes for c in mesh.cells) * 2 + len(mesh.points)
                       + sum(values.nbytes for values in mesh.point_data.values()) for mesh in raw)
    assert announced == pytest.approx(uncompressed, rel=0.01)


def test_export_again_replaces_its_own_files_and_leaves_others(two_bodies, tmp_path):
    result, _ = two_bodies
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "run_00007.vtu").write_text("left by an earlier, longer export")
    (folder / "notes.txt").write_text("the user's")
    result.export(tmp_path / "run.pvd")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "run_00000.vtu", "run_00001.vtu", "run_00002.vtu"]


def test_axisymmetric_stress_names_units_and_labels(axisymmetric, two_bodies):
    result, _ = axisymmetric
    snapshots = Snapshots(result)
    names = snapshots.names()
    assert {"sigma_rr", "sigma_zz", "sigma_rz", "sigma_tt", "mass", "volume"} <= set(names)
    assert not {"sigma_xx", "sigma_yy", "sigma_xy"} & set(names)
    assert not {"sigma_rr", "sigma_rz", "sigma_tt"} & set(Snapshots(two_bodies[0]).names())
    stress = joined(result, "stress", 2, RING)
    assert np.any(stress[:, 2, 2] != 0.0) and np.any(stress[:, 0, 1] != 0.0)   # a real hoop and shear stress
    for name, (row, column) in {"sigma_rr": (0, 0), "sigma_zz": (1, 1), "sigma_rz": (0, 1), "sigma_tt": (2, 2)}.items():
        np.testing.assert_array_equal(snapshots.field(name, 2), stress[:, row, column])
    with pytest.raises(jaxmpm.SceneError, match="field 'sigma_yy' is a plane-strain stress name"):
        snapshots.field("sigma_yy", 2)
    figure = result.plot(field="mass")
    axes, bar = figure.axes
    assert (axes.get_xlabel(), axes.get_ylabel(), bar.get_ylabel()) == ("r [m]", "z [m]", "mass [kg/rad]")
    assert result.plot(field="volume").axes[1].get_ylabel() == "volume [m^3/rad]"
    assert result.plot(field="sigma_tt").axes[1].get_ylabel() == "sigma_tt [Pa]"
    figure = result.plot_probes()
    assert [axes.get_ylabel() for axes in figure.axes] == ["top [m]", "hold [N]"]
    assert [line.get_label() for line in figure.axes[1].lines] == ["r", "z"]
    np.testing.assert_array_equal(figure.axes[1].lines[1].get_ydata(), result.probes["hold"][:, 1])
    assert two_bodies[0].plot().axes[0].get_xlabel() == "x [m]"
    plotting.pyplot().close("all")


def test_mirror_plot_shows_the_whole_diametral_section(axisymmetric, tmp_path):
    from PIL import Image

    result, path = axisymmetric
    figure = result.plot(field="sigma_tt", snapshot=1, mirror=True)
    axes = figure.axes[0]
    right = jaxmpm.Scene.from_toml(CYLINDER).grid.size[0]
    assert axes.get_xlim() == (-right, right)
    # the held cap has no stress update: drawn grey, and only the cylinder is coloured
    cap, points, section = *axes.collections, result.snapshots["cylinder"]["x"][1]
    np.testing.assert_array_equal(cap.get_offsets(), np.concatenate([result.snapshots["cap"]["x"][1]] * 2) * np.repeat(
        [[1.0, 1.0], [-1.0, 1.0]], len(result.snapshots["cap"]["x"][1]), axis=0))
    np.testing.assert_array_equal(points.get_offsets(), np.concatenate([section, section * [-1.0, 1.0]]))
    hoop = result.snapshots["cylinder"]["stress"][1][:, 2, 2]
    np.testing.assert_array_equal(points.get_array(), np.concatenate([hoop, hoop]))
    plotting.pyplot().close(figure)
    assert main(["plot", str(path), "--mirror", "-o", str(tmp_path / "whole.png")]) == 0
    assert Image.open(tmp_path / "whole.png").size[0] > 100
    assert main(["plot", str(path), "--mirror", "-o", str(tmp_path / "whole.gif")]) == 0
    assert Image.open(tmp_path / "whole.gif").n_frames == len(result.snapshots["time"])


def test_structures_are_grey_and_a_few_extreme_points_do_not_set_the_colour_scale(axisymmetric):
    # The pile example's pressure plot was scaled to a few crushed points at its tip, and drew
    # the pile (no stress update) in the sand's colours.
    result, _ = axisymmetric
    figure = result.plot(field="p", snapshot=1)
    cap, cylinder = figure.axes[0].collections
    np.testing.assert_array_equal(cap.get_offsets(), result.snapshots["cap"]["x"][1])
    assert cap.get_array() is None                      # one colour, not the field's
    np.testing.assert_array_equal(cylinder.get_offsets(), result.snapshots["cylinder"]["x"][1])
    plotting.pyplot().close(figure)
    assert len(result.plot(field="displacement", snapshot=1).axes[0].collections) == 1   # a motion: every body coloured
    snapshots = Snapshots(result)
    ordinary = plotting.colour_limits(snapshots, "p", [1])
    snapshots.stored["stress"][0] = snapshots.stored["stress"][0].copy()     # the fixture's arrays stay
    snapshots.stored["stress"][0][1][0] = -1e9 * np.eye(3)       # one point crushed: p = 1 GPa
    limits = plotting.colour_limits(snapshots, "p", [1])
    assert limits[1] < 1e-3 * 1e9 and limits[1] == pytest.approx(ordinary[1], rel=0.2)
    assert plotting.colour_extension(snapshots, "p", [1], limits) in ("max", "both")


def test_revolved_export_turns_points_vectors_and_stresses_about_the_axis(axisymmetric, tmp_path):
    meshio = pytest.importorskip("meshio")
    result, path = axisymmetric
    turns = 5
    assert main(["export", str(path), "--revolve", str(turns), "-o", str(tmp_path / "ring.pvd")]) == 0
    flat = meshio.read(result.export(tmp_path / "flat.pvd").with_suffix("") / "flat_00002.vtu")
    np.testing.assert_array_equal(flat.points[:, :2], joined(result, "x", 2, RING))   # the section: (r, z, 0)
    assert np.all(flat.points[:, 2] == 0.0)
    theta = 2 * np.pi * np.arange(turns)[:, None] / turns
    e_r = np.stack([np.cos(theta), np.sin(theta), 0 * theta], axis=-1)            # (turns, 1, 3)
    e_t = np.stack([-np.sin(theta), np.cos(theta), 0 * theta], axis=-1)
    e_z = np.broadcast_to([0.0, 0.0, 1.0], e_r.shape)
    for index in range(len(result.snapshots["time"])):
        mesh = meshio.read(tmp_path / "ring" / f"ring_{index:05d}.vtu")
        x, v, stress = (joined(result, name, index, RING) for name in ("x", "v", "stress"))
        count = len(x)
        points = mesh.points.reshape(turns, count, 3)
        np.testing.assert_allclose(np.hypot(points[..., 0], points[..., 1]), np.broadcast_to(x[:, 0], (turns, count)),
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(points[..., 2], np.broadcast_to(x[:, 1], (turns, count)), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.sum(points * e_t, axis=-1), 0.0, atol=1e-12)          # at angle theta_k
        np.testing.assert_allclose(np.sum(points * e_r, axis=-1), np.broadcast_to(x[:, 0], (turns, count)), atol=1e-12)
        turned = mesh.point_data["v"].reshape(turns, count, 3)
        for direction, expected in ((e_r, v[:, 0]), (e_z, v[:, 1]), (e_t, 0.0 * v[:, 0])):
            np.testing.assert_allclose(np.sum(turned * direction, axis=-1), np.broadcast_to(expected, (turns, count)),
                                       rtol=0, atol=1e-12 * np.max(np.abs(v)))
        cartesian = mesh.point_data["stress"].reshape(turns, count, 3, 3)
        scale = 1e-12 * np.max(np.abs(stress))
        for (a, b), (row, column) in {(0, 0): (e_r, e_r), (1, 1): (e_z, e_z), (2, 2): (e_t, e_t), (0, 1): (e_r, e_z),
                                      (0, 2): (e_r, e_t), (1, 2): (e_z, e_t)}.items():
            projected = np.einsum("kni,knij,knj->kn", np.broadcast_to(row, (turns, count, 3)), cartesian,
                                  np.broadcast_to(column, (turns, count, 3)))
            np.testing.assert_allclose(projected, np.broadcast_to(stress[:, a, b], (turns, count)), rtol=0, atol=scale)
        np.testing.assert_array_equal(mesh.point_data["body"], np.tile(np.repeat([0, 1], [
            len(result.snapshots["cylinder"]["x"][index]), len(result.snapshots["cap"]["x"][index])]), turns))
        np.testing.assert_array_equal(mesh.point_data["mass"], np.tile(joined(result, "mass", index, RING), turns))
        np.testing.assert_allclose(mesh.point_data["q"], np.tile(tensors.von_mises(jnp.asarray(stress)), turns),
                                   rtol=1e-10)
    assert len(ElementTree.parse(tmp_path / "ring.pvd").getroot().findall("Collection/DataSet")) == 3


def test_hdf5_says_its_geometry_and_extent_and_older_files_still_load(axisymmetric, two_bodies, tmp_path):
    import shutil

    import h5py

    for (result, path), geometry, extent in ((axisymmetric, "axisymmetric", "per radian"),
                                             (two_bodies, "plane_strain", "per metre of thickness")):
        with h5py.File(path, "r") as file:
            assert (file.attrs["geometry"], file.attrs["extent"]) == (geometry, extent)
        assert result.geometry == geometry
    older = shutil.copy(axisymmetric[1], tmp_path / "older.h5")          # as written before these attributes
    with h5py.File(older, "r+") as file:
        del file.attrs["geometry"], file.attrs["extent"]
    loaded = jaxmpm.Result.load(older)
    assert loaded.geometry == "axisymmetric" and loaded.scene_toml == axisymmetric[0].scene_toml
    np.testing.assert_array_equal(loaded.snapshots["cylinder"]["stress"],
                                  axisymmetric[0].snapshots["cylinder"]["stress"])


def test_plot_names_every_file_type_it_writes(tmp_path, capsys):
    # -o with a wrong type is refused before the result is read, naming the types -o takes:
    # .png, .gif and .mp4 for snapshots, .png for probe plots.
    assert main(["plot", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "a.jpg")]) == 2
    message = capsys.readouterr().err
    assert ".png, .gif, .mp4" in message and "a.jpg" in message
    assert main(["plot", str(tmp_path / "missing.h5"), "--probes", "-o", str(tmp_path / "a.gif")]) == 2
    assert "must be .png" in capsys.readouterr().err
