"""A one-run function batched over the runs with the runs on the last axis.

A filter's step works on a few-element state and small matrices; a chunk runs it for
thousands of runs. ``jax.vmap`` puts the runs first, (runs, 9, 9), and XLA's CPU kernels then
work along the short minor axes; asked for the runs last (``in_axes=-1``), its batching rules
move them to the front again for many primitives, at the cost of transposes. ``runs_last``
evaluates the step's jaxpr with every per-run value carried as (…, runs): each of the filters'
unrolled small-matrix operations (``tracklab.linalg``) is then an elementwise operation on
contiguous runs, and the errors and sums (runs last as well) read them without a transpose.

Every primitive is batched by a rule of its own where the runs-last layout needs nothing but an
extra trailing axis (elementwise arithmetic, slices, reshapes, reductions over the leading axes,
small matrix products as products and sums); nested jaxprs (``jit``, ``cond`` on a value shared
by the runs) are evaluated the same way; any other primitive falls back to its own ``vmap``
batching rule, with the runs moved to the front and back around it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence

import jax
import jax.extend.core as jcore
import jax.numpy as jnp
import numpy as np
from jax import lax

# primitives applied elementwise to operands of one shape (a select's predicate may be a scalar)
_ELEMENTWISE = frozenset("""
    abs acos acosh add add_any and asin asinh atan atan2 atanh cbrt ceil clamp convert_element_type copy copy_p cos
    cosh div eq erf erf_inv erfc exp exp2 expm1 floor ge gt imag integer_pow is_finite le lgamma digamma log log1p
    logistic lt max min mul ne neg nextafter not or pow real reduce_precision rem round rsqrt select_n sign sin sinh
    sqrt square sub tan tanh xor stop_gradient
""".split())

# primitives whose axis parameters name leading axes only, unchanged by a trailing runs axis
_SAME_PARAMS = frozenset("""
    squeeze reduce_sum reduce_max reduce_min reduce_prod reduce_and reduce_or reduce_xor argmax argmin cumsum
    cumprod cummax cummin cumlogsumexp rev
""".split())


class _Batched:
    """A per-run value laid out (…, runs)."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


def _aval_shape(v):
    return tuple(v.aval.shape)


def _as_batched(x, shape, size):
    """``x`` (batched or not) as an array (shape…, size): a shared value repeated over the runs, and a
    value broadcastable to ``shape`` as NumPy broadcasts (aligned on the right) spread over it."""
    shape = tuple(shape)
    batched = isinstance(x, _Batched)
    a = x.value if batched else jnp.asarray(x)
    lead = a.shape[:-1] if batched else a.shape
    if batched and lead == shape:
        return a
    dims = tuple(range(len(shape) - len(lead), len(shape))) + ((len(shape),) if batched else ())
    return lax.broadcast_in_dim(a, shape + (size,), dims)


def _elementwise(eqn, vals, size):
    """An elementwise primitive on operands broadcast to its output's shape, the runs last (XLA fuses
    the broadcasts into the arithmetic)."""
    shape = _aval_shape(eqn.outvars[0])
    if eqn.primitive.name == "select_n" and not isinstance(vals[0], _Batched) and np.ndim(vals[0]) == 0:
        return eqn.primitive.bind(vals[0], *(_as_batched(c, shape, size) for c in vals[1:]), **eqn.params)
    return eqn.primitive.bind(*(_as_batched(v, shape, size) for v in vals), **eqn.params)


def _dot_general(eqn, vals, size):
    """A small matrix product per run: the operands' products summed over the contracted axes.
    With one operand shared by the runs, one product whose free axes include the runs."""
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lhs, rhs = vals
    lshape, rshape = _aval_shape(eqn.invars[0]), _aval_shape(eqn.invars[1])
    out_dtype = eqn.outvars[0].aval.dtype
    if not isinstance(lhs, _Batched) and not lb:  # shared (…) · per run (…, runs): the runs a free axis
        return lax.dot_general(lhs, rhs.value, ((lc, rc), ((), ())), preferred_element_type=out_dtype)
    if not isinstance(rhs, _Batched) and not rb:  # per run · shared: the runs come out before rhs's free axes
        out = lax.dot_general(lhs.value, rhs, ((lc, rc), ((), ())), preferred_element_type=out_dtype)
        n_rfree = len(rshape) - len(rc)
        k = out.ndim - n_rfree - 1  # the runs' axis
        return jnp.moveaxis(out, k, -1)
    a = _as_batched(lhs, lshape, size)
    b = _as_batched(rhs, rshape, size)
    lfree = [i for i in range(len(lshape)) if i not in lc and i not in lb]
    rfree = [i for i in range(len(rshape)) if i not in rc and i not in rb]
    nb, nl, nr, nc = len(lb), len(lfree), len(rfree), len(lc)
    # (batch, lhs free, 1…, contracted, runs) · (batch, 1…, rhs free, contracted, runs)
    a = lax.transpose(a, tuple(lb) + tuple(lfree) + tuple(lc) + (len(lshape),))
    b = lax.transpose(b, tuple(rb) + tuple(rfree) + tuple(rc) + (len(rshape),))
    shape = [lshape[i] for i in lb] + [lshape[i] for i in lfree] + [rshape[i] for i in rfree] + \
            [lshape[i] for i in lc] + [size]
    a = lax.broadcast_in_dim(a, tuple(shape), tuple(range(nb + nl)) + tuple(range(nb + nl + nr, len(shape))))
    b = lax.broadcast_in_dim(b, tuple(shape), tuple(range(nb)) + tuple(range(nb + nl, len(shape))))
    prod = (a * b).astype(out_dtype)
    return jnp.sum(prod, axis=tuple(range(nb + nl + nr, nb + nl + nr + nc))) if nc else prod


