"""Every check of a scene that needs no compiling, run whenever a `Scene` is built.

First each value against its key in the schema (range, choices; so a scene built in Python
meets the same bounds as one read from a file), then what relates keys: bodies inside the
grid and on defined materials, names unique and safe, contact pairs and probe targets that
exist, axisymmetric restrictions, an explicit time step below the stable limit. Each failure
is one `SceneError` sentence naming the key and the value.
"""

from __future__ import annotations

import math

from jaxmpm.errors import SceneError
from jaxmpm.keys import check_range, check_value
from jaxmpm.scene.parts import BODY_PROBE_KINDS, KINEMATICS, NAME, Grid, Kinematics, Rectangle
from jaxmpm.scene.schema import SCENE_FILE
from jaxmpm.physics.time_step import check_scene_step


def check_fields(obj, section, path, variant=None):
    """The schema's checks on the attributes of `obj` that are values (not tables)."""
    for key in section.keys_for(variant):
        if key.section is None:
            check_value(f"{path}.{key.name}", key, getattr(obj, key.name))


def _section(*names):
    section = SCENE_FILE
    for name in names:
        section = section.key(name).section
    return section


def check_scene(scene):
    """Every check that needs no compiling. Raises SceneError naming the key and value."""
    check_fields(scene, _section("scene"), "scene")
    if scene.output_every is not None:
        check_range("scene.output_every", scene.output_every, low=0.0, high=scene.duration, high_inclusive=True)
    check_grid(scene.grid)
    check_fields(scene.numerics, _section("numerics"), "numerics")
    if scene.geometry == "axisymmetric":
        check_axisymmetric(scene)
    check_names(scene)
    for name, material in scene.materials.items():
        material.check(f"materials.{name}")
    check_bodies(scene)
    check_contacts(scene)
    check_probes(scene)
    check_scene_step(scene)


def check_grid(grid: Grid):
    check_fields(grid, _section("grid"), "grid")
    check_fields(grid.boundaries, _section("grid", "boundaries"), "grid.boundaries")
    for length in grid.size:
        cells = length / grid.cell
        if abs(cells - round(cells)) > 1e-6 * max(1.0, cells) or round(cells) < 1:
            raise SceneError(
                f"grid.size = {list(grid.size)} is not a whole number of cells of "
                f"grid.cell = {grid.cell}."
            )


def check_names(scene):
    """Names of materials, bodies and probes: safe in HDF5 paths and --set, never 'time'."""
    if not scene.materials:
        raise SceneError("materials is empty: define at least one [materials.NAME] table.")
    if not scene.bodies:
        raise SceneError("bodies is empty: define at least one [[bodies]] table.")
    named = [(f"materials.{name}", name) for name in scene.materials]
    named += [(f"bodies[{i}].name", body.name) for i, body in enumerate(scene.bodies)]
    named += [(f"probes[{i}].name", probe.name) for i, probe in enumerate(scene.probes)]
    for key, name in named:
        if not isinstance(name, str) or not NAME.match(name) or name == "time":
            raise SceneError(
                f"{key} = {name!r} must be a name of letters, digits, '_' or '-' starting with a "
                "letter or '_', other than 'time'."
            )
    for plural, singular, names in (("bodies", "body", [b.name for b in scene.bodies]),
                                    ("probes", "probe", [p.name for p in scene.probes])):
        for index, name in enumerate(names):
            if names.index(name) != index:
                raise SceneError(f"{plural}[{index}].name = {name!r} is used by more than one {singular}.")


def _inside_grid(grid: Grid, point) -> bool:
    tolerance = 1e-9 * grid.cell
    return all(
        grid.origin[axis] - tolerance <= point[axis] <= grid.origin[axis] + grid.size[axis] + tolerance
        for axis in (0, 1)
    )


def check_bodies(scene):
    body_keys = _section("bodies")
    for index, body in enumerate(scene.bodies):
        where = f"bodies[{index}]"
        check_fields(body, body_keys, where)
        if body.material not in scene.materials:
            known = ", ".join(repr(name) for name in scene.materials)
            raise SceneError(f"{where}.material = {body.material!r} is not defined (known: {known}).")
        check_region(where, body.region, scene.grid)
        check_kinematics(f"{where}.kinematics", body.kinematics)
        if body.kinematics.type == "prescribed" and tuple(body.velocity) != (0.0, 0.0):
            raise SceneError(
                f"{where}.velocity is given for a prescribed body: its velocity is "
                f"{where}.kinematics.velocity (remove {where}.velocity)."
            )
        if body.initial_stress is not None:
            check_initial_stress(scene, where, body)
        if body.kinematics.type == "rigid":
            check_rigid_not_on_held_edge(scene, where, body)


