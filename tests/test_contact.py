"""Soil-structure interaction: multi-field contact, prescribed and rigid bodies, their probes.

Sources: sliding block, g (sin theta - mu cos theta) (Coulomb friction on an incline, any
mechanics text; the classic MPM contact check of Bardenhagen et al. 2001, Comput. Model. Eng.
Sci. 2); head-on discs (Bardenhagen et al. 2001); active earth pressure, 1/2 K0 rho g H^2
before the wall moves and Rankine's 1/2 Ka rho g H^2, Ka = (1 - sin phi) / (1 + sin phi),
after (Rankine 1857; Coulomb 1776 with wall friction); free fall x = x0 + g t^2 / 2.
"""

import dataclasses
import math
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tomli_w

import jaxmpm
from jaxmpm.cli import main
from jaxmpm.physics.contact import Interface, contact_normals, contact_velocity_change, resolve_interfaces
from jaxmpm.running.simulation import velocity_fields
from tests.scenes import reverse_mode_against_central_differences
from jaxmpm import (
    Body, Boundaries, Contact, DruckerPrager, Geostatic, Grid, Kinematics, LinearElastic, Numerics, Polygon, Probe,
    Rectangle, Scene, SceneError, Simulation, with_values,
)

G = 9.81


# --------------------------------------------------------------------------- the nodal contact law


def test_contact_law_on_nodes():
    # Closing normal motion is removed; tangential motion kept below mu * closing speed,
    # removed (stick) when it is below; separating nodes are left alone.
    normal = jnp.asarray([[0.0, -1.0]] * 4)            # from a (above) into b (below)
    relative = jnp.asarray([[0.5, -1.0], [0.2, -1.0], [0.5, 1.0], [0.0, 0.0]])
    change = np.asarray(contact_velocity_change(relative, normal, 0.3))
    np.testing.assert_allclose(change[0], [-0.3, 1.0])   # slides: tangential change mu * 1
    np.testing.assert_allclose(change[1], [-0.2, 1.0])   # sticks: all relative motion removed
    np.testing.assert_allclose(change[2:], 0.0)          # separating, at rest


@pytest.mark.parametrize("relative", [[0.0, 0.0], [0.0, -1.0], [0.3, -1.0], [0.5, 1.0]])
def test_contact_law_gradients_are_finite_at_its_kinks(relative):
    # At rest, with zero tangential velocity, exactly at the stick/slip switch (|t| = mu c),
    # and separating; also with a zero normal (an empty node): finite Jacobians.
    for normal in ([0.0, -1.0], [0.0, 0.0]):
        jacobian = jax.jacfwd(contact_velocity_change, argnums=(0, 1, 2))(
            jnp.asarray(relative), jnp.asarray(normal), jnp.asarray(0.3)
        )
        assert all(bool(jnp.all(jnp.isfinite(part))) for part in jacobian)
    gradients = jax.jacfwd(lambda g: contact_normals(jnp.asarray(1.0), g, jnp.asarray(2.0), jnp.zeros(2)))(jnp.zeros(2))
    assert bool(jnp.all(jnp.isfinite(gradients)))


def test_interfaces_keep_momentum_and_kinematic_velocities():
    # Random node data: impulses are equal and opposite between free fields (total momentum
    # kept to round-off), and a prescribed field's velocity is never changed.
    rng = np.random.default_rng(0)
    mass = jnp.asarray(rng.uniform(0.0, 1.0, (3, 6, 5)) * (rng.uniform(size=(3, 6, 5)) > 0.3))
    velocity = jnp.asarray(rng.normal(size=(3, 6, 5, 2)))
    gradient = jnp.asarray(rng.normal(size=(3, 6, 5, 2)))
    occupied = mass > 0.0
    interfaces = (Interface(0, 1, "a/b"), Interface(0, 2, None, kinematic_second=True), Interface(1, 2, "b/c", kinematic_second=True))
    new, impulses, _ = resolve_interfaces(interfaces[:1], mass, velocity, gradient, {"a/b": 0.4}, occupied)
    momentum = lambda v: jnp.sum(mass[:2, ..., None] * v[:2], axis=(0, 1, 2))
    np.testing.assert_allclose(momentum(new), momentum(velocity), atol=1e-13)
    assert float(jnp.max(jnp.abs(impulses[0]))) > 0.0
    new, _, _ = resolve_interfaces(interfaces, mass, velocity, gradient, {"a/b": 0.4, "b/c": 0.0}, occupied)
    np.testing.assert_array_equal(np.asarray(new[2]), np.asarray(velocity[2]))
    both = np.asarray(occupied[0] & occupied[2])       # bonded to a prescribed field: its velocity
    np.testing.assert_allclose(np.asarray(new[0])[both], np.asarray(velocity[2])[both], atol=1e-13)


def test_a_grazing_free_field_hands_the_other_field_no_more_than_its_mass_share_allows():
    # One node where a stiff wall's field has 2e-5 of the node's mass but a trial velocity of
    # 40 m/s into the sand (a wall point 0.1 mm past a cell edge: mass m N_I from a weight near
    # zero, force from grad N_I = 1/h; the small elastic wall at 12.5 mm, docs/contact.md,
    # "Grazing nodes"), and one where both fields are well covered. Unramped, the impulse
    # m_r dv at the first node is the wall's whole momentum there, 3000 m/s^2 on the sand
    # node, and that blew the sand up; ramped over the lighter share up to GRAZING_SHARE it is
    # share / GRAZING_SHARE of that, and the covered node is unchanged. Momentum is kept.
    from jaxmpm.physics.contact import GRAZING_SHARE, interface_impulse

    wall, sand = 3.3e-6, 0.166
    mass = jnp.asarray([[[wall, 0.1]], [[sand, 0.1]]])                 # (field, 1, 2 nodes)
    velocity = jnp.asarray([[[[0.0, -40.0], [0.0, -1.0]]], [[[0.0, 0.0], [0.0, 0.0]]]])
    normal = jnp.asarray([[[0.0, -1.0], [0.0, -1.0]]])               # wall into sand
    occupied = mass > 0.0
    impulse = np.asarray(interface_impulse(Interface(0, 1, "wall/sand"), mass, velocity, normal, 0.4, occupied))
    reduced = wall * sand / (wall + sand)
    share = wall / (wall + sand)
    np.testing.assert_allclose(impulse[0, 0], [0.0, 40.0 * reduced * share / GRAZING_SHARE], rtol=1e-12)
    np.testing.assert_allclose(impulse[0, 1], [0.0, 1.0 * 0.05], rtol=1e-12)   # m_r = 0.05, closing 1 m/s
    outward = jnp.asarray([[[[0.0, -1.0]] * 2], [[[0.0, 1.0]] * 2]])      # wall above, sand below
    new, impulses, _ = resolve_interfaces((Interface(0, 1, "wall/sand"),), mass, velocity, outward,
                                          {"wall/sand": 0.4}, occupied)
    np.testing.assert_allclose(np.asarray(impulses[0]), impulse, rtol=1e-12)
    momentum = lambda v: jnp.sum(mass[..., None] * v, axis=(0, 1, 2))
    np.testing.assert_allclose(momentum(new), momentum(velocity), rtol=0, atol=1e-15)


