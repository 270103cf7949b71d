"""Plot a retaining-wall run: the deforming sand at a few times, and the wall's histories.

    jaxmpm run examples/retaining_wall_active.toml -o retaining_wall_active.h5
    python examples/plot_retaining_wall.py retaining_wall_active.h5 [-o PREFIX]

writes PREFIX_snapshots.png (the sand coloured by its equivalent plastic strain at four times,
the wall in grey, its initial outline dashed) and PREFIX_histories.png (the wall's
displacement and rotation, and the contact force of the sand on the wall as a moving
average), and prints the key numbers. PREFIX defaults to the result file's name without its
suffix. The scene is read from the result file: of the pair of its first `contact_force`
probe, the wall is the prescribed or rigid body (else the linear elastic one), the sand the
other; "horizontal thrust" is the horizontal force of the sand on the wall towards the side
away from the sand.

For the scene named retaining_wall_active the thrust panel also shows the at-rest thrust
1/2 K0 rho g H^2 and the active one of Rankine, 1/2 Ka rho g H^2 with
Ka = (1 - sin phi) / (1 + sin phi) (for a smooth vertical wall and a horizontal backfill
Coulomb's wedge gives the same Ka), H the backfill height and phi its friction angle.
"""

import argparse
import dataclasses
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm.pictures.plotting import save_png  # noqa: E402
from jaxmpm.pictures.snapshots import Snapshots  # noqa: E402

ACTIVE_SCENE = "retaining_wall_active"
AVERAGE_STEPS = 100      # the contact force changes sign step to step at single nodes: average it
PANELS = 4               # snapshots shown
DPI = 100


@dataclasses.dataclass(frozen=True)
class Setup:
    """What the plots need to know about the scene: the wall and sand body names, `sign`
    (+1 if the wall stands to the right of the sand, -1 if to the left: the horizontal thrust
    is sign * F_x) and the sand's height H [m] (top of its region above its bottom)."""

    scene: jaxmpm.Scene
    wall: str
    sand: str
    sign: float
    height: float


def region_centre_x(region):
    """x of the area centroid of a rectangle's or polygon's vertices (shoelace formula)."""
    x, y = np.array(region.vertices).T
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    return float(np.sum((x + np.roll(x, -1)) * cross) / (3.0 * np.sum(cross)))


def read_setup(scene):
    """The Setup of a scene with a contact_force probe between the sand and the wall."""
    probe = next(probe for probe in scene.probes if probe.kind == "contact_force")
    first, second = (scene.body_named(name) for name in probe.pair)

    def is_wall(body):
        return body.kinematics.type != "free" or scene.material_of(body).model == "linear_elastic"

    wall, sand = (first, second) if is_wall(first) and not is_wall(second) else (second, first)
    sign = 1.0 if region_centre_x(wall.region) > region_centre_x(sand.region) else -1.0
    heights = [vertex[1] for vertex in sand.region.vertices]
    return Setup(scene, wall.name, sand.name, sign, max(heights) - min(heights))


def snapshot_indices(count, panels=PANELS):
    """`panels` snapshot indices spread evenly from the first to the last."""
    return sorted(set(np.linspace(0, count - 1, min(panels, count)).round().astype(int).tolist()))


def point_side_points(axes, scene):
    """The side [pt] of a square marker as wide as the initial point spacing h / ppc."""
    figure = axes.figure
    figure.canvas.draw()                           # the axes' pixel size is known after a draw
    pixels_per_metre = axes.get_window_extent().width / scene.grid.size[0]
    return scene.grid.cell / scene.numerics.ppc * pixels_per_metre * 72.0 / figure.dpi


def rigid_fit(initial, current):
    """(R, c0, c) of the rigid motion x -> R (x - c0) + c that best maps the points `initial`
    onto `current` (least squares, Kabsch in 2D): how the wall has moved."""
    c0, c = initial.mean(axis=0), current.mean(axis=0)
    covariance = (current - c).T @ (initial - c0)
    angle = math.atan2(covariance[1, 0] - covariance[0, 1], covariance[0, 0] + covariance[1, 1])
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return rotation, c0, c


