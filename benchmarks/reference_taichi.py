"""A hand-written Taichi (CPU) kernel of jaxmpm's step, the reference of the throughput ratio.

    python benchmarks/reference_taichi.py                 # float64 agreement with jaxmpm, 100 steps
    python benchmarks/reference_taichi.py --steps 300 --exact-math   # longer, Taichi fast_math off
    python benchmarks/throughput.py --reference           # the timing (see there)

Needs the optional `bench` extra (`pip install -e .[bench]`); jaxmpm itself never imports
taichi. The kernel runs THE scheme jaxmpm runs for one free Drucker-Prager body with
numerics shape = "bspline2", transfer = "apic", update = "musl" (one velocity field, plane
strain, no damping, no contact), step by step as jaxmpm/physics/solver.py does it:

    stencil    quadratic B-spline, one ghost node layer: base = floor(x / h + 1 - 1/2)
    P2G        m_I = sum m_p N_I,  p_I = sum m_p N_I (v_p + C_p (x_I - x_p)),
               f_I = sum (m_p N_I g - V_p sigma_p . grad N_I); ghosts folded onto their mirror
               nodes beyond fixed / slip edges (mass +, vector components with the mirror signs)
    grid       v_I = (p_I + dt f_I) / m_I where m_I > 1e-10 max m_p, else 0; edge conditions:
               held components zeroed on the edge nodes, ghost nodes mirror the nodes inside
    G2P        v_p = sum N_I v_I,  x_p <- x_p + dt v_p
    MUSL       v_I = sum m_p N_I v_p / m_I (old stencil, new v_p), folded and constrained alike
    rate       L_p = sum v_I (x) grad N_I,  C_p = L_p
    stress     Jaumann (Hughes-Winget) rotation, elastic trial K tr(d) I + 2 G dev(d), return
               to the Drucker-Prager cone q = m p (radial at psi = 0) or to the apex
    volume     V_p <- V_p det(I + dt L_p)

Every operation is written in the order jaxmpm evaluates it, so in float64 the two codes agree
to round-off (what `main` checks); what differs is the order of the sums at a node (point by
point here, XLA's one-row-per-point scatter and s^2 shifted adds there). jaxmpm's APIC step also
evaluates the FLIP increment and multiplies it by 0, checks every point for non-finite values
and for leaving the grid, and records two probes each step; none of that changes the state, and
the kernel here does none of it.

The two scatters (P2G, MUSL re-map) run as serial loops by default: on two cores Taichi's
parallel loop pays for its atomic adds (compare-and-swap loops on floats) more than the second
thread gives back. `serial_scatter=False` gives the idiomatic parallel loop with atomics.
"""

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import taichi as ti

from jaxmpm.physics.solver import MASS_FLOOR

sys.path.insert(0, str(Path(__file__).resolve().parent))   # common.block_scene

GHOST = 1          # node layers beyond each edge (quadratic B-spline)
SUPPORT = 3        # stencil nodes per axis
THREADS = 2        # the machine's cores
EDGES = {"left": (0, 0), "right": (0, 1), "bottom": (1, 0), "top": (1, 1)}   # (axis, upper side?)


@dataclasses.dataclass(frozen=True)
class Scheme:
    """The static numbers of one run: origin (2,) [m], cell h [m], nodes (nx, ny) with ghosts,
    boundaries {edge: "fixed" | "slip" | "free"}, gravity (2,) [m/s^2], dt [s], the moduli K and G
    [Pa], the cone slopes m (friction) and m_psi (dilation), the node mass floor [kg/m]."""

    origin: tuple[float, float]
    cell: float
    nodes: tuple[int, int]
    boundaries: dict
    gravity: tuple[float, float]
    dt: float
    bulk: float
    shear: float
    slope: float
    dilation_slope: float
    floor: float


def paper_cone(angle_degrees):
    """m = 18 sin(phi) / (9 - sin^2 phi), jaxmpm's default ("paper") cone."""
    sine = math.sin(math.radians(angle_degrees))
    return 18.0 * sine / (9.0 - sine * sine)