def check_rigid_not_on_held_edge(scene, where, body):
    """A rigid body moves under gravity and its contacts only: the grid-edge conditions do not
    hold it (docs/physics.md, section 12), so one standing within a cell of a fixed or slip edge
    that gravity pulls it towards, with no other body between (a slab, soil), would fall
    through that edge and off the grid. (One higher up falls all the same; this catches the
    body set on the edge.)"""
    grid, gravity = scene.grid, scene.gravity
    low, high = bounds(body.region)
    edges = (("left", 0, -1, gravity[0] < 0.0, low[0] - grid.origin[0]),
             ("right", 0, 1, gravity[0] > 0.0, grid.origin[0] + grid.size[0] - high[0]),
             ("bottom", 1, -1, gravity[1] < 0.0, low[1] - grid.origin[1]),
             ("top", 1, 1, gravity[1] > 0.0, grid.origin[1] + grid.size[1] - high[1]))
    for edge, axis, side, pulled, gap in edges:
        kind = getattr(grid.boundaries, edge)
        if pulled and kind != "free" and gap < grid.cell and not held_by_another(scene, body, (low, high), axis, side):
            raise SceneError(
                f"{where} ({body.name!r}) is rigid and stands {gap:g} m from the {edge} grid edge "
                f"(grid.boundaries.{edge} = {kind!r}), which gravity pulls it towards: rigid bodies ignore the "
                "grid-edge conditions, so it would fall through; stand it on a prescribed body (a base slab) "
                "or on soil."
            )


def bounds(region):
    """(lowest, highest) corner of the region's bounding box."""
    vertices = region.vertices
    return ([min(vertex[axis] for vertex in vertices) for axis in (0, 1)],
            [max(vertex[axis] for vertex in vertices) for axis in (0, 1)])


def held_by_another(scene, body, box, axis, side):
    """Whether another body lies between `body` (bounding `box`, (lowest, highest)) and the
    grid edge on `side` (-1 low, +1 high) of `axis`: its extent along the edge overlaps the
    body's and it reaches further towards the edge than the body does."""
    low, high = box
    along = 1 - axis
    for other in scene.bodies:
        if other is body:
            continue
        other_low, other_high = bounds(other.region)
        overlaps = other_high[along] > low[along] and other_low[along] < high[along]
        nearer = other_low[axis] < low[axis] if side < 0 else other_high[axis] > high[axis]
        if overlaps and nearer:
            return True
    return False


def check_region(where, region, grid: Grid):
    vertices = region.vertices
    if isinstance(region, Rectangle):
        if not all(region.lower[a] < region.upper[a] for a in (0, 1)):
            raise SceneError(
                f"{where}.region.rectangle = {[list(region.lower), list(region.upper)]} "
                "must go from the lower-left to the upper-right corner."
            )
    elif len(vertices) < 3:
        raise SceneError(f"{where}.region.polygon has {len(vertices)} vertices: it needs at least 3.")
    for vertex in vertices:
        if not _inside_grid(grid, vertex):
            raise SceneError(
                f"{where}.region has the point {list(vertex)} outside the grid "
                f"(origin {list(grid.origin)}, size {list(grid.size)})."
            )


def check_initial_stress(scene, where, body):
    if body.kinematics.type != "free":
        raise SceneError(
            f"{where}.initial_stress is given for a {body.kinematics.type} body, whose stress is never used: "
            "remove it (only free bodies carry stress)."
        )
    key = f"{where}.initial_stress.geostatic.k0"
    check_value(key, _section("bodies", "initial_stress", "geostatic").key("k0"), body.initial_stress.k0)
    if body.initial_stress.k0 == "jaky" and not hasattr(scene.materials[body.material], "friction_angle"):
        raise SceneError(
            f"{key} = 'jaky' needs a friction angle, which material "
            f"{body.material!r} has not: give k0 as a number."
        )


def check_kinematics(key: str, kinematics: Kinematics):
    """SceneError unless the kinematics are complete and consistent."""
    if kinematics.type not in KINEMATICS:
        raise SceneError(f"{key}.type = {kinematics.type!r} is not one of {', '.join(map(repr, KINEMATICS))}.")
    if kinematics.substeps is not None:
        if kinematics.type != "free":
            raise SceneError(f"{key}.substeps = {kinematics.substeps!r} is given for a {kinematics.type} body: only free "
                             "bodies take steps of their own.")
        check_value(f"{key}.substeps", _section("bodies", "kinematics").key("substeps", "free"), kinematics.substeps)
    if kinematics.type != "prescribed":
        if kinematics.velocity is not None or kinematics.time is not None:
            raise SceneError(f"{key} gives a velocity table for a {kinematics.type} body: only prescribed bodies take one.")
        return
    if kinematics.velocity is None:
        raise SceneError(f"{key}.velocity is missing: a prescribed body needs its velocity [vx, vy].")
    if kinematics.time is None:
        if len(kinematics.velocity) != 2 or isinstance(kinematics.velocity[0], (tuple, list)):
            raise SceneError(f"{key}.velocity = {list(kinematics.velocity)!r} must be [vx, vy] (or give time for a table).")
        return
    times, rows = list(kinematics.time), list(kinematics.velocity)
    if len(times) < 2 or len(rows) != len(times) or any(not isinstance(row, (tuple, list)) or len(row) != 2 for row in rows):
        raise SceneError(
            f"{key}: time = {times} and velocity = {[list(row) if isinstance(row, (tuple, list)) else row for row in rows]} "
            "must be tables of the same length (at least 2), one [vx, vy] per time."
        )
    if times[0] != 0.0 or any(later <= earlier for earlier, later in zip(times, times[1:])):
        raise SceneError(f"{key}.time = {times} must start at 0 and increase strictly.")


