"""The parts a scene is made of: frozen dataclasses, one per table of the scene file but the
scene's own (`jaxmpm.scene.model.Scene`), and the words and presets they use.

Plain data, SI units, angles in degrees; nothing here reads files or checks a whole scene, so
the schema, the checks and the file reader all build on this module and none of them on
another's.
"""

from __future__ import annotations

import dataclasses
import math
import re

from jaxmpm.errors import SceneError

BOUNDARY_KINDS = ("fixed", "slip", "free")
NUMERICS_CHOICES = {"shape": ("linear", "gimp", "bspline2"), "transfer": ("flip", "apic"),
                    "dtype": ("float64", "float32"), "update": ("musl", "usl")}
SNAPSHOT_FIELDS = ("x", "v", "displacement", "stress", "plastic_strain", "volume", "mass")
PROBE_KINDS = ("displacement", "body_displacement", "body_rotation", "peak_speed", "contact_force", "reaction")
BODY_PROBE_KINDS = ("body_displacement", "body_rotation", "peak_speed", "reaction")    # they name a `body`
SCALAR_PROBE_KINDS = ("body_rotation", "peak_speed")                                  # one component, not two
KINEMATICS = ("free", "prescribed", "rigid")
GEOMETRIES = ("plane_strain", "axisymmetric")
NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")   # bodies, materials, probes: safe in HDF5 paths and --set


# --------------------------------------------------------------------------- data classes


@dataclasses.dataclass(frozen=True)
class Boundaries:
    """Condition on each grid edge: "fixed" (v = 0), "slip" (normal v = 0) or "free"."""

    left: str = "slip"
    right: str = "slip"
    bottom: str = "fixed"
    top: str = "free"


@dataclasses.dataclass(frozen=True)
class Grid:
    """Regular background grid: lower-left `origin` [m], `size` [m], square `cell` [m]."""

    size: tuple[float, float]
    cell: float
    origin: tuple[float, float] = (0.0, 0.0)
    boundaries: Boundaries = Boundaries()

    @property
    def cells(self) -> tuple[int, int]:
        """Number of cells along x and y."""
        return tuple(int(round(length / self.cell)) for length in self.size)


# Discretisation presets (docs/speed_accuracy.md measures each). Keys a scene gives explicitly
# override its preset's; damping is a physical choice (quasi-static settling), never preset.
PRESETS = {
    "fast": {"shape": "linear", "transfer": "flip", "flip": 0.99, "ppc": 2, "dtype": "float32", "update": "musl"},
    "balanced": {"shape": "bspline2", "transfer": "apic", "flip": 0.99, "ppc": 2, "dtype": "float64", "update": "musl"},
    "accurate": {"shape": "bspline2", "transfer": "apic", "flip": 0.99, "ppc": 3, "dtype": "float64", "update": "musl"},
}
DEFAULT_PRESET = "balanced"
# With APIC, the points' own velocity fades over this many cell crossings of the slowest free
# body's p-wave (solver.transfer_memory); 0 is plain APIC. docs/convergence.md measures 10 on the
# examples, and says why it is not yet the default (undamped elastic bodies keep vibrating, and
# creep on slopes; a point that leaves a granular flow glides on a no-slip base).
DEFAULT_RELAXATION = 0.0
DEFAULT_CORNER_RADIUS = 1.0
DEFAULT_STRESS_SUBSTEPS = 1
STRUCTURE_HOLDS = ("mass", "outline", "points")
DEFAULT_STRUCTURE_HOLD = "mass"
MAX_STRESS_SUBSTEPS = 64
DEFAULT_CFL = 0.4


@dataclasses.dataclass(frozen=True)
class Numerics:
    """Discretisation choices; each is static (changing one recompiles).

    preset: "fast" | "balanced" (the default) | "accurate" fills every choice left as None
    (`PRESETS`); a value given explicitly overrides the preset's. update: "musl" (strain rate
    from velocities re-mapped after the particle update, which keeps nodes with tiny mass from
    polluting stresses) or "usl". relaxation: with APIC, the time over which the points'
    own velocity fades into the grid's, in cell crossings of the slowest free body's p-wave
    (0: plain APIC, whose dissipation grows as dt shrinks). corner_radius: the radius, in cells,
    at which a prescribed body's outline has its corners rounded where it meets free bodies (0:
    sharp corners; `bodies.rounded_outline`). stress_substeps: the updates of dt / stress_substeps
    each step's stress update of a body that can yield is made of (`materials.base.points_update`).
    structure_hold: the nodes at which a structure (a prescribed or rigid body, or an elastic body
    whose outline bounds a contact's normal) holds the bodies in contact with it: "mass",
    wherever its points have mass (the multi-velocity-field rule), "outline", only where the
    node's cell (the square of side h centred on it) meets its outline (`bodies.held_by_outline`),
    or "points": a prescribed or rigid structure holds no node and pushes the points of the
    bodies it meets out of its outline (`physics.point_contact`).
    """

    preset: str = DEFAULT_PRESET
    shape: str | None = None
    transfer: str | None = None
    flip: float | None = None
    ppc: int | None = None
    dtype: str | None = None
    damping: float = 0.0
    update: str | None = None
    relaxation: float = DEFAULT_RELAXATION
    corner_radius: float = DEFAULT_CORNER_RADIUS
    stress_substeps: int = DEFAULT_STRESS_SUBSTEPS
    structure_hold: str = DEFAULT_STRUCTURE_HOLD
    # The values the preset filled in (not given by the user): `to_dict` leaves them out, and
    # `dataclasses.replace(numerics, preset=...)` fills them again from the new preset.
    filled: dict | None = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise SceneError(f"numerics.preset = {self.preset!r} is not one of {', '.join(map(repr, PRESETS))}.")
        if self.structure_hold not in STRUCTURE_HOLDS:
            raise SceneError(f"numerics.structure_hold = {self.structure_hold!r} is not one of "
                             f"{', '.join(map(repr, STRUCTURE_HOLDS))}.")
        previous, filled = self.filled or {}, {}
        for name, value in PRESETS[self.preset].items():
            given = getattr(self, name)
            if given is None or (name in previous and given == previous[name]):
                object.__setattr__(self, name, value)
                filled[name] = value
        object.__setattr__(self, "filled", filled)

    def given(self) -> dict:
        """The choices this Numerics states itself: its preset, damping, a relaxation and a
        corner radius other than the defaults, and every override."""
        defaults = {"relaxation": DEFAULT_RELAXATION, "corner_radius": DEFAULT_CORNER_RADIUS,
                    "stress_substeps": DEFAULT_STRESS_SUBSTEPS, "structure_hold": DEFAULT_STRUCTURE_HOLD}
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)
                if field.name != "filled" and field.name not in self.filled
                and not (field.name in defaults and getattr(self, field.name) == defaults[field.name])}


