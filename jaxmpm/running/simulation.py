"""`Simulation`: a scene split into static structure and a parameter pytree, its step and probes.

    sim = Simulation(scene)
    sim.params                      # {"materials": {"sand": {"density": 1800.0, ...}}, "contacts": ...}
    sim.probes(params)              # {name: (T, k)}, differentiable w.r.t. every parameter
    sim.run()                       # a forward run with progress, file and resume (`jaxmpm.running.runner`)

The structure (grid, shape function, which materials, step count, time step) is fixed when the
Simulation is built and compiled once; parameters are traced values, so `jax.grad`, `jax.jvp`
and `jax.vmap` over them never recompile. The time step is set once, from the scene's own
parameter values: a parameter change that raises the wave speed does not shorten it.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxmpm.physics.bodies import convex_outline, joined_edges, seeded_outline
from jaxmpm.running.budget import check_memory
from jaxmpm.errors import SceneError
from jaxmpm.physics.grid import GridLayout
from jaxmpm.physics.initial_stress import geostatic_stress, jaky_k0, thickness_above
from jaxmpm.physics.contact import Interface, bounding_fields
from jaxmpm.kernels.xla_options import compiler_options, jit_with_options
from jaxmpm.keys import is_concrete
from jaxmpm.materials.base import material_parameters
from jaxmpm.scene.parameters import scene_parameters
from jaxmpm.physics.probes import contact_facings, make_probes
from jaxmpm.running.runner import chunk_length, run_forward
from jaxmpm.running.results import Result
from jaxmpm.running.rollout import Checkpointing, checkpointed_rollout, scan_steps, state_bytes
from jaxmpm.scene import Scene
from jaxmpm.scene.seeding import padded, seed_bodies
from jaxmpm.physics.solver import (
    BodyBlock, Structure, body_memory, kept_grid_bytes, kept_solve_bytes, make_step, transfer_memory,
)
from jaxmpm.physics.state import Diagnostics, Particles, RigidMotion, State, counters_at_start
from jaxmpm.physics.time_step import exceeds, material_limits, substeps, time_stepping
from jaxmpm.running.tracing import collector_paused


def check_dtype(scene: Scene):
    """float64 scenes need JAX's 64-bit mode, which the library never switches on by itself."""
    if scene.numerics.dtype == "float64" and not jax.config.jax_enable_x64:
        raise SceneError(
            "numerics.dtype = 'float64' needs JAX's 64-bit mode: call "
            "jax.config.update('jax_enable_x64', True) at the start of the program "
            "(the jaxmpm command does), or set numerics.dtype = 'float32'."
        )


def slowest_crossing_time(scene: Scene) -> float:
    """h / c_p of the free body whose p-wave is slowest (scene values) [s]: the time scale
    of the APIC transfer's memory (`solver.transfer_memory`); inf without free bodies."""
    speeds = [float(scene.material_of(body).wave_speed(material_parameters(scene.material_of(body))))
              for body in scene.bodies if body.kinematics.type == "free"]
    return scene.grid.cell / min(speeds) if speeds else math.inf


