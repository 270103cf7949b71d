"""Rolling a step over time with `lax.scan`, checkpointed for reverse mode.

Outputs are the scan's `ys` (never a history buffer in the carry). Reverse-mode memory is set
by `Checkpointing`; see its docstring.
"""

import dataclasses
import math
import numbers

import jax
import jax.numpy as jnp

from jaxmpm.running.budget import physical_bytes
from jaxmpm.kernels.checkpoint_names import KEPT_GRID, KEPT_RATE, KEPT_SOLVES


def default_budget(physical: float) -> int:
    """What "auto" lets one rollout keep for its backward pass (states and node arrays): 2 GiB,
    or an eighth of the machine's physical memory where that is less (never under 256 MiB)."""
    return int(min(2 * 1024**3, max(256 * 1024**2, physical / 8)))


STORE_BUDGET_BYTES = default_budget(physical_bytes())

# Elementwise arithmetic and layout operations: under step = "recompute_arithmetic" the backward
# pass recomputes their results (XLA fuses the recomputation into its own kernels) instead of
# reading them back from memory. Everything else (gathers and scatters, reductions,
# transcendental functions, comparisons) is kept.
RECOMPUTED_PRIMITIVES = frozenset({
    "add", "add_any", "sub", "mul", "neg", "div", "max", "min", "select_n", "convert_element_type",
    "broadcast_in_dim", "reshape", "squeeze", "expand_dims", "concatenate", "slice", "pad", "transpose", "copy",
})


def arithmetic_recomputed(primitive, *_, **__):
    """Checkpoint policy of step = "recompute_arithmetic": keep every intermediate except the
    results of RECOMPUTED_PRIMITIVES."""
    return primitive.name not in RECOMPUTED_PRIMITIVES