@dataclasses.dataclass(frozen=True)
class Rectangle:
    """Axis-aligned rectangle from `lower` = (x0, y0) to `upper` = (x1, y1) [m]."""

    lower: tuple[float, float]
    upper: tuple[float, float]

    @property
    def vertices(self):
        (x0, y0), (x1, y1) = self.lower, self.upper
        return ((x0, y0), (x1, y0), (x1, y1), (x0, y1))


@dataclasses.dataclass(frozen=True)
class Polygon:
    """Simple polygon given by its vertices [m], in order."""

    vertices: tuple[tuple[float, float], ...]


@dataclasses.dataclass(frozen=True)
class Geostatic:
    """Initial geostatic stress: sigma_v from the depth below the body's top and the weight of
    other geostatic bodies stacked on it, sigma_h = K0 sigma_v; k0 = "jaky" (1 - sin phi of
    the body's friction angle) or a number."""

    k0: float | str = "jaky"


@dataclasses.dataclass(frozen=True)
class Kinematics:
    """How a body moves.

    free        deformable: its material's stress update, moved by the grid (the default);
    prescribed  moved at a given velocity [m/s], no stress update: `velocity` = (vx, vy), or
                one (vx, vy) per entry of `time` [s] (strictly increasing from 0), linear in
                between and held after the last; the velocity is a parameter
                (params["bodies"][name]["velocity"]);
    rigid       moves as one body (translation and rotation) under gravity and the forces of
                the bodies around it, no stress update.
    Prescribed and rigid bodies never set the time step: their stiffness plays no part.

    substeps (free bodies): None or 1, the body steps with the scene; n > 1 or "auto", the
    body takes n steps of its own within each step of the scene (subcycling, for a stiff
    structure whose p-wave would otherwise set the step: `physics.subcycling`); it then does not
    set the scene's step, and "auto" takes the fewest substeps that keep it within scene.cfl.
    """

    type: str = "free"
    velocity: tuple | None = None
    time: tuple[float, ...] | None = None
    substeps: int | str | None = None

    @property
    def subcycled(self) -> bool:
        """Whether the body takes steps of its own within the scene's (substeps n > 1 or "auto")."""
        return self.type == "free" and self.substeps not in (None, 1)

    @property
    def top_speed(self) -> float:
        """The largest prescribed speed [m/s] (0 for free and rigid bodies)."""
        if self.type != "prescribed":
            return 0.0
        rows = [self.velocity] if self.time is None else self.velocity
        return max(math.hypot(*row) for row in rows)


@dataclasses.dataclass(frozen=True)
class Body:
    """A region filled with material points of one material, with its `kinematics`, its
    initial `velocity` [m/s] (free and rigid bodies) and zero initial stress or a `Geostatic`
    one."""

    name: str
    material: str
    region: Rectangle | Polygon
    velocity: tuple[float, float] = (0.0, 0.0)
    kinematics: Kinematics = Kinematics()
    initial_stress: Geostatic | None = None


@dataclasses.dataclass(frozen=True)
class Contact:
    """Frictional contact between two bodies (Bardenhagen et al. 2001): each gets its own
    velocity field; they may not interpenetrate, may separate, and slide with Coulomb friction
    `friction` (mu >= 0, a parameter: params["contacts"]["first/second"]["friction"])."""

    pair: tuple[str, str]
    friction: float = 0.0

    @property
    def name(self) -> str:
        """'first/second', the pair's key in params["contacts"]."""
        return "/".join(self.pair)


@dataclasses.dataclass(frozen=True)
class Probe:
    """A recorded history. `displacement`: of the point nearest `at` at t = 0 (k = 2);
    `body_displacement`: mass-weighted mean displacement of `body` (k = 2);
    `body_rotation`: rotation of `body` about its centre of mass, counter-clockwise positive
    [rad] (k = 1); `peak_speed`: the largest speed of a point of `body` [m/s] (k = 1), a
    watch on numerical events that averages hide; `contact_force`: the force the first body of `pair` exerts on the second
    through their contact [N per m of thickness] (k = 2), with `facing` through the nodes whose
    contact normal (first into second) lies within 45 degrees of that direction only (one face,
    e.g. a wall's back apart from its base); `reaction`: the force that keeps the
    prescribed `body` on its path (what the driver applies) [N/m] (k = 2)."""

    name: str
    kind: str
    at: tuple[float, float] | None = None
    body: str | None = None
    pair: tuple[str, str] | None = None
    facing: tuple[float, float] | None = None
