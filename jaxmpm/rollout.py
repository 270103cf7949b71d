"""Rolling a step over time with `lax.scan`, checkpointed for reverse mode.

Outputs are the scan's `ys` (never a history buffer in the carry). Reverse-mode memory is set
by `Checkpointing`; see its docstring.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp


STORE_BUDGET_BYTES = 256 * 1024**2   # "auto" stores a segment's step intermediates up to this size
STORE_FROM_POINTS = 2_000            # ... for scenes of at least this many points: below, storing
# saved little per gradient (nothing at 104 points, 2-13 % at 484) and cost a slower compile
# (+1-5 s), so recomputing is faster over a calibration's few dozen gradients.

# Intermediates a step keeps for its backward pass, in values per point per stencil node:
# measured from the compiled gradients' temporaries (store minus recompute, 20-step segments):
# 294 values per point with 3 x 3 stencils (5,184 points in float32 and 484 in float64), 151
# with 2 x 2; 38 s^2 covers both with a margin.
STORED_VALUES_PER_STENCIL_NODE = 38


@dataclasses.dataclass(frozen=True)
class Checkpointing:
    """How reverse mode trades memory for recomputation (a static choice: changing it recompiles).

    The rollout is a scan over segments of `segment` steps; each segment, and each step within
    it, is wrapped in `jax.checkpoint`. The backward pass then keeps one state per segment and,
    while it differentiates a segment, one state per step of that segment: memory grows like
    steps / segment + segment states, least (about 2 sqrt(steps)) at the default
    segment = ceil(sqrt(steps)) (or a divisor of steps near it), for about one extra forward
    pass of compute.

    step: what the backward pass keeps of each step of the segment it differentiates:
    "auto" (the default: "store" for scenes of at least STORE_FROM_POINTS points whose segment
    intermediates are estimated to fit in STORE_BUDGET_BYTES, else "recompute");
    "recompute" (nothing, the step runs again); "store" (every intermediate: one forward pass
    fewer, gradients 15-25 % faster at 5k points, 2-13 % at 484, the same at 100, for 1-5 s
    more compiling; about 7 MB per step of a segment for 5k points in float32);
    "names:stencil" (only the shape-function stencil) or "dots" (JAX's
    dots_with_no_batch_dims_saveable policy). Measured in docs/benchmarks.md and
    benchmarks/reverse_decomposition.py. A calibration's starts run under vmap, so their
    stored intermediates add up: S starts store S times as much.
    """

    segment: int | None = None
    step: str = "auto"

    def resolved(self, steps, points, support, itemsize):
        """This policy with "auto" decided for a rollout of `steps` steps of `points` points
        with s x s stencils (s = `support`) and values of `itemsize` bytes."""
        if self.step != "auto":
            return self
        stored = self.segment_length(steps) * points * STORED_VALUES_PER_STENCIL_NODE * support**2 * itemsize
        store = points >= STORE_FROM_POINTS and stored <= STORE_BUDGET_BYTES
        return dataclasses.replace(self, step="store" if store else "recompute")

    def step_checkpoint(self, advance):
        """The per-step wrapper: "recompute" (jax.checkpoint, nothing saved), "store" (none:
        every residual of the segment's steps is kept), "names:a+b" (save those
        checkpoint_name'd values), "dots" (dots_with_no_batch_dims_saveable)."""
        if self.step == "store":
            return advance
        if self.step == "recompute":
            return jax.checkpoint(advance, prevent_cse=False)
        if self.step.startswith("names:"):
            names = self.step[len("names:"):].split("+")
            policy = jax.checkpoint_policies.save_only_these_names(*names)
            return jax.checkpoint(advance, prevent_cse=False, policy=policy)
        if self.step == "dots":
            return jax.checkpoint(advance, prevent_cse=False, policy=jax.checkpoint_policies.dots_with_no_batch_dims_saveable)
        if self.step == "auto":
            raise ValueError('step = "auto" must be resolved for a rollout first (Checkpointing.resolved)')
        raise ValueError(f"unknown step checkpointing {self.step!r}")

    def segment_length(self, steps):
        """The given segment, or the divisor of `steps` between sqrt(steps) / 2 and
        2 sqrt(steps) that keeps the fewest states (steps / d + d), or ceil(sqrt(steps)) when
        there is none (the last segment then skips its extra steps, which costs a few per cent
        per step on small scenes: `checkpointed_rollout`)."""
        if self.segment is not None:
            return max(1, min(int(self.segment), steps))
        root = math.sqrt(steps)
        divisors = [d for d in range(max(1, math.ceil(root / 2)), math.floor(2 * root) + 1) if steps % d == 0]
        if divisors:
            return min(divisors, key=lambda d: (steps // d + d, -d))
        return max(1, math.ceil(root))


def scan_steps(advance, state, length):
    """Run `advance(state) -> (state, output)` `length` times; outputs stacked on axis 0."""
    return jax.lax.scan(lambda carry, _: advance(carry), state, None, length=length)


def checkpointed_rollout(advance, state, steps, checkpointing):
    """Like scan_steps over `steps`, in checkpointed segments (memory ~ sqrt(steps)).

    When the segment does not divide `steps`, the last segment runs past the end and its extra
    steps are skipped (`lax.cond` on the step count): the program then holds one copy of the
    step, where a separate scan for the remaining steps compiled a second one (and two more in
    reverse mode: a quarter of the gradient's compile time)."""
    segment = checkpointing.segment_length(steps)
    segments = -(-steps // segment)
    advance = checkpointing.step_checkpoint(advance)
    if segments * segment > steps:
        advance = stopping_after(advance, steps, state)
    else:
        advance = counting(advance)

    def run_segment(carry):
        return scan_steps(advance, carry, segment)

    counted = (state, jnp.zeros((), jnp.int32))
    (state, _), outputs = scan_steps(jax.checkpoint(run_segment, prevent_cse=False), counted, segments)
    return state, jax.tree_util.tree_map(lambda y: y.reshape((segments * segment,) + y.shape[2:])[:steps], outputs)


def counting(advance):
    """advance on a carry (state, steps taken)."""
    def step(carry):
        state, taken = carry
        state, output = advance(state)
        return (state, taken + 1), output

    return step


def stopping_after(advance, steps, state):
    """advance on a carry (state, steps taken) that leaves the state alone (outputs zero)
    once `steps` steps are taken."""
    outputs = jax.eval_shape(advance, state)[1]

    def idle(state):
        return state, jax.tree_util.tree_map(lambda shape: jnp.zeros(shape.shape, shape.dtype), outputs)

    def step(carry):
        state, taken = carry
        state, output = jax.lax.cond(taken < steps, advance, idle, state)
        return (state, taken + 1), output

    return step
