"""numerics.structure_hold = "points": a prescribed or rigid body pushes the soil's points out of
its outline (`jaxmpm.physics.point_contact`) instead of holding the nodes it shares with them.

Sources: one-dimensional (oedometric) elastic compression, u = q H / M with the constrained
modulus M = E (1 - nu) / ((1 + nu)(1 - 2 nu)), plus the contact layer's own compliance q s / (4 E)
(the module's docstring); a rigid strip footing turned on an elastic half-space, M = pi E' a^2
theta / 4 (K. L. Johnson, Contact Mechanics, 1985, ch. 2), the same check as
benchmarks/wall_base_study.py rocking; the converged reference of a step is the same scene at
half the step; gradients against central differences.
"""

import dataclasses
import math

import numpy as np
import pytest

from jaxmpm import (
    Body, Boundaries, Contact, Geostatic, Grid, Kinematics, LinearElastic, Numerics, Probe, Rectangle, Scene,
    SceneError, Simulation,
)
from jaxmpm.physics.bodies import seeded_outline
from jaxmpm.scene import Polygon
from tests.test_convergence import points_inside_punch, punch, small_wall, wall_top

G = 9.81


def with_points(scene):
    return scene.with_value("numerics.structure_hold", "points")


def test_a_seeded_outline_is_the_outline_of_the_points_squares():
    # A rectangle whose edges fall between the lattice's rows: each edge moves to the outermost
    # points' squares (side s). A turned square: every point's square lies inside the moved
    # outline and the outermost touches each edge.
    spacing = 0.01
    lattice = np.stack(np.meshgrid(np.arange(-0.3, 0.3, spacing) + 0.5 * spacing,
                                   np.arange(-0.3, 0.3, spacing) + 0.5 * spacing, indexing="ij"), axis=-1).reshape(-1, 2)
    rectangle = ((0.013, 0.021), (0.147, 0.021), (0.147, 0.088), (0.013, 0.088))
    inside = lattice[(lattice[:, 0] > 0.013) & (lattice[:, 0] < 0.147) & (lattice[:, 1] > 0.021) & (lattice[:, 1] < 0.088)]
    moved = np.asarray(seeded_outline(rectangle, inside, spacing))
    np.testing.assert_allclose(moved, [[0.01, 0.02], [0.15, 0.02], [0.15, 0.09], [0.01, 0.09]], atol=1e-12)

    turn = 0.4
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    square = np.array([[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]]) @ rotation.T
    normals = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]) @ rotation.T
    inside = lattice[np.all(np.einsum("pkd,kd->pk", lattice[:, None, :] - square[None], normals) < 0.0, axis=1)]
    moved = np.asarray(seeded_outline(tuple(map(tuple, square)), inside, spacing))
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.5 * spacing           # of each point's square
    reach = np.einsum("pckd,kd->pck", (inside[:, None, :] + corners)[:, :, None, :] - moved[None, None], normals)
    assert np.max(reach) < 1e-12                                   # every square inside the moved outline
    np.testing.assert_allclose(np.max(reach, axis=(0, 1)), 0.0, atol=1e-12)   # the outermost on each edge