@dataclasses.dataclass(frozen=True)
class Checkpointing:
    """How reverse mode trades memory for recomputation (a static choice: changing it recompiles).

    The rollout is a scan over segments of `segment` steps; each segment, and each step within
    it, is wrapped in `jax.checkpoint`. The backward pass then keeps one state per segment and,
    while it differentiates a segment, one state per step of that segment: memory grows like
    steps / segment + segment states, least (about 2 sqrt(steps)) at the default
    segment = ceil(sqrt(steps)) (or a divisor of steps near it), for about one extra forward
    pass of compute.

    A rollout in one segment is not checkpointed as a whole: its steps keep what `step` says
    during the forward pass itself, so no forward pass runs twice (peak memory is the same).

    step: what the backward pass keeps of each step of the segment it differentiates:
    - "auto" (default): with no segment given, one segment of "recompute_grid" steps when the
      states and kept node arrays of the whole rollout fit in the budget, else one segment of
      "recompute" steps when the states alone fit (no forward pass runs twice); otherwise
      segments of "recompute_grid" steps;
    - "recompute_grid": the step runs again, all but its particle-to-grid transfers, whose
      node arrays (KEPT_GRID) are kept, and with 3 x 3 stencils the points' velocity
      gradients (KEPT_RATE);
    - "recompute": the step runs again whole;
    - "recompute_arithmetic": every intermediate but elementwise arithmetic, which the
      backward pass recomputes inside its own kernels;
    - "store": every intermediate (one forward pass fewer, the most memory);
    - "names:a+b" (only those `checkpoint_name`d values) or "dots" (JAX's
      dots_with_no_batch_dims_saveable policy).
    Every choice but "store" keeps the roots of implicit equations a law solves (KEPT_SOLVES,
    e.g. each viscoplastic point's Perzyna root), so a step run again solves none. Their
    measured speed and memory: docs/benchmarks.md ("Checkpointing").

    budget: the bytes "auto" lets one rollout keep (default STORE_BUDGET_BYTES: 2 GiB, or an
    eighth of the machine's physical memory where that is less; `default_budget`). Rollouts run
    together under vmap (a calibration's starts, experiments sharing a scene) each keep their
    own: `jaxmpm calibrate` gives each rollout its share of the default.
    """

    segment: int | None = None
    step: str = "auto"
    budget: int = STORE_BUDGET_BYTES

    def __post_init__(self):
        if isinstance(self.budget, bool) or not isinstance(self.budget, numbers.Integral) or self.budget < 0:
            raise ValueError(f"Checkpointing.budget = {self.budget!r}: give a number of bytes, an int >= 0.")

    def resolved(self, steps, state_bytes, grid_bytes):
        """This policy with "auto" decided for a rollout of `steps` steps that keeps
        `state_bytes` bytes a step with "recompute" (its state and the law's remembered values)
        and `grid_bytes` more with "recompute_grid" (the node arrays)."""
        if self.step != "auto":
            return self
        if self.segment is None:          # one segment: no forward pass runs twice
            if steps * (state_bytes + grid_bytes) <= self.budget:
                return dataclasses.replace(self, segment=steps, step="recompute_grid")
            if steps * state_bytes <= self.budget:
                return dataclasses.replace(self, segment=steps, step="recompute")
        return dataclasses.replace(self, step="recompute_grid")

    def step_checkpoint(self, advance):
        """The per-step wrapper: "recompute" (jax.checkpoint, nothing saved), "store" (none:
        every residual of the segment's steps is kept), "recompute_arithmetic" (jax.checkpoint
        with the arithmetic_recomputed policy), "names:a+b" (save those
        checkpoint_name'd values), "dots" (dots_with_no_batch_dims_saveable)."""
        if self.step == "store":
            return advance
        if self.step == "recompute_arithmetic":
            return jax.checkpoint(advance, prevent_cse=False, policy=arithmetic_recomputed)
        if self.step == "recompute":
            policy = jax.checkpoint_policies.save_only_these_names(KEPT_SOLVES)
            return jax.checkpoint(advance, prevent_cse=False, policy=policy)
        if self.step == "recompute_grid":
            policy = jax.checkpoint_policies.save_only_these_names(KEPT_GRID, KEPT_RATE, KEPT_SOLVES)
            return jax.checkpoint(advance, prevent_cse=False, policy=policy)
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

    def kept_bytes(self, steps, state_bytes, step_bytes):
        """Bytes `checkpointed_rollout` keeps for reverse mode over `steps` steps whose state
        takes `state_bytes` and whose checkpointed step keeps `step_bytes` (its state and the
        values the policy saves): one segment keeps every step's; segments keep one state a
        segment and every step's of one segment."""
        segment = self.segment_length(steps)
        segments = -(-steps // segment)
        return segment * step_bytes if segments == 1 else segments * state_bytes + segment * step_bytes


def state_bytes(state):
    """Bytes of one state (a pytree of arrays or tracers): what a rollout in one segment keeps per
    step for its backward pass."""
    return sum(math.prod(jnp.shape(leaf)) * jnp.dtype(leaf.dtype).itemsize for leaf in jax.tree_util.tree_leaves(state))


def scan_steps(advance, state, length):
    """Run `advance(state) -> (state, output)` `length` times; outputs stacked on axis 0."""
    return jax.lax.scan(lambda carry, _: advance(carry), state, None, length=length)


def checkpointed_rollout(advance, state, steps, checkpointing):
    """Like scan_steps over `steps`, in checkpointed segments (memory ~ sqrt(steps)).

    When the segment does not divide `steps`, the last segment runs past the end and its extra
    steps are skipped (`lax.cond` on the step count): the program then holds one copy of the
    step, where a separate scan for the remaining steps compiled a second one (and two more in
    reverse mode: a quarter of the gradient's compile time). A single segment is a plain scan
    of the (per-step checkpointed) step."""
    segment = checkpointing.segment_length(steps)
    segments = -(-steps // segment)
    advance = checkpointing.step_checkpoint(advance)
    if segments == 1:   # checkpointing the one segment would only run its forward pass twice
        return scan_steps(advance, state, steps)
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
