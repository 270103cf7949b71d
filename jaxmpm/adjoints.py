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
`hand_reversed(function, adjoint)` does the same for a nonlinear function with a hand-written
reverse mode (the stress updates, `jaxmpm.materials.base.points_update`): a custom JVP whose
tangent map is such a paired linear map, its residuals the primal inputs and what the forward
pass remembered for it; `_linear_call_jvp` lets those residuals carry tangents (forward over
reverse).
`linear_call` lives in JAX's private modules: if a JAX release moves it, the maps fall back to
their plain forward definitions (same values and derivatives, XLA's slower transpose).
"""

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

try:
    from jax._src import core
    from jax._src.custom_derivatives import _linear_call_jvp_rule, linear_call, linear_call_p
    from jax._src.interpreters import ad, batching
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


def hand_reversed(function, adjoint, tangent_function=None):
    """A function with a hand-written reverse mode, and JAX's own jvp as its forward mode.

    `function(*args, remembered=None) -> (outputs, remembered)`: its outputs, and values it
    computes on the way that neither mode should compute again (the root of an implicit
    equation, say; `()` when there are none). Given `remembered`, it must use them instead.
    `adjoint(args, remembered, cotangents) -> cotangents of args`. `tangent_function`: the same
    function written for forward mode (default `function`). Returns `f(*args) -> outputs`.

    A custom JVP whose tangent map is a `paired_linear` map: forward mode evaluates it as
    `jax.jvp` of `tangent_function` with `remembered` held, reverse mode transposes it by calling
    `adjoint` at the primal inputs and the remembered values (its residuals, with no
    derivative). Inputs whose tangent is a symbolic zero (e.g. a history that starts at zero)
    are not linear inputs of the map: a transpose must only be asked for cotangents of inputs
    that really carry a derivative. Without `linear_call`, `function`'s outputs."""
    if linear_call is None:
        return lambda *args: function(*args)[0]

    @jax.custom_jvp
    def wrapped(*args):
        return function(*args)[0]

    def rule(primals, tangents):
        tree = jax.tree_util.tree_structure(tuple(primals))
        tangent_leaves = jax.tree_util.tree_leaves(tuple(tangents), is_leaf=lambda t: isinstance(t, SymbolicZero))
        live = [not isinstance(t, SymbolicZero) for t in tangent_leaves]

        def tangent(residuals, live_tangents):
            # zeros made from the map's own residuals, not from the enclosing primals (under
            # vmap those are batched tracers of an outer trace)
            primals, remembered = residuals
            values = iter(live_tangents)
            full = [next(values) if on else jnp.zeros_like(x) for x, on in zip(jax.tree_util.tree_leaves(primals), live)]
            held = lambda *args: (tangent_function or function)(*args, remembered=remembered)[0]
            return jax.jvp(held, primals, tree.unflatten(full))[1]

        def transpose(residuals, cotangents):
            primals, remembered = residuals
            bars = jax.tree_util.tree_leaves(adjoint(primals, remembered, cotangents))
            return [bar for bar, on in zip(bars, live) if on]

        outputs, remembered = function(*primals)
        remembered = jax.lax.stop_gradient(remembered)
        live_tangents = [t for t, on in zip(tangent_leaves, live) if on]
        return outputs, paired_linear(tangent, transpose)((tuple(primals), remembered), live_tangents)

    wrapped.defjvp(rule, symbolic_zeros=True)
    return wrapped


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


def _linear_call_jvp(primals, tangents, *, callee, transpose_thunk, num_callee_consts, num_res):
    """jvp of a linear_call whose residuals carry tangents too (forward over reverse through a
    hand-written adjoint, whose residuals are the primal inputs): f(r, x) is linear in x only,
    so d f = f(r, dx) + (df/dr) dr, the first a linear_call (transposable in x), the second
    JAX's jvp of the map in r at fixed x. With zero residual tangents, JAX's own rule."""
    fixed = num_callee_consts + num_res
    if all(type(t) is ad.Zero for t in tangents[:fixed]):
        return _linear_call_jvp_rule(primals, tangents, callee=callee, transpose_thunk=transpose_thunk,
                                     num_callee_consts=num_callee_consts, num_res=num_res)
    parameters = dict(callee=callee, transpose_thunk=transpose_thunk, num_callee_consts=num_callee_consts, num_res=num_res)
    out = linear_call_p.bind(*primals, **parameters)
    linear_tangents = [ad.instantiate_zeros(t) for t in tangents[fixed:]]
    along_linear = linear_call_p.bind(*primals[:fixed], *linear_tangents, **parameters)
    live = [index for index, t in enumerate(tangents[:fixed]) if type(t) is not ad.Zero]

    def of_live(*values):
        args = list(primals)
        for index, value in zip(live, values):
            args[index] = value
        return core.eval_jaxpr(callee.jaxpr, callee.consts, *args)

    _, along_fixed = jax.jvp(of_live, [primals[i] for i in live], [tangents[i] for i in live])
    return out, [a + b for a, b in zip(along_linear, along_fixed)]


if linear_call is not None:
    batching.primitive_batchers[linear_call_p] = _batch_linear_call
    ad.primitive_jvps[linear_call_p] = _linear_call_jvp
