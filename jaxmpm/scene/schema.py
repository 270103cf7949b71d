"""The scene file's schema: every key once, with its kind, unit, default, range and meaning.

The reader (`jaxmpm.scene.files`), the checks of scenes built in Python
(`jaxmpm.scene.checks`) and the reference docs/scene_reference.md
(`python -m jaxmpm.scene.reference`) all come from `SCENE_FILE`. Materials declare their own
keys (`jaxmpm.materials`, each class's `keys`). Checks that relate several keys (a body inside
the grid, a probe naming a body) are in `jaxmpm.scene.checks`.
"""

from jaxmpm.keys import REQUIRED, Key, Section
from jaxmpm.materials import MODELS
from jaxmpm.scene.parts import (
    BOUNDARY_KINDS, DEFAULT_CORNER_RADIUS, DEFAULT_PRESET, DEFAULT_RELAXATION, DEFAULT_STRESS_SUBSTEPS, DEFAULT_STRUCTURE_HOLD, GEOMETRIES, MAX_STRESS_SUBSTEPS, KINEMATICS, NUMERICS_CHOICES, PRESETS, PROBE_KINDS, SNAPSHOT_FIELDS, STRUCTURE_HOLDS,
)


def _from_preset(name):
    """How the reference states a numerics default: each preset's value."""
    return "; default from the preset (" + ", ".join(f"{preset}: {values[name]!r}" for preset, values in PRESETS.items()) + ")"


SCENE = Section((
    Key("name", "str", "the run's name, written into the output file", default="scene"),
    Key("geometry", "str", "'plane_strain', or 'axisymmetric' (x is the radius r, y the axial z; "
        "masses, volumes and forces per radian, contact and reaction probes per whole ring)",
        default="plane_strain", choices=GEOMETRIES),
    Key("gravity", "vec2", "gravitational acceleration (in axisymmetry along the axis only)", unit="m/s^2",
        default=(0.0, -9.81)),
    Key("duration", "float", "simulated time", unit="s", low=0.0),
    Key("cfl", "float", "time step as a fraction of the stability limit h / max(c_p + |v|)", default=0.4,
        low=0.0, high=1.0, high_inclusive=True),
    Key("dt", "float", "time step; absent: cfl times the stability limit, trimmed so that whole steps fill "
        "each output interval; given, it must not exceed the limit", unit="s", default=None, low=0.0),
    Key("output_every", "float", "interval between snapshots and probe samples; absent: duration / 100; "
        "at most the duration", unit="s", default=None, low=0.0),
    Key("snapshot_fields", "strings", "per-point fields stored at each snapshot",
        default=("x", "stress", "plastic_strain"), choices=SNAPSHOT_FIELDS),
), "what is run: duration, gravity, time step, outputs")

BOUNDARIES = Section(tuple(
    Key(edge, "str", f"condition on the grid's {edge} edge: 'fixed' (v = 0), 'slip' (normal velocity 0) "
        "or 'free'", default=default, choices=BOUNDARY_KINDS)
    for edge, default in (("left", "slip"), ("right", "slip"), ("bottom", "fixed"), ("top", "free"))
), "the condition on each edge of the grid")

GRID = Section((
    Key("size", "vec2", "extent of the grid along x and y; a whole number of cells", unit="m", low=0.0),
    Key("cell", "float", "side h of the square cells", unit="m", low=0.0),
    Key("origin", "vec2", "lower-left corner (in axisymmetry origin[0] = 0: the axis)", unit="m", default=(0.0, 0.0)),
    Key("boundaries", "table", "edge conditions", default={}, section=BOUNDARIES),
), "the regular background grid")

