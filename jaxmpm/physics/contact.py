"""Multi-velocity-field contact on the grid (Bardenhagen et al. 2001, Comput. Model. Eng. Sci. 2).

Bodies named in a `[[contacts]]` pair, and prescribed and rigid bodies, each carry their own
velocity field on the grid; all other bodies share one field (no slip among them). Where two
fields both have mass at a node, their trial velocities v_a, v_b (after M a = F) are corrected
once per step by an impulse J on a and -J on b, so momentum is kept exactly:

  interface  a declared contact pair       or two fields that are not paired (bonded)
  normal     n = (m_a g_a/|g_a| - m_b g_b/|g_b|) / |...|, from a into b, with the outward mass
             gradient g = sum_p m_p grad N_I(x_p) of each field (the derivative with respect
             to the point, so g points out of the body)
  approach   c = (v_a - v_b) . n; only c > 0 (closing) is corrected, so bodies separate freely
  relative   dv = -c n - t min(1, mu c / |t|), t = (v_a - v_b) - c n   (Coulomb: stick while
             |t| <= mu c, else slide with a tangential change mu c)   | bonded: dv = -(v_a - v_b)
  impulse    J = m_r dv, m_r = m_a m_b / (m_a + m_b) for two free fields; m_r = m_a (or m_b) when
             b (or a) is prescribed or rigid: such a field acts as infinitely heavy, keeps its
             velocity, and the impulse it receives is reported (reaction, rigid-body motion).
             A rigid body's nodal velocity is set before, solved together with the impulses
             of all its interfaces (`bodies.solve_rigid_motions`).

Normals. Against a prescribed body, the normal is that body's own outward normal: its surface
does not deform, and where its outline is convex it is known exactly (`bodies.outline_normals`:
at a node inside or on the outline the normal of its nearest edge, outside it the direction
from the nearest point of the outline; the corners rounded at a cell, `bodies.rounded_outline`,
so that a node passing a corner sees the normal turn, not jump). The normal of its points' mass
gradient, used for other outlines, turns each time a row of the body's points crosses a cell
edge; a pile driven through many cells then met sand with a normal that flickered, and its
force shifted by up to 3 % when the step was halved (docs/convergence.md). Between two free
bodies, and between a free and a rigid body (the limit of a stiff free one, which must behave
the same), it is the mean of
their own outward normals, each weighted by its field's mass at the node: where one body only
grazes a node (a corner, a thin edge, a body just arriving) its normal is poorly resolved and
its mass there is small, so the well-covered body's normal decides. Where one side is a
structure whose outline is known, a rigid body or an elastic body against soil that yields
(its outline moved by its points' best-fit rigid motion), that mean is held in the
structure's normal cone (`within_cone`): on a face it is the face's normal, at a corner it
stays between the two faces' normals. The mean alone let a node beside a wall's flat back
face, where the sand parts from the wall and has most of the mass, take the sand's slanted
normal, and the face carried up to twice the friction Coulomb allows (docs/contact.md).
Both choices are antisymmetric (n_ab = -n_ba), so the two fields always get equal and
opposite impulses.
With the plain difference g_a - g_b (or the mass-weighted mean against a held slab), a block
sliding on a flat slab with mu = 0 met the slab's normal tilted at its leading corner, lost
7-8 % of its acceleration g sin(theta) and climbed (Nairn 2013, Comput. Model. Eng. Sci. 92,
compares normal choices; docs/contact.md gives our measurements). A rigid wall with its own
normal instead sank at its toe and turned 40 % further than the same wall as a stiff elastic
body (docs/convergence.md). Contact is detected where
both fields have mass at a node, i.e. up to about one cell before the bodies touch (the
supports of their shape functions overlap); docs/contact.md measures that gap.

Under numerics.structure_hold = "points" a prescribed or rigid body's contact is not found at
the nodes: its push on the soil's points (`point_contact`) arrives as the interface's normal
impulse (`PointPush`, in place of a normal), and only the friction is resolved here
(`pushed_impulse`).

Every division and norm is guarded (double `where`): values and gradients are finite at
empty nodes, zero normals and zero tangential velocity.
"""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

GRAZING_SHARE = 0.05   # a contact's impulse ramps in over the lighter free field's mass share 0 ... this (`grazing_weight`)


