"""Stability at the extremes (docs/stability.md, benchmarks/stability_study.py): settings the
study found stable stay finite, and an unstable one stops with a SimulationError that names
the step, the point and the body, and says that the step is unstable, never a silent NaN."""

import re

import numpy as np
import pytest

import jaxmpm

COLUMN = """
[scene]
name = "column"
duration = {duration}
cfl = {cfl}
output_every = 0.005
snapshot_fields = ["x", "v", "mass"]

[grid]
size = [0.2, 0.12]
cell = 0.01
boundaries = {{ left = "slip", right = "slip", bottom = "fixed", top = "free" }}

[numerics]
shape = "linear"
transfer = "flip"
flip = 0.99
update = "{update}"

[materials.soil]
model = "linear_elastic"
density = 1800.0
young = 1.0e6
poisson = 0.0

[[bodies]]
name = "column"
material = "soil"
region = {{ rectangle = [[0.0, 0.0], [0.2, 0.1]] }}

[[probes]]
name = "top"
kind = "displacement"
at = [0.1, 0.1]
"""

# A small dry-sand collapse (the study's, at twice its cell): 8 x 4 cells of column, 128 points.
COLLAPSE = """
[scene]
name = "collapse"
duration = {duration}
output_every = {every}
snapshot_fields = ["x", "v", "mass"]

[grid]
size = [0.25, 0.075]
cell = 0.0125
boundaries = {{ left = "slip", right = "free", bottom = "fixed", top = "free" }}

[materials.sand]
model = "drucker_prager"
density = 2650.0
young = {young}
poisson = 0.3
friction_angle = 19.8
cone = "plane_strain"
{perzyna}

[[bodies]]
name = "column"
material = "sand"
region = {{ rectangle = [[0.0, 0.0], [0.1, 0.05]] }}
initial_stress = {{ geostatic = {{ k0 = "jaky" }} }}
"""


def column(update, cfl, duration=0.02):
    return jaxmpm.Scene.from_toml(COLUMN.format(update=update, cfl=cfl, duration=duration))


def runout(result):
    """How far the column's front moved [m]."""
    x = result.snapshots["column"]["x"][..., 0]
    return float(x[-1].max() - x[0].max())


def kinetic_and_gravity_work(result, gravity=9.81):
    """Kinetic energy and the work gravity has done, per snapshot [J/m]."""
    snap = result.snapshots["column"]
    kinetic = 0.5 * np.sum(snap["mass"] * np.sum(snap["v"] ** 2, axis=-1), axis=-1)
    work = np.sum(snap["mass"] * gravity * (snap["x"][0, :, 1] - snap["x"][..., 1]), axis=-1)
    return kinetic, work


def test_an_unstable_step_stops_with_a_message_naming_step_point_body_and_cause():
    # The study (docs/stability.md, cfl table): linear shapes + FLIP 0.99 + USL on the released
    # elastic column blow up at cfl = 1.0 (a point leaves the grid within ~20 steps) and are
    # stable at 0.8. The run must stop with SimulationError naming where it failed and that the
    # step is unstable, and keep a partial, finite, incomplete result.
    with pytest.raises(jaxmpm.SimulationError) as caught:
        jaxmpm.Simulation(column("usl", 1.0)).run(progress=False)
    message = str(caught.value)
    assert caught.value.result is not None
    assert not caught.value.result.complete
    pattern = (r"^the run stopped at step (\d+) \(t = [0-9.e-]+ s\): point \d+ of body 'column' "
               r"(left the grid|became non-finite); .* \(by then (points moved up to [0-9.e+]+ cells per step|points "
               r"went non-finite): the step is unstable with scene.cfl = 1, "
               r"numerics.shape = 'linear', transfer = 'flip', update = 'usl'; lower scene.cfl")
    match = re.search(pattern, message)
    assert match, message
    steps_kept = len(caught.value.result.time)
    assert 1 <= steps_kept <= int(match.group(1))
    for values in caught.value.result.probes.values():
        assert np.all(np.isfinite(values))


def test_musl_at_the_same_cfl_stays_finite_and_bounded():
    # Same column and cfl = 1.0 with MUSL: stable in the study. Kinetic energy can never exceed
    # what gravity released (the strain energy is >= 0); an unstable mode would.
    result = jaxmpm.Simulation(column("musl", 1.0, duration=0.03)).run(progress=False)
    assert result.complete
    kinetic, work = kinetic_and_gravity_work(result)
    assert np.all(np.isfinite(kinetic)) and work.max() > 0.0
    assert np.all(kinetic <= 1.1 * np.maximum.accumulate(work) + 1e-12)