def scheme_of(sim, params) -> Scheme:
    """The Scheme of a jaxmpm Simulation; AssertionError unless the kernel runs its exact step."""
    structure = sim.structure
    (block,) = structure.bodies
    law = block.law
    supported = (structure.layout.shape_name == "bspline2", structure.transfer == "apic", structure.update == "musl",
                 structure.fields == 1, not structure.damped, not structure.axisymmetric, block.kinematics == "free",
                 type(law).__name__ == "DruckerPragerLaw", law.cone == "paper", not law.viscoplastic)
    assert all(supported), f"the reference kernel runs bspline2 + APIC + MUSL Drucker-Prager only: {supported}"
    material = {name: float(value) for name, value in params["materials"][block.material_name].items()}
    young, poisson = material["young"], material["poisson"]
    layout = structure.layout
    bulk = young / (3.0 * (1.0 - 2.0 * poisson))
    return Scheme(
        origin=tuple(layout.origin), cell=layout.cell, nodes=layout.nodes,
        boundaries=dataclasses.asdict(structure.boundaries), gravity=tuple(float(g) for g in params["scene"]["gravity"]), dt=structure.dt,
        bulk=bulk, shear=young / (2.0 * (1.0 + poisson)),
        slope=paper_cone(material["friction_angle"]), dilation_slope=paper_cone(material["dilation_angle"]),
        floor=MASS_FLOOR * float(np.max(np.asarray(sim.initial_state(params).particles.mass))),
    )


def edge_layers(scheme):
    """(axis, edge node, held components, ghost, mirror, mirror signs) of every fixed or slip
    edge, in jaxmpm's edge order: the ghost layer lies one node outside the edge node, its
    mirror one node inside; a held component (both at a fixed edge, the normal one at a slip
    edge) changes sign in the mirror image."""
    layers = []
    for edge, (axis, upper) in EDGES.items():
        kind = scheme.boundaries[edge]
        if kind == "free":
            continue
        node = scheme.nodes[axis] - 1 - GHOST if upper else GHOST
        outwards = 1 if upper else -1
        held = (0, 1) if kind == "fixed" else (axis,)
        signs = tuple(-1.0 if component in held else 1.0 for component in (0, 1))
        layers.append((axis, node, held, node + outwards, node - outwards, signs))
    return layers


@ti.func
def layer_node(axis: ti.template(), layer: ti.template(), k):
    """Index (2,) of the k-th node of node layer `layer` across grid `axis`."""
    node = ti.Vector([k, k])
    node[axis] = layer
    return node