@dataclasses.dataclass(frozen=True)
class Interface:
    """Two velocity fields that meet on the grid (static).

    first, second: field indices; contact: the pair's name "body/body" for a declared contact
    (frictional), None for bonded fields (no slip); kinematic_first / kinematic_second: whether
    that field is a prescribed or rigid body (then it keeps its own velocity); normal_from: the
    field whose own outward normal the contact uses (a prescribed body's), None for the
    mass-weighted mean of both (`contact_normals`); shared_with: the fields of other parts of
    the same prescribed structure (`bodies.joined_edges`) whose interfaces with the same free
    field come later: at a node where several parts have mass, each part takes the share of
    the impulse that its mass has among them (`part_share`); bounded_by: the field whose
    outline's normal cone holds the mass-weighted mean normal (`within_cone`): a rigid body,
    or an elastic one whose partner's outline is known less well (`simulation.bounding_side`);
    None for none."""

    first: int
    second: int
    contact: str | None
    kinematic_first: bool = False
    kinematic_second: bool = False
    normal_from: int | None = None
    shared_with: tuple[int, ...] = ()
    bounded_by: int | None = None


class PointPush(NamedTuple):
    """What a contact at the points (`point_contact`) gives the grid in place of a normal: the
    normal impulse (nx, ny, 2) the free body's points received from the structure over the
    step, on the free body's field (pointing out of the structure)."""

    impulse: jax.Array


def bounding_fields(interfaces):
    """The fields whose outline bounds some contact's normal (`Interface.bounded_by`)."""
    return {interface.bounded_by for interface in interfaces if interface.bounded_by is not None}


def safe_norm(vectors):
    """|v| over the last axis (length 2), with a zero (not NaN) gradient at v = 0."""
    squares = vectors[..., 0] * vectors[..., 0] + vectors[..., 1] * vectors[..., 1]
    positive = squares > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squares, 1.0)), 0.0)


def unit(vectors):
    """v / |v| over the last axis, zero where v = 0 (finite value and gradient)."""
    length = safe_norm(vectors)
    return vectors / jnp.where(length > 0.0, length, 1.0)[..., None]


def contact_normals(mass_first, gradient_first, mass_second, gradient_second):
    """Unit normals from a into b at each node, (..., 2): the mass-weighted mean of a's outward
    normal and b's inward one, m_a g_a/|g_a| - m_b g_b/|g_b| normalised (zero where it vanishes)."""
    return unit(mass_first[..., None] * unit(gradient_first) - mass_second[..., None] * unit(gradient_second))


def contact_velocity_change(relative, normal, friction):
    """The change of v_a - v_b that contact with Coulomb friction makes at each node, (..., 2).

    relative: v_a - v_b (..., 2); normal: unit normal from a into b (..., 2); friction: mu.
    Zero where the fields separate (c <= 0)."""
    approach = relative[..., 0] * normal[..., 0] + relative[..., 1] * normal[..., 1]
    closing = approach > 0.0
    approach = jnp.where(closing, approach, 0.0)
    tangential = relative - approach[..., None] * normal
    slip_speed = safe_norm(tangential)
    limit = friction * approach
    sliding = slip_speed > limit                 # then slip_speed > 0: the division is safe
    kept = jnp.where(sliding, limit / jnp.where(sliding, slip_speed, 1.0), 1.0)
    change = -approach[..., None] * normal - kept[..., None] * tangential
    return jnp.where(closing[..., None], change, 0.0)


def dot(first, second):
    """first . second over the last axis (length 2), (...,)."""
    return first[..., 0] * second[..., 0] + first[..., 1] * second[..., 1]


def cross(first, second):
    """z-component of first x second over the last axis (length 2), (...,)."""
    return first[..., 0] * second[..., 1] - first[..., 1] * second[..., 0]


