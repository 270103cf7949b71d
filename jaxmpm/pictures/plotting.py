"""Pictures of a run: points coloured by a field (PNG, or a GIF/MP4 over all snapshots), and
probe histories.

    jaxmpm plot OUT.h5                          # OUT.png: the last snapshot, coloured by q
    jaxmpm plot OUT.h5 -o run.gif --field p     # every snapshot, one colour scale
    jaxmpm plot OUT.h5 --probes -o probes.png   # probe histories against time
    jaxmpm plot OUT.h5 --mirror                 # axisymmetric run: the whole diametral section

Field names are those of `jaxmpm.pictures.snapshots` (stored fields and p, q, sigma_xx, ... or, in
axisymmetry, sigma_rr, ..., speed). Points are drawn as squares of their initial spacing
(h / ppc), so a body looks solid. In axisymmetry the axes are r and z, mass and volume are
per radian, and force probes are the whole ring's (N); `mirror` also draws the section's
mirror image about the axis (points at -r, same colours).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.files import atomic_path
from jaxmpm.pictures.snapshots import STRESS_NAMES, Snapshots

FORMATS = (".png", ".gif", ".mp4")
PREFERRED_FIELDS = ("q", "plastic_strain", "displacement", "body")
UNITS = {"p": "Pa", "q": "Pa", **{name: "Pa" for names in STRESS_NAMES.values() for name in names},
         "displacement": "m", "speed": "m/s", "plastic_strain": "-", "volume": "m^3/m", "mass": "kg/m"}
PER_RADIAN_UNITS = {"volume": "m^3/rad", "mass": "kg/rad"}          # axisymmetry: per radian


PROBE_UNITS = {"displacement": "m", "body_displacement": "m", "body_rotation": "rad", "peak_speed": "m/s",
               "contact_force": "N/m", "reaction": "N/m"}
RING_PROBE_UNITS = {"contact_force": "N", "reaction": "N"}          # axisymmetry: the whole ring


def pyplot():
    """matplotlib.pyplot with whatever backend the program chose (the CLI chooses Agg;
    Jupyter its inline one)."""
    import matplotlib.pyplot as plt

    return plt


def default_field(snapshots):
    scalars = snapshots.names()
    return next(name for name in PREFERRED_FIELDS + tuple(scalars) if name in scalars)


def field_unit(snapshots, field):
    """The unit of a scalar field in this file's geometry (mass and volume per radian in axisymmetry)."""
    if snapshots.axisymmetric and field in PER_RADIAN_UNITS:
        return PER_RADIAN_UNITS[field]
    return UNITS.get(field, "-")


def check_output(path, allowed=FORMATS):
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        kinds = allowed[0] if len(allowed) == 1 else "one of " + ", ".join(allowed)
        raise SceneError(f"-o {str(path)!r}: the file type must be {kinds}.")
    return suffix


def check_mirror(snapshots, mirror):
    if mirror and not snapshots.axisymmetric:
        raise SceneError("--mirror draws an axisymmetric section's mirror image about the axis; "
                         "this run is plane strain.")


STRUCTURE_COLOUR = "0.62"    # prescribed and rigid bodies, where the field is a material state


def describes_material_state(snapshots, field):
    """Whether `field` is a stress measure or the plastic strain, which prescribed and rigid
    bodies (no stress update) do not have."""
    return field in ("p", "q", "plastic_strain") or field in snapshots.components


def coloured_points(snapshots, field):
    """(N,) mask of the points coloured by `field`: all of them, except the points of prescribed
    and rigid bodies where the field is a material state (drawn in STRUCTURE_COLOUR)."""
    if describes_material_state(snapshots, field):
        return snapshots.deforming
    return np.ones_like(snapshots.deforming)


def mirrored(positions, mirror):
    """The positions, followed with `mirror` by their mirror images (-r, z)."""
    return np.concatenate([positions, positions * np.array([-1.0, 1.0])]) if mirror else positions


def placed(snapshots, field, index, mirror):
    """(positions (n, 2), values (n,)) of the coloured points to draw (`coloured_points`);
    with `mirror`, followed by their mirror images (-r, z) with the same values."""
    shown = coloured_points(snapshots, field)
    positions, values = snapshots.positions(index)[shown], snapshots.field(field, index)[shown]
    return mirrored(positions, mirror), np.concatenate([values, values]) if mirror else values