def check_axisymmetric(scene):
    """In axisymmetry x is the radius: the grid starts on the axis, whose edge holds the
    radial velocity, gravity is axial, and a rigid body (a ring) starts with no radial
    velocity: it moves along the axis only."""
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
        if body.kinematics.type == "rigid" and body.velocity[0] != 0.0:
            raise SceneError(
                f"bodies[{index}].velocity = {list(body.velocity)}: in axisymmetry a rigid body (a ring) moves along "
                "the axis only, so velocity[0] must be 0."
            )


def check_contacts(scene):
    names = [body.name for body in scene.bodies]
    kinds = {body.name: body.kinematics.type for body in scene.bodies}
    subcycled_bodies = {body.name: body.kinematics.subcycled for body in scene.bodies}
    declared = []
    for index, contact in enumerate(scene.contacts):
        check_fields(contact, _section("contacts"), f"contacts[{index}]")
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
        subcycled = [name for name in contact.pair if kinds[name] == "free" and subcycled_bodies.get(name)]
        if subcycled and (len(subcycled) == 2 or any(kinds[name] != "free" for name in contact.pair)):
            raise SceneError(
                f"{key} = {list(contact.pair)} pairs the subcycled body {subcycled[0]!r} with a body that is "
                "subcycled, prescribed or rigid: a subcycled body's contacts are with free bodies that step with the scene."
            )
        if set(contact.pair) in declared:
            raise SceneError(f"{key} = {list(contact.pair)}: these two bodies are already paired.")
        declared.append(set(contact.pair))
        if scene.numerics.structure_hold == "points":
            check_pushes_points(scene, key, contact)


def check_pushes_points(scene, key, contact):
    """Under numerics.structure_hold = "points" a prescribed or rigid body pushes the points of
    the body it meets out of its outline, which must be a convex polygon."""
    from jaxmpm.physics.bodies import convex_outline

    for body in scene.bodies:
        if body.name in contact.pair and body.kinematics.type != "free" and convex_outline(body.region.vertices) is None:
            raise SceneError(
                f"{key} = {list(contact.pair)} pairs the {body.kinematics.type} body {body.name!r}, whose region is not "
                "a convex polygon, while numerics.structure_hold = 'points' pushes points out of a convex outline "
                "only; use a convex region or structure_hold = 'mass'."
            )


def check_probes(scene):
    kinds = {body.name: body.kinematics.type for body in scene.bodies}
    declared = [set(contact.pair) for contact in scene.contacts]
    probe_keys = _section("probes")
    for index, probe in enumerate(scene.probes):
        where = f"probes[{index}]"
        check_value(f"{where}.kind", probe_keys.key("kind"), probe.kind)
        check_fields(probe, probe_keys, where, probe.kind)
        if probe.kind in BODY_PROBE_KINDS and probe.body not in kinds:
            raise SceneError(f"{where}.body = {probe.body!r} is not the name of a body.")
        if probe.kind == "reaction" and kinds[probe.body] != "prescribed":
            raise SceneError(
                f"{where}.body = {probe.body!r} is {kinds[probe.body]}, not prescribed: a reaction is the "
                "force that keeps a prescribed body on its path."
            )
        if probe.kind == "contact_force" and set(probe.pair) not in declared:
            raise SceneError(f"{where}.pair = {list(probe.pair)} is not a pair of [[contacts]].")
        if probe.facing is not None and probe.kind != "contact_force":
            raise SceneError(f"{where}.facing = {list(probe.facing)} is given on a {probe.kind!r} probe: "
                             "only a contact_force probe reads one face.")
        if probe.facing is not None and not math.hypot(*probe.facing) > 0.0:
            raise SceneError(f"{where}.facing = {list(probe.facing)} has no direction: give a nonzero [x, y].")
        if probe.kind == "displacement" and not _inside_grid(scene.grid, probe.at):
            raise SceneError(f"{where}.at = {list(probe.at)} is outside the grid.")