def within_cone(normal, cone):
    """The outward normals (..., 2) a structure's contact takes, from the mass-weighted mean
    `normal` (outward from the structure) and its outline's `bodies.NormalCone`: on a face the
    face's own normal; off a face (a corner) the mean normal where it lies in the cone between
    the two nearest faces' normals, else the nearer of the two; the outline's normal where the
    mean vanishes. A flat face then carries at most Coulomb's friction: a node beside it where
    the soil's mass dominates, e.g. where soil parts from a wall, took the soil's own slanted
    normal and pulled the wall down with twice the friction mu allows (docs/contact.md)."""
    span = cross(cone.first, cone.second)
    inside = ((cross(cone.first, normal) * span >= 0.0) & (cross(normal, cone.second) * span >= 0.0)
              & (dot(normal, cone.first + cone.second) > 0.0))
    nearer = jnp.where((dot(normal, cone.first) >= dot(normal, cone.second))[..., None], cone.first, cone.second)
    held = jnp.where(inside[..., None], normal, nearer)
    held = jnp.where((safe_norm(normal) > 0.0)[..., None], held, cone.normal)
    return jnp.where(cone.on_face[..., None], cone.normal, held)


def interface_normals(interface, mass, mass_gradient, outline_normals=None):
    """Unit normals from `first` into `second` at each node, (nx, ny, 2): the prescribed body's
    own outward normal when one side is such a body (from its outline where `outline_normals`
    {field: (nx, ny, 2)} has it, else from its mass gradient), else `contact_normals`, held in
    the normal cone of the side `bounded_by` (`within_cone`, its `bodies.NormalCone` from
    `outline_normals`)."""
    a, b = interface.first, interface.second
    outline_normals = outline_normals or {}
    if interface.normal_from is not None:
        side = interface.normal_from
        own = outline_normals[side] if side in outline_normals else unit(mass_gradient[side])
        return -own if side == b else own
    mean = contact_normals(mass[a], mass_gradient[a], mass[b], mass_gradient[b])
    if interface.bounded_by is None:
        return mean
    outward = 1.0 if interface.bounded_by == a else -1.0
    return outward * within_cone(outward * mean, outline_normals[interface.bounded_by])


def interface_impulse(interface, mass, velocity, normal, friction, occupied):
    """Impulse J on field `first` (and -J on `second`) at each node, (nx, ny, 2).

    mass: (F, nx, ny); velocity: (F, nx, ny, 2) trial velocities; normal: (nx, ny, 2) from
    first into second (None for a bonded interface); occupied: (F, nx, ny) bool."""
    if isinstance(normal, PointPush):
        return pushed_impulse(interface, mass, velocity, normal, friction, occupied)
    a, b = interface.first, interface.second
    relative = velocity[a] - velocity[b]
    if interface.contact is None:
        change = -relative
    else:
        change = contact_velocity_change(relative, normal, friction)
    if interface.kinematic_second:
        reduced = mass[a]
    elif interface.kinematic_first:
        reduced = mass[b]
    else:
        total = mass[a] + mass[b]
        both = occupied[a] & occupied[b]
        reduced = mass[a] * mass[b] / jnp.where(both, total, 1.0)
        if interface.contact is not None:
            reduced = reduced * grazing_weight(mass[a], mass[b], both)
    both = occupied[a] & occupied[b]
    return jnp.where(both[..., None], reduced[..., None] * change, 0.0)


def pushed_impulse(interface, mass, velocity, push, friction, occupied):
    """Impulse on field `first` (nx, ny, 2) of a contact at the points (`point_contact`): the
    points' normal impulse J_n on the free field, and Coulomb friction at its nodes with J_n
    as the normal impulse: the free field's velocity relative to the structure's after J_n,
    u = v_f + J_n / m_f - v_s, loses its part t across n = J_n / |J_n|, all of it while
    m_f |t| <= mu |J_n| (stick), else mu |J_n| / m_f of it (slide)."""
    free, other = (interface.second, interface.first) if interface.kinematic_first else (interface.first, interface.second)
    safe_mass = jnp.where(occupied[free], mass[free], 1.0)
    normal_impulse = jnp.where(occupied[free][..., None], push.impulse, 0.0)
    relative = velocity[free] + normal_impulse / safe_mass[..., None] - velocity[other]
    normal = unit(normal_impulse)
    tangential = relative - dot(relative, normal)[..., None] * normal
    slip_speed = safe_norm(tangential)
    limit = friction * safe_norm(normal_impulse) / safe_mass
    sliding = slip_speed > limit
    kept = jnp.where(sliding, limit / jnp.where(sliding, slip_speed, 1.0), 1.0)
    on_free = normal_impulse - (mass[free] * kept)[..., None] * tangential
    on_free = jnp.where(occupied[free][..., None], on_free, 0.0)
    return -on_free if interface.kinematic_first else on_free