def wall_outline(snapshots, index, wall):
    """(initial, moved): the wall's region as a closed polygon ((n + 1, 2) vertices), and the
    same moved rigidly with the wall's points to snapshot `index`."""
    in_wall = snapshots.body_number == snapshots.bodies.index(wall)
    vertices = snapshots.scene.body_named(wall).region.vertices
    vertices = np.array(vertices + vertices[:1])
    rotation, c0, c = rigid_fit(snapshots.positions(0)[in_wall], snapshots.positions(index)[in_wall])
    return vertices, (vertices - c0) @ rotation.T + c


def draw_snapshot(axes, snapshots, index, wall, limits):
    """Sand points coloured by plastic strain, the wall grey (its initial outline dashed);
    returns the sand's scatter artist (for the colour bar)."""
    scene = snapshots.scene
    grid = scene.grid
    axes.set_xlim(grid.origin[0], grid.origin[0] + grid.size[0])
    axes.set_ylim(grid.origin[1], grid.origin[1] + grid.size[1])
    axes.set_aspect("equal")
    side = point_side_points(axes, scene)
    positions = snapshots.positions(index)
    strain = snapshots.field("plastic_strain", index)
    sand = snapshots.body_number != snapshots.bodies.index(wall)
    shown = axes.scatter(*positions[sand].T, c=strain[sand], s=side**2, marker="s", linewidths=0,
                         cmap="viridis", vmin=limits[0], vmax=limits[1], rasterized=True)
    initial, moved = wall_outline(snapshots, index, wall)
    axes.fill(*moved.T, color="0.5", ec="k", lw=0.6)
    axes.plot(*initial.T, ls="--", lw=0.8, color="k")
    axes.set_title(f"t = {snapshots.times[index]:.2f} s", fontsize=10)
    return shown


def snapshots_figure(result, wall):
    """The sand at a few times, side by side (two columns), one colour scale."""
    snapshots = Snapshots(result)
    indices = snapshot_indices(len(snapshots))
    strain = np.concatenate([snapshots.field("plastic_strain", index) for index in indices])
    limits = (0.0, max(float(np.percentile(strain, 99.5)), 1e-12))
    grid = snapshots.scene.grid
    columns = 2 if len(indices) > 2 else len(indices)
    rows = math.ceil(len(indices) / columns)
    panel_height = 4.6 * grid.size[1] / grid.size[0] + 0.5
    figure, panels = plt.subplots(rows, columns, figsize=(10.5, rows * panel_height + 0.6), squeeze=False,
                                  sharex=True, sharey=True, layout="constrained")
    for axes, index in zip(panels.flat, indices):
        shown = draw_snapshot(axes, snapshots, index, wall, limits)
    for axes in panels.flat[len(indices):]:
        axes.set_visible(False)
    for axes in panels[-1, :]:
        axes.set_xlabel("x [m]")
    for axes in panels[:, 0]:
        axes.set_ylabel("y [m]")
    figure.colorbar(shown, ax=panels, label="equivalent plastic strain", shrink=0.8, extend="max")
    figure.suptitle(f"{snapshots.scene.name}: sand coloured by plastic strain, wall grey "
                    "(initial outline dashed)", fontsize=11)
    return figure