def draw_points(axes, snapshots, field, index, limits, mirror=False):
    """Scatter one snapshot on `axes` with squares of the point spacing; returns the artist.
    With `mirror` (axisymmetry) the x-axis runs from -R to R and the points are drawn twice."""
    grid = snapshots.scene.grid
    right = grid.origin[0] + grid.size[0]
    left = -right if mirror else grid.origin[0]
    axes.set_xlim(left, right)
    axes.set_ylim(grid.origin[1], grid.origin[1] + grid.size[1])
    axes.set_aspect("equal")
    axes.set_xlabel("r [m]" if snapshots.axisymmetric else "x [m]")
    axes.set_ylabel("z [m]" if snapshots.axisymmetric else "y [m]")
    figure = axes.figure
    figure.canvas.draw()                        # axes size in pixels is known after a draw
    pixels_per_metre = axes.get_window_extent().width / (right - left)
    side = grid.cell / snapshots.scene.numerics.ppc * pixels_per_metre * 72.0 / figure.dpi
    structure = mirrored(snapshots.positions(index)[~coloured_points(snapshots, field)], mirror)
    if len(structure):
        axes.scatter(structure[:, 0], structure[:, 1], c=STRUCTURE_COLOUR, s=side**2, marker="s", linewidths=0)
    positions, values = placed(snapshots, field, index, mirror)
    artist = axes.scatter(
        positions[:, 0], positions[:, 1], c=values, s=side**2, marker="s",
        linewidths=0, vmin=limits[0], vmax=limits[1], cmap="viridis",
    )
    if mirror:
        axes.axvline(0.0, color="0.4", linewidth=0.6, linestyle="-.")     # the axis
    return artist


def figure_size(scene, mirror=False):
    """(width, height) [in] that fits the grid's aspect ratio (twice as wide with the mirror
    image) beside a colour bar."""
    aspect = scene.grid.size[1] / (scene.grid.size[0] * (2.0 if mirror else 1.0))
    return 9.0, min(9.0, max(3.0, 7.0 * aspect + 1.2))


ROBUST_PERCENTILES = (1.0, 99.0)    # a few extreme points (a pile's tip) must not set the whole scale


def colour_limits(snapshots, field, indices):
    """(low, high) of the colour scale over the coloured points of the snapshots `indices`:
    their 1st and 99th percentiles, so that a handful of extreme points do not wash out the
    rest (the colour bar's ends then say the scale is clipped, `colour_extension`)."""
    shown = coloured_points(snapshots, field)
    values = np.concatenate([snapshots.field(field, index)[shown] for index in indices])
    if values.size == 0:
        return 0.0, 1.0
    low, high = (float(value) for value in np.percentile(values, ROBUST_PERCENTILES, method="nearest"))
    return (low, high) if high > low else (low - 0.5, high + 0.5)


def colour_extension(snapshots, field, indices, limits):
    """The colour bar's `extend`: "min", "max" or "both" where coloured values lie beyond the
    limits, else "neither"."""
    shown = coloured_points(snapshots, field)
    values = np.concatenate([snapshots.field(field, index)[shown] for index in indices])
    below = values.size and np.min(values) < limits[0]
    above = values.size and np.max(values) > limits[1]
    return {(True, True): "both", (True, False): "min", (False, True): "max"}.get((bool(below), bool(above)), "neither")


def snapshot_figure(result, field=None, snapshot=-1, mirror=False, ax=None):
    """A matplotlib figure of snapshot `snapshot` coloured by `field` (default: q, else the
    plastic strain, the displacement or the body). `mirror` (axisymmetric runs only) also
    draws the mirror image about the axis: the whole diametral section. `ax`: draw into
    these axes (e.g. one panel of `plt.subplots(1, 3)`) and return their figure."""
    snapshots = Snapshots(result)
    check_mirror(snapshots, mirror)
    field = field or default_field(snapshots)
    index = range(len(snapshots))[snapshot]
    if ax is None:
        figure, axes = pyplot().subplots(figsize=figure_size(snapshots.scene, mirror), layout="constrained")
    else:
        figure, axes = ax.figure, ax
    limits = colour_limits(snapshots, field, [index])
    artist = draw_points(axes, snapshots, field, index, limits, mirror)
    figure.colorbar(artist, ax=axes, label=f"{field} [{field_unit(snapshots, field)}]",
                    extend=colour_extension(snapshots, field, [index], limits))
    axes.set_title(f"{snapshots.scene.name}: t = {snapshots.times[index]:.4g} s")
    return figure