@ti.data_oriented
class ReferenceMPM:
    """Particle and node fields of one body, and the step kernel (see the module docstring).
    serial_scatter: P2G and the MUSL re-map as serial loops (True) or parallel with atomic adds."""

    def __init__(self, scheme: Scheme, count: int, dtype, serial_scatter=True):
        self.scheme, self.count, self.dtype = scheme, count, dtype
        self.serial_scatter = serial_scatter
        self.numpy_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.layers = edge_layers(scheme)
        self.x = ti.Vector.field(2, dtype, count)
        self.v = ti.Vector.field(2, dtype, count)
        self.affine = ti.Matrix.field(2, 2, dtype, count)
        self.stress = ti.Matrix.field(3, 3, dtype, count)
        self.volume = ti.field(dtype, count)
        self.mass = ti.field(dtype, count)
        self.plastic_strain = ti.field(dtype, count)
        self.node_mass = ti.field(dtype, scheme.nodes)
        self.node_momentum = ti.Vector.field(2, dtype, scheme.nodes)
        self.node_force = ti.Vector.field(2, dtype, scheme.nodes)
        self.node_velocity = ti.Vector.field(2, dtype, scheme.nodes)

    def load(self, particles: dict):
        """Set the points from numpy arrays {x, v, affine, stress, volume, mass, plastic_strain}."""
        for name, values in particles.items():
            getattr(self, name).from_numpy(np.ascontiguousarray(values, dtype=self.numpy_dtype))

    def dump(self) -> dict:
        """The points as numpy arrays (same keys as `load`)."""
        names = ("x", "v", "affine", "stress", "volume", "mass", "plastic_strain")
        return {name: getattr(self, name).to_numpy() for name in names}

    def advance(self, steps: int):
        """Run `steps` steps (asynchronous: call ti.sync() before reading a clock)."""
        for _ in range(steps):
            self.step()

    @ti.func
    def stencil(self, position):
        """base node (2,) int, 1-D weights N (2 axes x 3) and slopes dN/dx [1/m] (2 x 3):
        N = (3/2 - r)^2 / 2, 3/4 - (r - 1)^2, (r - 1/2)^2 / 2 at r = x / h + 1 - base."""
        local = (position - ti.Vector(self.scheme.origin)) / self.scheme.cell + GHOST
        base = ti.cast(ti.floor(local - 0.5), ti.i32)
        for axis in ti.static(range(2)):
            base[axis] = ti.min(ti.max(base[axis], 0), self.scheme.nodes[axis] - SUPPORT)
        offset = local - ti.cast(base, self.dtype)
        first, middle, last = 1.5 - offset, offset - 1.0, offset - 0.5
        weights = ti.Matrix.rows([0.5 * first * first, 0.75 - middle * middle, 0.5 * last * last]).transpose()
        slopes = ti.Matrix.rows([-first, -2.0 * middle, last]).transpose() / self.scheme.cell
        return base, weights, slopes

    @ti.func
    def clear_nodes(self):
        for i, j in self.node_mass:
            self.node_mass[i, j] = 0.0
            self.node_momentum[i, j] = ti.Vector.zero(self.dtype, 2)
            self.node_force[i, j] = ti.Vector.zero(self.dtype, 2)

    @ti.func
    def particles_to_grid(self):
        """m_I, p_I = sum m_p N_I (v_p + C_p (x_I - x_p)), f_I = sum (N_I m_p g - V_p sigma_p grad N_I)."""
        ti.loop_config(serialize=self.serial_scatter)
        for p in range(self.count):
            base, weights, slopes = self.stencil(self.x[p])
            mass, velocity, affine = self.mass[p], self.v[p], self.affine[p]
            stress = -self.volume[p] * self.stress[p]
            corner = ti.cast(base - GHOST, self.dtype) * self.scheme.cell + ti.Vector(self.scheme.origin) - self.x[p]
            for a, b in ti.static(ti.ndrange(SUPPORT, SUPPORT)):
                weight = weights[0, a] * weights[1, b]
                grad_x, grad_y = slopes[0, a] * weights[1, b], weights[0, a] * slopes[1, b]
                weighted = mass * weight
                offset_x, offset_y = corner[0] + a * self.scheme.cell, corner[1] + b * self.scheme.cell
                node = base + ti.Vector([a, b])
                self.node_mass[node] += weight * mass
                self.node_momentum[node] += ti.Vector([
                    weight * (mass * velocity[0]) + weighted * offset_x * affine[0, 0] + weighted * offset_y * affine[0, 1],
                    weight * (mass * velocity[1]) + weighted * offset_x * affine[1, 0] + weighted * offset_y * affine[1, 1],
                ])
                self.node_force[node] += ti.Vector([
                    weight * (mass * self.scheme.gravity[0]) + grad_x * stress[0, 0] + grad_y * stress[0, 1],
                    weight * (mass * self.scheme.gravity[1]) + grad_x * stress[1, 0] + grad_y * stress[1, 1],
                ])

    @ti.func
    def fold_ghosts(self, with_mass: ti.template()):
        """Ghost node values beyond fixed / slip edges added onto their mirror nodes: mass with +,
        momentum (and force, `with_mass`: the P2G fold) with the mirror signs."""
        for axis, node, held, ghost, mirror, signs in ti.static(self.layers):
            for k in range(self.scheme.nodes[1 - axis]):
                outside, inside = layer_node(axis, ghost, k), layer_node(axis, mirror, k)
                sign = ti.Vector(signs, self.dtype)
                self.node_momentum[inside] += sign * self.node_momentum[outside]
                if ti.static(with_mass):
                    self.node_mass[inside] += self.node_mass[outside]
                    self.node_force[inside] += sign * self.node_force[outside]

    @ti.func
    def node_velocities(self, with_force: ti.template()):
        """v_I = (p_I [+ dt f_I]) / m_I on nodes heavier than the floor, else 0; then held
        components zeroed on the edge nodes."""
        for i, j in self.node_mass:
            momentum = self.node_momentum[i, j]
            if ti.static(with_force):
                momentum = momentum + self.scheme.dt * self.node_force[i, j]
            velocity = ti.Vector.zero(self.dtype, 2)
            if self.node_mass[i, j] > self.scheme.floor:
                velocity = momentum / self.node_mass[i, j]
            index = ti.Vector([i, j])
            for axis, node, held, ghost, mirror, signs in ti.static(self.layers):
                if index[axis] == node:
                    for component in ti.static(held):
                        velocity[component] = 0.0
            self.node_velocity[i, j] = velocity

    @ti.func
    def mirror_ghosts(self):
        """Ghost node velocities beyond fixed / slip edges: the mirror node's, held components negated."""
        for axis, node, held, ghost, mirror, signs in ti.static(self.layers):
            for k in range(self.scheme.nodes[1 - axis]):
                outside, inside = layer_node(axis, ghost, k), layer_node(axis, mirror, k)
                self.node_velocity[outside] = ti.Vector(signs, self.dtype) * self.node_velocity[inside]

    @ti.func
    def grid_to_particles(self):
        """v_p = sum N_I v_I."""
        for p in range(self.count):
            base, weights, slopes = self.stencil(self.x[p])
            velocity = ti.Vector.zero(self.dtype, 2)
            for a, b in ti.static(ti.ndrange(SUPPORT, SUPPORT)):
                velocity += weights[0, a] * weights[1, b] * self.node_velocity[base + ti.Vector([a, b])]
            self.v[p] = velocity

    @ti.func
    def remap_momentum(self):
        """The MUSL momentum sum m_p N_I v_p (old stencil, new v_p) into node_momentum, which the
        caller has cleared."""
        ti.loop_config(serialize=self.serial_scatter)
        for p in range(self.count):
            base, weights, slopes = self.stencil(self.x[p])
            for a, b in ti.static(ti.ndrange(SUPPORT, SUPPORT)):
                self.node_momentum[base + ti.Vector([a, b])] += self.mass[p] * (weights[0, a] * weights[1, b]) * self.v[p]

    @ti.func
    def clear_momentum(self):
        for i, j in self.node_momentum:
            self.node_momentum[i, j] = ti.Vector.zero(self.dtype, 2)

    @ti.func
    def update_points(self):
        """L_p = sum v_I (x) grad N_I (re-mapped v_I), C_p = L_p, stress, V_p det(I + dt L_p), x_p + dt v_p."""
        for p in range(self.count):
            base, weights, slopes = self.stencil(self.x[p])
            gradient = ti.Matrix.zero(self.dtype, 2, 2)
            for a, b in ti.static(ti.ndrange(SUPPORT, SUPPORT)):
                grad = ti.Vector([slopes[0, a] * weights[1, b], weights[0, a] * slopes[1, b]])
                gradient += self.node_velocity[base + ti.Vector([a, b])].outer_product(grad)
            self.affine[p] = gradient
            stress, increment = self.drucker_prager(self.stress[p], gradient)
            self.stress[p] = stress
            self.plastic_strain[p] += increment
            stretch = (1.0 + self.scheme.dt * gradient[0, 0]) * (1.0 + self.scheme.dt * gradient[1, 1]) \
                - (self.scheme.dt * self.scheme.dt) * gradient[0, 1] * gradient[1, 0]
            self.volume[p] *= stretch
            self.x[p] += self.scheme.dt * self.v[p]

    @ti.func
    def drucker_prager(self, stress, gradient):
        """Q sigma Q^T + dt (K tr(d) I + 2 G dev(d)), then the return: f = q - m p > 0 or p < 0
        yields; q K m_psi + 3 G p <= 0 returns to the apex (sigma = 0, dl = q / 3G), otherwise
        dl = f / (3 G + K m m_psi), q <- q - 3 G dl, p <- p + K m_psi dl. Returns (sigma, dl)."""
        a = (0.25 * self.scheme.dt) * (gradient[1, 0] - gradient[0, 1])
        scale = 1.0 / (1.0 + a * a)
        cos, sin = (1.0 - a * a) * scale, 2.0 * a * scale
        rotation = ti.Matrix([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]], self.dtype)
        rate = ti.Matrix.zero(self.dtype, 3, 3)
        for i, j in ti.static(ti.ndrange(2, 2)):
            rate[i, j] = 0.5 * (gradient[i, j] + gradient[j, i])
        volumetric = rate[0, 0] + rate[1, 1] + rate[2, 2]
        identity = ti.Matrix.identity(self.dtype, 3)
        trial = rotation @ stress @ rotation.transpose() + self.scheme.dt * (
            self.scheme.bulk * volumetric * identity + (2.0 * self.scheme.shear) * deviator(rate))
        pressure = -(trial[0, 0] + trial[1, 1] + trial[2, 2]) / 3.0
        deviatoric = deviator(trial)
        squares = 0.0
        for i, j in ti.static(ti.ndrange(3, 3)):
            squares += deviatoric[i, j] * deviatoric[i, j]
        q = 0.0
        if squares > 0.0:
            q = ti.sqrt(1.5 * squares)
        overstress = q - self.scheme.slope * pressure
        dilation_rate = self.scheme.bulk * self.scheme.dilation_slope
        new_stress, increment = trial, 0.0
        if overstress > 0.0 or pressure < 0.0:
            if q * dilation_rate + (3.0 * self.scheme.shear) * pressure <= 0.0:
                new_stress, increment = ti.Matrix.zero(self.dtype, 3, 3), q / (3.0 * self.scheme.shear)
            else:
                increment = overstress / (3.0 * self.scheme.shear + self.scheme.slope * dilation_rate)
                returned = q - (3.0 * self.scheme.shear) * increment
                new_stress = deviatoric * (returned / q) - (pressure + dilation_rate * increment) * identity
        return new_stress, increment

    @ti.kernel
    def step(self):
        """One explicit MUSL step; Taichi runs the top-level loops one after another."""
        self.clear_nodes()
        self.particles_to_grid()
        self.fold_ghosts(True)
        self.node_velocities(True)
        self.mirror_ghosts()
        self.grid_to_particles()
        self.clear_momentum()
        self.remap_momentum()
        self.fold_ghosts(False)
        self.node_velocities(False)
        self.mirror_ghosts()
        self.update_points()