def moving_average(values, steps=AVERAGE_STEPS):
    """Centred running mean over `steps` steps of a (T, k) history; (T - steps + 1, k)."""
    steps = max(1, min(steps, len(values) // 5))
    kernel = np.ones(steps) / steps
    return np.stack([np.convolve(column, kernel, mode="valid") for column in values.T], axis=1), steps


def earth_pressures(setup):
    """{label: thrust [N/m]} at rest (K0) and active (Rankine) for the sand body's material,
    gravity and height."""
    scene = setup.scene
    body = scene.body_named(setup.sand)
    material = scene.material_of(body)
    sine = math.sin(math.radians(material.friction_angle))
    k0 = body.initial_stress.k0 if body.initial_stress is not None else "jaky"
    k0 = 1.0 - sine if k0 == "jaky" else float(k0)
    ka = (1.0 - sine) / (1.0 + sine)
    weight = material.density * abs(scene.gravity[1]) * setup.height**2 / 2.0
    return {f"at rest 1/2 K0 rho g H^2, K0 = {k0:.3f}: {k0 * weight:.0f} N/m": k0 * weight,
            f"Rankine (= Coulomb, smooth wall) 1/2 Ka rho g H^2, Ka = {ka:.3f}: {ka * weight:.0f} N/m": ka * weight}


def probes_of(scene, kind):
    """The scene's probes of one kind."""
    return [probe for probe in scene.probes if probe.kind == kind]


def draw_displacements(axes, result, scene):
    """Both components of every displacement and body_displacement probe [mm] against time."""
    for probe in probes_of(scene, "body_displacement") + probes_of(scene, "displacement"):
        values = np.asarray(result.probes[probe.name]) * 1000.0
        where = f"of {probe.body}" if probe.body else f"at ({probe.at[0]:g}, {probe.at[1]:g})"
        axes.plot(result.time, values[:, 0], label=f"{probe.name} x ({where})")
        axes.plot(result.time, values[:, 1], ls="--", label=f"{probe.name} y")
    axes.set_ylabel("displacement [mm]")
    axes.legend(fontsize=7, loc="best", ncol=2)


def draw_rotations(axes, result, scene):
    """Every body_rotation probe [deg] against time."""
    for probe in probes_of(scene, "body_rotation"):
        axes.plot(result.time, np.degrees(np.asarray(result.probes[probe.name])[:, 0]), label=probe.name)
    axes.set_ylabel("rotation [deg]\n(counter-clockwise +)")
    axes.legend(fontsize=7, loc="best")


def averaged_forces(result, probe):
    """(times, raw (T-1, 2), averaged (T', 2), centred times of the averages, steps averaged)
    of a contact_force probe, leaving out its first entry (before the first step: zero)."""
    time = np.asarray(result.time)[1:]
    force = np.asarray(result.probes[probe.name])[1:]
    average, steps = moving_average(force)
    start = (steps - 1) // 2
    return time, force, average, time[start : start + len(average)], steps


def draw_references(axes, setup):
    """Horizontal lines at the at-rest and active thrusts (the active scene only)."""
    if setup.scene.name == ACTIVE_SCENE:
        for (label, value), style in zip(earth_pressures(setup).items(), ("--", ":")):
            axes.axhline(value, color="k", ls=style, lw=1, label=label)


def face_of(probe):
    """How a contact_force probe's reach is named in the plot: its `facing`, or the whole contact."""
    if probe.facing is None:
        return "whole contact"
    return f"face towards [{probe.facing[0]:g}, {probe.facing[1]:g}]"


def draw_thrust(axes, result, setup):
    """The contact force of the sand on the wall against time, one colour per contact_force
    probe (the whole contact, or one face of it): horizontal (away from the sand) raw and
    averaged, vertical averaged (dashed)."""
    sign = setup.sign
    for index, probe in enumerate(probes_of(setup.scene, "contact_force")):
        time, force, average, middle, steps = averaged_forces(result, probe)
        colour = f"C{index}"
        axes.plot(time, sign * force[:, 0], color=colour, alpha=0.2, lw=0.5)
        axes.plot(middle, sign * average[:, 0], color=colour,
                  label=f"{probe.name} ({face_of(probe)}): horizontal, {'-' if sign < 0 else '+'}F_x")
        axes.plot(middle, average[:, 1], color=colour, ls="--", label=f"{probe.name}: vertical F_y")
        axes.set_title(f"force of {probe.pair[0]} on {probe.pair[1]} (mean over {steps} steps; raw horizontal pale)",
                       fontsize=9)
    draw_references(axes, setup)
    axes.set_ylabel("force [N/m]")
    axes.set_xlabel("t [s]")
    axes.legend(fontsize=7, loc="best")


def draw_thrust_against_movement(axes, result, setup):
    """The averaged horizontal thrust against the wall's horizontal movement away from the
    sand (its body_displacement probe), as a percentage of the backfill height: the classical
    earth-pressure plot."""
    sign = setup.sign
    mover = next(probe for probe in probes_of(setup.scene, "body_displacement") if probe.body == setup.wall)
    for probe in probes_of(setup.scene, "contact_force"):
        _, _, average, middle, _ = averaged_forces(result, probe)
        movement = sign * np.interp(middle, result.time, np.asarray(result.probes[mover.name])[:, 0])
        axes.plot(100.0 * movement / setup.height, sign * average[:, 0], color="C0", label="horizontal thrust")
    draw_references(axes, setup)
    axes.set_xlabel(f"wall movement away from the backfill / H [%] (H = {setup.height:g} m)")
    axes.set_ylabel("force [N/m]")
    axes.legend(fontsize=7, loc="best")


def histories_figure(result, setup):
    """Wall displacement, wall rotation (if probed) and the thrust against time; for the active
    scene also the thrust against the wall's movement."""
    scene = setup.scene
    rotated = bool(probes_of(scene, "body_rotation"))
    active = scene.name == ACTIVE_SCENE
    rows = 2 + rotated + active
    figure, panels = plt.subplots(rows, 1, figsize=(8, 2.6 * rows + 0.4), layout="constrained")
    timed = panels[: rows - active]
    for axes in timed[:-1]:
        axes.sharex(timed[-1])
        axes.tick_params(labelbottom=False)
    draw_displacements(panels[0], result, scene)
    if rotated:
        draw_rotations(panels[1], result, scene)
    draw_thrust(timed[-1], result, setup)
    if active:
        draw_thrust_against_movement(panels[-1], result, setup)
    figure.suptitle(f"{scene.name}: the wall's motion and the contact force", fontsize=11)
    return figure


def summary(result, setup):
    """Lines of key numbers: the thrust (mean over the first and last AVERAGE_STEPS steps),
    and the final value of every displacement and rotation probe."""
    scene, sign = setup.scene, setup.sign
    lines = []
    for probe in probes_of(scene, "contact_force"):
        force = np.asarray(result.probes[probe.name])[1:]
        first, last = force[:AVERAGE_STEPS].mean(axis=0), force[-AVERAGE_STEPS:].mean(axis=0)
        lines.append(f"{probe.name} ({face_of(probe)}): horizontal {sign * first[0]:.1f} -> {sign * last[0]:.1f} N/m, "
                     f"vertical {first[1]:.1f} -> {last[1]:.1f} N/m "
                     f"(means of the first and last {AVERAGE_STEPS} steps)")
    if scene.name == ACTIVE_SCENE:
        lines += [f"  {label}" for label in earth_pressures(setup)]
    for probe in probes_of(scene, "body_displacement") + probes_of(scene, "displacement"):
        x, y = np.asarray(result.probes[probe.name])[-1] * 1000.0
        lines.append(f"{probe.name} at t = {result.time[-1]:.3g} s: ({x:.2f}, {y:.2f}) mm")
    for probe in probes_of(scene, "body_rotation"):
        angle = float(np.asarray(result.probes[probe.name])[-1, 0])
        lines.append(f"{probe.name} at t = {result.time[-1]:.3g} s: {math.degrees(angle):.2f} deg "
                     "(counter-clockwise +)")
    return lines


def save(figure, path):
    """Write a PNG atomically (jaxmpm's writer) and close the figure."""
    save_png(figure, path, dpi=DPI)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", help="HDF5 file of a retaining_wall or retaining_wall_active run")
    parser.add_argument("-o", "--output", help="prefix of the PNG files (default: the result's name)")
    arguments = parser.parse_args()

    result = jaxmpm.Result.load(arguments.result)
    scene = jaxmpm.Scene.from_toml(result.scene_toml)
    if not result.complete:
        print(f"warning: the run stopped early ({result.message}); plotting what it computed")
    setup = read_setup(scene)
    prefix = arguments.output or str(Path(arguments.result).with_suffix(""))
    save(snapshots_figure(result, setup.wall), f"{prefix}_snapshots.png")
    save(histories_figure(result, setup), f"{prefix}_histories.png")
    print("\n".join(summary(result, setup)))


if __name__ == "__main__":
    main()
