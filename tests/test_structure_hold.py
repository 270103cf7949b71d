"""numerics.structure_hold: the nodes at which a structure (prescribed, rigid or elastic) holds the soil.

Sources: the separating-axis theorem for two convex polygons (a square and the outline are
apart exactly when their projections on one of their edge normals do not overlap), checked
against brute-force sampling; the twin's measurements behind the option are in
docs/convergence.md ("Examples under cell refinement")."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm import Scene, SceneError, Simulation
from jaxmpm.physics.bodies import cell_meets_outline


def sampled_meets(corners, positions, cell, samples=41):
    """(P,) whether the square of side `cell` about each of `positions` (P, 2) and the convex
    outline share a point, by sampling the square and testing the outline's corners in it."""
    edges = np.roll(corners, -1, axis=0) - corners
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=-1) / np.linalg.norm(edges, axis=1)[:, None]
    offsets = np.linspace(-0.5 * cell, 0.5 * cell, samples)
    square = np.stack(np.meshgrid(offsets, offsets), axis=-1).reshape(-1, 2)                 # (S, 2)
    points = positions[:, None, :] + square[None]                                             # (P, S, 2)
    beyond = np.einsum("pskd,kd->psk", points[:, :, None, :] - corners[None, None], normals)  # (P, S, K)
    inside = np.any(np.all(beyond <= 0.0, axis=-1), axis=-1)
    corner_in_square = np.any(np.all(np.abs(corners[None] - positions[:, None, :]) <= 0.5 * cell, axis=-1), axis=-1)
    return inside | corner_in_square


def test_a_nodes_cell_meets_an_outline_exactly_where_sampling_finds_a_shared_point():
    # A 0.3 x 0.1 rectangle and a hexagon, each turned by 0, 0.3 and 0.785 rad; nodes of a grid
    # of 0.02 m round them, cells of 0.05 m. Positions whose answer changes within 2 % of the
    # cell (tangent squares) are left out: sampling cannot resolve them.
    cell = 0.05
    axis = np.arange(-0.3, 0.3001, cell / 2.5)
    positions = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
    compared = 0
    for turn in (0.0, 0.3, 0.785):
        rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
        rectangle = np.array([[-0.15, -0.05], [0.15, -0.05], [0.15, 0.05], [-0.15, 0.05]]) @ rotation.T
        angles = np.arange(6) * np.pi / 3 + turn
        hexagon = 0.12 * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
        for corners in (rectangle, hexagon):
            meets = np.asarray(cell_meets_outline(corners, positions, cell))
            settled = (meets == np.asarray(cell_meets_outline(corners, positions, 0.98 * cell))) & \
                      (meets == np.asarray(cell_meets_outline(corners, positions, 1.02 * cell)))
            assert 0 < np.sum(meets) < meets.size
            np.testing.assert_array_equal(meets[settled], sampled_meets(corners, positions[settled], cell))
            compared += int(np.sum(settled))
    assert compared > 5000


FOOTING = """
[scene]
name = "footing"
duration = 0.003
dt = 1e-4
output_every = 1e-3
[grid]
size = [0.6, 0.3]
cell = 0.025
boundaries = { left = "slip", right = "slip", bottom = "fixed", top = "free" }
[numerics]
shape = "bspline2"
transfer = "apic"
ppc = 2
dtype = "float64"
[materials.sand]
model = "linear_elastic"
density = 1800.0
young = 5.0e6
poisson = 0.3
[materials.steel]
model = "linear_elastic"
density = 7800.0
young = 2.0e11
poisson = 0.3
[[bodies]]
name = "sand"
material = "sand"
region = { rectangle = [[0.0, 0.0], [0.6, 0.15]] }
[[bodies]]
name = "footing"
material = "steel"
region = { rectangle = [[0.25, 0.15], [0.35, 0.2]] }
kinematics = { type = "prescribed", velocity = [0.0, -0.05] }
[[contacts]]
pair = ["sand", "footing"]
friction = 0.5
[[probes]]
name = "push"
kind = "reaction"
body = "footing"
"""