def _structural(eqn, vals, size):
    """The primitives that take the runs as one more trailing axis by a change of parameters."""
    name, p = eqn.primitive.name, dict(eqn.params)
    x = vals[0]
    if name == "broadcast_in_dim":
        shape = tuple(p["shape"])
        return lax.broadcast_in_dim(x.value, shape + (size,), tuple(p["broadcast_dimensions"]) + (len(shape),))
    if name == "reshape" and p.get("dimensions") is None:
        return jnp.reshape(x.value, tuple(p["new_sizes"]) + (size,))
    if name == "transpose":
        perm = tuple(p["permutation"])
        return lax.transpose(x.value, perm + (len(perm),))
    if name == "slice":
        strides = p["strides"]
        return lax.slice(x.value, tuple(p["start_indices"]) + (0,), tuple(p["limit_indices"]) + (size,),
                         None if strides is None else tuple(strides) + (1,))
    if name == "split":
        return eqn.primitive.bind(x.value, **p)
    if name == "dynamic_slice" and not any(isinstance(v, _Batched) for v in vals[1:]):  # shared start indices
        zero = jnp.zeros((), jnp.result_type(vals[1]))  # the runs' start, of the indices' type
        return lax.dynamic_slice(x.value, tuple(vals[1:]) + (zero,), tuple(p["slice_sizes"]) + (size,))
    if name == "pad" and not isinstance(vals[1], _Batched):
        return lax.pad(x.value, jnp.asarray(vals[1], x.value.dtype), tuple(p["padding_config"]) + ((0, 0, 0),))
    if name == "reshard":
        return x.value
    return None


def _fallback(eqn, vals, size):
    """Any other primitive by its own ``vmap`` rule, the runs moved to the front and back."""
    at = [i for i, v in enumerate(vals) if isinstance(v, _Batched)]
    params = eqn.primitive.get_bind_params(eqn.params)

    def one(*batched):
        args = list(vals)
        for i, a in zip(at, batched):
            args[i] = a
        outs = eqn.primitive.bind(*args, **params)
        return outs if eqn.primitive.multiple_results else [outs]

    outs = jax.vmap(one, axis_size=size)(*(jnp.moveaxis(vals[i].value, -1, 0) for i in at))
    return [_Batched(jnp.moveaxis(o, 0, -1)) for o in outs]


def _cond(eqn, vals, size, batched_out):
    index, *ops = vals
    branches = eqn.params["branches"]

    def branch(closed):
        def run(*args):
            given = [_Batched(a) if was else a for a, was in zip(args, flags)]
            outs = _eval(closed.jaxpr, closed.consts, given, size)
            return [_as_batched(o, _aval_shape(v), size) if b else o
                    for o, v, b in zip(outs, closed.jaxpr.outvars, batched_out)]
        return run

    flags = [isinstance(o, _Batched) for o in ops]
    plain = [o.value if isinstance(o, _Batched) else o for o in ops]
    outs = lax.switch(index, [branch(b) for b in branches], *plain)
    return [_Batched(o) if b else o for o, b in zip(outs, batched_out)]


def _depends(jaxpr, flags):
    """Which outputs of ``jaxpr`` depend on the inputs flagged (an equation with any dependent input
    makes all its outputs dependent)."""
    dep = {v for v, f in zip(jaxpr.invars, flags) if f}
    for eqn in jaxpr.eqns:
        if any(isinstance(v, jcore.Var) and v in dep for v in eqn.invars):
            dep.update(eqn.outvars)
    return [isinstance(v, jcore.Var) and v in dep for v in jaxpr.outvars]