def velocity_fields(scene: Scene):
    """(field of each body, number of fields, interfaces): bodies of a contact pair and
    prescribed, rigid or subcycled bodies get a field each; all other bodies share field 0 (no
    slip among them). Every pair of fields meets at an interface: frictional contact for a
    declared pair, bonded (no slip) otherwise; two prescribed, rigid or subcycled fields ignore
    each other. A contact takes a prescribed side's own normal, else the mass-weighted mean
    normal held in the normal cone of a rigid or elastic side's outline (`bounding_side`)."""
    paired = {name for contact in scene.contacts for name in contact.pair}
    whole = {body.name for body in scene.bodies if body.kinematics.type != "free" or body.kinematics.subcycled}
    own = [body.name for body in scene.bodies if body.name in paired or body.name in whole]
    shared = [body.name for body in scene.bodies if body.name not in own]
    field = {name: 0 for name in shared}
    field.update({name: index + bool(shared) for index, name in enumerate(own)})
    count = len(own) + bool(shared)
    kinematic = {field[name] for name in whole}    # keep their velocity in contact (`contact.Interface`)
    prescribed = {field[body.name] for body in scene.bodies if body.kinematics.type == "prescribed"}
    contacts = {frozenset(field[name] for name in contact.pair): contact for contact in scene.contacts}
    outline_rank = outline_ranks(scene, field)
    interfaces = []
    for pair in itertools.combinations(range(count), 2):
        if set(pair) <= kinematic:
            continue
        contact = contacts.get(frozenset(pair))
        first, second = pair if contact is None else (field[contact.pair[0]], field[contact.pair[1]])
        name = None if contact is None else contact.name      # a contact keeps its pair's order
        held = next((side for side in (first, second) if side in prescribed), None)
        bounded = None if held is not None or contact is None else bounding_side(first, second, outline_rank)
        interfaces.append(Interface(first, second, name, first in kinematic, second in kinematic, held,
                                    bounded_by=bounded))
    return field, count, tuple(interfaces)


def outline_ranks(scene: Scene, field: dict) -> dict:
    """{field: 2 for a rigid body, 1 for a free elastic one (its law does not yield), 0
    otherwise}, for the fields of bodies with a convex region: how well the body's outline
    is known at any time (a rigid body's exactly, a stiff elastic one's to its strain)."""
    ranks = {}
    for body in scene.bodies:
        convex = convex_outline(body.region.vertices) is not None
        if body.kinematics.type == "rigid" and convex:
            ranks[field[body.name]] = 2
        elif body.kinematics.type == "free" and convex and not scene.material_of(body).law.yields:
            ranks[field[body.name]] = 1
    return ranks


def bounding_side(first, second, rank):
    """The side of a contact (neither prescribed) whose outline bounds its normal
    (`contact.Interface.bounded_by`): the one whose outline is better known, None if neither
    or both alike (two elastic bodies: the mass-weighted mean alone)."""
    first_rank, second_rank = rank.get(first, 0), rank.get(second, 0)
    if first_rank == second_rank:
        return None
    return first if first_rank > second_rank else second


def joined_structures(scene: Scene) -> dict:
    """{body: (joined edges (K,) bool, the other parts' names)} for each prescribed body with a
    convex outline: prescribed bodies that move together (the same velocity and velocity
    table) and share an edge (`bodies.joined_edges`) are parts of one structure, e.g. a pile's
    tip and shaft split to read their forces apart; parts joined through others belong to it too.
    Decided from the scene's values: parts later given different velocities stay joined."""
    moving = [body for body in scene.bodies if body.kinematics.type == "prescribed"]
    outlines = {body.name: convex_outline(body.region.vertices) for body in moving}
    motion = {body.name: (np.asarray(body.kinematics.velocity, float).tolist(),
                          None if body.kinematics.time is None else [float(t) for t in body.kinematics.time])
              for body in moving}
    named = [name for name, outline in outlines.items() if outline is not None]

    def meet(a, b):
        return motion[a] == motion[b] and (joined_edges(outlines[a], [outlines[b]]).any()
                                           or joined_edges(outlines[b], [outlines[a]]).any())

    neighbours = {a: [b for b in named if b != a and meet(a, b)] for a in named}
    found = {}
    for name in named:
        parts, frontier = {name}, [name]
        while frontier:
            for other in neighbours[frontier.pop()]:
                if other not in parts:
                    parts.add(other)
                    frontier.append(other)
        edges = joined_edges(outlines[name], [outlines[other] for other in neighbours[name]])
        found[name] = (tuple(bool(edge) for edge in edges), tuple(other for other in named if other in parts - {name}))
    return found


def share_among_parts(interfaces, parts_of_field) -> tuple:
    """The interfaces, each between a free field and a part of a joined structure
    (`joined_structures`; parts_of_field {field: the other parts' fields}) told which of the
    other parts' interfaces with the same free field come after it (`Interface.shared_with`)."""
    shared = []
    for index, interface in enumerate(interfaces):
        part = interface.normal_from
        free = interface.second if part == interface.first else interface.first
        later = tuple(
            other.normal_from for other in interfaces[index + 1:]
            if other.normal_from in parts_of_field.get(part, ()) and free in (other.first, other.second)
        )
        shared.append(dataclasses.replace(interface, shared_with=later) if later else interface)
    return tuple(shared)


