"""Scenes: the TOML scene format, read into frozen dataclasses and checked.

A `Scene` says everything about a run: grid, numerics, materials, bodies, probes. It is plain
data (SI units, angles in degrees); `Simulation` splits it into static structure and a
parameter pytree. Reading checks every key and value and raises `SceneError` with one sentence
naming the key before anything is compiled. `Scene.from_toml(scene.to_toml()) == scene`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tomllib
from typing import Any

import tomli_w

from jaxmpm.errors import SceneError
from jaxmpm.materials import MODELS
from jaxmpm.materials.base import check_range, is_concrete, material_parameters, number_fields

REQUIRED = object()
BOUNDARY_KINDS = ("fixed", "slip", "free")
NUMERICS_CHOICES = {"shape": ("linear", "gimp", "bspline2"), "transfer": ("flip", "apic"),
                    "dtype": ("float64", "float32"), "update": ("musl", "usl")}
SNAPSHOT_FIELDS = ("x", "v", "displacement", "stress", "plastic_strain", "volume", "mass")
PROBE_KINDS = ("displacement", "body_displacement", "body_rotation", "contact_force", "reaction")
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


@dataclasses.dataclass(frozen=True)
class Numerics:
    """Discretisation choices; each is static (changing one recompiles).

    preset: "fast" | "balanced" (the default) | "accurate" fills every choice left as None
    (`PRESETS`); a value given explicitly overrides the preset's. update: "musl" (strain rate
    from velocities re-mapped after the particle update, which keeps nodes with tiny mass from
    polluting stresses) or "usl".
    """

    preset: str = DEFAULT_PRESET
    shape: str | None = None
    transfer: str | None = None
    flip: float | None = None
    ppc: int | None = None
    dtype: str | None = None
    damping: float = 0.0
    update: str | None = None
    # The values the preset filled in (not given by the user): `to_dict` leaves them out, and
    # `dataclasses.replace(numerics, preset=...)` fills them again from the new preset.
    filled: dict | None = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise SceneError(f"numerics.preset = {self.preset!r} is not one of {', '.join(map(repr, PRESETS))}.")
        previous, filled = self.filled or {}, {}
        for name, value in PRESETS[self.preset].items():
            given = getattr(self, name)
            if given is None or (name in previous and given == previous[name]):
                object.__setattr__(self, name, value)
                filled[name] = value
        object.__setattr__(self, "filled", filled)

    def given(self) -> dict:
        """The choices this Numerics states itself: its preset, damping and every override."""
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)
                if field.name != "filled" and field.name not in self.filled}


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
    """Initial geostatic stress: sigma_v from the depth below the body's top, sigma_h = K0 sigma_v;
    k0 = "jaky" (1 - sin phi of the body's friction angle) or a number."""

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
    """

    type: str = "free"
    velocity: tuple | None = None
    time: tuple[float, ...] | None = None

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
    [rad] (k = 1); `contact_force`: the force the first body of `pair` exerts on the second
    through their contact [N per m of thickness] (k = 2); `reaction`: the force that keeps the
    prescribed `body` on its path (what the driver applies) [N/m] (k = 2)."""

    name: str
    kind: str
    at: tuple[float, float] | None = None
    body: str | None = None
    pair: tuple[str, str] | None = None


@dataclasses.dataclass(frozen=True)
class Scene:
    """A complete scene. Build one in Python, or read it with `load_scene` / `from_toml`."""

    grid: Grid
    materials: dict[str, Any]
    bodies: tuple[Body, ...]
    duration: float
    name: str = "scene"
    geometry: str = "plane_strain"
    gravity: tuple[float, float] = (0.0, -9.81)
    cfl: float = 0.4
    dt: float | None = None
    output_every: float | None = None
    snapshot_fields: tuple[str, ...] = ("x", "stress", "plastic_strain")
    numerics: Numerics = Numerics()
    probes: tuple[Probe, ...] = ()
    contacts: tuple[Contact, ...] = ()

    def __post_init__(self):
        check_scene(self)

    # ----------------------------------------------------------------- conversions

    @classmethod
    def from_dict(cls, data: dict) -> Scene:
        return scene_from_dict(data)

    @classmethod
    def from_toml(cls, text: str) -> Scene:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise SceneError(f"the scene is not valid TOML: {error}.") from None
        return scene_from_dict(data)

    def to_dict(self) -> dict:
        return scene_to_dict(self)

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_dict())

    def with_value(self, key: str, value) -> Scene:
        """A copy with one value replaced. `key` is a dotted path: a parameter name
        ("sand.young", "materials.sand.young", "contacts.backfill/wall.friction",
        "bodies.pile.velocity": a prescribed body's velocity), or a scene value ("grid.cell",
        "scene.duration", "numerics.ppc", "bodies.block.velocity": a free body's initial
        velocity)."""
        from jaxmpm.parameters import qualify

        data = self.to_dict()
        owners = {"materials": tuple(self.materials), "contacts": tuple(c.name for c in self.contacts),
                  "bodies": tuple(body.name for body in self.bodies)}
        head = key.partition(".")[0]
        if head not in data and head not in ("scene", "grid", "numerics", "probes"):
            try:
                key = qualify(key, owners)
            except SceneError as error:
                raise SceneError(f"--set {key}: {error}") from None
        parts = key.split(".")
        if parts[0] == "contacts" and len(parts) == 3:
            if parts[1] not in owners["contacts"]:
                raise SceneError(f"--set {key}: there is no contact pair {parts[1]!r} (pairs: {', '.join(owners['contacts']) or 'none'}).")
            parts[1] = owners["contacts"].index(parts[1])
        elif parts[0] in ("bodies", "probes") and len(parts) > 2:
            names = [entry["name"] for entry in data[parts[0]]]
            if parts[1] not in names:
                raise SceneError(f"--set {key}: there is no {parts[0][:-1]} named {parts[1]!r}.")
            parts[1] = names.index(parts[1])
            entry = data[parts[0]][parts[1]]
            if parts[0] == "bodies" and parts[2:] == ["velocity"] and entry["kinematics"]["type"] == "prescribed":
                parts[2:] = ["kinematics", "velocity"]
        table = data
        for part in parts[:-1]:
            if isinstance(part, int):
                table = table[part]
                continue
            if not isinstance(table, dict) or not isinstance(table.get(part), (dict, list)):
                raise SceneError(f"--set {key}: the scene has no section {part!r} there.")
            table = table[part]
        if not isinstance(table, dict):
            raise SceneError(f"--set {key}: {parts[-1]!r} is not a key of a table.")
        table[parts[-1]] = value
        return scene_from_dict(data)

    # ----------------------------------------------------------------- derived facts

    def material_of(self, body: Body):
        return self.materials[body.material]

    def body_named(self, name: str) -> Body:
        return next(body for body in self.bodies if body.name == name)

    @property
    def max_wave_speed(self) -> float:
        """The CFL denominator [m/s]: max over free bodies of c_p + |v0|, and over prescribed
        and rigid bodies of their speed alone (their stiffness never sets the step)."""
        speeds = [body_speed(self, body) for body in self.bodies]
        return max(speeds)

    @property
    def stable_dt(self) -> float:
        """The stability limit h / max(c_p + |v|) [s]; the scene runs at cfl times this."""
        speed = self.max_wave_speed
        return self.grid.cell / speed if speed > 0.0 else math.inf

    @property
    def output_interval(self) -> float:
        return self.output_every if self.output_every is not None else self.duration / 100.0