def _eval(jaxpr, consts, args, size):
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        with _source_of(eqn):
            outs = _eval_eqn(eqn, [read(v) for v in eqn.invars], size)
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _eval_eqn(eqn, vals, size):
    """One equation's outputs, the per-run values among ``vals`` batched."""
    name = eqn.primitive.name
    if not any(isinstance(v, _Batched) for v in vals):  # shared by the runs: evaluated once
        outs = eqn.primitive.bind(*vals, **eqn.primitive.get_bind_params(eqn.params))
        return outs if eqn.primitive.multiple_results else [outs]
    if name in ("jit", "pjit", "closed_call", "core_call"):
        closed = eqn.params["jaxpr" if "jaxpr" in eqn.params else "call_jaxpr"]
        if isinstance(closed, jcore.Jaxpr):
            closed = jcore.ClosedJaxpr(closed, [])
        return _eval(closed.jaxpr, closed.consts, vals, size)
    if name == "cond" and not isinstance(vals[0], _Batched):
        flags = [isinstance(v, _Batched) for v in vals[1:]]
        batched_out = [any(fl) for fl in zip(*(_depends(b.jaxpr, flags) for b in eqn.params["branches"]))]
        return _cond(eqn, vals, size, batched_out)
    if name == "optimization_barrier":  # per operand, whatever its layout
        outs = eqn.primitive.bind(*(v.value if isinstance(v, _Batched) else v for v in vals), **eqn.params)
        return [_Batched(o) if isinstance(v, _Batched) else o for o, v in zip(outs, vals)]
    if name in _ELEMENTWISE:
        return [_Batched(_elementwise(eqn, vals, size))]
    if name == "dot_general":
        return [_Batched(_dot_general(eqn, vals, size))]
    if name in _SAME_PARAMS and len(vals) == 1:
        return [_Batched(eqn.primitive.bind(vals[0].value, **eqn.params))]
    if name in ("concatenate", "stack"):  # any operand per run: all of them
        shapes = [np.shape(v.val) if isinstance(v, jcore.Literal) else _aval_shape(v) for v in eqn.invars]
        return [_Batched(eqn.primitive.bind(*(_as_batched(v, s, size) for v, s in zip(vals, shapes)), **eqn.params))]
    out = _structural(eqn, vals, size) if isinstance(vals[0], _Batched) else None
    if out is None:
        return _fallback(eqn, vals, size)
    return [_Batched(o) for o in out] if eqn.primitive.multiple_results else [_Batched(out)]


def _source_of(eqn):
    """The equation's own source location and name stack for what it lowers to (XLA's metadata,
    profiles), as ``jax.core.eval_jaxpr`` keeps them; nothing where JAX has moved that API."""
    try:
        from jax._src import source_info_util
    except ImportError:  # pragma: no cover - JAX moved it
        return contextlib.nullcontext()
    return source_info_util.user_context(eqn.source_info.traceback,
                                         name_stack=source_info_util.current_name_stack() + eqn.source_info.name_stack)


def runs_last(fn: Callable, in_axes, out_axes=-1, size: int | None = None) -> Callable:
    """``fn`` of one run, batched over the runs with every per-run value laid out (…, runs).

    ``in_axes`` (a pytree prefix of the arguments, as ``jax.vmap``'s): -1 for an argument batched
    with the runs last, None for one shared by the runs. Outputs that depend on a batched argument
    come out with the runs last; ``out_axes`` (a prefix of the outputs): None where an output must
    be shared (it is an error if it depends on the runs), -1 where it must be batched (a shared
    value is then broadcast)."""

    def batched(*args):
        flat_axes = _broadcast_prefix(in_axes, args)
        leaves, tree = jax.tree_util.tree_flatten(args)
        for a, ax in zip(leaves, flat_axes):
            if ax not in (None, -1):
                raise ValueError(f"runs_last: in_axes must be -1 or None, got {ax}")
        n = size
        if n is None:
            n = next(np.shape(a)[-1] for a, ax in zip(leaves, flat_axes) if ax == -1)
        one = [jax.ShapeDtypeStruct(np.shape(a)[:-1] if ax == -1 else np.shape(a), jnp.result_type(a))
               for a, ax in zip(leaves, flat_axes)]
        closed, shapes = jax.make_jaxpr(lambda *flat: fn(*jax.tree_util.tree_unflatten(tree, flat)),
                                        return_shape=True)(*one)
        given = [_Batched(a) if ax == -1 else a for a, ax in zip(leaves, flat_axes)]
        outs = _eval(closed.jaxpr, closed.consts, given, n)
        out_leaves, out_tree = jax.tree_util.tree_flatten(shapes)
        want = _broadcast_prefix(out_axes, jax.tree_util.tree_unflatten(out_tree, [0] * len(out_leaves)))
        res = []
        for o, s, w in zip(outs, out_leaves, want):
            if w is None:
                if isinstance(o, _Batched):
                    raise ValueError("runs_last: an output declared shared depends on the runs")
                res.append(o)
            else:
                res.append(_as_batched(o, tuple(s.shape), n))
        return jax.tree_util.tree_unflatten(out_tree, res)

    return batched


def _broadcast_prefix(prefix, tree) -> Sequence:
    """``prefix``'s entries repeated over the leaves of ``tree`` below each (None a leaf of the prefix)."""
    out = []
    jax.tree_util.tree_map(lambda ax, sub: out.extend([ax] * len(jax.tree_util.tree_leaves(sub))), prefix, tree,
                           is_leaf=lambda x: x is None)
    return out