def test_an_outline_hold_gives_the_soil_only_the_nodes_whose_cell_meets_the_structure():
    # A prescribed footing pushed into an elastic layer, three steps. Under the default hold the
    # footing's points (a quarter cell inside its outline, quadratic B-splines) reach nodes a
    # cell and a quarter beyond it, and the sand there is set moving with it at the first step:
    # the force that drives it down (its reaction) is that of a footing a cell wider on each
    # side and a cell deeper. Under "outline" only the nodes whose cell meets the footing hold
    # the sand (checked node by node below): less sand is set moving, and the force is less
    # than half.
    from jaxmpm.physics.bodies import held_by_outline, node_positions

    scene = Scene.from_toml(FOOTING)
    outline = Scene.from_toml(FOOTING.replace('dtype = "float64"', 'dtype = "float64"\nstructure_hold = "outline"'))
    assert outline.numerics.structure_hold == "outline" and scene.numerics.structure_hold == "mass"
    assert outline.to_dict()["numerics"]["structure_hold"] == "outline"
    sims = Simulation(scene), Simulation(outline)
    assert sims[1].structure.structure_hold == "outline"
    pushes = [float(np.asarray(sim.probes()["push"])[-1, 1]) for sim in sims]
    assert 0.0 < -pushes[1] < -pushes[0]        # the force driving the footing down, smaller
    assert -pushes[1] < 0.5 * -pushes[0]        # measured: 113 against 502 N/m

    sim = sims[1]
    state = sim.initial_state()
    positions = np.asarray(node_positions(sim.structure.layout, state.particles.x.dtype))
    footing = next(block for block in sim.structure.bodies if block.name == "footing")
    everywhere = jnp.ones((sim.structure.fields,) + positions.shape[:2], bool)
    held = np.asarray(held_by_outline(sim.structure, state, everywhere))[footing.field]
    cell = sim.structure.layout.cell
    expected = ((positions[..., 0] >= 0.25 - cell / 2 - 1e-12) & (positions[..., 0] <= 0.35 + cell / 2 + 1e-12)
                & (positions[..., 1] >= 0.15 - cell / 2 - 1e-12) & (positions[..., 1] <= 0.2 + cell / 2 + 1e-12))
    np.testing.assert_array_equal(held, expected)
    assert np.asarray(held_by_outline(sim.structure, state, everywhere))[0].all()   # the sand's field untouched

    # An elastic structure (a free body of elastic material and convex region in contact with
    # sand that yields: its outline bounds the contact's normal) is held to its outline alike: its contact otherwise acts
    # wherever both fields have mass, and a stiff elastic body would not move as the rigid one.
    elastic = Simulation(Scene.from_toml(FOOTING.replace('dtype = "float64"', 'dtype = "float64"\nstructure_hold = "outline"')
                                         .replace('kinematics = { type = "prescribed", velocity = [0.0, -0.05] }', '')
                                         .replace('kind = "reaction"\nbody = "footing"', 'kind = "contact_force"\npair = ["sand", "footing"]')
                                         .replace("dt = 1e-4", "dt = 4e-6")
                                         .replace('model = "linear_elastic"\ndensity = 1800.0',
                                                  'model = "drucker_prager"\nfriction_angle = 30.0\ndensity = 1800.0')))
    assert [interface.bounded_by for interface in elastic.structure.interfaces] == [footing.field]
    state = elastic.initial_state()
    held = np.asarray(held_by_outline(elastic.structure, state, everywhere))
    np.testing.assert_array_equal(held[footing.field], expected)
    assert held[0].all()


def test_the_outline_hold_comes_with_a_note():
    # benchmarks/wall_base_study.py: a rigid block on an elastic layer under the outline hold
    # turned 2.6 times as far as the elastic solution with quadratic B-splines, and against its
    # load with its sides half a cell off the nodes (either shape); the default hold did not.
    outline = FOOTING.replace('dtype = "float64"', 'dtype = "float64"\nstructure_hold = "outline"')
    for text in (outline, outline.replace('shape = "bspline2"', 'shape = "linear"')):
        (note,) = Scene.from_toml(text).notes
        assert note.startswith("numerics.structure_hold = 'outline' is a study option")
    assert Scene.from_toml(FOOTING).notes == ()


def test_an_unknown_structure_hold_is_one_clear_error():
    with pytest.raises(SceneError, match=r"^numerics\.structure_hold = 'nodes' is not one of 'mass', 'outline', 'points'\.$"):
        Scene.from_toml(FOOTING.replace('dtype = "float64"', 'dtype = "float64"\nstructure_hold = "nodes"'))


def test_gradients_through_the_outline_hold_match_central_differences():
    # The outline hold is a mask from a separating-axis test: it adds no singular point, and the
    # rigid body's solve and the contact under it must give the derivatives of what they
    # compute. A rigid footing set on yielding sand under gravity tilted by 0.1 rad, so that it
    # sinks and slides in 30 steps; the loss reads both. Reverse mode against central
    # differences (the same check as the default hold's in tests/test_contact.py), with a
    # relative step of 1e-4: the loss moves by only 1e-7 of itself per unit of the contact's
    # friction, and at 1e-6 the differences carry the run's round-off (AD 9.32842e-8 against
    # 9.32842e-8 / 9.32862e-8 / 9.31644e-8 at steps of 1e-3 / 1e-4 / 1e-6).
    footing_gradients_against_central_differences("outline", relative_step=1e-4)


def footing_gradients_against_central_differences(hold, relative_step):
    """The rigid footing of FOOTING on Drucker-Prager sand under gravity tilted by 0.1 rad
    (it sinks and slides in 30 steps) under structure hold `hold`: the reverse-mode gradient of
    its centre's displacement (y + 0.3 x) in young, friction angle and contact friction against
    central differences, within `relative_step` at that relative step."""
    from tests.scenes import reverse_mode_against_central_differences

    text = (FOOTING.replace('dtype = "float64"', f'dtype = "float64"\nstructure_hold = "{hold}"')
            .replace('[scene]', '[scene]\ngravity = [0.979, -9.760]')
            .replace('kinematics = { type = "prescribed", velocity = [0.0, -0.05] }', 'kinematics = { type = "rigid" }')
            .replace('model = "linear_elastic"\ndensity = 1800.0', 'model = "drucker_prager"\nfriction_angle = 30.0\ndensity = 1800.0')
            .replace('name = "push"\nkind = "reaction"\nbody = "footing"', 'name = "centre"\nkind = "displacement"\nat = [0.3, 0.175]'))
    sim = Simulation(Scene.from_toml(text))
    assert sim.structure.structure_hold == hold
    reverse_mode_against_central_differences(sim, lambda probes: probes["centre"][-1, 1] + 0.3 * probes["centre"][-1, 0], [
        ("sand.young", 5.0e6, ("materials", "sand", "young")),
        ("sand.friction_angle", 30.0, ("materials", "sand", "friction_angle")),
        ("sand/footing.friction", 0.5, ("contacts", "sand/footing", "friction")),
    ], rel=relative_step, relative_step=relative_step)