NUMERICS = Section((
    Key("preset", "str", "fills every discretisation choice not given: 'fast' (linear, FLIP 0.99, float32), "
        "'balanced' (bspline2, APIC, float64), 'accurate' (balanced with 3 x 3 points per cell); "
        "static: changing a choice recompiles", default=DEFAULT_PRESET, choices=tuple(PRESETS)),
    Key("shape", "str", "shape functions: 'linear' (tent), 'gimp' (uGIMP), 'bspline2' (quadratic B-spline)"
        + _from_preset("shape"), default=None, choices=NUMERICS_CHOICES["shape"]),
    Key("transfer", "str", "particle-grid velocity transfer: 'flip' (FLIP/PIC blend) or 'apic' (affine PIC)"
        + _from_preset("transfer") + "; a scene with contact pairs takes 'apic' where the fast preset would give "
        "'flip' (FLIP lets frictional contact creep)", default=None, choices=NUMERICS_CHOICES["transfer"]),
    Key("flip", "float", "FLIP fraction of the blend (1 = pure FLIP, 0 = PIC; only with transfer = 'flip')"
        + _from_preset("flip"), default=None, low=0.0, high=1.0, low_inclusive=True, high_inclusive=True),
    Key("ppc", "int", "material points per cell along each axis" + _from_preset("ppc"), default=None,
        low=1, high=8, low_inclusive=True, high_inclusive=True),
    Key("dtype", "str", "floating-point precision (float64 needs JAX's 64-bit mode)" + _from_preset("dtype"),
        default=None, choices=NUMERICS_CHOICES["dtype"]),
    Key("update", "str", "'musl' (strain rate from velocities re-mapped after the particle update) or "
        "'usl'" + _from_preset("update"), default=None, choices=NUMERICS_CHOICES["update"]),
    Key("relaxation", "float", "with transfer = 'apic': the points keep a memory of their own (FLIP) "
        "velocity that fades into the grid's over this many crossings of a cell by the slowest free body's "
        "p-wave, a fixed time whatever dt, so results do not drift with dt (10 on the paper's examples); "
        "0 gives plain APIC, whose dissipation grows with the number of steps (docs/convergence.md)", default=DEFAULT_RELAXATION, low=0.0,
        low_inclusive=True),
    Key("corner_radius", "float", "the radius, in cells, at which a prescribed body's outline has its corners "
        "rounded where free bodies meet it (at most a quarter of the body's width): the contact normal then "
        "turns over about a cell of travel round a corner instead of at once, which removed a sawtooth of a "
        "third of a pile's head force at every cell of penetration; 0 keeps the corners sharp (docs/convergence.md)",
        default=DEFAULT_CORNER_RADIUS, low=0.0, low_inclusive=True),
    Key("stress_substeps", "int", "the stress update of a body that can yield (Drucker-Prager) is made of this "
        "many updates of dt / stress_substeps with the step's velocity gradient: the Perzyna update (backward "
        "Euler) is first order in its own step, and a viscoplastic sand's result then moves with dt; each "
        "substep costs another stress update (docs/convergence.md)", default=DEFAULT_STRESS_SUBSTEPS, low=1,
        high=MAX_STRESS_SUBSTEPS, low_inclusive=True, high_inclusive=True),
    Key("structure_hold", "str", "how a structure (a prescribed or rigid body, or an elastic body of convex region "
        "in contact with soil that yields) holds the bodies in contact with it: 'mass', at every node where its "
        "points have mass, up to a cell and a quarter beyond its outline with quadratic B-splines (the "
        "multi-velocity-field rule); 'outline', only at the nodes whose cell (the square of side h centred on the "
        "node) meets its outline, a study option (a rigid base under it is 2.6 times too soft with quadratic "
        "B-splines and walks against its load with its sides half a cell off the nodes); or 'points', where a "
        "prescribed or rigid body of convex region holds no node and pushes the points that reach into its outline "
        "back out (a penalty layer a quarter point spacing thick, as stiff as the soil; Coulomb friction at the "
        "nodes), which resolves a base to the point spacing: a rigid block three cells wide on an elastic layer "
        "turns 1.3 times as far as on an elastic half-space at the cell, converging with it, and 10 % less with the grid lines moved half a cell, where the node "
        "holds are 3 times too stiff or 2.6 times too soft (docs/contact.md, \"Contact at the points\")",
        default=DEFAULT_STRUCTURE_HOLD, choices=STRUCTURE_HOLDS),
    Key("damping", "float", "local (Cundall) damping coefficient: each node's force is reduced by damping "
        "|f| sign(v); for quasi-static settling, never set by a preset", default=0.0, low=0.0, high=1.0,
        low_inclusive=True, high_inclusive=True),
), "discretisation choices; each is static (compiled in)")

MATERIAL = Section(
    (Key("model", "str", "the constitutive model; its keys follow", choices=tuple(MODELS)),),
    "one material, named by its table ([materials.sand]); its numbers are differentiable parameters "
    "(params['materials'][NAME])",
    variant_key="model",
    variants={name: cls.keys for name, cls in MODELS.items()},
)

REGION = Section((
    Key("rectangle", "points", "lower-left and upper-right corners [[x0, y0], [x1, y1]]", unit="m", length=2),
    Key("polygon", "points", "vertices of a simple polygon, in order (at least 3)", unit="m"),
), "where the body's points are seeded: exactly one of rectangle or polygon", one_of=True)