class Simulation:
    """The differentiable handle on a scene. See the module docstring."""

    def __init__(self, scene: Scene, checkpointing: Checkpointing = Checkpointing(), devices=None):
        """`devices` (a list of two or more, e.g. `jax.devices()`): the points are sharded over
        them along one mesh axis, the grid replicated; XLA combines each device's part of the
        particle-to-grid sums (docs/devices.md)."""
        check_dtype(scene)
        self.scene = scene
        self.checkpointing = checkpointing
        self.dtype = jnp.dtype(scene.numerics.dtype)
        self.dt, self.steps_per_output, self.outputs = time_stepping(scene)
        self.steps = self.steps_per_output * self.outputs
        check_memory(scene, self.steps)          # before anything of that size is allocated
        self.seeds = seed_bodies(scene)
        self.body_slices = self.seeds.slices        # each body's points in outputs (no padding)
        self.mesh = None if devices is None or len(devices) < 2 else Mesh(np.asarray(devices), ("points",))
        if self.mesh is not None:
            self.seeds = padded(self.seeds, self.mesh.devices.size)
        self.time = np.arange(self.steps + 1) * self.dt
        field, fields, interfaces = velocity_fields(scene)
        bounding = bounding_fields(interfaces)
        memory = transfer_memory(scene.transfer, scene.numerics.flip, scene.numerics.relaxation, self.dt,
                                 slowest_crossing_time(scene))
        blocks = tuple(
            BodyBlock(body.name, body.material, scene.material_of(body).law, start, stop, field[body.name],
                      body.kinematics.type, body.kinematics.time,
                      *self.outline_of(body, start, stop, field[body.name] in bounding),
                      memory=body_memory(memory, scene.material_of(body).law, scene.transfer, scene.numerics.relaxation),
                      substeps=substeps(scene, body, self.dt))
            for body, (start, stop) in zip(scene.bodies, self.seeds.slices)
        )
        structures = joined_structures(scene)
        blocks = tuple(
            dataclasses.replace(block, joined=structures[block.name][0],
                                partners=tuple(field[other] for other in structures[block.name][1]))
            if block.name in structures else block for block in blocks
        )
        interfaces = share_among_parts(interfaces, {block.field: block.partners for block in blocks if block.partners})
        self.structure = Structure(
            layout=GridLayout(scene.grid.origin, scene.grid.cell, scene.grid.cells, scene.numerics.shape, scene.numerics.ppc),
            boundaries=scene.grid.boundaries,
            dt=self.dt,
            transfer=scene.transfer,
            memory=memory,
            damped=bool(scene.numerics.damping),
            update=scene.numerics.update,
            bodies=blocks,
            fields=fields,
            interfaces=interfaces,
            point_spacing=scene.grid.cell / scene.numerics.ppc,
            axisymmetric=scene.geometry == "axisymmetric",
            corner_radius=scene.numerics.corner_radius,
            stress_substeps=scene.numerics.stress_substeps,
            structure_hold=scene.numerics.structure_hold,
            facings=contact_facings(scene),
        )
        self.params = scene_parameters(scene)
        self.step = make_step(self.structure)
        self.observe = make_probes(scene, self.seeds)
        self._probes = jax.jit(self._probes_from_state)    # also nested in callers' jits: XLA's defaults
        self._initial = jax.jit(self._initial_state_from)   # one small program, not an op at a time
        self.compiled_cache = {}     # compiled work built on this simulation (e.g. calibrations)
        self.chunk = chunk_length(self.steps_per_output, self.point_count)   # steps per compiled call of `run`
        self._advance = jit_with_options(self._advance_chunk, several_fields=self.several_fields)
        self._advance_rest = jit_with_options(self._advance_remainder, several_fields=self.several_fields)
        self._variants = {}         # the same simulation for other `derivatives` (`for_derivatives`)

    def forward_only(self) -> "Simulation":
        """This simulation, compiled for programs that are evaluated, vmapped and differentiated
        in forward mode only (`jax.jvp`, `jax.jacfwd`: Levenberg-Marquardt Jacobians,
        ensembles): its particle-to-grid scatter batches with its own rule
        (`jaxmpm.kernels.scatter`). The same values; reverse mode raises. Made once."""
        return self.for_derivatives("forward")

    def reverse_only(self) -> "Simulation":
        """This simulation, compiled for programs differentiated in reverse mode only
        (`jax.grad`, `jax.vjp`): its transfers transpose into each other
        (`jaxmpm.kernels.transposes`). The same values and gradients; forward mode raises.
        Made once."""
        return self.for_derivatives("reverse")

    def for_derivatives(self, derivatives: str) -> "Simulation":
        """This simulation with `Structure.derivatives` = derivatives ("any", "forward" or
        "reverse"), sharing everything else (made once per kind)."""
        if derivatives == self.structure.derivatives:
            return self
        if derivatives not in self._variants:
            variant = copy.copy(self)
            variant.structure = dataclasses.replace(self.structure, derivatives=derivatives)
            variant.step = make_step(variant.structure)
            variant._probes = jax.jit(variant._probes_from_state)
            variant.compiled_cache = {}
            variant._advance = jit_with_options(variant._advance_chunk, several_fields=variant.several_fields)
            variant._advance_rest = jit_with_options(variant._advance_remainder, several_fields=variant.several_fields)
            variant._variants = {}
            self._variants[derivatives] = variant
        return self._variants[derivatives]

    def outline_of(self, body, start, stop, bounds):
        """(outline, outline_centre, reference_arms) of a prescribed or rigid body whose region
        is convex, or of a free body whose outline `bounds` a contact's normal (see
        `solver.BodyBlock`); Nones otherwise. A rigid body's centre is its centre of mass (its
        density is uniform), which its translation and rotation refer to."""
        outline = convex_outline(body.region.vertices)
        if outline is None or (body.kinematics.type == "free" and not bounds):
            return None, None, None
        positions = self.seeds.positions[start:stop]
        if self.scene.numerics.structure_hold == "points" and body.kinematics.type != "free":
            outline = seeded_outline(outline, positions, self.scene.grid.cell / self.scene.numerics.ppc)
        weights = self.seeds.volumes[start:stop] if body.kinematics.type == "rigid" else np.ones(stop - start)
        centre = weights @ positions / weights.sum()
        arms = None
        if body.kinematics.type == "free":
            arms = tuple(map(tuple, (positions - centre).tolist()))
        return outline, (float(centre[0]), float(centre[1])), arms

    @property
    def several_fields(self) -> bool:
        """Whether the grid carries several velocity fields (contact, prescribed or rigid bodies)."""
        return self.structure.fields > 1

    def compiler_options(self, reverse_mode: bool = False) -> dict:
        """The XLA options jaxmpm compiles this scene's programs with (`jaxmpm.kernels.xla_options`),
        for your own jits: `jax.jit(jax.grad(loss), compiler_options=sim.compiler_options(True))`."""
        return compiler_options(reverse_mode=reverse_mode, several_fields=self.several_fields)

    @property
    def point_count(self) -> int:
        """The scene's material points (without the inert ones that pad a sharded state)."""
        return self.body_slices[-1][1]

    def place(self, state: State) -> State:
        """The state laid out over the devices: per-point arrays sharded along the points,
        everything else replicated (as it is, without `devices`)."""
        if self.mesh is None:
            return state
        count = len(self.seeds.positions)
        points, whole = NamedSharding(self.mesh, PartitionSpec("points")), NamedSharding(self.mesh, PartitionSpec())
        return jax.tree_util.tree_map(
            lambda leaf: jax.device_put(leaf, points if jnp.ndim(leaf) and jnp.shape(leaf)[0] == count else whole), state)

    def material_time_steps(self, params, initial: State | None = None) -> dict:
        """{material: h / (c_p + max speed of its free bodies)} for these parameter values [s]
        (`time_step.material_limits`); the speed is each body's scene velocity, or the largest
        |v| of its points in `initial`."""
        speeds = None
        if initial is not None:
            speeds = {}
            for block in self.structure.bodies:
                velocity = np.asarray(initial.particles.v[block.points])
                speeds[block.name] = float(np.max(np.hypot(velocity[:, 0], velocity[:, 1])))
        return material_limits(self.scene, params["materials"], speeds)

    def stable_time_step(self, params, initial: State | None = None) -> float:
        """h / max over free bodies of (c_p + |v|) for these parameter values (and initial
        state) [s]; the scene's own values give `scene.stable_dt` (when a free body sets it)."""
        return min(self.material_time_steps(params, initial).values(), default=math.inf)

    def check_time_step(self, params, initial: State | None = None):
        """SceneError if concrete parameter values (or initial velocities) make the fixed time
        step unstable. Traced values (inside jit, grad, vmap) cannot be checked here: there an
        unstable step shows up as a non-finite state (error bits, SimulationError in `run`). A
        relative slack (`time_step.STEP_SLACK`) absorbs round-off (float32 parameters, the rounding of dt
        to whole steps)."""
        leaves = jax.tree_util.tree_leaves(params) + ([] if initial is None else [initial.particles.v])
        if not all(is_concrete(leaf) for leaf in leaves):
            return
        for material, limit in self.material_time_steps(params, initial).items():
            if exceeds(self.dt, limit):
                own = self.params["materials"][material]
                changed = {
                    key: float(value) for key, value in params["materials"][material].items()
                    if float(value) != float(own[key])
                }
                values = ", ".join(f"{key} = {value:g}" for key, value in changed.items()) or "the scene's values"
                moving = "" if initial is None else (
                    f" with the initial velocities (up to {float(np.max(np.abs(np.asarray(initial.particles.v)))):.4g} m/s)"
                )
                raise SceneError(
                    f"params['materials'][{material!r}] ({values}){moving} need a time step below {limit:.4g} s, "
                    f"but the one fixed from the scene is {self.dt:.4g} s: build the Simulation from a scene "
                    f"holding these values (scene.with_value) or lower scene.cfl."
                )
        for body, values in params.get("bodies", {}).items():
            speed = float(np.max(np.hypot(*np.reshape(np.asarray(values["velocity"]), (-1, 2)).T)))
            if exceeds(speed * self.dt, self.scene.grid.cell):
                raise SceneError(
                    f"params['bodies'][{body!r}]['velocity'] reaches {speed:.4g} m/s, which moves the body more than "
                    f"a cell ({self.scene.grid.cell:g} m) in the fixed time step {self.dt:.4g} s: build the "
                    "Simulation from a scene holding this velocity (scene.with_value) or lower scene.cfl."
                )

    def cast(self, params):
        """Parameters as arrays of the scene's dtype (so values of any kind never retrace),
        replicated over the devices of a sharded simulation."""
        params = jax.tree_util.tree_map(lambda value: jnp.asarray(value, self.dtype), params)
        if self.mesh is None:
            return params
        return jax.device_put(params, NamedSharding(self.mesh, PartitionSpec()))

    def initial_state(self, params=None) -> State:
        """The state at t = 0: seeded points at rest (or at their body's velocity; prescribed
        bodies at their velocity at t = 0), zero stress or geostatic; rigid bodies not yet
        moved. Masses follow params["materials"][material]["density"] and geostatic stresses also
        params["scene"]["gravity"], so gradients reach them."""
        params = self.cast(self.params if params is None else params)
        return self.place(self._initial(params))

    def _initial_state_from(self, params) -> State:
        """`initial_state` on one device (compiled once per simulation as `_initial`)."""
        count, dtype = len(self.seeds.positions), self.dtype
        masses, velocities, stresses, histories, rigid = [], [], [], [], {}
        for block, body in zip(self.structure.bodies, self.scene.bodies):
            size = block.stop - block.start
            material = params["materials"][block.material_name]
            volume = jnp.asarray(self.seeds.volumes[block.points], dtype)
            masses.append(material["density"] * volume)
            velocity = jnp.asarray(body.velocity, dtype)
            if block.kinematics == "prescribed":
                velocity = params["bodies"][block.name]["velocity"]
                velocity = velocity if block.times is None else velocity[0]
            velocities.append(jnp.broadcast_to(velocity, (size, 2)))
            stresses.append(self.body_initial_stress(body, block, params))
            histories.append(block.law.init_state(size, dtype))
            if block.kinematics == "rigid":
                zero = jnp.zeros((), dtype)
                rigid[block.name] = RigidMotion(jnp.zeros(2, dtype), zero, velocity, zero)
        particles = Particles(
            x=jnp.asarray(self.seeds.positions, dtype),
            v=jnp.concatenate(velocities),
            affine=jnp.zeros((count, 2, 2), dtype),
            stress_voigt=jnp.concatenate(stresses),
            volume=jnp.asarray(self.seeds.volumes, dtype),
            mass=jnp.concatenate(masses),
            history=tuple(histories),
            flags=jnp.zeros((count,), jnp.int32),
        )
        return State(particles=particles, rigid=rigid, **counters_at_start())

    def body_initial_stress(self, body, block, params):
        """(n_body, 4) initial stress of one body (`Particles.stress_voigt`): zero, or
        geostatic under the weight of the geostatic bodies' points above each point, its own
        body's and those stacked on it (`initial_stress`), from the materials' params and the
        gravity (2,) of params["scene"]."""
        size = block.stop - block.start
        if body.initial_stress is None:
            return jnp.zeros((size, 4), self.dtype)
        material = params["materials"][block.material_name]
        k0 = body.initial_stress.k0
        k0 = jaky_k0(material["friction_angle"]) if k0 == "jaky" else k0
        spacing = self.scene.grid.cell / self.scene.numerics.ppc
        origin = self.scene.grid.origin
        positions = self.seeds.positions[block.points]
        overburden = material["density"] * jnp.full(len(positions), 0.5 * spacing, self.dtype)
        for other_block, other in zip(self.structure.bodies, self.scene.bodies):
            if other.initial_stress is not None:
                thickness = thickness_above(positions, self.seeds.positions[other_block.points], spacing, origin)
                if thickness.any():
                    density = params["materials"][other_block.material_name]["density"]
                    overburden = overburden + density * jnp.asarray(thickness, self.dtype)
        return geostatic_stress(overburden, params["scene"]["gravity"][1], k0)

    # ------------------------------------------------------------------ differentiable

    def _advance_and_observe(self, params, initial_x):
        def advance(state):
            state, diagnostics = self.step(params, state)
            return state, self.observe(state, diagnostics, initial_x)

        return advance

    def checkpointing_for(self, initial: State) -> Checkpointing:
        """The checkpointing of a probe rollout from `initial`, "auto" decided for its size."""
        return self.checkpointing.resolved(self.steps, *self._kept_bytes_per_step(initial)[1:])

    def _kept_bytes_per_step(self, initial):
        """(state, state and the laws' remembered values, node arrays and velocity gradients):
        the bytes a step of a probe rollout from `initial` keeps for reverse mode."""
        dtype = initial.particles.x.dtype
        state = state_bytes(initial)
        solves = kept_solve_bytes(self.structure, dtype)
        return state, state + solves, kept_grid_bytes(self.structure, self.point_count, dtype.itemsize)

    def reverse_mode_memory(self) -> tuple[Checkpointing, int | None]:
        """(checkpointing, bytes): how a gradient through the probe rollout is checkpointed
        ("auto" decided for this scene) and the bytes it keeps for its backward pass, counted
        from shapes without running anything: one segment keeps every step's state, what the
        laws remember and (with "recompute_grid") the node arrays; segments keep one state a
        segment and that for the steps of one segment. The step's own temporaries come on top.
        None for the policies that keep intermediates ("store", "recompute_arithmetic",
        "names:...", "dots"), which are not counted."""
        state, recomputed, grid = self._kept_bytes_per_step(jax.eval_shape(self.initial_state))
        checkpointing = self.checkpointing.resolved(self.steps, recomputed, grid)
        per_step = {"recompute": recomputed, "recompute_grid": recomputed + grid}.get(checkpointing.step)
        if per_step is None:
            return checkpointing, None
        return checkpointing, checkpointing.kept_bytes(self.steps, state, per_step)

    def _probes_from_state(self, params, initial):
        advance = self._advance_and_observe(params, initial.particles.x)
        checkpointing = self.checkpointing_for(initial)
        final, histories = checkpointed_rollout(advance, initial, self.steps, checkpointing)
        first = self.observe_start(initial)
        probes = {name: jnp.concatenate([first[name][None], histories[name]]) for name in first}
        return probes, final

    def observe_start(self, state):
        """Probe values of a state before any step ({name: (k,)}): forces read 0 there (the
        first step's forces are the first ones a run records)."""
        return self.observe(state, self.quiet_diagnostics(state.particles.x.dtype), state.particles.x)

    def quiet_diagnostics(self, dtype):
        """Diagnostics of no step: every contact force and reaction zero."""
        zero = jnp.zeros(2, dtype)
        return Diagnostics(
            {contact.name: zero for contact in self.scene.contacts},
            {block.name: zero for block in self.structure.blocks_of("prescribed")},
            {face: zero for face in self.structure.facings},
        )

    def probes(self, params=None, initial: State | None = None):
        """Probe histories {name: (T, k)} with T = steps + 1 (t = 0 included), from `params`
        (default `self.params`) and an optional initial state (default `initial_state(params)`).
        Differentiable with respect to params and to the initial state."""
        params = self.cast(self.params if params is None else params)
        self.check_time_step(params, initial)
        initial = self.initial_state(params) if initial is None else initial
        with collector_paused():
            return self._probes(params, initial)[0]

    def final_state(self, params=None, initial: State | None = None) -> State:
        """The state after the last step (differentiable, like `probes`)."""
        return self.probes_and_final_state(params, initial)[1]

    def probes_and_final_state(self, params=None, initial: State | None = None):
        """(probe histories, final state) of one rollout: `probes` and `final_state` together."""
        params = self.cast(self.params if params is None else params)
        self.check_time_step(params, initial)
        initial = self.initial_state(params) if initial is None else initial
        with collector_paused():
            return self._probes(params, initial)

    # ------------------------------------------------------------------ forward runs

    def _advance_chunk(self, params, state, initial_x):
        """`chunk` steps and their probe rows: the compiled unit of `run`."""
        advance = self._advance_and_observe(params, initial_x)
        return scan_steps(advance, state, self.chunk)

    def _advance_remainder(self, params, state, initial_x):
        """The steps of an output interval after its whole chunks (fewer than `chunk`, when
        `chunk` does not divide it) and their probe rows: `run`'s second compiled unit."""
        advance = self._advance_and_observe(params, initial_x)
        return scan_steps(advance, state, self.steps_per_output % self.chunk)

    def run(self, params=None, initial=None, progress=True, save_to=None, resume=False):
        """Forward run with a progress bar; see `simulate` and `runner.run_forward`."""
        return run_forward(self, params, initial, progress, save_to, resume)


def simulate(scene: Scene, params=None, progress=True, save_to=None, resume=False) -> Result:
    """Run a scene forward and return its Result (time, probes, snapshots).

    With `save_to`, the HDF5 file grows output by output (valid and readable throughout,
    complete = false until the end) and the Result's snapshots stay in it (read when asked
    for), so memory does not grow with the run. A run that stops early (non-finite state,
    point off the grid, Ctrl-C or SIGTERM, taken between output intervals) keeps what it
    computed; `resume=True` continues such a run from its last output and ends exactly as
    the uninterrupted run would. A failed run raises SimulationError, whose `.result` holds
    the part computed."""
    return Simulation(scene).run(params=params, progress=progress, save_to=save_to, resume=resume)
