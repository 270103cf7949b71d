"""`jaxmpm plot` and `jaxmpm export`: the pictures and ParaView files show what the run stored.

The VTU files are read back with meshio, a reader independent of how we wrote them, and
compared point by point with the HDF5 output; p and q are checked against the solver's own
invariants (jaxmpm.tensors), a second implementation of the p and q formulas.
"""

import xml.etree.ElementTree as ElementTree

import matplotlib

matplotlib.use("Agg")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm import plotting, tensors  # noqa: E402
from jaxmpm.cli import main  # noqa: E402
from jaxmpm.snapshots import Snapshots  # noqa: E402
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


def joined(result, field, index):
    """A stored field at a snapshot, the bodies joined in scene order (block, then cap)."""
    return np.concatenate([result.snapshots[body][field][index] for body in ("block", "cap")])


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
        (["plot", "{run}", "--field", "porosity"], ["field 'porosity'", "choose one of"]),
        (["plot", "{run}", "--field", "v"], ["field 'v'", "speed"]),
        (["plot", "{run}", "--field", "stress"], ["field 'stress'", "sigma_xx"]),
        (["plot", "{run}", "--probes", "--field", "q"], ["--field q", "--probes"]),
        (["plot", "{run}", "-o", "{tmp}/run.gif", "--snapshot", "1"], ["--snapshot 1", ".gif"]),
        (["export", "{run}", "-o", "{tmp}/clash.pvd"], ["clash", "not a folder"]),
        (["plot", "{run}", "--snapshot", "7"], ["--snapshot 7", "3 snapshots"]),
        (["plot", "{run}", "-o", "{tmp}/picture.jpg"], ["picture.jpg", ".png"]),
        (["export", "{run}", "-o", "{tmp}/out.vtk"], ["out.vtk", ".pvd"]),
    ],
)
def test_plot_and_export_user_errors_exit_2_with_one_line(two_bodies, tmp_path, capsys, arguments, words):
    import h5py

    (tmp_path / "notes.h5").write_text("not hdf5")
    (tmp_path / "clash").write_text("a file where the VTU folder would go")
    with h5py.File(tmp_path / "other.h5", "w") as file:
        file["data"] = np.zeros(3)
    names = {"missing": tmp_path / "missing.h5", "not_hdf5": tmp_path / "notes.h5",
             "not_jaxmpm": tmp_path / "other.h5", "run": two_bodies[1], "tmp": tmp_path}
    assert main([argument.format(**names) for argument in arguments]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error
    for word in words:
        assert word in error


def test_export_again_replaces_its_own_files_and_leaves_others(two_bodies, tmp_path):
    result, _ = two_bodies
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "run_00007.vtu").write_text("left by an earlier, longer export")
    (folder / "notes.txt").write_text("the user's")
    result.export(tmp_path / "run.pvd")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "run_00000.vtu", "run_00001.vtu", "run_00002.vtu"]