def body_speed(scene: Scene, body: Body, params=None, initial_speed=None) -> float:
    """The speed that limits the time step for one body [m/s]: c_p (from `params` of its
    material, default the scene's values) + its initial speed for a free body; its initial or
    prescribed speed alone for a rigid or prescribed one."""
    motion = math.hypot(*body.velocity) if initial_speed is None else initial_speed
    if body.kinematics.type == "prescribed":
        return body.kinematics.top_speed
    if body.kinematics.type == "rigid":
        return motion
    material = scene.material_of(body)
    values = material_parameters(material) if params is None else params
    return float(material.wave_speed(values)) + motion


def load_scene(path) -> Scene:
    """Read and check a TOML scene file."""
    try:
        with open(path, "rb") as stream:
            text = stream.read().decode()
    except OSError as error:
        raise SceneError(f"cannot read scene file {str(path)!r}: {error.strerror}.") from None
    return Scene.from_toml(text)


# --------------------------------------------------------------------------- reading


class _Table:
    """A TOML table being read: typed access by key, with the key's path in every message."""

    def __init__(self, data, path):
        if not isinstance(data, dict):
            raise SceneError(f"{path} = {data!r} must be a table.")
        self.data, self.path, self.used = data, path, set()

    def key(self, name):
        return f"{self.path}.{name}" if self.path else name

    def get(self, name, kind, default=REQUIRED, choices=None):
        if name not in self.data:
            if default is REQUIRED:
                unknown = [key for key in self.data if key not in (getattr(self, "known", None) or ())]
                typo = difflib.get_close_matches(name, unknown, n=1)
                hint = f" (is {self.key(typo[0])!r} a misspelling of it?)" if typo else ""
                raise SceneError(f"{self.key(name)} is missing: it is required{hint}.")
            return default
        self.used.add(name)
        value = convert(self.key(name), self.data[name], kind)
        if choices is not None and value not in choices:
            options = ", ".join(repr(choice) for choice in choices)
            raise SceneError(f"{self.key(name)} = {value!r} is not one of {options}.")
        return value

    def table(self, name, default=REQUIRED):
        if name not in self.data and default is not REQUIRED:
            return _Table(default, self.key(name))
        return _Table(self.get(name, "any"), self.key(name))

    def finish(self):
        for name in self.data:
            if name not in self.used:
                known = getattr(self, "known", None)
                hint = difflib.get_close_matches(name, known or [], n=1)
                suggestion = f" (did you mean {hint[0]!r}?)" if hint else ""
                raise SceneError(f"{self.key(name)} is not a known key{suggestion}.")


