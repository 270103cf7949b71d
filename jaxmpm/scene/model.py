"""The scene as data: `Scene`, made of the parts of `jaxmpm.scene.parts`.

A `Scene` says everything about a run: grid, numerics, materials, bodies, probes. It is plain
data (SI units, angles in degrees); `Simulation` splits it into static structure and a
parameter pytree. Building one checks it (`jaxmpm.scene.checks`), so a scene read from a file
and one built in Python pass the same checks; the file format is `jaxmpm.scene.schema` and
`jaxmpm.scene.files`. `Scene.from_toml(scene.to_toml()) == scene`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxmpm.keys import is_concrete
from jaxmpm.scene.checks import check_scene
from jaxmpm.scene.files import dict_with_value, read_scene_file, scene_arguments, scene_to_dict, toml_text, toml_values
from jaxmpm.scene.parts import DEFAULT_CFL, Body, Contact, Grid, Numerics, Probe
from jaxmpm.physics.time_step import body_speed, stable_limit

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
    cfl: float = DEFAULT_CFL
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
        """Build a checked Scene from the nested dict of a TOML file."""
        return cls(**scene_arguments(data))

    @classmethod
    def from_toml(cls, text: str) -> Scene:
        return cls.from_dict(toml_values(text))

    def to_dict(self) -> dict:
        """The nested dict that `from_dict` reads back into an equal Scene."""
        return scene_to_dict(self)

    def to_toml(self) -> str:
        return toml_text(self.to_dict())

    def with_value(self, key: str, value) -> Scene:
        """A copy with one value replaced. `key` is a dotted path: a parameter name
        ("sand.young", "materials.sand.young", "contacts.backfill/wall.friction",
        "bodies.pile.velocity": a prescribed body's velocity), or a scene value ("grid.cell",
        "scene.duration", "numerics.ppc", "bodies.block.velocity": a free body's initial
        velocity)."""
        return Scene.from_dict(dict_with_value(self, key, value))

    # ----------------------------------------------------------------- derived facts

    def material_of(self, body: Body):
        return self.materials[body.material]

    def body_named(self, name: str) -> Body:
        return next(body for body in self.bodies if body.name == name)

    @property
    def max_wave_speed(self) -> float:
        """The CFL denominator [m/s]: max over free bodies of c_p + |v0|, and over prescribed
        and rigid bodies of their speed alone (their stiffness never sets the step)."""
        return max(body_speed(self, body) for body in self.bodies)

    @property
    def stable_dt(self) -> float:
        """The stability limit h / max(c_p + |v|) [s]; the scene runs at cfl times this
        (`jaxmpm.physics.time_step`)."""
        return stable_limit(self)

    @property
    def transfer(self) -> str:
        """The velocity transfer the scene runs with: numerics.transfer, except that the `fast`
        preset's FLIP becomes APIC in a scene with contact pairs. FLIP's per-step blend carries
        no affine velocity, and its noise lets a block that friction should hold creep down a
        slope (5.4 mm in 0.4 s at mu = 1.5 on 30 degrees, where APIC holds it to 0.18 mm of
        elastic shear; docs/contact.md). A transfer the scene states itself is kept."""
        switched = (self.contacts and self.numerics.preset == "fast" and "transfer" in self.numerics.filled
                    and self.numerics.transfer == "flip")
        return "apic" if switched else self.numerics.transfer

    @property
    def notes(self) -> tuple[str, ...]:
        """Sentences on choices made for this scene that its file does not state, or states twice."""
        notes = []
        if self.transfer != self.numerics.transfer:
            notes.append("the fast preset's FLIP transfer lets frictional contact creep, so this scene with contact "
                         "pairs runs with transfer = 'apic' (set numerics.transfer to choose)")
        if self.filters_flowing_soil_every_step:
            notes.append("numerics.relaxation = 0 (plain APIC) filters the points' velocity once per step, so soil "
                         "that flows moves less as the step shrinks (a released retaining wall turned 8 % less at "
                         "half the step): give numerics.relaxation (the examples use 10 to 25) and check a result "
                         "with --refine dt")
        for name, exponent in self.nonlinear_perzyna_updated_once:
            notes.append(f"materials.{name} is viscoplastic with exponent {exponent:g}, and one stress update a step "
                         "(numerics.stress_substeps = 1) has a first-order error of its own that halving dt can hide "
                         "(2-5 % on the retaining wall example, which uses 4): check a result with --refine stress")
        if self.holds_structures_to_outline:
            notes.append("numerics.structure_hold = 'outline' is a study option: a rigid block resting on an elastic "
                         "layer turned 2.6 times as far as the elastic solution under it with quadratic B-splines, "
                         "and against its load with its sides half a cell off the nodes (docs/convergence.md, "
                         "\"A rigid base on deformable soil\"): prefer the default hold")
        for name in self.elastic_structures_held_at_nodes:
            notes.append(f"numerics.structure_hold = 'points' pushes points out of prescribed and rigid bodies only: "
                         f"the elastic body {name!r} still holds the soil at every node where it has mass, so it "
                         "does not move as the same body made rigid would (a stiff elastic wall on a base two cells "
                         "wide moved 12 % less than the rigid one; docs/contact.md, \"Contact at the points\")")
        if self.dt is not None and self.cfl != DEFAULT_CFL:
            notes.append(f"scene.dt = {self.dt:g} s is given, so scene.cfl = {self.cfl:g} is not used: that dt is "
                         f"{self.dt / self.stable_dt:.3g} of the stable limit {self.stable_dt:.4g} s")
        return tuple(notes)

    @property
    def holds_structures_to_outline(self) -> bool:
        """Whether structures (prescribed or rigid bodies, or the bodies of a contact pair) hold
        the soil only at the nodes whose cell meets their outline: an option that measured badly
        on a rigid base (docs/convergence.md, "A rigid base on deformable soil")."""
        structures = self.contacts or any(body.kinematics.type in ("prescribed", "rigid") for body in self.bodies)
        return bool(structures) and self.numerics.structure_hold == "outline"

    @property
    def elastic_structures_held_at_nodes(self) -> tuple[str, ...]:
        """Under numerics.structure_hold = "points", the free bodies of convex region and a
        material that does not yield in contact with a free one that does (elastic structures,
        whose outline bounds the contact's normal): the points hold leaves them held at the
        nodes."""
        if self.numerics.structure_hold != "points":
            return ()
        from jaxmpm.physics.bodies import convex_outline

        bodies = {body.name: body for body in self.bodies}

        def yields(name):
            return self.material_of(bodies[name]).law.yields

        return tuple(dict.fromkeys(
            name for contact in self.contacts for name, other in (contact.pair, contact.pair[::-1])
            if bodies[name].kinematics.type == "free" and bodies[other].kinematics.type == "free"
            and not yields(name) and yields(other) and convex_outline(bodies[name].region.vertices) is not None))

    @property
    def filters_flowing_soil_every_step(self) -> bool:
        """Whether the scene runs plain APIC (no relaxation) on a free body that can yield and
        flow: a filter once per step, whose effect grows as the step shrinks (docs/convergence.md)."""
        flowing = any(body.kinematics.type == "free" and not body.kinematics.subcycled
                      and self.material_of(body).law.yields for body in self.bodies)
        return self.transfer == "apic" and self.numerics.relaxation == 0.0 and flowing

    @property
    def nonlinear_perzyna_updated_once(self) -> tuple[tuple[str, float], ...]:
        """(material name, exponent) of each Perzyna material with N != 1 that a free body uses,
        when each step's stress update is one backward-Euler step (numerics.stress_substeps =
        1): its own first-order error grows with N (docs/convergence.md)."""
        if self.numerics.stress_substeps != 1:
            return ()
        used = {body.material for body in self.bodies if body.kinematics.type == "free"}
        return tuple((name, float(material.exponent)) for name, material in self.materials.items()
                     if name in used and getattr(material, "viscoplastic", False)
                     and is_concrete(material.exponent) and float(material.exponent) != 1.0)

    def component_names(self, count: int) -> list[str]:
        """Names of a probe's `count` components: its axes ("x", "y"; "r", "z" in axisymmetry)
        for two, else their indices."""
        if count == 2:
            return ["r", "z"] if self.geometry == "axisymmetric" else ["x", "y"]
        return [str(index) for index in range(count)]

    @property
    def output_interval(self) -> float:
        return self.output_every if self.output_every is not None else self.duration / 100.0


def load_scene(path) -> Scene:
    """Read and check a TOML scene file."""
    return Scene.from_dict(read_scene_file(path))


def scene_from_dict(data) -> Scene:
    return Scene.from_dict(data)


def scene_to_toml(scene: Scene) -> str:
    return scene.to_toml()