def test_a_structures_normal_cone_holds_the_mean_normal_between_its_faces():
    # A unit square's cone at three nodes: on its left face (the face's normal whatever the
    # mean), beyond its bottom-left corner with a mean normal inside the cone (kept) and one
    # outside it (the nearer face's normal). A convex body's surface pushes only that way.
    from jaxmpm.physics.bodies import NormalCone, edge_normals
    from jaxmpm.physics.contact import within_cone

    faces = np.asarray(edge_normals(jnp.asarray([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])))
    bottom, left = faces[0], faces[3]
    np.testing.assert_allclose([bottom, left], [[0.0, -1.0], [-1.0, 0.0]], atol=1e-15)
    cone = NormalCone(normal=jnp.asarray([left, [-0.6, -0.8], [-0.6, -0.8]]), on_face=jnp.asarray([True, False, False]),
                      first=jnp.asarray([left] * 3), second=jnp.asarray([bottom] * 3))
    held = np.asarray(within_cone(jnp.asarray([[-0.6, -0.8], [-0.8, -0.6], [-0.6, 0.8]]), cone))
    np.testing.assert_array_equal(held, [left, [-0.8, -0.6], left])


def test_an_elastic_structures_outline_follows_its_points_best_fit_motion():
    # Points turned by 0.3 rad about their mean and moved by (0.2, -0.1): the outline is the
    # region turned and moved alike (exact for a rigid motion; Kabsch in 2-D); in axisymmetry
    # (a ring) it only moves along the axis.
    from types import SimpleNamespace

    from jaxmpm.physics.bodies import outline_now, turned_by

    rng = np.random.default_rng(1)
    points = rng.uniform([0.0, 0.0], [0.1, 0.4], (50, 2))
    centre = points.mean(axis=0)
    region = np.asarray([[0.0, 0.0], [0.1, 0.0], [0.1, 0.4], [0.0, 0.4]])
    block = SimpleNamespace(kinematics="free", points=slice(0, 50), outline=tuple(map(tuple, region)),
                            outline_centre=tuple(centre), reference_arms=tuple(map(tuple, points - centre)))
    moved = np.asarray(turned_by(0.3, jnp.asarray(points - centre))) + centre + [0.2, -0.1]
    state = SimpleNamespace(particles=SimpleNamespace(x=jnp.asarray(moved)))
    expected = np.asarray(turned_by(0.3, jnp.asarray(region - centre))) + centre + [0.2, -0.1]
    np.testing.assert_allclose(outline_now(block, state, jnp.float64), expected, atol=1e-14)
    np.testing.assert_allclose(outline_now(block, state, jnp.float64, axisymmetric=True),
                               region + [0.0, moved[:, 1].mean() - centre[1]], atol=1e-14)


# --------------------------------------------------------------------------- block on a slab