KINEMATICS_TABLE = Section(
    (Key("type", "str", "'free' (deformable, its material's stress update), 'prescribed' (moved at a "
         "given velocity, no stress update) or 'rigid' (one body under gravity and contact forces; "
         "in axisymmetry it moves along the axis only)", default="free", choices=KINEMATICS),),
    "how the body moves",
    variant_key="type",
    variants={"free": (
        Key("substeps", "int", "steps the body takes within each step of the scene (subcycling, for a stiff "
            "structure); 'auto': the fewest that keep it within scene.cfl. A subcycled body does not set the "
            "scene's step. Its contacts are resolved once per scene step, and it takes their impulse as a whole "
            "(with its mass and moment of inertia, as a rigid body): its substeps carry its deformation under its "
            "weight and inertia, not the local deformation a contact load would cause. In axisymmetry it "
            "moves as one along the axis only; absent: 1", default=None, low=1, low_inclusive=True, words=("auto",)),
    ), "prescribed": (
        Key("velocity", "vec2_or_points", "the prescribed velocity [vx, vy], or one [vx, vy] per entry of "
            "time (linear in between, held after the last); a parameter: params['bodies'][NAME]['velocity']",
            unit="m/s"),
        Key("time", "floats", "times of the velocity table, from 0, strictly increasing", unit="s", default=None),
    )},
)

GEOSTATIC = Section((
    Key("k0", "float", "earth pressure coefficient sigma_h / sigma_v, or 'jaky' for 1 - sin(phi) of the body's "
        "friction angle", default="jaky", low=0.0, words=("jaky",)),
), "vertical stress sigma_v from the depth below the body's top (its weight, and that of other geostatic bodies stacked on it), sigma_h = K0 sigma_v")

INITIAL_STRESS = Section((
    Key("geostatic", "table", "a geostatic initial stress", section=GEOSTATIC),
), "the initial stress of a free body (absent: zero)")

BODY = Section((
    Key("name", "str", "the body's name (letters, digits, '_', '-'; not 'time')"),
    Key("material", "str", "name of a [materials.NAME] table"),
    Key("region", "table", "where its points are", section=REGION),
    Key("velocity", "vec2", "initial velocity of a free or rigid body (a prescribed body's is "
        "kinematics.velocity)", unit="m/s", default=(0.0, 0.0)),
    Key("kinematics", "table", "how it moves", default={"type": "free"}, section=KINEMATICS_TABLE),
    Key("initial_stress", "table", "initial stress (absent: zero)", default=None, section=INITIAL_STRESS),
), "one body: a region of material points of one material")

CONTACT = Section((
    Key("pair", "strings", "the two bodies [first, second]; at least one is free", length=2),
    Key("friction", "float", "Coulomb friction coefficient mu of the interface; a parameter: "
        "params['contacts']['first/second']['friction']", default=0.0, low=0.0, low_inclusive=True),
), "frictional contact between two bodies (Bardenhagen et al. 2001): each gets its own velocity field")

PROBE = Section(
    (Key("name", "str", "the probe's name in outputs and observations"),
     Key("kind", "str", "what it records; the keys of each kind follow", choices=PROBE_KINDS)),
    "a history recorded at every output time",
    variant_key="kind",
    variants={
        "displacement": (Key("at", "vec2", "the point nearest this position at t = 0; records its "
                             "displacement (2 components)", unit="m"),),
        "body_displacement": (Key("body", "str", "the body whose mass-weighted mean displacement [m] is "
                                  "recorded (2 components)"),),
        "body_rotation": (Key("body", "str", "the body whose rotation about its centre of mass is recorded "
                              "[rad, counter-clockwise positive] (1 component)"),),
        "peak_speed": (Key("body", "str", "the body whose fastest point's speed is recorded [m/s] "
                           "(1 component): a watch on local numerical events that averages hide"),),
        "contact_force": (Key("pair", "strings", "a [[contacts]] pair; records the force of the first body "
                              "on the second [N per m of thickness; whole-ring N in axisymmetry]", length=2),
                          Key("facing", "vec2", "records only the force through the nodes where the "
                              "contact normal, from the first body into the second, lies within 45 degrees "
                              "of this direction: one face, e.g. [-1, 0] for sand pushing on the back of a "
                              "wall that faces +x, [0, 1] for the ground under its base; absent: the whole "
                              "contact", default=None)),
        "reaction": (Key("body", "str", "a prescribed body; records the force that keeps it on its path "
                         "[N/m; whole-ring N in axisymmetry]"),),
    },
)

SCENE_FILE = Section((
    Key("scene", "table", "the run", section=SCENE),
    Key("grid", "table", "the background grid", section=GRID),
    Key("numerics", "table", "discretisation", default={}, section=NUMERICS),
    Key("materials", "named_tables", "the materials, each a [materials.NAME] table", section=MATERIAL),
    Key("bodies", "tables", "the bodies, each a [[bodies]] table", section=BODY),
    Key("contacts", "tables", "contact pairs, each a [[contacts]] table", default=(), section=CONTACT),
    Key("probes", "tables", "recorded histories, each a [[probes]] table", default=(), section=PROBE),
))

__all__ = ["REQUIRED", "SCENE_FILE"]