def _number(key, value):
    if not is_concrete(value):          # a JAX value being differentiated (e.g. in `drive`)
        return value
    if hasattr(value, "dtype") and getattr(value, "shape", None) == ():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"{key} = {value!r} must be a number.")
    if not math.isfinite(value):
        raise SceneError(f"{key} = {value!r} must be finite.")
    return float(value)


def convert(key, value, kind):
    """Check a TOML value against `kind` and convert it (ints to floats where a float is due)."""
    if kind == "any":
        return value
    if kind == "float":
        return _number(key, value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{key} = {value!r} must be an integer.")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise SceneError(f"{key} = {value!r} must be a string.")
        return value
    if kind == "strings":
        if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
            raise SceneError(f"{key} = {value!r} must be a list of strings.")
        return tuple(value)
    if kind == "vec2":
        if not isinstance(value, list) or len(value) != 2:
            raise SceneError(f"{key} = {value!r} must be a pair of numbers [x, y].")
        return tuple(_number(key, item) for item in value)
    if kind == "points":
        if not isinstance(value, list) or not value:
            raise SceneError(f"{key} = {value!r} must be a list of points [[x, y], ...].")
        return tuple(convert(key, item, "vec2") for item in value)
    raise AssertionError(kind)


def read_material(table: _Table):
    model = table.get("model", "str", choices=tuple(MODELS))
    cls = MODELS[model]
    numbers = number_fields(cls)
    table.known = ["model", *numbers, *cls.option_names]
    values = {}
    for field in dataclasses.fields(cls):
        default = REQUIRED if field.default is dataclasses.MISSING else field.default
        kind = "float" if field.name in numbers else "str"
        values[field.name] = table.get(field.name, kind, default)
    table.finish()
    return cls(**values)


def _read_region(table: _Table):
    table.known = ["rectangle", "polygon"]
    if len(table.data) != 1 or next(iter(table.data)) not in table.known:
        raise SceneError(
            f"{table.path} = {table.data!r} must hold exactly one of rectangle = [[x0, y0], "
            "[x1, y1]] or polygon = [[x, y], ...]."
        )
    if "rectangle" in table.data:
        corners = table.get("rectangle", "points")
        if len(corners) != 2:
            raise SceneError(f"{table.key('rectangle')} = {list(corners)!r} must be two corners.")
        return Rectangle(*corners)
    return Polygon(table.get("polygon", "points"))


def _read_body(table: _Table):
    table.known = ["name", "material", "region", "velocity", "kinematics", "initial_stress"]
    name = table.get("name", "str")
    material = table.get("material", "str")
    region = _read_region(table.table("region"))
    velocity = table.get("velocity", "vec2", (0.0, 0.0))
    kinematics = _read_kinematics(table.table("kinematics", {"type": "free"}))
    if kinematics.type == "prescribed" and "velocity" in table.data:
        raise SceneError(
            f"{table.key('velocity')} is given for a prescribed body: its velocity is "
            f"{table.key('kinematics.velocity')} (remove {table.key('velocity')})."
        )
    initial_stress = None
    if "initial_stress" in table.data:
        stress_table = table.table("initial_stress")
        stress_table.known = ["geostatic"]
        geostatic = stress_table.table("geostatic")
        geostatic.known = ["k0"]
        k0 = geostatic.get("k0", "any", "jaky")
        if k0 != "jaky":
            k0 = convert(geostatic.key("k0"), k0, "float")
        geostatic.finish()
        stress_table.finish()
        initial_stress = Geostatic(k0)
    table.finish()
    return Body(name, material, region, velocity, kinematics, initial_stress)


def _read_kinematics(table: _Table) -> Kinematics:
    table.known = ["type", "velocity", "time"]
    kind = table.get("type", "str", choices=KINEMATICS)
    velocity = time = None
    if kind == "prescribed":
        if "time" in table.data:
            time = tuple(convert(table.key("time"), item, "float") for item in _list(table, "time"))
            velocity = table.get("velocity", "points")
        else:
            velocity = table.get("velocity", "vec2")
    table.finish()
    return Kinematics(kind, velocity, time)


def _list(table: _Table, name):
    value = table.get(name, "any")
    if not isinstance(value, list) or not value:
        raise SceneError(f"{table.key(name)} = {value!r} must be a list of numbers.")
    return value


def _read_contact(table: _Table) -> Contact:
    table.known = ["pair", "friction"]
    pair = table.get("pair", "strings")
    if len(pair) != 2:
        raise SceneError(f"{table.key('pair')} = {list(pair)!r} must name two bodies.")
    friction = table.get("friction", "float", 0.0)
    table.finish()
    return Contact(pair, friction)


def _read_probe(table: _Table):
    table.known = ["name", "kind", "at", "body", "pair"]
    name = table.get("name", "str")
    kind = table.get("kind", "str", choices=PROBE_KINDS)
    at = table.get("at", "vec2") if kind == "displacement" else None
    body = table.get("body", "str") if kind in ("body_displacement", "body_rotation", "reaction") else None
    pair = table.get("pair", "strings") if kind == "contact_force" else None
    if pair is not None and len(pair) != 2:
        raise SceneError(f"{table.key('pair')} = {list(pair)!r} must name two bodies.")
    table.finish()
    return Probe(name, kind, at, body, pair)


def _array_of_tables(root: _Table, name):
    entries = root.get(name, "any", [])
    if not isinstance(entries, list):
        raise SceneError(f"{name} must be an array of tables ([[{name}]]).")
    return [_Table(entry, f"{name}[{index}]") for index, entry in enumerate(entries)]


def scene_from_dict(data) -> Scene:
    """Build a checked Scene from the nested dict of a TOML file."""
    root = _Table(data, "")
    root.known = ["scene", "grid", "numerics", "materials", "bodies", "probes", "contacts"]

    head = root.table("scene")
    head.known = [f.name for f in dataclasses.fields(Scene)]
    run = dict(
        name=head.get("name", "str", "scene"),
        geometry=head.get("geometry", "str", "plane_strain", choices=GEOMETRIES),
        gravity=head.get("gravity", "vec2", (0.0, -9.81)),
        duration=head.get("duration", "float"),
        cfl=head.get("cfl", "float", 0.4),
        dt=head.get("dt", "float", None),
        output_every=head.get("output_every", "float", None),
        snapshot_fields=head.get("snapshot_fields", "strings", ("x", "stress", "plastic_strain")),
    )
    head.finish()

    grid_table = root.table("grid")
    grid_table.known = ["origin", "size", "cell", "boundaries"]
    edges = grid_table.table("boundaries", {})
    edges.known = ["left", "right", "bottom", "top"]
    boundaries = Boundaries(
        **{
            edge: edges.get(edge, "str", getattr(Boundaries(), edge), choices=BOUNDARY_KINDS)
            for edge in edges.known
        }
    )
    edges.finish()
    grid = Grid(
        size=grid_table.get("size", "vec2"),
        cell=grid_table.get("cell", "float"),
        origin=grid_table.get("origin", "vec2", (0.0, 0.0)),
        boundaries=boundaries,
    )
    grid_table.finish()

    options = root.table("numerics", {})
    options.known = [f.name for f in dataclasses.fields(Numerics) if f.name != "filled"]
    numerics = Numerics(
        preset=options.get("preset", "str", DEFAULT_PRESET, choices=tuple(PRESETS)),
        shape=options.get("shape", "str", None, choices=NUMERICS_CHOICES["shape"]),
        transfer=options.get("transfer", "str", None, choices=NUMERICS_CHOICES["transfer"]),
        flip=options.get("flip", "float", None),
        ppc=options.get("ppc", "int", None),
        dtype=options.get("dtype", "str", None, choices=NUMERICS_CHOICES["dtype"]),
        damping=options.get("damping", "float", 0.0),
        update=options.get("update", "str", None, choices=NUMERICS_CHOICES["update"]),
    )
    options.finish()

    material_tables = root.table("materials")
    material_tables.known = list(material_tables.data)
    materials = {
        name: read_material(material_tables.table(name)) for name in material_tables.data
    }
    material_tables.finish()

    bodies = tuple(_read_body(table) for table in _array_of_tables(root, "bodies"))
    probes = tuple(_read_probe(table) for table in _array_of_tables(root, "probes"))
    contacts = tuple(_read_contact(table) for table in _array_of_tables(root, "contacts"))
    root.finish()
    return Scene(
        grid=grid, materials=materials, bodies=bodies, numerics=numerics, probes=probes, contacts=contacts, **run
    )


# --------------------------------------------------------------------------- writing


def _drop_none(mapping):
    return {key: value for key, value in mapping.items() if value is not None}


def scene_to_dict(scene: Scene) -> dict:
    """The nested dict that `scene_from_dict` reads back into an equal Scene."""
    head = _drop_none(
        {
            "name": scene.name,
            "geometry": scene.geometry,
            "gravity": list(scene.gravity),
            "duration": scene.duration,
            "cfl": scene.cfl,
            "dt": scene.dt,
            "output_every": scene.output_every,
            "snapshot_fields": list(scene.snapshot_fields),
        }
    )
    grid = {
        "origin": list(scene.grid.origin),
        "size": list(scene.grid.size),
        "cell": scene.grid.cell,
        "boundaries": dataclasses.asdict(scene.grid.boundaries),
    }
    materials = {
        name: _drop_none(
            {"model": material.model}
            | {field.name: getattr(material, field.name) for field in dataclasses.fields(material)}
        )
        for name, material in scene.materials.items()
    }
    bodies = []
    for body in scene.bodies:
        if isinstance(body.region, Rectangle):
            region = {"rectangle": [list(body.region.lower), list(body.region.upper)]}
        else:
            region = {"polygon": [list(vertex) for vertex in body.region.vertices]}
        entry = {
            "name": body.name,
            "material": body.material,
            "region": region,
            "kinematics": _kinematics_to_dict(body.kinematics),
        }
        if body.kinematics.type != "prescribed":
            entry["velocity"] = list(body.velocity)
        if body.initial_stress is not None:
            entry["initial_stress"] = {"geostatic": {"k0": body.initial_stress.k0}}
        bodies.append(entry)
    probes = [
        _drop_none(
            {
                "name": probe.name,
                "kind": probe.kind,
                "at": None if probe.at is None else list(probe.at),
                "body": probe.body,
                "pair": None if probe.pair is None else list(probe.pair),
            }
        )
        for probe in scene.probes
    ]
    data = {
        "scene": head,
        "grid": grid,
        "numerics": scene.numerics.given(),
        "materials": materials,
        "bodies": bodies,
    }
    if probes:
        data["probes"] = probes
    if scene.contacts:
        data["contacts"] = [{"pair": list(contact.pair), "friction": contact.friction} for contact in scene.contacts]
    return data


def _kinematics_to_dict(kinematics: Kinematics) -> dict:
    entry = {"type": kinematics.type}
    if kinematics.type == "prescribed":
        if kinematics.time is None:
            entry["velocity"] = list(kinematics.velocity)
        else:
            entry["time"] = list(kinematics.time)
            entry["velocity"] = [list(row) for row in kinematics.velocity]
    return entry


# --------------------------------------------------------------------------- checking


def _inside_grid(grid: Grid, point) -> bool:
    tolerance = 1e-9 * grid.cell
    return all(
        grid.origin[axis] - tolerance <= point[axis] <= grid.origin[axis] + grid.size[axis] + tolerance
        for axis in (0, 1)
    )


def check_kinematics(key: str, kinematics: Kinematics):
    """SceneError unless the kinematics are complete and consistent."""
    if kinematics.type not in KINEMATICS:
        raise SceneError(f"{key}.type = {kinematics.type!r} is not one of {', '.join(map(repr, KINEMATICS))}.")
    if kinematics.type != "prescribed":
        if kinematics.velocity is not None or kinematics.time is not None:
            raise SceneError(f"{key} gives a velocity table for a {kinematics.type} body: only prescribed bodies take one.")
        return
    if kinematics.velocity is None:
        raise SceneError(f"{key}.velocity is missing: a prescribed body needs its velocity [vx, vy].")
    if kinematics.time is None:
        if len(kinematics.velocity) != 2:
            raise SceneError(f"{key}.velocity = {list(kinematics.velocity)!r} must be [vx, vy].")
        return
    times, rows = list(kinematics.time), list(kinematics.velocity)
    if len(times) < 2 or len(rows) != len(times) or any(len(row) != 2 for row in rows):
        raise SceneError(
            f"{key}: time = {times} and velocity = {[list(row) for row in rows]} must be tables of the same "
            "length (at least 2), one [vx, vy] per time."
        )
    if times[0] != 0.0 or any(later <= earlier for earlier, later in zip(times, times[1:])):
        raise SceneError(f"{key}.time = {times} must start at 0 and increase strictly.")


def check_axisymmetric(scene: Scene):
    """In axisymmetry x is the radius: the grid starts on the axis, whose edge holds the
    radial velocity, gravity is axial, and no body turns in the (r, z) plane."""
    grid = scene.grid
    if grid.origin[0] != 0.0:
        raise SceneError(
            f"grid.origin = {list(grid.origin)}: in axisymmetry the grid starts on the axis, so origin[0] must be 0."
        )
    if grid.boundaries.left not in ("slip", "fixed"):
        raise SceneError(
            f"grid.boundaries.left = {grid.boundaries.left!r}: in axisymmetry the left edge is the axis, where "
            "the radial velocity is zero; make it 'slip' (or 'fixed')."
        )
    if scene.gravity[0] != 0.0:
        raise SceneError(f"scene.gravity = {list(scene.gravity)}: in axisymmetry gravity is axial, so gravity[0] must be 0.")
    for index, body in enumerate(scene.bodies):
        if body.kinematics.type == "rigid":
            raise SceneError(
                f"bodies[{index}].kinematics.type = 'rigid' is not available in axisymmetry (a ring cannot turn in "
                "the (r, z) plane): use 'prescribed', or a stiff free body."
            )


def check_scene(scene: Scene):
    """Every check that needs no compiling. Raises SceneError naming the key and value."""
    check_range("scene.duration", scene.duration, low=0.0)
    check_range("scene.cfl", scene.cfl, low=0.0, high=1.0, high_inclusive=True)
    if scene.output_every is not None:
        check_range("scene.output_every", scene.output_every, low=0.0, high=scene.duration, high_inclusive=True)
    for field in scene.snapshot_fields:
        if field not in SNAPSHOT_FIELDS:
            options = ", ".join(SNAPSHOT_FIELDS)
            raise SceneError(f"scene.snapshot_fields has {field!r}, which is not one of {options}.")

    grid = scene.grid
    check_range("grid.cell", grid.cell, low=0.0)
    if scene.geometry not in GEOMETRIES:
        raise SceneError(f"scene.geometry = {scene.geometry!r} is not one of {', '.join(map(repr, GEOMETRIES))}.")
    if scene.geometry == "axisymmetric":
        check_axisymmetric(scene)
    for axis, length in enumerate(grid.size):
        check_range(f"grid.size[{axis}]", length, low=0.0)
        cells = length / grid.cell
        if abs(cells - round(cells)) > 1e-6 * max(1.0, cells) or round(cells) < 1:
            raise SceneError(
                f"grid.size = {list(grid.size)} is not a whole number of cells of "
                f"grid.cell = {grid.cell}."
            )

    numerics = scene.numerics
    for name, choices in NUMERICS_CHOICES.items():      # scenes built in Python skip the reader
        value = getattr(numerics, name)
        if value not in choices:
            raise SceneError(f"numerics.{name} = {value!r} is not one of {', '.join(map(repr, choices))}.")
    check_range("numerics.flip", numerics.flip, low=0.0, high=1.0, low_inclusive=True, high_inclusive=True)
    check_range("numerics.ppc", numerics.ppc, low=1, high=8, low_inclusive=True, high_inclusive=True)
    check_range("numerics.damping", numerics.damping, low=0.0, high=1.0, low_inclusive=True, high_inclusive=True)

    if not scene.materials:
        raise SceneError("materials is empty: define at least one [materials.NAME] table.")
    named = [(f"materials.{name}", name) for name in scene.materials]
    named += [(f"bodies[{i}].name", body.name) for i, body in enumerate(scene.bodies)]
    named += [(f"probes[{i}].name", probe.name) for i, probe in enumerate(scene.probes)]
    for key, name in named:
        if not isinstance(name, str) or not NAME.match(name) or name == "time":
            raise SceneError(
                f"{key} = {name!r} must be a name of letters, digits, '_' or '-' starting with a "
                "letter or '_', other than 'time'."
            )
    for name, material in scene.materials.items():
        material.check(f"materials.{name}")

    if not scene.bodies:
        raise SceneError("bodies is empty: define at least one [[bodies]] table.")
    names = [body.name for body in scene.bodies]
    for index, body in enumerate(scene.bodies):
        where = f"bodies[{index}]"
        if names.count(body.name) > 1:
            raise SceneError(f"{where}.name = {body.name!r} is used by more than one body.")
        if body.material not in scene.materials:
            known = ", ".join(repr(name) for name in scene.materials)
            raise SceneError(f"{where}.material = {body.material!r} is not defined (known: {known}).")
        vertices = body.region.vertices
        if isinstance(body.region, Rectangle):
            if not all(body.region.lower[a] < body.region.upper[a] for a in (0, 1)):
                raise SceneError(
                    f"{where}.region.rectangle = {[list(body.region.lower), list(body.region.upper)]} "
                    "must go from the lower-left to the upper-right corner."
                )
        elif len(vertices) < 3:
            raise SceneError(f"{where}.region.polygon has {len(vertices)} vertices: it needs at least 3.")
        if body.initial_stress is not None and body.kinematics.type != "free":
            raise SceneError(
                f"{where}.initial_stress is given for a {body.kinematics.type} body, whose stress is never used: "
                "remove it (only free bodies carry stress)."
            )
        if body.initial_stress is not None:
            k0 = body.initial_stress.k0
            key = f"{where}.initial_stress.geostatic.k0"
            if k0 == "jaky":
                if not hasattr(scene.materials[body.material], "friction_angle"):
                    raise SceneError(
                        f"{key} = 'jaky' needs a friction angle, which material "
                        f"{body.material!r} has not: give k0 as a number."
                    )
            else:
                check_range(key, k0, low=0.0)
        for vertex in vertices:
            if not _inside_grid(grid, vertex):
                raise SceneError(
                    f"{where}.region has the point {list(vertex)} outside the grid "
                    f"(origin {list(grid.origin)}, size {list(grid.size)})."
                )

        check_kinematics(f"{where}.kinematics", body.kinematics)

    kinds = {body.name: body.kinematics.type for body in scene.bodies}
    declared = []
    for index, contact in enumerate(scene.contacts):
        key = f"contacts[{index}].pair"
        first, second = contact.pair
        for name in contact.pair:
            if name not in names:
                raise SceneError(f"{key} = {list(contact.pair)} names {name!r}, which is not a body.")
        if first == second:
            raise SceneError(f"{key} = {list(contact.pair)} pairs body {first!r} with itself.")
        if kinds[first] != "free" and kinds[second] != "free":
            raise SceneError(
                f"{key} = {list(contact.pair)} pairs two bodies that are not free ({kinds[first]} and "
                f"{kinds[second]}): contact needs at least one deformable (free) body."
            )
        if set(contact.pair) in declared:
            raise SceneError(f"{key} = {list(contact.pair)}: these two bodies are already paired.")
        declared.append(set(contact.pair))
        check_range(f"contacts[{index}].friction", contact.friction, low=0.0, low_inclusive=True)

    for index, probe in enumerate(scene.probes):
        where = f"probes[{index}]"
        if [p.name for p in scene.probes].count(probe.name) > 1:
            raise SceneError(f"{where}.name = {probe.name!r} is used by more than one probe.")
        if probe.kind in ("body_displacement", "body_rotation", "reaction") and probe.body not in names:
            raise SceneError(f"{where}.body = {probe.body!r} is not the name of a body.")
        if probe.kind == "reaction" and kinds[probe.body] != "prescribed":
            raise SceneError(
                f"{where}.body = {probe.body!r} is {kinds[probe.body]}, not prescribed: a reaction is the "
                "force that keeps a prescribed body on its path."
            )
        if probe.kind == "contact_force" and set(probe.pair) not in declared:
            raise SceneError(f"{where}.pair = {list(probe.pair)} is not a pair of [[contacts]].")
        if probe.kind == "displacement" and not _inside_grid(grid, probe.at):
            raise SceneError(f"{where}.at = {list(probe.at)} is outside the grid.")

    if scene.dt is not None:
        check_range("scene.dt", scene.dt, low=0.0)
        if scene.dt > scene.stable_dt:
            raise SceneError(
                f"scene.dt = {scene.dt:g} s is above the stable limit {scene.stable_dt:.4g} s "
                "(cell / max wave speed): use a smaller dt, or give cfl instead."
            )