def sliding_block(theta_degrees, friction, duration=0.2, shape="linear"):
    """An elastic block (0.2 x 0.1 m) resting on a held slab, gravity tilted by theta: the
    axis-aligned grid stands in for an inclined plane. APIC (FLIP's noise makes a block that
    should stick creep)."""
    theta = math.radians(theta_degrees)
    return Scene(
        name="slide",
        grid=Grid(size=(1.0, 0.3), cell=0.02, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={"rubber": LinearElastic(density=1000.0, young=1.0e6, poisson=0.3)},
        bodies=(
            Body("slab", "rubber", Rectangle((0.0, 0.0), (1.0, 0.1)), kinematics=Kinematics("prescribed", (0.0, 0.0))),
            Body("block", "rubber", Rectangle((0.2, 0.1), (0.4, 0.2))),
        ),
        contacts=(Contact(("block", "slab"), friction),),
        gravity=(G * math.sin(theta), -G * math.cos(theta)),
        duration=duration,
        output_every=duration / 4,
        numerics=Numerics(ppc=2, transfer="apic", shape=shape),
        probes=(
            Probe("move", "body_displacement", body="block"),
            Probe("load", "contact_force", pair=("block", "slab")),
            Probe("hold", "reaction", body="slab"),
        ),
    )


def fitted_acceleration(sim, displacement):
    """2 c2 of the least-squares parabola through the last two thirds of x(t)."""
    start = len(sim.time) // 3
    return 2.0 * np.polyfit(sim.time[start:], displacement[start:], 2)[0]


@pytest.mark.parametrize("shape", ["linear", "bspline2"])
def test_block_slides_with_coulomb_acceleration(shape):
    # a = g (sin theta - mu cos theta) once the block slides (tan theta > mu): theta = 30 deg,
    # mu = 0 and 0.3 in one batch (the friction is a parameter: one compiled run, vmapped).
    theta = math.radians(30.0)
    sim = Simulation(sliding_block(30.0, 0.3, shape=shape))
    frictions = jnp.asarray([0.0, 0.3])
    probes = jax.vmap(lambda mu: sim.probes(with_values(sim.params, {"block/slab.friction": mu})))(frictions)
    weight = 1000.0 * 0.2 * 0.1 * G
    for index, friction in enumerate([0.0, 0.3]):
        expected = G * (math.sin(theta) - friction * math.cos(theta))
        measured = fitted_acceleration(sim, np.asarray(probes["move"][index, :, 0]))
        assert measured == pytest.approx(expected, rel=0.02)
        # The block's weight goes into the slab: normal load m g cos(theta), friction mu of it.
        load = np.asarray(probes["load"][index, len(sim.time) // 2 :]).mean(axis=0)
        assert load[1] == pytest.approx(-weight * math.cos(theta), rel=0.03)
        assert load[0] == pytest.approx(friction * weight * math.cos(theta), abs=0.03 * weight)


def test_block_sticks_when_tan_theta_is_below_friction():
    # tan 20 deg = 0.36 < mu = 0.5: the block stays (only its elastic shear, ~0.3 mm, shows).
    sim = Simulation(sliding_block(20.0, 0.5))
    probes = sim.probes()
    moved = np.asarray(probes["move"][:, 0])
    assert np.max(np.abs(moved)) < 5e-4
    # with mu = 0.3 it would slide g (sin - 0.3 cos) t^2 / 2 = 11.8 mm in 0.2 s
    # The slab is held at rest: the force that holds it is minus the weight of slab and block.
    hold = np.asarray(probes["hold"][len(sim.time) // 2 :]).mean(axis=0)
    weights = 1000.0 * (1.0 * 0.1 + 0.2 * 0.1) * np.asarray(sim.scene.gravity)
    np.testing.assert_allclose(hold, -weights, rtol=0.03)


def steep_held_block(numerics):
    """A block on a 30 degree slope with mu = 1.5 > tan 30 (friction must hold it), 0.4 s."""
    scene = sliding_block(30.0, 1.5, duration=0.4)
    return dataclasses.replace(scene, numerics=numerics)


def test_fast_preset_holds_frictional_contact(tmp_path, capsys):
    # Friction holds the block: it moves only by its elastic shear (~0.2 mm). FLIP's per-step
    # blend lets it creep (5.4 mm in 0.4 s, and growing), so the fast preset runs contact scenes
    # with APIC and says so; a transfer the scene states is kept.
    fast = steep_held_block(Numerics(preset="fast"))
    assert fast.transfer == "apic" and fast.notes
    moved = np.abs(np.asarray(Simulation(fast).probes()["move"][:, 0]))
    assert np.max(moved) < 3e-4
    flip = steep_held_block(Numerics(preset="fast", transfer="flip"))
    assert flip.transfer == "flip" and not flip.notes
    crept = np.asarray(Simulation(flip).probes()["move"][:, 0])
    assert crept[-1] > 2e-3
    assert sliding_block(30.0, 1.5).notes == ()          # APIC scenes: nothing to say
    path = tmp_path / "held.toml"
    path.write_text(fast.to_toml())
    assert "transfer" not in jaxmpm.load_scene(path).numerics.given()   # the file states nothing new
    assert main(["check", str(path), "--quick"]) == 0
    assert "note: the fast preset's FLIP transfer" in capsys.readouterr().err


# --------------------------------------------------------------------------- two discs


def disc(centre, radius, sides=32):
    angles = 2 * np.pi * np.arange(sides) / sides
    return Polygon(tuple((centre[0] + radius * math.cos(a), centre[1] + radius * math.sin(a)) for a in angles))


def test_discs_collide_without_interpenetration_and_separate():
    # Bardenhagen et al. (2001): two elastic discs approaching head-on, mu = 0. They must not
    # interpenetrate, must separate after the impact, and total momentum is conserved exactly
    # (equal and opposite contact impulses; P2G/G2P conserve momentum).
    scene = Scene(
        name="discs",
        grid=Grid(size=(1.0, 0.5), cell=0.02, boundaries=Boundaries("free", "free", "free", "free")),
        materials={"rubber": LinearElastic(density=1000.0, young=1.0e6, poisson=0.3)},
        bodies=(
            Body("left", "rubber", disc((0.33, 0.25), 0.1), velocity=(2.0, 0.0)),
            Body("right", "rubber", disc((0.67, 0.25), 0.1), velocity=(-2.0, 0.0)),
        ),
        contacts=(Contact(("left", "right"), 0.0),),
        gravity=(0.0, 0.0),
        duration=0.1,
        output_every=0.005,
        snapshot_fields=("x", "v", "mass"),
        numerics=Numerics(shape="linear", ppc=2, transfer="apic"),
        probes=(Probe("squeeze", "contact_force", pair=("left", "right")),),
    )
    result = Simulation(scene).run(progress=False)
    left, right = result.snapshots["left"], result.snapshots["right"]
    gap = right["x"][:, :, 0].min(axis=1) - left["x"][:, :, 0].max(axis=1)
    assert np.all(gap > 0.0)                      # points of one disc never pass the other's
    momentum = np.einsum("sn,snk->sk", left["mass"], left["v"]) + np.einsum("sn,snk->sk", right["mass"], right["v"])
    scale = np.sum(left["mass"][0]) * 2.0
    assert np.max(np.abs(momentum - momentum[0])) < 1e-10 * scale
    mean_left = np.einsum("n,nk->k", left["mass"][-1], left["v"][-1]) / np.sum(left["mass"][-1])
    assert mean_left[0] < -0.5                    # bounced back
    assert gap[-1] > gap.min() + 0.02              # and moving apart
    squeeze = result.probes["squeeze"]
    assert squeeze[:, 0].max() > 0.0 and np.all(np.abs(squeeze[:, 1]) < 1e-6 * squeeze[:, 0].max())   # mu = 0: normal only


# --------------------------------------------------------------------------- rigid bodies


def test_rigid_body_falls_freely():
    # x(t_n) = x0 + g dt^2 n (n + 1) / 2 for the explicit (symplectic Euler) update, i.e.
    # g t^2 / 2 + g dt t / 2: within one step's error of free fall; no rotation.
    scene = Scene(
        name="fall",
        grid=Grid(size=(1.0, 1.0), cell=0.05, boundaries=Boundaries("free", "free", "free", "free")),
        materials={"steel": LinearElastic(density=7800.0, young=2e11, poisson=0.3)},
        bodies=(Body("weight", "steel", Rectangle((0.4, 0.6), (0.6, 0.8)), kinematics=Kinematics("rigid")),),
        duration=0.2,
        dt=1e-3,
        output_every=0.05,
        probes=(Probe("drop", "body_displacement", body="weight"), Probe("turn", "body_rotation", body="weight")),
    )
    sim = Simulation(scene)
    probes = sim.probes()
    steps = np.arange(sim.steps + 1)
    exact = -G * sim.dt**2 * steps * (steps + 1) / 2.0
    np.testing.assert_allclose(np.asarray(probes["drop"][:, 1]), exact, rtol=1e-10, atol=1e-14)
    assert np.max(np.abs(np.asarray(probes["drop"][:, 0]))) < 1e-14
    assert np.max(np.abs(np.asarray(probes["turn"]))) < 1e-12
    motion = sim.final_state().rigid["weight"]
    assert float(motion.velocity[1]) == pytest.approx(-G * sim.steps * sim.dt, rel=1e-12)


def rigid_weight_near(edges, gravity, lower, *others):
    """The free-fall scene's rigid weight, its lower-left corner at `lower`, with `others` bodies."""
    return Scene(
        name="near_edge",
        grid=Grid(size=(1.0, 1.0), cell=0.05, boundaries=Boundaries(*edges)),
        materials={"steel": LinearElastic(density=7800.0, young=2e11, poisson=0.3)},
        bodies=(Body("weight", "steel", Rectangle(lower, (lower[0] + 0.2, lower[1] + 0.2)),
                     kinematics=Kinematics("rigid")), *others),
        gravity=gravity, duration=0.01, dt=1e-3, output_every=0.005,
    )


def test_a_rigid_body_on_a_held_grid_edge_that_gravity_pulls_it_into_is_refused():
    # rigid bodies ignore the grid-edge conditions (docs/physics.md section 12): standing on the
    # fixed bottom edge, the weight fell through it and left the grid after 231 steps
    with pytest.raises(SceneError, match=r"bodies\[0\] \('weight'\) is rigid and stands 0.02 m from the bottom "
                                         r"grid edge \(grid.boundaries.bottom = 'fixed'\)"):
        Simulation(rigid_weight_near(("slip", "slip", "fixed", "free"), (0.0, -G), (0.4, 0.02)))
    with pytest.raises(SceneError, match=r"the left grid edge \(grid.boundaries.left = 'slip'\)"):
        Simulation(rigid_weight_near(("slip", "slip", "free", "free"), (-3.0, -G), (0.0, 0.4)))
    # accepted: a free edge, an edge gravity does not pull it towards, a slab thinner than a cell
    # between it and the edge, or a cell of room (which the check does not judge: such a body
    # falls through all the same when nothing is below it)
    Simulation(rigid_weight_near(("slip", "slip", "free", "free"), (0.0, -G), (0.4, 0.0)))
    Simulation(rigid_weight_near(("slip", "slip", "fixed", "free"), (0.0, -G), (0.0, 0.4)))
    slab = Body("slab", "steel", Rectangle((0.0, 0.0), (1.0, 0.02)), kinematics=Kinematics("prescribed", velocity=(0.0, 0.0)))
    Simulation(rigid_weight_near(("slip", "slip", "fixed", "free"), (0.0, -G), (0.4, 0.02), slab))
    Simulation(rigid_weight_near(("slip", "slip", "fixed", "free"), (0.0, -G), (0.4, 0.05)))


def test_rigid_body_comes_to_rest_on_sand():
    # A rigid footing on a sand layer: at equilibrium the sand carries its weight (contact
    # force = weight) and it stops. Local damping speeds up the approach to rest.
    scene = Scene(
        name="footing",
        grid=Grid(size=(0.6, 0.4), cell=0.02, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={
            "sand": DruckerPrager(density=1800.0, young=5e6, poisson=0.3, friction_angle=35.0),
            "steel": LinearElastic(density=7800.0, young=2e11, poisson=0.3),
        },
        bodies=(
            Body("sand", "sand", Rectangle((0.0, 0.0), (0.6, 0.2)), initial_stress=Geostatic("jaky")),
            Body("footing", "steel", Rectangle((0.2, 0.2), (0.4, 0.24)), kinematics=Kinematics("rigid")),
        ),
        contacts=(Contact(("sand", "footing"), 0.5),),
        duration=0.15,
        output_every=0.05,
        numerics=Numerics(shape="linear", ppc=2, transfer="apic", damping=0.2),
        probes=(
            Probe("bearing", "contact_force", pair=("sand", "footing")),
            Probe("settlement", "body_displacement", body="footing"),
        ),
    )
    sim = Simulation(scene)
    probes, final = sim.probes_and_final_state()
    weight = 7800.0 * 0.2 * 0.04 * G
    late = slice(int(0.8 * sim.steps), None)
    bearing = np.asarray(probes["bearing"][late]).mean(axis=0)
    assert bearing[1] == pytest.approx(weight, rel=0.02)
    assert abs(bearing[0]) < 0.02 * weight
    settlement = np.asarray(probes["settlement"][:, 1])
    assert settlement[-1] < 0.0                   # it pressed into the sand ...
    assert abs(float(final.rigid["footing"].velocity[1])) < 2e-3    # ... and stopped
    assert np.ptp(settlement[late]) < 0.05 * abs(settlement[-1])


def bonded_plate(duration=0.3):
    """A rigid plate (1000 kg/m^3, 0.05 x 0.2 m) launched at 0.2 m/s, bonded (no contact pair)
    to a soft block (2000 kg/m^3, 0.3 x 0.2 m, E = 1 MPa) at rest, no gravity, bspline2 + APIC."""
    return Scene(
        name="drag",
        grid=Grid(size=(1.0, 0.6), cell=0.05, boundaries=Boundaries("free", "free", "free", "free")),
        materials={"soft": LinearElastic(density=2000.0, young=1e6, poisson=0.3),
                   "plate": LinearElastic(density=1000.0, young=1e9, poisson=0.3)},
        bodies=(
            Body("block", "soft", Rectangle((0.3, 0.2), (0.6, 0.4))),
            Body("plate", "plate", Rectangle((0.6, 0.2), (0.65, 0.4)), velocity=(0.2, 0.0),
                 kinematics=Kinematics("rigid")),
        ),
        gravity=(0.0, 0.0),
        duration=duration,
        output_every=0.01,
        numerics=Numerics(shape="bspline2", transfer="apic"),
        probes=(Probe("plate", "body_displacement", body="plate"),),
    )


def test_a_rigid_plate_bonded_to_a_lighter_block_drags_it_along():
    # No gravity, nothing else touching: a rigid plate launched at v0, bonded (no contact
    # pair) to a block at rest that outweighs it 12:1, on bspline2 (the wide stencil on which
    # predicting the bonded force from the last step diverged). Momentum is kept exactly,
    # M V + sum m_p v_p = M v0, and the two move on together at M v0 / (M + m) (perfectly
    # inelastic impact), the plate oscillating about it as the block rings.
    sim = Simulation(bonded_plate())
    probes, state = sim.probes_and_final_state()
    plate, block = 1000.0 * 0.05 * 0.2, 2000.0 * 0.3 * 0.2
    particles = state.particles
    free = sim.structure.bodies[0].points
    momentum = plate * np.asarray(state.rigid["plate"].velocity) + np.asarray(
        particles.mass[free]) @ np.asarray(particles.v[free])
    np.testing.assert_allclose(momentum, [plate * 0.2, 0.0], rtol=0, atol=1e-10 * plate * 0.2)
    shift = np.asarray(probes["plate"][:, 0])
    times = sim.dt * np.arange(len(shift))
    late = times >= 0.1
    speed = np.polyfit(times[late], shift[late], 1)[0]
    assert speed == pytest.approx(plate * 0.2 / (plate + block), rel=0.05)


def test_a_rigid_plate_moves_by_the_impulses_the_step_gives_it():
    # A prescribed plate, speeding up, pushes two thin soft blocks (one cell thick, quadratic
    # B-splines, no gravity), bonded to each other (no pair between them), against a rigid
    # plate at rest that meets both across their seam. The step applies the pusher's contacts
    # first, then the bond, then the plate's contacts; the plate's motion must be solved with
    # the impulses the step then gives it: M V = sum_steps F dt, F the contact-force probes.
    # Solved from the blocks' trial velocities, before the bond, a wall on a foundation and
    # its backfill moved with impulses the sand never got and crept on (docs/convergence.md);
    # solved with the pusher at its grid velocity (its points' velocity of the step before)
    # instead of its path velocity, the plate took a third of what it was given.
    scene = dataclasses.replace(
        bonded_plate(duration=0.03),
        bodies=(Body("pusher", "plate", Rectangle((0.25, 0.2), (0.3, 0.4)),
                     kinematics=Kinematics("prescribed", ((0.0, 0.0), (1.0, 0.0)), (0.0, 0.03))),
                Body("lower", "soft", Rectangle((0.3, 0.2), (0.35, 0.3))),
                Body("upper", "soft", Rectangle((0.3, 0.3), (0.35, 0.4))),
                Body("plate", "plate", Rectangle((0.35, 0.2), (0.4, 0.4)), kinematics=Kinematics("rigid"))),
        contacts=tuple(Contact((block, other), friction=0.4) for block in ("lower", "upper") for other in ("pusher", "plate")),
        probes=(Probe("lower", "contact_force", pair=("lower", "plate")),
                Probe("upper", "contact_force", pair=("upper", "plate"))),
    )
    sim = Simulation(scene)
    assert [interface.contact for interface in sim.structure.interfaces] == [
        "lower/pusher", "upper/pusher", None, "lower/plate", "upper/plate"]
    probes, state = sim.probes_and_final_state()
    mass = 1000.0 * 0.05 * 0.2
    momentum = mass * np.asarray(state.rigid["plate"].velocity)
    received = sim.dt * np.sum(np.asarray(probes["lower"]) + np.asarray(probes["upper"]), axis=0)
    assert momentum[0] > 0.1 * mass * 0.5      # pushed along
    np.testing.assert_allclose(momentum, received, rtol=0, atol=1e-10 * abs(momentum[0]))


def test_bonded_rigid_plate_gradients_match_finite_differences():
    # Reverse mode through the bonded rigid-body solve (bodies.solve_rigid_motions): the
    # plate's mean displacement over 0.05 s against the block's stiffness and the plate's own
    # density (its mass M in the 3 x 3 system), central differences with relative step 1e-6.
    sim = Simulation(bonded_plate(duration=0.05))

    def loss(probes):
        return jnp.mean(probes["plate"][:, 0])

    reverse_mode_against_central_differences(sim, loss, [
        ("soft.young", 1e6, ("materials", "soft", "young")),
        ("plate.density", 1000.0, ("materials", "plate", "density")),
    ], rel=1e-5)


def test_a_light_rigid_footing_bonded_to_sand_comes_to_rest():
    # A rigid footing ten times lighter than the sand it is bonded to (no contact pair),
    # off-centre so that it may turn, released on bspline2: before the bonded interface was
    # solved with the body (bodies.solve_rigid_motions) this left the grid within 14 steps.
    # It settles and stops: velocity and spin decay, sideways motion stays a fraction of the
    # settlement.
    scene = Scene(
        name="footing",
        grid=Grid(size=(0.6, 0.3), cell=0.025, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={
            "sand": DruckerPrager(density=1800.0, young=2e6, poisson=0.3, friction_angle=30.0),
            "block": LinearElastic(density=2000.0, young=5e7, poisson=0.2),
        },
        bodies=(
            Body("sand", "sand", Rectangle((0.0, 0.0), (0.6, 0.15)), initial_stress=Geostatic("jaky")),
            Body("footing", "block", Rectangle((0.1, 0.15), (0.2, 0.2)), kinematics=Kinematics("rigid")),
        ),
        duration=0.3,
        output_every=0.05,
        numerics=Numerics(shape="bspline2", transfer="apic", damping=0.1),
        probes=(Probe("settlement", "body_displacement", body="footing"),
                Probe("turn", "body_rotation", body="footing")),
    )
    sim = Simulation(scene)
    probes, final = sim.probes_and_final_state()
    motion = final.rigid["footing"]
    settlement = np.asarray(probes["settlement"])[:: sim.steps_per_output]      # at the output times
    assert settlement[-1, 1] < 0.0
    assert np.max(np.abs(settlement[:, 0])) < 0.2 * abs(settlement[-1, 1])
    assert float(np.linalg.norm(motion.velocity)) < 1e-3
    assert abs(float(motion.spin)) < 1e-2


# --------------------------------------------------------------------------- active earth pressure


def active_wall(cell=0.025, friction=0.0, duration=0.3, speed=0.005, friction_angle=30.0, hold=0.05, output_every=0.05):
    """A prescribed wall moving away from a level sand backfill (0.5 m high) in its geostatic
    K0 state, smooth base (slip) so that the whole backfill can reach Rankine's active state.
    The plane-strain cone m = sqrt(3) sin(phi) makes Drucker-Prager match Mohr-Coulomb at phi
    in plane strain, so Ka uses phi itself."""
    table = ((0.0, 0.0), (0.0, 0.0), (-speed, 0.0), (-speed, 0.0))
    return Scene(
        name="active",
        grid=Grid(size=(2.0, 0.75), cell=cell, boundaries=Boundaries("slip", "slip", "slip", "free")),
        materials={
            "sand": DruckerPrager(density=1800.0, young=10e6, poisson=0.3, friction_angle=friction_angle,
                                  cone="plane_strain"),
            "concrete": LinearElastic(density=2400.0, young=30e9, poisson=0.2),
        },
        bodies=(
            Body("backfill", "sand", Rectangle((0.3, 0.0), (2.0, 0.5)), initial_stress=Geostatic("jaky")),
            Body("wall", "concrete", Rectangle((0.2, 0.0), (0.3, 0.6)),
                 kinematics=Kinematics("prescribed", table, (0.0, hold, hold + 0.01, 10.0))),
        ),
        contacts=(Contact(("backfill", "wall"), friction),),
        duration=duration,
        output_every=output_every,
        numerics=Numerics(shape="linear", ppc=2, transfer="apic"),
        probes=(Probe("thrust", "contact_force", pair=("backfill", "wall")), Probe("push", "reaction", body="wall")),
    )


def earth_pressures(friction_angle=30.0, wall_friction=0.0, height=0.5, density=1800.0):
    """(1/2 K0 rho g H^2, Rankine's, Coulomb's horizontal component) [N/m]."""
    phi, delta = math.radians(friction_angle), math.atan(wall_friction)
    weight = 0.5 * density * G * height**2
    rankine = (1 - math.sin(phi)) / (1 + math.sin(phi))
    coulomb = math.cos(phi) ** 2 / (
        math.cos(delta) * (1 + math.sqrt(math.sin(phi + delta) * math.sin(phi) / math.cos(delta))) ** 2
    )
    return weight * (1 - math.sin(phi)), weight * rankine, weight * coulomb * math.cos(delta)


FACES = {"back": (-1.0, 0.0), "base": (0.0, 1.0), "front": (1.0, 0.0), "top": (0.0, -1.0)}


def test_a_contact_force_splits_into_the_faces_of_a_wall_and_its_gradients_match_finite_differences():
    # The rigid wall of tests/test_convergence.py (a wall on a sand foundation holding a
    # backfill behind it, released at t = 0) over its first 0.04 s, with the force of the sand
    # on it read whole and by face (`facing`: nodes whose normal, sand into wall, lies within
    # 45 degrees of the direction). The four faces partition the contact; the back carries the
    # backfill's push towards the open side, the base the wall's weight, and the front and top,
    # where there is no sand, nothing.
    # Reverse mode through the rigid wall's Newton solve (its derivative is the implicit
    # function theorem's, bodies.solve_rigid_motions), the transfer memory, the points kept
    # outside its outline and the stress substeps (a loop of K Perzyna solves in each step,
    # whose roots a checkpointed step keeps: K values a point), the backfill viscoplastic: the
    # wall top's mean displacement over a short release (its first 0.02 s, the first output
    # interval: the same steps as a run of 0.02 s) against the sand's friction angle, fluidity
    # and exponent and the wall friction, central differences with relative step 1e-6. One
    # scene for all, so the program that runs it is compiled once for the reads and the
    # differences.
    from jaxmpm.physics.solver import kept_solve_bytes
    from tests.test_convergence import small_wall

    scene = small_wall(duration=0.04).with_value("numerics.stress_substeps", 3)
    scene = dataclasses.replace(scene, materials={
        **scene.materials, "sand": dataclasses.replace(scene.materials["sand"], fluidity=0.5, exponent=3.0)})
    faces = tuple(Probe(name, "contact_force", pair=("sand", "wall"), facing=direction) for name, direction in FACES.items())
    probes = (Probe("whole", "contact_force", pair=("sand", "wall")),
              Probe("back_read_backwards", "contact_force", pair=("wall", "sand"), facing=(3.0, 0.0))) + faces
    wall_top = dataclasses.replace(scene.probes[0], name="wall_top")         # "top" names a face here
    sim = Simulation(dataclasses.replace(scene, probes=probes + (wall_top,)))
    sand_points = sim.body_slices[0][1] - sim.body_slices[0][0]
    assert kept_solve_bytes(sim.structure, np.float64) == 3 * sand_points * 8
    force = {name: np.asarray(history) for name, history in sim.probes().items()}
    whole = force["whole"]
    np.testing.assert_allclose(sum(force[name] for name in FACES), whole, rtol=0, atol=1e-9 * np.abs(whole).max())
    np.testing.assert_array_equal(force["back_read_backwards"], -force["back"])    # the wall on the sand
    assert not np.any(force["front"]) and not np.any(force["top"])
    settled = sim.time > 0.015          # after the first contact's transient
    back = force["back"][settled].mean(axis=0)
    assert back[0] < 0.0 and abs(back[1]) <= 0.4 * -back[0]     # towards -x, within Coulomb's mu = 0.4
    weight = 2400.0 * G * 0.05 * 0.35
    assert force["base"][settled, 1].mean() > 0.9 * weight
    with pytest.raises(SceneError, match=r"probes\[2\]\.facing = \[0\.0, 0\.0\] has no direction"):
        dataclasses.replace(scene, probes=probes[:2] + (dataclasses.replace(faces[0], facing=(0.0, 0.0)),))

    release = sim.steps_per_output + 1          # t = 0 ... 0.02 s
    assert sim.time[release - 1] == pytest.approx(0.02)
    reverse_mode_against_central_differences(sim, lambda probes: probes["wall_top"][:release, 0].mean(), [
        ("sand.friction_angle", 30.0, ("materials", "sand", "friction_angle")),
        ("sand.fluidity", 0.5, ("materials", "sand", "fluidity")),
        ("sand.exponent", 3.0, ("materials", "sand", "exponent")),
        ("sand/wall.friction", 0.4, ("contacts", "sand/wall", "friction")),
    ], rel=1e-4)


@pytest.mark.parametrize("kinematics, substeps", [("rigid", None), ("free", "auto")])
def test_a_walls_flat_back_face_carries_no_more_friction_than_coulomb_allows(kinematics, substeps):
    # Coulomb: a flat face turned by theta carries a force whose parts along and across the
    # (untilted) face obey |F_y| / |F_x| <= (mu + tan theta) / (1 - mu tan theta). The small
    # wall turns several degrees in 0.2 s and the backfill slides down its back. With the
    # mass-weighted mean normal alone, a node beside the face where the sand parts from the
    # wall took the sand's slanted normal, and the back face pulled the wall down with 0.59
    # of its push against a bound of 0.44 at 0.15 s (0.77 against 0.47 at 0.2 s;
    # docs/contact.md). Held in the wall's normal cone: at the bound, as sliding must be. The
    # free wall (E = 3 GPa, subcycled at the sand's step) meets the sand with the cone of its
    # points' best-fit motion; with the mean normal alone it too passed the bound (0.58
    # against 0.44 at 0.15 s).
    from tests.test_convergence import small_wall

    mu, window = 0.4, 0.05
    scene = small_wall(kinematics, young=3.0e9, duration=0.2, substeps=substeps)
    probes = (Probe("back", "contact_force", pair=("sand", "wall"), facing=(-1.0, 0.0)),
              Probe("rotation", "body_rotation", body="wall"))
    sim = Simulation(dataclasses.replace(scene, probes=probes))
    force, rotation = (np.asarray(history) for history in sim.probes().values())
    assert abs(rotation[-1, 0]) > math.radians(3.0)        # a large turn, sliding sand
    for end in (0.15, 0.2):
        inside = (sim.time > end - window) & (sim.time <= end)
        mean = force[inside].mean(axis=0)
        tilt = math.tan(abs(rotation[inside, 0].mean()))
        assert abs(mean[1] / mean[0]) <= 1.02 * (mu + tilt) / (1.0 - mu * tilt), (end, mean)


def test_a_subcycled_wall_reads_its_faces_and_its_gradients_match_finite_differences():
    # A subcycled body steps alone between the scene's steps (physics/subcycling.py), with no
    # contact of its own: the faces are read in the scene's step. Before its lone step dropped
    # them, a face probe on a subcycled wall failed while tracing.
    # Reverse mode through the subcycled wall's two passes of substeps and the contact solve it
    # starts from: the wall top's mean displacement over a short release against the wall's
    # stiffness (read only inside the substeps), its density and the wall friction, central
    # differences with relative step 1e-6. One scene for both (the face probes only read the
    # run; the loss reads the wall top alone), so the program that runs it is compiled once for
    # the reads and the differences (two tests: 97 s of CPU, most of it compiling; one: 88 s).
    # The wall is the 3 GPa one of the back-face test above, 20 substeps a step: at 30 GPa (61
    # substeps) the same checks ran the substeps three times as long (54 s of CPU against 44 s).
    from tests.test_convergence import small_wall

    scene = small_wall("free", young=3.0e9, substeps="auto", duration=0.02)
    faces = tuple(Probe(name, "contact_force", pair=("sand", "wall"), facing=direction) for name, direction in FACES.items())
    wall_top = dataclasses.replace(scene.probes[0], name="wall_top")         # "top" names a face here
    sim = Simulation(dataclasses.replace(scene, probes=(wall_top, Probe("whole", "contact_force", pair=("sand", "wall")))
                                         + faces))
    force = {name: np.asarray(history) for name, history in sim.probes().items()}
    np.testing.assert_allclose(sum(force[name] for name in FACES), force["whole"], rtol=0,
                               atol=1e-9 * np.abs(force["whole"]).max())
    assert force["back"][-10:, 0].mean() < 0.0                  # the backfill pushes towards -x

    reverse_mode_against_central_differences(sim, lambda probes: probes["wall_top"][:, 0].mean(), [
        ("concrete.young", 3.0e9, ("materials", "concrete", "young")),
        ("concrete.density", 2400.0, ("materials", "concrete", "density")),
        ("sand/wall.friction", 0.4, ("contacts", "sand/wall", "friction")),
    ], rel=1e-4)


@pytest.mark.slow
def test_wall_thrust_falls_from_k0_to_rankine_and_below_with_wall_friction():
    # Smooth wall: before it moves the backfill holds it with 1/2 K0 rho g H^2 (K0 = 1 - sin
    # phi, Jaky); after ~1.2 mm (0.24 % of H) the thrust has fallen to Rankine's active
    # 1/2 Ka rho g H^2. Resolution study (benchmarks/contact_study.py, docs/contact.md): at
    # cells 0.025 / 0.0125 m the at-rest thrust is -0.2 / -0.0 % off K0 and the active one
    # +1.9 / +2.4 % off Rankine (the rest of the fall is still under way), hence 1 % and 4 %.
    at_rest, rankine, coulomb = earth_pressures(wall_friction=0.4)
    scene = active_wall()
    back = Probe("back", "contact_force", pair=("backfill", "wall"), facing=(-1.0, 0.0))
    sim = Simulation(dataclasses.replace(scene, probes=scene.probes + (back,)))
    probes = sim.probes()
    thrust = np.asarray(probes["thrust"])
    late = sim.time > sim.time[-1] - 0.05
    smooth = -thrust[late, 0].mean()
    holding = (sim.time > 0.01) & (sim.time < 0.05)
    assert -thrust[holding, 0].mean() == pytest.approx(at_rest, rel=0.01)
    # the wall's back face alone (the `facing` probe) carries the same: only the foot's node differs
    assert -np.asarray(probes["back"])[holding, 0].mean() == pytest.approx(at_rest, rel=0.01)
    assert smooth == pytest.approx(rankine, rel=0.04)
    # mu = 0: no shear on the wall; only at the node of the wall's foot (the corner of its
    # normal field, on the slip base) does the normal tilt: 2.3 N/m of 750 measured
    assert abs(thrust[late, 1].mean()) < 0.01 * smooth
    # Rough wall, mu = tan(delta) = 0.4: the settling backfill hangs on the wall (it drags it
    # down, with at most mu times the normal force), which lowers the horizontal thrust, but
    # not below Coulomb's active value for a fully mobilised delta. The friction is a
    # parameter: the same compiled run as the smooth wall's, with mu = 0.4.
    thrust = np.asarray(sim.probes(with_values(sim.params, {"backfill/wall.friction": 0.4}))["thrust"])
    rough, drag = -thrust[late, 0].mean(), -thrust[late, 1].mean()
    assert coulomb < rough < smooth
    assert 0.0 < drag <= 0.4 * rough


# --------------------------------------------------------------------------- gradients


def small_active_wall(friction=0.3, duration=0.05):
    """A coarse, short active-wall scene: the wall starts moving at once, faster."""
    return active_wall(cell=0.05, friction=friction, duration=duration, speed=0.05, hold=0.001, output_every=duration)


def small_active_wall_read_behind():
    """The small active wall with its back face also read alone (`facing`): the scene of the
    gradient check below, and of the tests after it that only need some short run of a
    contact scene, so that one compiled program runs them all."""
    scene = small_active_wall()
    back = Probe("back", "contact_force", pair=("backfill", "wall"), facing=(-1.0, 0.0))
    return dataclasses.replace(scene, probes=scene.probes + (back,))


def test_thrust_and_reaction_gradients_match_finite_differences():
    # One reverse-mode gradient (as calibration computes it) of the mean thrust and reaction
    # over a rollout in which the wall starts to leave (closing speed 0, then separation,
    # zero tangential velocity at first), the sand goes plastic and slides along the rough
    # wall, and most nodes of each field are empty: every entry of the whole parameter pytree
    # is finite, and d/d(phi, mu) matches central differences (relative step 1e-6, float64;
    # docs/validation.md §8). The back face read alone (`facing`) is in the loss too.
    sim = Simulation(small_active_wall_read_behind())
    late = sim.time > 0.03

    def loss(probes):
        return (probes["thrust"][late, 0].mean() + probes["thrust"][late, 1].mean() + probes["push"][late, 0].mean()
                + 0.5 * probes["back"][late, 1].mean())

    reverse_mode_against_central_differences(sim, loss, [
        ("sand.friction_angle", 30.0, ("materials", "sand", "friction_angle")),
        ("backfill/wall.friction", 0.3, ("contacts", "backfill/wall", "friction")),
    ], rel=1e-4)


# --------------------------------------------------------------------------- structure and parameters


def test_fields_and_parameters_follow_the_scene():
    sim = Simulation(small_active_wall())
    assert sim.structure.fields == 2 and len(sim.structure.interfaces) == 1
    assert set(sim.params) == {"materials", "contacts", "bodies", "scene"}
    assert sim.params["contacts"] == {"backfill/wall": {"friction": 0.3}}
    assert sim.params["bodies"]["wall"]["velocity"].shape == (4, 2)
    single = Simulation(dataclasses.replace(sliding_block(30.0, 0.3), contacts=(), probes=(),
                                            bodies=(sliding_block(30.0, 0.3).bodies[1],)))
    assert single.structure.fields == 1 and single.structure.interfaces == ()
    assert set(single.params) == {"materials", "scene"}


def test_scenes_with_several_fields_compile_with_their_options_and_the_same_numbers():
    # jaxmpm.kernels.xla_options: programs of scenes with several velocity fields are compiled with
    # XLA's region-analysis copy insertion (docs/benchmarks.md). It must change no number
    # (it removes copies only). One-field scenes keep XLA's defaults.
    from jaxmpm.kernels.xla_options import accepted, compiler_options

    single = Simulation(dataclasses.replace(sliding_block(30.0, 0.3), contacts=(), probes=(),
                                            bodies=(sliding_block(30.0, 0.3).bodies[1],)))
    assert not single.several_fields and single.compiler_options() == {}
    sim = Simulation(sliding_block(30.0, 0.3, duration=0.02, shape="linear"))
    assert sim.several_fields
    assert sim.compiler_options(reverse_mode=True) == compiler_options(reverse_mode=True, several_fields=True)
    if not accepted("region_analysis"):
        pytest.skip("this jaxlib does not accept the option")

    def loss(friction):
        probes = sim.probes(with_values(sim.params, {"block/slab.friction": friction}))
        return jnp.sum(probes["move"][:, 0]) + jnp.sum(probes["load"])

    for program, reverse_mode in ((loss, False), (jax.grad(loss), True)):
        plain = jax.jit(program, compiler_options=compiler_options(reverse_mode=reverse_mode) or None).lower(0.3).compile()
        tuned = jax.jit(program, compiler_options=sim.compiler_options(reverse_mode)).lower(0.3).compile()
        assert float(tuned(0.3)) == float(plain(0.3))


def test_unpaired_bodies_are_bonded_to_paired_ones():
    # A foundation that is in no pair shares field 0; the backfill and the wall get their own.
    # The foundation is bonded (no slip) to both, the pair is in frictional contact, in the
    # pair's own order (its impulse acts on the backfill). The prescribed wall's own normal is used.
    scene = small_active_wall()
    foundation = Body("foundation", "sand", Rectangle((0.0, 0.0), (2.0, 0.1)))
    backfill = dataclasses.replace(scene.bodies[0], region=Rectangle((0.3, 0.1), (2.0, 0.5)))
    wall = dataclasses.replace(scene.bodies[1], region=Rectangle((0.2, 0.1), (0.3, 0.6)))
    field, count, interfaces = velocity_fields(dataclasses.replace(scene, bodies=(foundation, wall, backfill)))
    assert field == {"foundation": 0, "wall": 1, "backfill": 2} and count == 3
    assert interfaces == (
        Interface(0, 1, None, kinematic_second=True, normal_from=1),
        Interface(0, 2, None),
        Interface(2, 1, "backfill/wall", kinematic_second=True, normal_from=1),
    )


def test_friction_changes_do_not_recompile(count_step_traces):
    sim = Simulation(small_active_wall_read_behind())
    traces = count_step_traces(sim)
    for friction in (0.1, 0.2, np.float64(0.5), jnp.asarray(0.7)):
        sim.probes(with_values(sim.params, {"backfill/wall.friction": friction}))["thrust"].block_until_ready()
    assert len(traces) == 1


def test_a_prescribed_velocity_beyond_the_time_step_is_refused():
    # The scene's time step keeps every body within a cell per step; a faster prescribed
    # velocity passed later as a parameter is one clear error, not a broken run.
    sim = Simulation(small_active_wall_read_behind())
    fast = np.asarray(sim.params["bodies"]["wall"]["velocity"]) * 0.0
    fast[2:, 0] = -2.0 * sim.scene.grid.cell / sim.dt
    with pytest.raises(SceneError, match=r"params\['bodies'\]\['wall'\]\['velocity'\] reaches"):
        sim.probes(with_values(sim.params, {"bodies.wall.velocity": fast}))
    sim.check_time_step(sim.cast(sim.params))            # the scene's own values pass
    # A velocity table written as nested lists, as in a scene file, is the same value.
    table = [list(row) for row in np.asarray(sim.params["bodies"]["wall"]["velocity"])]
    listed = with_values(sim.params, {"bodies.wall.velocity": table})
    np.testing.assert_array_equal(sim.probes(listed)["thrust"], sim.probes()["thrust"])


def test_calibration_names_reach_contact_friction():
    from inverse.parameters import ParameterSpace

    sim = Simulation(small_active_wall())
    space = ParameterSpace(sim.params, {"backfill/wall.friction": (0.0, 1.0), "materials.sand.friction_angle": (20, 40)})
    params = space.insert(jnp.asarray([0.45, 33.0]))
    assert float(params["contacts"]["backfill/wall"]["friction"]) == 0.45
    assert float(params["materials"]["sand"]["friction_angle"]) == 33.0
    assert sim.params["contacts"]["backfill/wall"]["friction"] == 0.3           # the template is untouched
    with pytest.raises(SceneError, match="not a single number"):
        ParameterSpace(sim.params, {"bodies.wall.velocity": (-1, 1)})
    with pytest.raises(SceneError, match="is not a parameter of the scene"):
        ParameterSpace(sim.params, {"backfill/wall.frction": (0, 1)})


def test_dotted_names_address_contacts_and_bodies():
    scene = small_active_wall()
    assert scene.with_value("contacts.backfill/wall.friction", 0.5).contacts[0].friction == 0.5
    assert scene.with_value("backfill/wall.friction", 0.6).contacts[0].friction == 0.6
    table = [[0.0, 0.0], [0.0, 0.0], [-0.01, 0.0], [-0.01, 0.0]]
    moved = scene.with_value("bodies.wall.velocity", table)
    assert moved.bodies[1].kinematics.velocity[2] == (-0.01, 0.0)
    assert scene.with_value("sand.friction_angle", 33.0).materials["sand"].friction_angle == 33.0
    assert Scene.from_toml(scene.to_toml()) == scene


# --------------------------------------------------------------------------- bad input


BAD = [
    (lambda s: dataclasses.replace(s, contacts=(Contact(("backfill", "pile"), 0.3),)), "'pile', which is not a body"),
    (lambda s: dataclasses.replace(s, contacts=(Contact(("wall", "wall"), 0.3),)), "pairs body 'wall' with itself"),
    (lambda s: dataclasses.replace(s, contacts=(Contact(("backfill", "wall"), -0.1),)), r"contacts\[0\].friction = -0.1"),
    (lambda s: dataclasses.replace(s, bodies=(s.bodies[0], dataclasses.replace(
        s.bodies[1], kinematics=Kinematics("prescribed", ((0, 0), (0, -1)), (0.0, 0.0))))),
     "must start at 0 and increase strictly"),
    (lambda s: dataclasses.replace(s, materials={**s.materials, "concrete": LinearElastic(0.0, 30e9, 0.2)}),
     r"materials.concrete.density = 0.0"),
    (lambda s: dataclasses.replace(s, bodies=(s.bodies[0], dataclasses.replace(s.bodies[1], kinematics=Kinematics("prescribed")))),
     "a prescribed body needs its velocity"),
    (lambda s: dataclasses.replace(s, probes=(Probe("r", "reaction", body="backfill"),)), "is free, not prescribed"),
    (lambda s: dataclasses.replace(s, bodies=(s.bodies[0], dataclasses.replace(s.bodies[1], initial_stress=Geostatic(0.5)))),
     "initial_stress is given for a prescribed body"),
    (lambda s: dataclasses.replace(s, probes=(Probe("f", "contact_force", pair=("wall", "nothing")),)), "is not a pair of"),
]


@pytest.mark.parametrize("change, message", BAD)
def test_bad_contact_and_kinematics_input_is_one_clear_error(change, message):
    with pytest.raises(SceneError, match=message):
        change(small_active_wall())


def test_rigid_body_without_mass_is_refused_by_the_command(tmp_path):
    text = small_active_wall().to_dict()
    text["bodies"][1]["kinematics"] = {"type": "rigid"}
    text["materials"]["concrete"]["density"] = 0.0
    text["probes"] = [text["probes"][0]]
    path = tmp_path / "rigid.toml"
    path.write_text(tomli_w.dumps(text))
    run = subprocess.run([sys.executable, "-m", "jaxmpm.cli", "run", str(path), "-o", str(tmp_path / "out.h5")],
                         capture_output=True, text=True)
    assert run.returncode == 2
    assert "materials.concrete.density = 0.0" in run.stderr and "Traceback" not in run.stderr