def slab_on_layer(hold="points", cell=0.025):
    """A rigid slab (0.05 m, 2400 kg/m^3) over the whole width of a 0.1 m elastic layer in its
    geostatic state, between slip edges: one-dimensional compression under the slab's weight."""
    layer = LinearElastic(density=1800.0, young=5.0e6, poisson=0.3)
    return Scene(
        name="oedometer",
        grid=Grid(size=(0.2, 0.2), cell=cell, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={"soil": layer, "concrete": LinearElastic(density=2400.0, young=3.0e10, poisson=0.2)},
        bodies=(Body("layer", "soil", Rectangle((0.0, 0.0), (0.2, 0.1)), initial_stress=Geostatic(0.3 / 0.7)),
                Body("slab", "concrete", Rectangle((0.0, 0.1), (0.2, 0.15)), kinematics=Kinematics("rigid"))),
        contacts=(Contact(("layer", "slab"), 0.4),),
        duration=0.15, cfl=0.4, output_every=0.01,
        numerics=Numerics(shape="bspline2", transfer="apic", ppc=2, relaxation=10.0, damping=0.3, structure_hold=hold),
        probes=(Probe("slab", "body_displacement", body="slab"),),
    )


def test_a_slab_settles_on_an_elastic_layer_as_one_dimensional_compression_says():
    # q = 2400 * 9.81 * 0.05 = 1177 Pa on H = 0.1 m, M = 6.73 MPa: u = 17.5 um, and the contact
    # layer (s / 4 thick, as stiff as E) adds q s / (4 E) = 0.74 um at s = 12.5 mm, 0.37 um at
    # half the cell: the slab's settlement (the mean over the last 0.05 s, damped) is that sum.
    # Measured 18.38 and 18.08 um against 18.23 and 17.86 (under the node hold 15.05 and 16.22:
    # the slab held the sand a cell below its base).
    q, height = 2400.0 * G * 0.05, 0.1
    young, poisson = 5.0e6, 0.3
    constrained = young * (1.0 - poisson) / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    for cell in (0.025, 0.0125):
        sim = Simulation(slab_on_layer(cell=cell))
        settled = -np.mean(np.asarray(sim.probes()["slab"])[-sim.steps // 3:, 1])
        expected = q * height / constrained + q * (0.5 * cell) / (4.0 * young)
        assert settled == pytest.approx(expected, rel=0.03), (cell, settled, expected)


def test_a_released_rigid_wall_under_the_points_hold_moves_the_same_at_half_the_step():
    # The small wall of tests/test_convergence.py (released, tilting forward on its toe into a
    # rate-independent backfill) with structures pushing points: within 1 % at every output
    # once it has moved a millimetre.
    coarse, fine = (wall_top(with_points(small_wall(cfl=cfl))) for cfl in (0.4, 0.2))
    moving = np.abs(fine) > 1e-3
    assert moving.sum() >= 4
    assert np.max(np.abs(coarse - fine)[moving] / np.abs(fine)[moving]) < 0.01


def test_no_sand_point_ends_inside_a_punch_pushing_points(monkeypatch):
    # The punch of tests/test_convergence.py (5 cells into Drucker-Prager sand). The push itself
    # keeps the sand out: with the points no longer put back on the outline, none is inside.
    import jaxmpm.physics.bodies

    monkeypatch.setattr(jaxmpm.physics.bodies, "outline_pairs", lambda structure: ())
    assert points_inside_punch(Simulation(with_points(punch(0.5)))) == 0


TILT = math.radians(2.0)


def rocking_block(along=0.0, duration=1.0):
    """The rigid block of benchmarks/wall_base_study.py rocking (0.075 x 0.35 m, 2400 kg/m^3) on
    a 0.15 m elastic layer (E = 2 MPa, nu = 0.3), gravity tilted 2 degrees, damping 0.3; `along`
    moves the block that many cells along x."""
    cell, shift = 0.025, along * 0.025
    return Scene(
        name="rocking",
        gravity=(G * math.sin(TILT), -G * math.cos(TILT)),
        grid=Grid(size=(1.0, 0.55), cell=cell, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={"layer": LinearElastic(density=1800.0, young=2.0e6, poisson=0.3),
                   "concrete": LinearElastic(density=2400.0, young=3.0e10, poisson=0.2)},
        bodies=(Body("layer", "layer", Rectangle((0.0, 0.0), (1.0, 0.15)), initial_stress=Geostatic(0.3 / 0.7)),
                Body("block", "concrete", Rectangle((0.45 + shift, 0.15), (0.525 + shift, 0.5)), kinematics=Kinematics("rigid"))),
        contacts=(Contact(("layer", "block"), 0.4),),
        duration=duration, cfl=0.4, output_every=0.01,
        numerics=Numerics(shape="bspline2", transfer="apic", ppc=2, relaxation=10.0, damping=0.3, structure_hold="points"),
        probes=(Probe("top", "displacement", at=(0.4875 + shift, 0.5)), Probe("base", "displacement", at=(0.4875 + shift, 0.156))),
    )


def settled_rotation(scene, since=0.7):
    sim = Simulation(scene)
    probes = sim.probes()
    rotation = (np.asarray(probes["top"])[:, 0] - np.asarray(probes["base"])[:, 0]) / (0.5 - 0.156)
    return float(np.mean(rotation[sim.time >= since]))


def test_a_rigid_block_on_an_elastic_layer_turns_as_elasticity_says_wherever_the_grid_lines_fall():
    # theta = M / (pi E' a^2 / 4 - m g h_c) = 1.63 mrad on a half-space (the layer, four
    # half-widths deep, resists a little more). Measured at the cell 0.025 m: 2.18 mrad on the
    # grid lines, 1.94 moved half a cell (under the node hold 0.51 and 0.83; under the outline
    # hold, over 1.5 s, 4.3 and -3.1: docs/convergence.md). Over 1.5 s it goes 2.15, 1.95,
    # 1.79 mrad at h, h/2 and h/4. Within 40 % of the half-space here, and within 15 % of itself
    # when moved.
    width, height, density = 0.075, 0.35, 2400.0
    mass, centre = density * width * height, 0.5 * height
    plane_modulus = 2.0e6 / (1.0 - 0.3 ** 2)
    elastic = mass * G * math.sin(TILT) * centre / (math.pi * plane_modulus * (0.5 * width) ** 2 / 4.0
                                                     - mass * G * math.cos(TILT) * centre)
    aligned, moved = settled_rotation(rocking_block()), settled_rotation(rocking_block(along=0.5))
    for rotation in (aligned, moved):
        assert elastic < rotation < 1.4 * elastic, (rotation, elastic)
    assert abs(aligned - moved) < 0.15 * aligned


def test_gradients_through_the_points_hold_match_central_differences():
    # The push is piecewise smooth (a point starts or stops touching): a rigid footing set on
    # yielding sand under gravity tilted by 0.1 rad, sinking and sliding for 30 steps, as for
    # the outline hold in tests/test_structure_hold.py; young enters the push's stiffness too.
    # The friction's derivative is 3.5e-10 of a loss of 1e-3: at a relative step of 1e-4 the
    # differences carry the run's round-off (AD 3.48964e-10 against 3.48987e-10 / 3.48888e-10 /
    # 3.46612e-10 at steps of 1e-2 / 1e-3 / 1e-4), so the step is 1e-3.
    from tests.test_structure_hold import footing_gradients_against_central_differences

    footing_gradients_against_central_differences("points", relative_step=1e-3)


def test_a_pile_in_two_joined_parts_pushes_as_one():
    # A prescribed pile as one body and as a tip and a shaft that share an edge: the sand meets
    # the union's outline, each point pushed by the part whose surface is nearest, never by
    # both, so the two push the sand alike and the parts' reactions add up to the whole pile's.
    # Not to round-off: each part's contact takes its own friction at the nodes both push
    # (the Coulomb limit of each part's push, in turn), which moves the sand by 1e-6 m of its
    # millimetres here and the sideways reaction (0.6 % of the vertical) by 3 % of itself.
    def pile(parts):
        bodies = [Body("sand", "sand", Rectangle((0.0, 0.0), (0.3, 0.2)), initial_stress=Geostatic(0.3 / 0.7))]
        if parts == 1:
            bodies.append(Body("pile", "steel", Rectangle((0.1, 0.2), (0.15, 0.35)), kinematics=Kinematics("prescribed", (0.0, -0.2))))
        else:
            bodies += [Body("tip", "steel", Rectangle((0.1, 0.2), (0.15, 0.25)), kinematics=Kinematics("prescribed", (0.0, -0.2))),
                       Body("shaft", "steel", Rectangle((0.1, 0.25), (0.15, 0.35)), kinematics=Kinematics("prescribed", (0.0, -0.2)))]
        names = [body.name for body in bodies[1:]]
        return Scene(
            name="pile", grid=Grid(size=(0.3, 0.4), cell=0.02, boundaries=Boundaries("slip", "slip", "fixed", "free")),
            materials={"sand": LinearElastic(density=1800.0, young=5e6, poisson=0.3),
                       "steel": LinearElastic(density=7800.0, young=2e11, poisson=0.3)},
            bodies=tuple(bodies), contacts=tuple(Contact(("sand", name), 0.3) for name in names),
            duration=0.02, output_every=0.02,
            numerics=Numerics(shape="linear", transfer="apic", ppc=2, structure_hold="points"),
            probes=tuple(Probe(name, "reaction", body=name) for name in names),
        )

    whole, split = Simulation(pile(1)), Simulation(pile(2))
    sand = [np.asarray(sim.final_state().particles.x)[slice(*sim.body_slices[0])] for sim in (whole, split)]
    moved = np.max(np.abs(sand[0] - np.asarray(whole.initial_state().particles.x)[slice(*whole.body_slices[0])]))
    assert moved > 5e-4
    assert np.max(np.abs(sand[1] - sand[0])) < 1e-3 * moved
    reactions = [np.asarray(whole.probes()["pile"][-1]), np.asarray(split.probes()["tip"][-1] + split.probes()["shaft"][-1])]
    assert abs(reactions[0][1]) > 10.0                  # it pushes the sand
    np.testing.assert_allclose(reactions[1], reactions[0], rtol=0, atol=1e-3 * abs(reactions[0][1]))


def test_a_structure_that_is_not_convex_is_refused_under_the_points_hold():
    scene = with_points(punch(0.05))
    notched = Polygon(((0.17, 0.2), (0.23, 0.2), (0.23, 0.3), (0.2, 0.25), (0.17, 0.3)))
    bodies = (scene.bodies[0], Body("punch", "steel", notched, kinematics=Kinematics("prescribed", (0.0, -0.2))))
    with pytest.raises(SceneError, match=r"^contacts\[0\]\.pair = \['sand', 'punch'\] pairs the prescribed body 'punch', "
                                         r"whose region is not a convex polygon.*'mass'\.$"):
        dataclasses.replace(scene, bodies=bodies)


def test_an_elastic_structure_under_the_points_hold_comes_with_a_note():
    # Elastic structures are still held at the nodes under "points": the small wall of
    # tests/test_convergence.py as a 30 GPa free body moved 2.27 mm at 0.045 s where the rigid
    # wall pushing points moved 2.58 mm (both 2.27 under "mass").
    elastic = with_points(small_wall("free", young=30.0e9))
    (note,) = elastic.notes
    assert note.startswith("numerics.structure_hold = 'points' pushes points out of prescribed and rigid bodies only: "
                           "the elastic body 'wall'")
    assert with_points(small_wall("rigid")).notes == ()
    assert small_wall("free", young=30.0e9).notes == ()