@ti.func
def deviator(tensor):
    """t - tr(t)/3 I of a 3x3 tensor (the mean taken off the diagonal only, as t - mean I does)."""
    mean = (tensor[0, 0] + tensor[1, 1] + tensor[2, 2]) / 3.0
    result = tensor
    for i in ti.static(range(3)):
        result[i, i] = tensor[i, i] - mean
    return result


def start_taichi(dtype, fast_math=True):
    """ti.init on the CPU backend with THREADS threads and `dtype` as the default float."""
    ti.init(arch=ti.cpu, cpu_max_num_threads=THREADS, default_fp=dtype, fast_math=fast_math, log_level=ti.WARN)


def particle_arrays(state) -> dict:
    """The points of a jaxmpm State as numpy arrays, keyed as `ReferenceMPM.load` takes them."""
    particles = state.particles
    (history,) = particles.history
    arrays = {name: getattr(particles, name) for name in ("x", "v", "affine", "stress", "volume", "mass")}
    arrays["plastic_strain"] = history["plastic_strain"]
    return {name: np.asarray(values) for name, values in arrays.items()}


def reference_for(sim, params, initial, dtype, fast_math=True, serial_scatter=True) -> ReferenceMPM:
    """Taichi started and a ReferenceMPM of `sim` loaded with the jaxmpm state `initial`."""
    start_taichi(dtype, fast_math)
    reference = ReferenceMPM(scheme_of(sim, params), sim.point_count, dtype, serial_scatter)
    reference.load(particle_arrays(initial))
    return reference


