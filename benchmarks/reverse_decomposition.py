"""Where the reverse-mode time goes: rollout forward/gradient, and one step's forward, backward.

    python benchmarks/reverse_decomposition.py POINTS DTYPE MATERIAL SHAPE [--variants a,b] [--steps 200]

For the throughput scene (benchmarks/throughput.py), in one process, alternating variants:
- loss: jax.jit(loss) over a `steps`-step rollout (Simulation.probes), and its gradient
  jax.jit(jax.grad(loss)); their ratio; XLA temp memory of the gradient;
- per step, in a scan of K steps: forward step; backward step alone (the vjp of one step
  applied K times to its own residuals); forward + backward of one step (jax.vjp inside the scan).
Variants are `Checkpointing` settings (see jaxmpm.running.rollout).
"""

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).parent))


def best_median(function, *args, repeats=5):
    jax.block_until_ready(function(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*args))
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times)


def split_floats(tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    mask = [jax.numpy.issubdtype(leaf.dtype, jax.numpy.floating) for leaf in leaves]
    return [l for l, m in zip(leaves, mask) if m], (leaves, treedef, mask)


def merge_floats(floats, info):
    leaves, treedef, mask = info
    it = iter(floats)
    return jax.tree_util.tree_unflatten(treedef, [next(it) if m else l for l, m in zip(leaves, mask)])



def parse_checkpointing(text):
    """jaxmpm.Checkpointing from "default" or "seg=N;step=..."."""
    from jaxmpm import Checkpointing

    if text == "default":
        return Checkpointing()
    fields = dict(part.split("=", 1) for part in text.split(";"))
    return Checkpointing(segment=int(fields["seg"]) if "seg" in fields else None, step=fields.get("step", "recompute"))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("points", type=int)
    parser.add_argument("dtype")
    parser.add_argument("material")
    parser.add_argument("shape")
    parser.add_argument("--variants", default="default")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--cells", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--per-step", action="store_true")
    parser.add_argument("--skip-rollout", action="store_true")
    parser.add_argument("--jit-options", default="", help="'noynn' to compile without YNNPACK fusions")
    args = parser.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxmpm
    from jaxmpm.kernels.xla_options import NO_YNNPACK
    from common import block_scene
    from throughput import SIZES

    options = NO_YNNPACK if args.jit_options == "noynn" else {}
    cells = args.cells or SIZES[args.points]
    scene = block_scene(cells, args.dtype, args.steps, args.material, args.shape)
    variants = args.variants.split(",")
    print(f"# {args.points} {args.dtype} {args.material} {args.shape} steps={args.steps} cells={cells} "
          f"options={args.jit_options or 'default'} load={os.getloadavg()[0]:.2f}", flush=True)
    compiled = {}
    for name in ([] if args.skip_rollout else variants):
        sim = jaxmpm.Simulation(scene, jaxmpm.Checkpointing() if name == "default" else parse_checkpointing(name))

        def loss(young, sim=sim):
            probes = sim.probes(jaxmpm.with_values(sim.params, {"block.young": young}))
            return jnp.sum(probes["top"][:, 1]) + jnp.sum(probes["centre_of_mass"][:, 1])

        young = jnp.asarray(sim.params["materials"]["block"]["young"], sim.dtype)
        forward = jax.jit(loss, compiler_options=options)
        gradient = jax.jit(jax.grad(loss), compiler_options=options)
        start = time.perf_counter()
        lowered = gradient.lower(young).compile()
        compile_s = time.perf_counter() - start
        memory = lowered.memory_analysis()
        compiled[name] = (forward, gradient, young, memory.temp_size_in_bytes / 2**20, compile_s, sim)
        print(f"  {name}: points={sim.point_count} compile grad {compile_s:.1f} s, temp {memory.temp_size_in_bytes / 2**20:.1f} MB, "
              f"loss {float(forward(young)):.12e} grad {float(gradient(young)):.12e}", flush=True)
    results = {name: {"loss": [], "grad": []} for name in compiled}
    for _ in range(args.rounds):
        for name in compiled:
            forward, gradient, young, *_ = compiled[name]
            results[name]["loss"].append(best_median(forward, young, repeats=args.repeats))
            results[name]["grad"].append(best_median(gradient, young, repeats=max(2, args.repeats // 2 + 1)))
    for name in compiled:
        loss_best = min(b for b, _ in results[name]["loss"])
        grad_best = min(b for b, _ in results[name]["grad"])
        loss_med = statistics.median(m for _, m in results[name]["loss"])
        grad_med = statistics.median(m for _, m in results[name]["grad"])
        temp, compile_s = compiled[name][3], compiled[name][4]
        print(f"  {name:28s} loss {loss_best * 1e3:8.1f} / {loss_med * 1e3:8.1f} ms  grad {grad_best * 1e3:8.1f} / "
              f"{grad_med * 1e3:8.1f} ms  ratio best {grad_best / loss_best:5.2f} median {grad_med / loss_med:5.2f}  "
              f"temp {temp:7.1f} MB", flush=True)

    if args.per_step:
        sim = jaxmpm.Simulation(scene)
        params = sim.cast(sim.params)
        initial = sim.initial_state(params)
        advance_of = lambda p: sim._advance_and_observe(p, initial.particles.x)   # noqa: E731
        # a state a few steps in (the block is moving)
        state = jax.jit(lambda p, s: jaxmpm.running.rollout.scan_steps(advance_of(p), s, 20)[0])(params, initial)
        floats, info = split_floats(state)
        pfloats, pinfo = split_floats(params)
        K = 20

        def step_floats(pf, sf):
            new, out = advance_of(merge_floats(pf, pinfo))(merge_floats(sf, info))
            return split_floats(new)[0], out

        def forward_k(pf, sf):
            return jax.lax.scan(lambda s, _: (step_floats(pf, s)[0], None), sf, None, length=K)[0]

        _, vjp_fn = jax.vjp(step_floats, pfloats, floats)
        ct_out = jax.tree_util.tree_map(jnp.ones_like, step_floats(pfloats, floats))

        def backward_k(vjp_fn, ct):
            def body(c, _):
                gp, gs = vjp_fn((c, ct[1]))
                return [x * 1e-3 for x in gs], None
            return jax.lax.scan(body, ct[0], None, length=K)[0]

        def both_k(pf, sf, ct):
            def body(c, _):
                _, f = jax.vjp(step_floats, pf, sf)
                gp, gs = f((c, ct[1]))
                return [x * 1e-3 for x in gs], None
            return jax.lax.scan(body, ct[0], None, length=K)[0]

        jf = jax.jit(forward_k, compiler_options=options)
        jb = jax.jit(backward_k, compiler_options=options)
        jboth = jax.jit(both_k, compiler_options=options)
        rows = {"forward": [], "backward": [], "fwd+bwd": []}
        for _ in range(args.rounds + 1):
            rows["forward"].append(best_median(jf, pfloats, floats, repeats=args.repeats))
            rows["backward"].append(best_median(jb, vjp_fn, ct_out, repeats=args.repeats))
            rows["fwd+bwd"].append(best_median(jboth, pfloats, floats, ct_out, repeats=args.repeats))
        fb = min(b for b, _ in rows["forward"])
        for name, values in rows.items():
            best = min(b for b, _ in values)
            med = statistics.median(m for _, m in values)
            print(f"  one step {name:10s} {best / K * 1e3:7.3f} / {med / K * 1e3:7.3f} ms  (x forward {best / fb:.2f})", flush=True)
    print(f"# load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