def save_png(figure, path, dpi=120):
    """Write a figure as PNG atomically, then close it."""
    check_output(path, (".png",))
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=dpi, format="png")
    pyplot().close(figure)
    return Path(path)


def save_snapshot(result, path, field=None, snapshot=-1, mirror=False):
    """PNG of one snapshot, written atomically."""
    check_output(path, (".png",))
    return save_png(snapshot_figure(result, field, snapshot, mirror), path)


def save_animation(result, path, field=None, fps=10, mirror=False):
    """GIF (Pillow) or MP4 (ffmpeg) over every snapshot, one colour scale for all frames."""
    suffix = check_output(path, (".gif", ".mp4"))
    plt = pyplot()
    from matplotlib import animation

    writer_name = "pillow" if suffix == ".gif" else "ffmpeg"
    if not animation.writers.is_available(writer_name):
        raise SceneError(f"-o {str(path)!r}: writing {suffix} needs {writer_name}, which is not installed; use .gif.")
    snapshots = Snapshots(result)
    check_mirror(snapshots, mirror)
    field = field or default_field(snapshots)
    frames = range(len(snapshots))
    limits = colour_limits(snapshots, field, frames)
    figure, axes = plt.subplots(figsize=figure_size(snapshots.scene, mirror), layout="constrained")
    artist = draw_points(axes, snapshots, field, 0, limits, mirror)
    structure = axes.collections[0] if len(axes.collections) > 1 else None
    figure.colorbar(artist, ax=axes, label=f"{field} [{field_unit(snapshots, field)}]",
                    extend=colour_extension(snapshots, field, frames, limits))

    def frame(index):
        positions, values = placed(snapshots, field, index, mirror)
        artist.set_offsets(positions)
        artist.set_array(values)
        if structure is not None:
            structure.set_offsets(mirrored(snapshots.positions(index)[~coloured_points(snapshots, field)], mirror))
        axes.set_title(f"{snapshots.scene.name}: t = {snapshots.times[index]:.4g} s")
        return (artist,)

    movie = animation.FuncAnimation(figure, frame, frames=len(snapshots), blit=False)
    with atomic_path(path) as temporary:
        movie.save(temporary, writer=animation.writers[writer_name](fps=fps), dpi=100)
    plt.close(figure)
    return Path(path)


def probes_figure(result):
    """One panel per probe: its components against time (r and z in axisymmetry, where the
    force probes are the whole ring's, in N)."""
    if not result.probes:
        raise SceneError("the output file has no probes to plot: add [[probes]] to the scene.")
    from jaxmpm.scene import Scene

    plt = pyplot()
    scene = Scene.from_toml(result.scene_toml)
    axisymmetric = scene.geometry == "axisymmetric"
    units = {**PROBE_UNITS, **RING_PROBE_UNITS} if axisymmetric else PROBE_UNITS
    names = list(result.probes)
    kinds = {probe.name: probe.kind for probe in scene.probes}
    figure, panels = plt.subplots(len(names), 1, figsize=(8, 2.5 * len(names)), sharex=True,
                                  layout="constrained", squeeze=False)
    for axes, name in zip(panels[:, 0], names):
        values = np.asarray(result.probes[name]).reshape(len(result.time), -1)
        for component, label in enumerate(scene.component_names(values.shape[1])):
            axes.plot(result.time, values[:, component], label=label)
        axes.set_ylabel(f"{name} [{units.get(kinds.get(name), '-')}]")
        axes.legend(loc="best")
    panels[-1, 0].set_xlabel("t [s]")
    return figure


def save_probes(result, path):
    """PNG of the probe histories, written atomically."""
    check_output(path, (".png",))
    return save_png(probes_figure(result), path)
