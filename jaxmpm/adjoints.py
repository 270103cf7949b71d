"""Linear maps that bring their own transpose, under every JAX transformation.

Reverse mode transposes each linear operation of the step. XLA's generic transpose of the
transfers is slow on CPU (the adjoint of our keyed scatter became a 2-3.5x slower gather, the
adjoint of the windowed gather a scatter with per-element index arithmetic), yet the two
transfers are each other's exact transpose: reading node values at each point's stencil is the
adjoint of adding stencil values into the nodes. `paired_linear(forward, transpose)` makes
reverse mode call the fast forward implementation of the partner.

`jax.custom_vjp` would do that for `jax.grad` alone, but a custom-VJP function cannot be
differentiated in forward mode, which the Levenberg-Marquardt Jacobians (`jax.jvp`) need. JAX's
`linear_call` primitive carries a custom transpose and keeps forward mode (its tangent is the
same linear map), but JAX 0.10 gives it no batching rule; `_batch_linear_call` below adds one
(vmap the map and its transpose alike), so `jax.vmap` over calibration starts works too.
`linear_call` lives in JAX's private modules: if a JAX release moves it, the maps fall back to
their plain forward definitions (same values and derivatives, XLA's slower transpose).
"""

import jax
import jax.numpy as jnp

try:
    from jax._src import core
    from jax._src.custom_derivatives import linear_call, linear_call_p
    from jax._src.interpreters import batching
except ImportError:          # pragma: no cover - a JAX without these private modules
    linear_call = None


def paired_linear(forward, transpose):
    """f(residuals, linear) = forward(residuals, linear), linear in `linear`, whose transpose
    (for reverse mode) is transpose(residuals, cotangent). `residuals` (integer indices here)
    carry no derivative."""
    if linear_call is None:
        return forward

    def call(residuals, linear):
        return linear_call(forward, transpose, residuals, linear)

    return call


def _is_mapped(axis):
    return type(axis) is int


def _batch_linear_call(args, axes, *, callee, transpose_thunk, num_callee_consts, num_res):
    """vmap of a linear_call: a linear_call of the vmapped map and the vmapped transpose (all
    batch axes moved to the front; unbatched linear inputs broadcast, so the transpose returns
    batched cotangents for all)."""
    size = next(arg.shape[axis] for arg, axis in zip(args, axes) if _is_mapped(axis))
    moved = [batching.moveaxis(arg, axis, 0) if _is_mapped(axis) else arg for arg, axis in zip(args, axes)]
    in_axes = [0 if _is_mapped(axis) else None for axis in axes]
    fixed_count = num_callee_consts + num_res
    fixed, fixed_axes = moved[:fixed_count], in_axes[:fixed_count]
    linear = [arg if axis == 0 else jnp.broadcast_to(arg, (size,) + arg.shape)
              for arg, axis in zip(moved[fixed_count:], in_axes[fixed_count:])]
    transpose, transpose_consts = transpose_thunk()
    residual_axes = fixed_axes[num_callee_consts:]

    def forward(fixed, linear):
        def one(fixed, linear):
            return core.eval_jaxpr(callee.jaxpr, callee.consts, *fixed, *linear)
        return jax.vmap(one, in_axes=(fixed_axes, 0))(fixed, linear)

    def backward(fixed, cotangents):
        def one(residuals, cotangents):
            return core.eval_jaxpr(transpose.jaxpr, transpose.consts, *transpose_consts, *residuals, *cotangents)
        return jax.vmap(one, in_axes=(residual_axes, 0))(fixed[num_callee_consts:], cotangents)

    out = linear_call(forward, backward, fixed, linear)
    return out, [0] * len(out)


if linear_call is not None:
    batching.primitive_batchers[linear_call_p] = _batch_linear_call