@pytest.mark.parametrize("speed", [2.0, 30.0])
def test_a_body_leaving_the_grid_at_its_own_speed_is_not_called_unstable(speed):
    # A block thrown at 2 or 30 m/s through a free edge leaves the grid physically (|v| dt is
    # below a cell: the CFL step counts the body's speed): the message names the point and
    # body but must not call the step unstable. (At 30 m/s every point has left the grid by the
    # end of the output interval, where their values mean nothing: they were taken for an
    # instability; now the message gives both readings.)
    scene = column("musl", 0.4).with_value("scene.gravity", [0.0, 0.0])
    scene = scene.with_value("grid.boundaries.right", "free").with_value("scene.duration", 0.1)
    scene = scene.with_value("bodies.column.velocity", [speed, 0.0])
    with pytest.raises(jaxmpm.SimulationError, match=r"point \d+ of body 'column' left the grid") as caught:
        jaxmpm.Simulation(scene).run(progress=False)
    assert "the step is unstable" not in str(caught.value)
    if speed > 10.0:
        assert "enlarge grid.size" in str(caught.value)
    else:
        assert "unstable" not in str(caught.value)
        # the largest |v| dt / h of the points still on the grid: the body's own speed, plus
        # what the points that lost their support at the edge picked up (well below a cell)
        sim = jaxmpm.Simulation(scene)
        measured = float(re.search(r"move at most ([0-9.e-]+) of a cell per step", str(caught.value)).group(1))
        assert speed * sim.dt / scene.grid.cell <= measured < 2 * speed * sim.dt / scene.grid.cell


@pytest.fixture(scope="module")
def perzyna_collapse():
    # One compiled viscoplastic collapse shared by the gamma*dt and friction-angle cases.
    scene = jaxmpm.Scene.from_toml(COLLAPSE.format(duration=0.1, every=0.01, young=0.84e6,
                                                   perzyna="fluidity = 1.0\nexponent = 1.0"))
    return jaxmpm.Simulation(scene)


def test_perzyna_at_extreme_gamma_dt_stays_finite_between_its_two_limits(perzyna_collapse):
    # The Perzyna solve is stable for any gamma*dt (jaxmpm/materials/drucker_prager.py; the
    # study swept 1e-8..1e8). gamma*dt = 1e-8 is nearly elastic: the column's front stays put;
    # 1e8 is nearly rate-independent: the front creeps out (on this coarse grid about 2 mm in
    # 0.1 s, the same as Drucker-Prager's to 0.1 mm). Both must finish finite.
    sim = perzyna_collapse
    moved = {}
    for rate in (1e-8, 1e8):
        params = jaxmpm.with_values(sim.params, {"sand.fluidity": rate / sim.dt})
        result = sim.run(params, progress=False)
        assert result.complete
        assert np.all(np.isfinite(result.snapshots["column"]["x"]))
        moved[rate] = runout(result)
    assert moved[1e8] > 0.1 * sim.scene.grid.cell
    assert moved[1e-8] < 0.05 * moved[1e8]


def test_a_friction_angle_of_50_degrees_stays_finite_and_stops_the_collapse(perzyna_collapse):
    # phi = 50 (the top of the study's sweep; m = sqrt(3) sin 50 = 1.33) in the fast-flowing
    # (gamma*dt = 1e8) limit: finite, and a steeper cone than 19.8 degrees spreads less.
    sim = perzyna_collapse
    fast = {"sand.fluidity": 1e8 / sim.dt}
    steep = sim.run(jaxmpm.with_values(sim.params, fast | {"sand.friction_angle": 50.0}), progress=False)
    base = sim.run(jaxmpm.with_values(sim.params, fast), progress=False)
    assert steep.complete and np.all(np.isfinite(steep.snapshots["column"]["x"]))
    assert runout(steep) < 0.5 * runout(base)


def test_a_stiff_sand_of_1e8_pa_stays_finite():
    # E = 1e8 Pa (the top of the study's sweep): c_p = 225 m/s, dt = 2.2e-5 s. A rate-independent
    # collapse over 0.01 s (450 steps) must finish with bounded kinetic energy.
    scene = jaxmpm.Scene.from_toml(COLLAPSE.format(duration=0.01, every=0.001, young=1e8, perzyna=""))
    sim = jaxmpm.Simulation(scene)
    result = sim.run(progress=False)
    assert result.complete and sim.steps > 300
    kinetic, work = kinetic_and_gravity_work(result)
    assert np.all(np.isfinite(kinetic)) and work.max() > 0.0
    assert np.all(kinetic <= 1.1 * np.maximum.accumulate(work) + 1e-12)
