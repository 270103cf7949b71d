"""Plot a pile-driving run: the deformed sand at three penetrations, and the force-penetration curves.

    jaxmpm run examples/pile_driving.toml -o pile_driving.h5
    python examples/plot_pile_driving.py pile_driving.h5 [-o PREFIX] [--compare OTHER.h5 ...]

writes
- PREFIX_snapshots.png: the whole diametral section (the run's half mirrored about the axis)
  at three penetrations, the sand coloured by its equivalent plastic strain (top row) and by
  its mean pressure p (bottom row), the pile grey;
- PREFIX_force.png: the soil resistance against the penetration, total and split into tip and
  shaft (weight subtracted, see below), with the shaft's friction bound mu |F_r| (mu times the
  sand's radial push on it, from its contact_force probe) and rough static estimates (the
  tip by Reissner's N_q and by Vesic's cavity expansion, the shaft by mu K0 sigma_v'); the
  point where the total stops growing linearly is marked, or said not to exist; below it, the
  surface heave beside the pile;
- with --compare, PREFIX_compare.png: the total resistance of this run and of every OTHER run
  against the penetration, each labelled by its pile velocity and its sand (viscoplastic, with
  its fluidity and exponent, or rate-independent): one colour per velocity, dashed for
  rate-independent sand;
and prints the key numbers. PREFIX defaults to the result file's name without its suffix.

Reading the scene (from the result file): the pile is made of the prescribed bodies, the tip
being the lowest; the sand is the free body. The soil resistance on a pile body is the upward
force of the sand on it, F = M a - M g - R from its `reaction` probe R (the force that keeps
the body on its path; at constant velocity F_z = W - R_z, W its weight M |g|, a constant).
The head force that drives the pile is F_z - W. Where the scene also has `contact_force`
probes between the sand and the pile bodies, the script checks that they agree with F.
The penetration is the downward displacement of the tip (its `body_displacement` probe).

Curves are centred moving averages over the steps in which the pile travels one cell (the
force ripples as the tip crosses cells); "force at a penetration d" is the mean of the raw
force over d +- half a cell. The force stops growing linearly at the first penetration where
the slope of the total resistance, a least-squares fit over a window of KNEE_CELLS cells of
penetration sliding by one cell, falls below KNEE_FRACTION (half) of the first window's slope
(which starts one cell in, after the start-up transient). A frictional soil's resistance
grows with the overburden at the tip, so there need not be such a point.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm  # noqa: E402
from jaxmpm.pictures.plotting import draw_points, save_png  # noqa: E402
from jaxmpm.scene.seeding import seed_bodies  # noqa: E402
from jaxmpm.pictures.snapshots import Snapshots  # noqa: E402

DPI = 100
PANELS = 3                  # penetrations shown in the snapshot figure
REPORTED = (0.05, 0.10, 0.15, 0.20, 0.25)      # penetrations [m] whose forces are printed
KNEE_FRACTION = 0.5         # the linear growth ends where the slope falls below this x initial
KNEE_CELLS = 4              # slopes are fitted over windows of this many cells of penetration


@dataclasses.dataclass(frozen=True)
class Pile:
    """What the analysis needs to know about a pile scene.

    sand: the free body's name; parts: the prescribed bodies, lowest (the tip) first;
    reactions / contacts: {part: probe name} of its reaction and sand-on-part contact_force
    probes (contact signs: +1 if the pair is [sand, part], -1 if [part, sand]); masses
    {part: M [kg]} (whole ring in axisymmetry); gravity g_z [m/s^2]; radius [m] of the tip;
    speed [m/s] of the pile (its final prescribed speed); cell [m]."""

    scene: jaxmpm.Scene
    sand: str
    parts: tuple[str, ...]
    reactions: dict
    contacts: dict
    masses: dict
    gravity: float
    radius: float
    speed: float
    cell: float

    @property
    def tip(self):
        return self.parts[0]

    def weight(self, part):
        """|M g| [N] of one pile body."""
        return self.masses[part] * abs(self.gravity)


def read_pile(scene):
    """The Pile of a scene with prescribed pile bodies and a free sand body."""
    parts = sorted((body for body in scene.bodies if body.kinematics.type == "prescribed"),
                   key=lambda body: min(vertex[1] for vertex in body.region.vertices))
    if not parts:
        raise SystemExit(f"scene {scene.name!r} has no prescribed body: not a pile-driving run.")
    sand = next(body.name for body in scene.bodies if body.kinematics.type == "free")
    names = tuple(body.name for body in parts)
    reactions = {probe.body: probe.name for probe in scene.probes if probe.kind == "reaction"}
    missing = [name for name in names if name not in reactions]
    if missing:
        raise SystemExit(f"the pile bodies {missing} have no reaction probe: the forces cannot be read.")
    contacts = {}
    for probe in scene.probes:
        if probe.kind == "contact_force" and sand in probe.pair:
            other = probe.pair[1] if probe.pair[0] == sand else probe.pair[0]
            contacts[other] = (probe.name, 1.0 if probe.pair[0] == sand else -1.0)
    seeds = seed_bodies(scene)
    ring = 2.0 * math.pi if scene.geometry == "axisymmetric" else 1.0
    masses = {}
    for body, (start, stop) in zip(scene.bodies, seeds.slices):
        if body.name in names:
            masses[body.name] = ring * scene.material_of(body).density * float(np.sum(seeds.volumes[start:stop]))
    kinematics = parts[0].kinematics
    last = kinematics.velocity if kinematics.time is None else kinematics.velocity[-1]
    radius = max(vertex[0] for vertex in parts[0].region.vertices)
    return Pile(scene, sand, names, reactions, contacts, masses, scene.gravity[1], radius,
                math.hypot(*last), scene.grid.cell)


def prescribed_velocity_z(body, times):
    """The axial velocity [m/s] of a prescribed body at `times` (its table, linear in between)."""
    kinematics = body.kinematics
    if kinematics.time is None:
        return np.full(len(times), kinematics.velocity[1])
    return np.interp(times, kinematics.time, [row[1] for row in kinematics.velocity])


@dataclasses.dataclass
class Curves:
    """Per-step histories from the first step on (the probes' t = 0 entry is left out):
    time [s], penetration [m] (downward displacement of the tip), resistance {part: F_z [N]}
    and its sum "total", contact {part: F_z from the contact_force probe} and radial {part:
    F_r, the sand's whole-ring radial push on the part (negative: towards the axis)} where
    probed, heave
    (z displacement of the surface point [m]) where probed, and the number of steps in which
    the pile travels one cell (`window`)."""

    time: np.ndarray
    penetration: np.ndarray
    resistance: dict
    contact: dict
    radial: dict
    heave: np.ndarray | None
    heave_at: tuple | None
    window: int


def curves(result, pile):
    """The Curves of a run."""
    scene = pile.scene
    time = np.asarray(result.time)
    dt = time[1] - time[0]
    resistance = {}
    for part in pile.parts:
        body = scene.body_named(part)
        velocity = prescribed_velocity_z(body, time)
        acceleration = np.diff(velocity) / dt
        reaction = np.asarray(result.probes[pile.reactions[part]])[1:, 1]
        mass = pile.masses[part]
        resistance[part] = mass * acceleration - mass * pile.gravity - reaction
    resistance["total"] = sum(resistance[part] for part in pile.parts)
    contact = {part: sign * np.asarray(result.probes[name])[1:, 1] for part, (name, sign) in pile.contacts.items()}
    radial = {part: sign * np.asarray(result.probes[name])[1:, 0] for part, (name, sign) in pile.contacts.items()}
    mover = next((probe for probe in scene.probes if probe.kind == "body_displacement" and probe.body == pile.tip), None)
    if mover is not None:
        penetration = -np.asarray(result.probes[mover.name])[1:, 1]
    else:
        velocity = prescribed_velocity_z(scene.body_named(pile.tip), time)
        penetration = -np.cumsum(velocity[1:]) * dt
    heave, heave_at = None, None
    surface = next((probe for probe in scene.probes if probe.kind == "displacement"), None)
    if surface is not None:
        heave, heave_at = np.asarray(result.probes[surface.name])[1:, 1], surface.at
    window = max(1, int(round(pile.cell / (pile.speed * dt)))) if pile.speed > 0 else 1
    return Curves(time[1:], penetration, resistance, contact, radial, heave, heave_at, window)


def moving_average(values, steps):
    """Centred running mean over `steps` samples: (values averaged, index of the first centre)."""
    steps = max(1, min(steps, len(values)))
    averaged = np.convolve(values, np.ones(steps) / steps, mode="valid")
    return averaged, (steps - 1) // 2


def smoothed(data, values):
    """(penetration, values) averaged over one cell of travel."""
    averaged, start = moving_average(values, data.window)
    return data.penetration[start : start + len(averaged)], averaged


def force_at(data, values, depth, half_width):
    """Mean of `values` over the steps whose penetration is within depth +- half_width (NaN
    if the run never got there)."""
    near = np.abs(data.penetration - depth) <= half_width
    return float(np.mean(values[near])) if near.any() else math.nan


def window_slope(data, values, low, high):
    """Least-squares slope [N/m] of `values` against the penetration over the steps with
    penetration in [low, high] (NaN if fewer than 10 steps)."""
    inside = (data.penetration >= low) & (data.penetration <= high)
    if inside.sum() < 10:
        return math.nan
    return float(np.polyfit(data.penetration[inside], values[inside], 1)[0])


def knee(data, pile):
    """Where the total resistance stops growing linearly: (penetration [m] or NaN if it never
    does, force there [N], initial slope [N/m], slope over the last window [N/m]).

    Slopes are least-squares fits over windows of KNEE_CELLS cells of penetration (the force
    ripples with period one cell as the tip crosses cells); the initial slope is the first
    window's, from one cell of penetration on (the first cell holds the start-up transient);
    the windows then slide one cell at a time, and the knee is the centre of the first window
    whose slope is below KNEE_FRACTION x the initial one."""
    total = data.resistance["total"]
    width = KNEE_CELLS * pile.cell
    low = pile.cell
    initial = window_slope(data, total, low, low + width)
    last = window_slope(data, total, data.penetration[-1] - width, data.penetration[-1])
    while low + width <= data.penetration[-1] + 1e-9:
        slope = window_slope(data, total, low, low + width)
        if slope < KNEE_FRACTION * initial:
            where = low + width / 2
            return where, force_at(data, total, where, pile.cell / 2), initial, last
        low += pile.cell
    return math.nan, math.nan, initial, last


def material_label(scene, sand):
    """'viscoplastic (fluidity 10 1/s, exponent 1)' or 'rate-independent', with phi."""
    material = scene.material_of(scene.body_named(sand))
    phi = f"phi = {material.friction_angle:g} deg"
    if getattr(material, "fluidity", None) is not None:
        return f"viscoplastic ({phi}, fluidity {material.fluidity:g} 1/s, exponent {material.exponent:g})"
    return f"rate-independent ({phi})"


def run_label(pile):
    return f"v = {pile.speed:g} m/s, {material_label(pile.scene, pile.sand)}"


# --------------------------------------------------------------------------- estimates


def reissner_nq(phi):
    """N_q = exp(pi tan phi) tan^2(45 deg + phi/2) (Prandtl-Reissner; phi in radians): the
    bearing factor of the overburden for a shallow footing."""
    return math.exp(math.pi * math.tan(phi)) * math.tan(math.pi / 4 + phi / 2) ** 2


def vesic_n_sigma(phi, rigidity):
    """Vesic's (1977) cavity-expansion end-bearing factor on the mean stress sigma_0' for a soil
    that keeps its volume (I_rr = I_r): 3 / (3 - sin phi) exp((pi/2 - phi) tan phi)
    tan^2(45 deg + phi/2) I_r^(4 sin phi / (3 (1 + sin phi)))."""
    sine = math.sin(phi)
    return (3.0 / (3.0 - sine) * math.exp((math.pi / 2 - phi) * math.tan(phi))
            * math.tan(math.pi / 4 + phi / 2) ** 2 * rigidity ** (4.0 * sine / (3.0 * (1.0 + sine))))


def triaxial_friction_angle(scene, sand):
    """The friction angle [deg] that the sand's Drucker-Prager cone matches in triaxial
    compression, sin phi_c = 3 m / (6 + m) (m the cone's slope in q = m p)."""
    from jaxmpm.materials.drucker_prager import cone_slope

    material = scene.material_of(scene.body_named(sand))
    m = float(cone_slope(material.cone, material.friction_angle))
    return math.degrees(math.asin(3.0 * m / (6.0 + m)))


def friction_of(pile, part):
    """The Coulomb friction of the contact between the sand and a pile body (0 if not paired)."""
    return next((c.friction for c in pile.scene.contacts if set(c.pair) == {pile.sand, part}), 0.0)


def estimates(pile, depth):
    """Rough static estimates at penetration `depth` [m], with phi_c the cone's
    triaxial-compression angle, sigma_v' = rho g depth, A = pi R^2:
      "tip_reissner"  N_q sigma_v' A, Reissner's N_q (a shallow footing's failure mechanism);
      "tip_vesic"     N*_sigma sigma_0' A, Vesic's cavity expansion, sigma_0' = (1 + 2 K0)/3
                      sigma_v', rigidity index I_r = G / (sigma_0' tan phi_c);
      "shaft"         mu K0 sigma_v' over the shaft's embedded length L = depth minus the tip
                      length (the whole depth for a one-body pile; mean sigma_v' = rho g L / 2,
                      area 2 pi R L);
    all in N (0 at depth 0), plus the factors used ("N_q", "N_sigma", "I_r", "phi_c", "K0", "mu")."""
    scene = pile.scene
    body = scene.body_named(pile.sand)
    material = scene.material_of(body)
    unit_weight = material.density * abs(pile.gravity)
    phi_c = triaxial_friction_angle(scene, pile.sand)
    phi = math.radians(phi_c)
    k0 = body.initial_stress.k0 if body.initial_stress is not None else "jaky"
    k0 = 1.0 - math.sin(math.radians(material.friction_angle)) if k0 == "jaky" else float(k0)
    friction = friction_of(pile, pile.parts[-1])
    tip_length = np.ptp([vertex[1] for vertex in scene.body_named(pile.tip).region.vertices]) if len(pile.parts) > 1 else 0.0
    area = math.pi * pile.radius**2
    vertical = unit_weight * depth
    mean = (1.0 + 2.0 * k0) / 3.0 * vertical
    shear_modulus = material.young / (2.0 * (1.0 + material.poisson))
    rigidity = shear_modulus / (mean * math.tan(phi)) if depth > 0 else math.inf
    n_sigma = vesic_n_sigma(phi, rigidity) if depth > 0 else math.nan
    embedded = max(depth - tip_length, 0.0)
    return {
        "tip_reissner": reissner_nq(phi) * vertical * area,
        "tip_vesic": n_sigma * mean * area if depth > 0 else 0.0,
        "shaft": friction * k0 * unit_weight * embedded / 2.0 * 2.0 * math.pi * pile.radius * embedded,
        "N_q": reissner_nq(phi), "N_sigma": n_sigma, "I_r": rigidity, "phi_c": phi_c, "K0": k0, "mu": friction,
    }


# --------------------------------------------------------------------------- figures


def snapshot_at(snapshots, data, depth):
    """Index of the snapshot whose penetration is nearest `depth`."""
    penetration = np.interp(snapshots.times, data.time, data.penetration, left=0.0)
    return int(np.argmin(np.abs(penetration - depth)))


def pile_outline(snapshots, index, part):
    """The pile body's region at snapshot `index` (moved with its points' mean displacement),
    a closed (n + 1, 2) polygon."""
    in_part = snapshots.body_number == snapshots.bodies.index(part)
    shift = (snapshots.positions(index)[in_part] - snapshots.positions(0)[in_part]).mean(axis=0)
    vertices = snapshots.scene.body_named(part).region.vertices
    return np.array(vertices + vertices[:1]) + shift


def zoom(axes, artist, snapshots, xlim, ylim, enlarge=1.4):
    """Show only xlim x ylim and resize the point squares to the new scale, `enlarge` times
    their initial spacing (so that the sand spread around the pile still looks solid)."""
    axes.set_xlim(*xlim)
    axes.set_ylim(*ylim)
    figure = axes.figure
    figure.canvas.draw()
    pixels_per_metre = axes.get_window_extent().width / (xlim[1] - xlim[0])
    side = snapshots.scene.grid.cell / snapshots.scene.numerics.ppc * pixels_per_metre * 72.0 / figure.dpi
    artist.set_sizes([(enlarge * side) ** 2])


def snapshots_figure(result, pile, data):
    """Two rows (plastic strain, p) x PANELS penetrations, mirrored about the axis, pile grey."""
    snapshots = Snapshots(result)
    final = float(data.penetration[-1])
    indices = sorted({snapshot_at(snapshots, data, final * (k + 1) / PANELS) for k in range(PANELS)})
    sand = snapshots.body_number == snapshots.bodies.index(pile.sand)
    fields = {"plastic_strain": ("equivalent plastic strain", 1.0, 99.0),
              "p": ("mean pressure p [kPa]", 1e-3, 99.5)}
    grid = pile.scene.grid
    top = grid.origin[1] + grid.size[1]
    xlim = (-min(grid.size[0], 0.35), min(grid.size[0], 0.35))
    surface = max(vertex[1] for vertex in pile.scene.body_named(pile.sand).region.vertices)
    ylim = (max(grid.origin[1], surface - 0.6), min(top, surface + 0.15))
    aspect = (ylim[1] - ylim[0]) / (xlim[1] - xlim[0])
    figure, panels = plt.subplots(2, len(indices), figsize=(3.3 * len(indices) + 1.4, 2 * 3.3 * aspect + 1.0),
                                  squeeze=False, sharex=True, sharey=True, layout="constrained")
    for row, (field, (label, scale, percentile)) in enumerate(fields.items()):
        values = np.concatenate([snapshots.field(field, index)[sand] for index in indices])
        limits = (0.0, max(float(np.percentile(values, percentile)), 1e-12))
        for axes, index in zip(panels[row], indices):
            artist = draw_points(axes, snapshots, field, index, limits, mirror=True)
            artist.set_array(artist.get_array() * scale)
            artist.set_clim(limits[0] * scale, limits[1] * scale)
            artist.set_rasterized(True)
            zoom(axes, artist, snapshots, xlim, ylim)
            for part in pile.parts:
                outline = pile_outline(snapshots, index, part)
                for side in (1.0, -1.0):
                    axes.fill(side * outline[:, 0], outline[:, 1], color="0.55", ec="k", lw=0.5)
            axes.axhline(surface, color="0.3", lw=0.5, ls=":")
            depth = float(np.interp(snapshots.times[index], data.time, data.penetration, left=0.0))
            axes.set_title(f"penetration {100 * depth:.1f} cm (t = {snapshots.times[index]:.2f} s)", fontsize=9)
            if row == 0:
                axes.set_xlabel("")
            if axes is not panels[row, 0]:
                axes.set_ylabel("")
        figure.colorbar(artist, ax=panels[row, :], label=label, shrink=0.9, extend="max")
    figure.suptitle(f"{pile.scene.name}: {run_label(pile)}; the section mirrored about the axis "
                    "(dash-dot), pile grey, initial surface dotted", fontsize=9)
    return figure


def draw_resistance(axes, data, pile, knee_point):
    """Total, tip and shaft resistance against penetration: raw (pale) and averaged; the
    shaft's friction bound mu |F_r|; the static estimates; the knee (or a note that there is none)."""
    colours = {"total": "k", pile.tip: "C0"}
    names = {"total": "total", pile.tip: f"{pile.tip} (bottom)"}
    for index, part in enumerate(pile.parts[1:]):
        colours[part] = f"C{index + 1}"
        names[part] = part
    for part in ["total", *pile.parts]:
        values = data.resistance[part]
        axes.plot(100 * data.penetration, values, color=colours[part], alpha=0.15, lw=0.4)
        axes.plot(*np.array(smoothed(data, values)) * [[100], [1]], color=colours[part], lw=1.4,
                  label=f"{names[part]}")
    for part in pile.parts[1:]:
        if part in data.radial:
            mu = friction_of(pile, part)
            axes.plot(*np.array(smoothed(data, mu * np.abs(data.radial[part]))) * [[100], [1]], color=colours[part],
                      lw=1.0, ls="--", label=f"{part}: mu x radial push |F_r| (mu = {mu:g}; its friction if it slides)")
    depth, force, initial, last = knee_point
    if math.isfinite(depth):
        axes.plot(100 * depth, force, "o", mfc="none", mec="r", ms=9,
                  label=f"slope < {KNEE_FRACTION:g} x initial: {100 * depth:.1f} cm, {force:.0f} N")
    else:
        axes.plot([], [], " ", label=f"no knee: the {KNEE_CELLS}-cell slope of the total never falls below "
                                     f"{KNEE_FRACTION:g} x its initial {initial / 1000:.1f} N/mm (last {last / 1000:.1f})")
    reach = np.linspace(0.0, data.penetration[-1], 60)
    rough = [estimates(pile, depth) for depth in reach]
    end = rough[-1]
    axes.plot(100 * reach, [r["tip_vesic"] for r in rough], color="C0", ls="-.", lw=1,
              label=f"tip, Vesic cavity expansion (N*_sigma = {end['N_sigma']:.0f} at the end, "
                    f"I_r = {end['I_r']:.0f}, phi_c = {end['phi_c']:.1f} deg)")
    axes.plot(100 * reach, [r["tip_reissner"] for r in rough], color="C0", ls=":", lw=1,
              label=f"tip, N_q sigma_v' pi R^2 (Reissner N_q = {end['N_q']:.1f})")
    if len(pile.parts) > 1:
        axes.plot(100 * reach, [r["shaft"] for r in rough], color="C1", ls=":", lw=1,
                  label=f"shaft, mu K0 sigma_v' x area (mu = {end['mu']:g}, K0 = {end['K0']:.2f})")
    axes.set_ylabel("soil resistance F_z [N]\n(whole ring, weight subtracted)")
    top = max(float(np.max(data.resistance["total"])), 1.45 * float(np.max(smoothed(data, data.resistance["total"])[1])))
    axes.set_ylim(top=top)                      # room for the legend above the curves
    axes.legend(fontsize=7, loc="upper left")
    axes.grid(alpha=0.3)


def draw_heave(axes, data):
    """Axial displacement of the surface probe against penetration [mm]."""
    axes.plot(100 * data.penetration, 1000 * data.heave, color="C2")
    axes.set_ylabel(f"heave at r = {data.heave_at[0]:g} m [mm]")
    axes.grid(alpha=0.3)


def force_figure(data, pile, knee_point):
    rows = 2 if data.heave is not None else 1
    figure, panels = plt.subplots(rows, 1, figsize=(8, 4.4 + 2.0 * (rows - 1)), sharex=True, squeeze=False,
                                  height_ratios=[2.2, 1][:rows], layout="constrained")
    draw_resistance(panels[0, 0], data, pile, knee_point)
    if data.heave is not None:
        draw_heave(panels[1, 0], data)
    panels[-1, 0].set_xlabel("penetration of the pile tip [cm]")
    panels[0, 0].set_title(f"{pile.scene.name}: {run_label(pile)}\n(pale: every step; solid: mean over one cell "
                           f"of travel, {data.window} steps)", fontsize=9)
    return figure


def is_viscoplastic(pile):
    return getattr(pile.scene.material_of(pile.scene.body_named(pile.sand)), "fluidity", None) is not None


def compare_figure(runs):
    """The averaged total resistance of several runs against penetration: one colour per pile
    velocity, solid for viscoplastic sand, dashed for rate-independent."""
    figure, axes = plt.subplots(figsize=(8, 4.6), layout="constrained")
    speeds = sorted({pile.speed for _, pile, _ in runs}, reverse=True)
    for path, pile, data in runs:
        colour = f"C{speeds.index(pile.speed)}"
        axes.plot(*np.array(smoothed(data, data.resistance["total"])) * [[100], [1]], color=colour,
                  ls="-" if is_viscoplastic(pile) else "--", label=f"{run_label(pile)}  [{Path(path).name}]")
    axes.set_xlabel("penetration of the pile tip [cm]")
    axes.set_ylabel("total soil resistance F_z [N]\n(whole ring, weight subtracted)")
    axes.set_title("pile driving: total resistance against penetration (mean over one cell of travel)", fontsize=9)
    axes.legend(fontsize=7, loc="upper left")
    axes.grid(alpha=0.3)
    return figure


# --------------------------------------------------------------------------- numbers


def summary(result, pile, data, knee_point):
    lines = [f"{pile.scene.name}: {run_label(pile)}; {len(data.time)} steps of {data.time[1] - data.time[0]:.4g} s, "
             f"final penetration {data.penetration[-1]:.4f} m"]
    weights = ", ".join(f"{part} {pile.weight(part):.1f} N" for part in pile.parts)
    lines.append(f"pile weights (constant, subtracted from the reactions): {weights}")
    for part in pile.parts:
        if part in data.contact:
            gap = np.max(np.abs(data.contact[part] - data.resistance[part]))
            lines.append(f"  {part}: M a - M g - R_z against the contact_force probe: largest difference {gap:.2e} N")
    half = pile.cell / 2
    shafts = [part for part in pile.parts[1:] if part in data.radial]
    lines.append(f"soil resistance [N] (mean over +-{1000 * half:.2f} mm of penetration; head force = total - "
                 f"{sum(pile.weight(part) for part in pile.parts):.1f} N):")
    lines.append("  penetration [m] | total | " + " | ".join(pile.parts) + " | tip share | "
                 + "".join(f"{part}: mu |F_r| | " for part in shafts) + "tip: Vesic | tip: Reissner | shaft: mu K0")
    for depth in REPORTED:
        if depth > data.penetration[-1] - half + 1e-9:
            continue
        values = [force_at(data, data.resistance[key], depth, half) for key in ["total", *pile.parts]]
        bounds = [friction_of(pile, part) * abs(force_at(data, data.radial[part], depth, half)) for part in shafts]
        rough = estimates(pile, depth)
        lines.append(f"  {depth:.2f} | {values[0]:.0f} | " + " | ".join(f"{v:.0f}" for v in values[1:])
                     + f" | {values[1] / values[0]:.2f} | " + "".join(f"{v:.0f} | " for v in bounds)
                     + f"{rough['tip_vesic']:.0f} | {rough['tip_reissner']:.0f} | {rough['shaft']:.0f}")
    depth, force, initial, last = knee_point
    slopes = (f"initial slope {initial / 1000:.1f} N/mm (over {1000 * pile.cell:g}-"
              f"{1000 * (1 + KNEE_CELLS) * pile.cell:g} mm), last {last / 1000:.1f} N/mm (over the last "
              f"{1000 * KNEE_CELLS * pile.cell:g} mm)")
    if math.isfinite(depth):
        lines.append(f"linear growth ends (a {KNEE_CELLS}-cell slope below {KNEE_FRACTION:g} x the initial): "
                     f"penetration {1000 * depth:.1f} mm, total resistance {force:.0f} N; {slopes}")
    else:
        lines.append(f"linear growth does not end within the run (no {KNEE_CELLS}-cell slope below "
                     f"{KNEE_FRACTION:g} x the initial): {slopes}")
    peak = int(np.argmax(data.resistance["total"]))
    lines.append(f"largest total resistance in one step: {data.resistance['total'][peak]:.0f} N at penetration "
                 f"{1000 * data.penetration[peak]:.1f} mm; first step {data.resistance['total'][0]:.0f} N (the impact)")
    if data.heave is not None:
        lines.append(f"surface at r = {data.heave_at[0]:g} m: z displacement {1000 * data.heave[-1]:+.2f} mm at the end "
                     f"(largest {1000 * np.max(data.heave):+.2f} mm)")
    for probe in (probe for probe in jaxmpm.Scene.from_toml(result.scene_toml).probes if probe.kind == "peak_speed"):
        speeds = np.asarray(result.probes[probe.name])[1:, 0]
        fastest = int(np.argmax(speeds))
        lines.append(f"fastest point of {probe.body}: {speeds[fastest]:.2f} m/s at penetration "
                     f"{1000 * data.penetration[fastest]:.1f} mm ({speeds[fastest] / pile.speed:.1f} x the pile's "
                     f"speed; a numerical event shows here first)")
    rough = estimates(pile, float(data.penetration[-1]))
    lines.append(f"estimates: phi_c = {rough['phi_c']:.1f} deg (the cone's triaxial-compression angle), Reissner "
                 f"N_q = {rough['N_q']:.1f}; Vesic N*_sigma = {rough['N_sigma']:.0f} at the end (I_r = {rough['I_r']:.0f}); "
                 f"K0 = {rough['K0']:.2f}, mu = {rough['mu']:g}")
    return lines


def save(figure, path):
    """Write a PNG atomically (jaxmpm's writer) and close the figure."""
    save_png(figure, path, dpi=DPI)
    print(f"wrote {path}")


def load(path):
    """(Result, Pile, Curves) of a result file."""
    result = jaxmpm.Result.load(path)
    if not result.complete:
        print(f"warning: {path}: the run stopped early ({result.message}); using what it computed")
    pile = read_pile(jaxmpm.Scene.from_toml(result.scene_toml))
    return result, pile, curves(result, pile)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", help="HDF5 file of a pile_driving run")
    parser.add_argument("-o", "--output", help="prefix of the PNG files (default: the result's name)")
    parser.add_argument("--compare", nargs="+", default=[], metavar="OTHER.h5",
                        help="other pile runs whose total resistance is drawn with this one's")
    arguments = parser.parse_args()

    result, pile, data = load(arguments.result)
    prefix = arguments.output or str(Path(arguments.result).with_suffix(""))
    knee_point = knee(data, pile)
    save(snapshots_figure(result, pile, data), f"{prefix}_snapshots.png")
    save(force_figure(data, pile, knee_point), f"{prefix}_force.png")
    print("\n".join(summary(result, pile, data, knee_point)))
    if arguments.compare:
        runs = [(arguments.result, pile, data)]
        for path in arguments.compare:
            _, other, other_data = load(path)
            runs.append((path, other, other_data))
            print(f"{path}: {run_label(other)}: total resistance "
                  + ", ".join(f"{force_at(other_data, other_data.resistance['total'], d, other.cell / 2):.0f} N at {d:g} m"
                              for d in REPORTED if d <= other_data.penetration[-1] - other.cell / 2 + 1e-9))
        save(compare_figure(runs), f"{prefix}_compare.png")


if __name__ == "__main__":
    main()