def grazing_weight(mass_first, mass_second, both):
    """(nx, ny) factor on a contact's impulse between two free fields: the lighter field's share
    s = min(m_a, m_b) / (m_a + m_b) of the node's mass over GRAZING_SHARE, at most 1.

    A point that has just crossed into a cell gives its new nodes a mass m_p N_I that starts at
    zero but a force -V_p sigma_p . grad N_I that does not (grad N_I jumps to +-1/h): its field's
    trial velocity there is f dt / m, and the impulse that stops it closing, J ~ m_r dv ~ dt f . n,
    handed the other body that whole force whatever the mass behind it. A stiff elastic wall
    pivoting on its toe kept its corner point 0.1 mm past a cell edge for thousands of steps, and
    the couple of its toe stress (some 500 N/m at 12.5 mm cells, growing as the sand gave way)
    went into the sand node in front of it until the sand there ran away (docs/contact.md).
    Ramped in, the impulse grows with the mass behind it; momentum is kept (J on a, -J on b)."""
    share = jnp.minimum(mass_first, mass_second) / jnp.where(both, mass_first + mass_second, 1.0)
    return jnp.clip(share / GRAZING_SHARE, 0.0, 1.0)


def part_share(interface, mass, occupied):
    """(nx, ny): the fraction of the impulse that the part `normal_from` of a joined structure
    takes at each node: m_k / (m_k + sum of the later parts' masses). The parts move alike and
    share one normal, so the later parts' interfaces then correct the rest of the free field's
    velocity, each taking its own share, and the whole impulse is that of one body: for the
    Coulomb correction dv, dv(r + s dv(r)) = (1 - s) dv(r) for 0 <= s <= 1. Exact when the
    parts' contacts with that body have the same friction and kind and no other interface of
    it comes between them (as on the pile); otherwise a blend of the parts' laws."""
    own = jnp.where(occupied[interface.normal_from], mass[interface.normal_from], 0.0)
    total = own + sum(jnp.where(occupied[part], mass[part], 0.0) for part in interface.shared_with)
    return jnp.where(total > 0.0, own / jnp.where(total > 0.0, total, 1.0), 1.0)


def normals_of(interfaces, mass, mass_gradient, outline_normals=None, pushes=None):
    """The unit normal (nx, ny, 2) of each interface at the nodes (`interface_normals`), None
    for a bonded one, its `PointPush` for a contact at the points (`pushes` {index: PointPush}).
    They read no velocity, so a step takes them once."""
    pushes = pushes or {}
    return tuple(pushes[index] if index in pushes
                 else None if interface.contact is None
                 else interface_normals(interface, mass, mass_gradient, outline_normals)
                 for index, interface in enumerate(interfaces))


def apply_interfaces(interfaces, mass, velocity, normals, frictions, occupied):
    """Apply every interface's impulse in turn to the free fields' velocities, each from the
    velocities the ones before it left (`normals` from `normals_of`).

    Returns (velocity (F, nx, ny, 2), impulses): impulses[k] (nx, ny, 2) is the impulse on the
    `first` field of interfaces[k] (its `second` field received minus it). Prescribed and rigid
    fields keep their velocities; what they receive is read from the impulses."""
    impulses = []
    safe_mass = jnp.where(occupied, mass, 1.0)[..., None]
    for interface, normal in zip(interfaces, normals, strict=True):
        impulse = interface_impulse(interface, mass, velocity, normal, frictions.get(interface.contact), occupied)
        if interface.shared_with and not isinstance(normal, PointPush):
            impulse = impulse * part_share(interface, mass, occupied)[..., None]
        if not interface.kinematic_first:
            velocity = velocity.at[interface.first].add(impulse / safe_mass[interface.first])
        if not interface.kinematic_second:
            velocity = velocity.at[interface.second].add(-impulse / safe_mass[interface.second])
        impulses.append(impulse)
    return velocity, impulses


def resolve_interfaces(interfaces, mass, velocity, mass_gradient, frictions, occupied, outline_normals=None):
    """`apply_interfaces` with the normals of `normals_of`: (velocity, impulses, normals)."""
    normals = normals_of(interfaces, mass, mass_gradient, outline_normals)
    velocity, impulses = apply_interfaces(interfaces, mass, velocity, normals, frictions, occupied)
    return velocity, impulses, normals
