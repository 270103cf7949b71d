"""Pictures of a run: points coloured by a field (PNG, or a GIF/MP4 over all snapshots), and
probe histories.

    jaxmpm plot OUT.h5                          # OUT.png: the last snapshot, coloured by q
    jaxmpm plot OUT.h5 -o run.gif --field p     # every snapshot, one colour scale
    jaxmpm plot OUT.h5 --probes -o probes.png   # probe histories against time

Field names are those of `jaxmpm.snapshots` (stored fields and p, q, sigma_xx, ..., speed).
Points are drawn as squares of their initial spacing (h / ppc), so a body looks solid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.snapshots import Snapshots

FORMATS = (".png", ".gif", ".mp4")
PREFERRED_FIELDS = ("q", "plastic_strain", "displacement", "body")
UNITS = {"p": "Pa", "q": "Pa", "sigma_xx": "Pa", "sigma_yy": "Pa", "sigma_xy": "Pa", "sigma_zz": "Pa",
         "displacement": "m", "speed": "m/s", "plastic_strain": "-", "volume": "m^3/m", "mass": "kg/m"}


PROBE_UNITS = {"displacement": "m", "body_displacement": "m", "body_rotation": "rad",
               "contact_force": "N/m", "reaction": "N/m"}


def pyplot():
    """matplotlib.pyplot with whatever backend the program chose (the CLI chooses Agg;
    Jupyter its inline one)."""
    import matplotlib.pyplot as plt

    return plt


def default_field(snapshots):
    scalars = snapshots.names()
    return next(name for name in PREFERRED_FIELDS + tuple(scalars) if name in scalars)


def check_output(path, allowed=FORMATS):
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise SceneError(f"-o {str(path)!r}: the file type must be one of {', '.join(allowed)}.")
    return suffix


def draw_points(axes, snapshots, field, index, limits):
    """Scatter one snapshot on `axes` with squares of the point spacing; returns the artist."""
    grid = snapshots.scene.grid
    axes.set_xlim(grid.origin[0], grid.origin[0] + grid.size[0])
    axes.set_ylim(grid.origin[1], grid.origin[1] + grid.size[1])
    axes.set_aspect("equal")
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    figure = axes.figure
    figure.canvas.draw()                        # axes size in pixels is known after a draw
    pixels_per_metre = axes.get_window_extent().width / grid.size[0]
    side = grid.cell / snapshots.scene.numerics.ppc * pixels_per_metre * 72.0 / figure.dpi
    positions = snapshots.positions(index)
    return axes.scatter(
        positions[:, 0], positions[:, 1], c=snapshots.field(field, index), s=side**2, marker="s",
        linewidths=0, vmin=limits[0], vmax=limits[1], cmap="viridis",
    )


def figure_size(scene):
    """(width, height) [in] that fits the grid's aspect ratio beside a colour bar."""
    aspect = scene.grid.size[1] / scene.grid.size[0]
    return 9.0, min(9.0, max(3.0, 7.0 * aspect + 1.2))


def colour_limits(snapshots, field, indices):
    values = np.concatenate([snapshots.field(field, index) for index in indices])
    low, high = float(np.min(values)), float(np.max(values))
    return (low, high) if high > low else (low - 0.5, high + 0.5)


def snapshot_figure(result, field=None, snapshot=-1):
    """A matplotlib figure of snapshot `snapshot` coloured by `field` (default: q, else the
    plastic strain, the displacement or the body)."""
    snapshots = Snapshots(result)
    field = field or default_field(snapshots)
    index = range(len(snapshots))[snapshot]
    plt = pyplot()
    figure, axes = plt.subplots(figsize=figure_size(snapshots.scene), layout="constrained")
    artist = draw_points(axes, snapshots, field, index, colour_limits(snapshots, field, [index]))
    figure.colorbar(artist, ax=axes, label=f"{field} [{UNITS.get(field, '-')}]")
    axes.set_title(f"{snapshots.scene.name}: t = {snapshots.times[index]:.4g} s")
    return figure


def save_png(figure, path):
    """Write a figure as PNG atomically, then close it."""
    check_output(path, (".png",))
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=120, format="png")
    pyplot().close(figure)
    return Path(path)


def save_snapshot(result, path, field=None, snapshot=-1):
    """PNG of one snapshot, written atomically."""
    check_output(path, (".png",))
    return save_png(snapshot_figure(result, field, snapshot), path)


def save_animation(result, path, field=None, fps=10):
    """GIF (Pillow) or MP4 (ffmpeg) over every snapshot, one colour scale for all frames."""
    suffix = check_output(path, (".gif", ".mp4"))
    plt = pyplot()
    from matplotlib import animation

    writer_name = "pillow" if suffix == ".gif" else "ffmpeg"
    if not animation.writers.is_available(writer_name):
        raise SceneError(f"-o {str(path)!r}: writing {suffix} needs {writer_name}, which is not installed; use .gif.")
    snapshots = Snapshots(result)
    field = field or default_field(snapshots)
    limits = colour_limits(snapshots, field, range(len(snapshots)))
    figure, axes = plt.subplots(figsize=figure_size(snapshots.scene), layout="constrained")
    artist = draw_points(axes, snapshots, field, 0, limits)
    figure.colorbar(artist, ax=axes, label=f"{field} [{UNITS.get(field, '-')}]")

    def frame(index):
        artist.set_offsets(snapshots.positions(index))
        artist.set_array(snapshots.field(field, index))
        axes.set_title(f"{snapshots.scene.name}: t = {snapshots.times[index]:.4g} s")
        return (artist,)

    movie = animation.FuncAnimation(figure, frame, frames=len(snapshots), blit=False)
    with atomic_path(path) as temporary:
        movie.save(temporary, writer=animation.writers[writer_name](fps=fps), dpi=100)
    plt.close(figure)
    return Path(path)


def probes_figure(result):
    """One panel per probe: its components against time."""
    if not result.probes:
        raise SceneError("the output file has no probes to plot: add [[probes]] to the scene.")
    from jaxmpm.scene import Scene

    plt = pyplot()
    names = list(result.probes)
    kinds = {probe.name: probe.kind for probe in Scene.from_toml(result.scene_toml).probes}
    figure, panels = plt.subplots(len(names), 1, figsize=(8, 2.5 * len(names)), sharex=True,
                                  layout="constrained", squeeze=False)
    for axes, name in zip(panels[:, 0], names):
        values = np.asarray(result.probes[name]).reshape(len(result.time), -1)
        labels = ["x", "y"] if values.shape[1] == 2 else [str(k) for k in range(values.shape[1])]
        for component, label in enumerate(labels):
            axes.plot(result.time, values[:, component], label=label)
        axes.set_ylabel(f"{name} [{PROBE_UNITS.get(kinds.get(name), '-')}]")
        axes.legend(loc="best")
    panels[-1, 0].set_xlabel("t [s]")
    return figure


def save_probes(result, path):
    """PNG of the probe histories, written atomically."""
    check_output(path, (".png",))
    return save_png(probes_figure(result), path)