def run_jaxmpm(sim, params, initial):
    """The jaxmpm state after sim.steps steps from `initial`."""
    state = initial
    for _ in range(sim.outputs):
        state, _ = sim._advance(params, state, initial.particles.x)
    assert int(state.error_step) < 0, "the jaxmpm run failed"
    return state


def agreement(ours: dict, theirs: dict, cell: float) -> dict:
    """Largest differences of the two end states: positions (absolute [m] and in cells), and
    velocity, stress, volume and plastic strain relative to their largest magnitude."""
    def relative(name):
        return float(np.max(np.abs(ours[name] - theirs[name])) / np.max(np.abs(theirs[name])))

    position = float(np.max(np.abs(ours["x"] - theirs["x"])))
    return {"position_m": position, "position_cells": position / cell,
            **{name: relative(name) for name in ("v", "stress", "volume", "plastic_strain")}}


def check(steps: int, fast_math: bool) -> dict:
    """Both codes `steps` steps in float64 from jaxmpm's initial state of the throughput scene
    (16,384 points, Drucker-Prager, bspline2 + APIC + MUSL): the motion, and the differences of
    the kernel with serial and with atomic scatters ({"serial": ..., "atomic": ...})."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxmpm import Simulation
    from common import block_scene

    sim = Simulation(block_scene(128, "float64", steps, "drucker_prager", "bspline2", transfer="apic"))
    params = sim.cast(sim.params)
    initial = sim.initial_state(params)
    theirs = particle_arrays(run_jaxmpm(sim, params, initial))
    result = {"steps": sim.steps, "points": sim.point_count, "fast_math": fast_math,
              "largest_displacement_m": float(np.max(np.abs(theirs["x"] - np.asarray(initial.particles.x)))),
              "largest_stress_pa": float(np.max(np.abs(theirs["stress"]))),
              "yielded_points": int(np.count_nonzero(theirs["plastic_strain"]))}
    for scatter in ("serial", "atomic"):
        reference = reference_for(sim, params, initial, ti.f64, fast_math, serial_scatter=scatter == "serial")
        reference.advance(sim.steps)
        ti.sync()
        result[scatter] = agreement(reference.dump(), theirs, sim.scene.grid.cell)
    return result


def describe(result: dict) -> str:
    """The check's result in two sentences."""
    lines = [f"{result['points']:,} points, {result['steps']} steps, float64, Taichi fast_math "
             f"{'on' if result['fast_math'] else 'off'}: largest displacement {result['largest_displacement_m']:.3g} m, "
             f"largest |sigma| {result['largest_stress_pa']:.4g} Pa, {result['yielded_points']:,} points yielded."]
    for scatter in ("serial", "atomic"):
        d = result[scatter]
        lines.append(f"{scatter} scatters: max |x difference| {d['position_m']:.2g} m ({d['position_cells']:.2g} cells); "
                     f"max difference over the largest value: v {d['v']:.2g}, stress {d['stress']:.2g}, "
                     f"volume {d['volume']:.2g}, plastic strain {d['plastic_strain']:.2g}.")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description="float64 agreement of the Taichi reference with jaxmpm")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--exact-math", action="store_true", help="Taichi's fast_math off (the timing runs with it on)")
    parser.add_argument("--json", action="store_true", help="the result as JSON on the last line")
    args = parser.parse_args()
    result = check(args.steps, fast_math=not args.exact_math)
    print(json.dumps(result) if args.json else describe(result))


if __name__ == "__main__":
    main()
