"""Forward and backward (vjp with stored residuals) time of each phase of one MPM step.

    python benchmarks/reverse_phases.py POINTS DTYPE MATERIAL SHAPE [--noynn]
"""

import argparse
import os
import sys
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).parent))


from reverse_decomposition import best_median  # noqa: E402  (same directory)


def best(function, *args):
    """Best and median of 15 timed calls after one untimed call."""
    return best_median(function, *args, repeats=15)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("points", type=int)
    parser.add_argument("dtype")
    parser.add_argument("material")
    parser.add_argument("shape")
    parser.add_argument("--noynn", action="store_true")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxmpm
    from jaxmpm.physics import solver
    from jaxmpm.physics.grid import apply_edge_conditions, boundary_mask
    from jaxmpm.kernels.xla_options import NO_YNNPACK
    from common import block_scene
    from throughput import SIZES

    options = NO_YNNPACK if args.noynn else {}
    sim = jaxmpm.Simulation(block_scene(SIZES[args.points], args.dtype, 200, args.material, args.shape))
    params = sim.cast(sim.params)
    initial = sim.initial_state(params)
    state = jax.jit(lambda p, s: jaxmpm.running.rollout.scan_steps(sim._advance_and_observe(p, s.particles.x), s, 20)[0])(params, initial)
    structure, layout, dt = sim.structure, sim.structure.layout, sim.structure.dt
    mask = boundary_mask(layout, structure.boundaries, state.particles.x.dtype)

    def constrain(v):
        return apply_edge_conditions(v, mask, layout, structure.boundaries)

    floor = solver.MASS_FLOOR * jnp.max(state.particles.mass)
    particles = state.particles
    stencil = layout.stencil(particles.x)
    nodes = solver.particles_to_grid(particles, stencil, None, None, structure, params["scene"]["gravity"])
    v_old, v_new = solver.update_grid_velocity(nodes, dt, None, constrain, floor)
    moved = solver.grid_to_particles(particles, stencil, v_old, v_new, None, structure.memory, dt, layout)
    remapped = solver.remap_velocity(moved, stencil, None, structure, nodes.mass, constrain, floor)
    gradient = solver.velocity_gradient(stencil, remapped, None, structure, particles.x)

    phases = {
        "stencil": (lambda x: layout.stencil(x)[1:], (particles.x,)),
        "particles_to_grid": (lambda p, w, g: solver.particles_to_grid(p, stencil._replace(weights=w, gradients=g), None, None, structure, params["scene"]["gravity"])[:3],
                              (particles, stencil.weights, stencil.gradients)),
        "update_grid": (lambda n: solver.update_grid_velocity(n, dt, None, constrain, floor), (nodes,)),
        "grid_to_particles": (lambda p, w, vo, vn: solver.grid_to_particles(p, stencil._replace(weights=w), vo, vn, None, structure.memory,
                                                                         dt, layout),
                              (particles, stencil.weights, v_old, v_new)),
        "remap_velocity": (lambda p, w, m: solver.remap_velocity(p, stencil._replace(weights=w), None, structure, m, constrain, floor),
                           (moved, stencil.weights, nodes.mass)),
        "velocity_gradient": (lambda g, v: solver.velocity_gradient(stencil._replace(gradients=g), v, None, structure, particles.x),
                              (stencil.gradients, remapped)),
        "update_stress": (lambda p, m, L: solver.update_stress(m, p, L, structure.bodies, dt), (moved, params["materials"], gradient)),
    }
    print(f"# {args.points} {args.dtype} {args.material} {args.shape} noynn={args.noynn} load={os.getloadavg()[0]:.2f}", flush=True)

    def floats_only(tree):
        return jax.tree_util.tree_map(lambda x: x if jnp.issubdtype(x.dtype, jnp.floating) else None, tree)

    jitted = {}
    for name, (function, inputs) in phases.items():
        def wrapped(*xs, function=function, inputs=inputs):
            return floats_only(function(*xs))

        # differentiate only floating leaves: close over the rest
        leaves, treedef = jax.tree_util.tree_flatten(inputs)
        is_float = [jnp.issubdtype(l.dtype, jnp.floating) for l in leaves]
        floats = [l for l, f in zip(leaves, is_float) if f]

        def of_floats(fl, wrapped=wrapped, leaves=leaves, treedef=treedef, is_float=is_float):
            it = iter(fl)
            return wrapped(*jax.tree_util.tree_unflatten(treedef, [next(it) if f else l for l, f in zip(leaves, is_float)]))

        out, vjp_fn = jax.vjp(of_floats, floats)
        ct = jax.tree_util.tree_map(jnp.ones_like, out)
        jf = jax.jit(of_floats, compiler_options=options)
        jb = jax.jit(lambda f, c: f(c), compiler_options=options)
        jitted[name] = (jf, floats, jb, vjp_fn, ct)
    rows = {name: ([], []) for name in phases}
    for _ in range(args.rounds):
        for name, (jf, floats, jb, vjp_fn, ct) in jitted.items():
            rows[name][0].append(best(jf, floats))
            rows[name][1].append(best(jb, vjp_fn, ct))
    total_f = total_b = 0.0
    for name, (f, b) in rows.items():
        fb, bb = min(x for x, _ in f), min(x for x, _ in b)
        total_f += fb
        total_b += bb
        print(f"  {name:20s} forward {fb * 1e3:7.3f} ms  backward {bb * 1e3:7.3f} ms  ratio {bb / fb:5.2f}", flush=True)
    print(f"  {'sum':20s} forward {total_f * 1e3:7.3f} ms  backward {total_b * 1e3:7.3f} ms  ratio {total_b / total_f:5.2f}")
    print(f"# load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
