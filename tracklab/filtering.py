"""A filter run over a user's own measurements (no simulation): ``run_filter``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from tracklab.checks import (
    check_covariance,
    check_filter,
    check_finite,
    check_measurements,
    check_positive,
    check_precision,
    numeric,
    refuse,
    shape_of,
)
from tracklab.filters.core import Filter, Meas, Prior, measurement_sizes, trace_problem
from tracklab.montecarlo.runner import in_precision
from tracklab.pytree import like

MEASUREMENT_SIZES = 12  # a filter refusing z's size is traced with each size up to this, to say which it takes


@dataclass(frozen=True)
class FilterResult:
    x: jax.Array  # (..., T, n) filtered means
    P: jax.Array  # (..., T, n, n) filtered covariances
    x_pred: jax.Array | None  # (..., T, n) one-step predictions (None: the filter reports none)
    nu: jax.Array | None  # (..., T, m) innovations (0 where not used; None: none reported)
    S: jax.Array | None  # (..., T, m, m) innovation covariances
    valid: jax.Array | None  # (..., T) update happened
    dof: jax.Array | None  # (..., T) innovation components used
    aux: Any = None  # what the filter family adds (e.g. the STF's fading factor), per step
    validated: Any = None  # a filter of scans: returns validated per step (tracklab.filters.association)
    layout: Any = None  # where position and velocity sit in x (the filter's; None: [x, ẋ, y, ẏ, …])


def run_filter(flt: Filter, z, *, x0, P0, params=None, dt: float = 1.0, precision: str = "float64",
               scans: bool = False) -> FilterResult:
    """Run a filter over a user's measurements.

    ``z`` is (T, m) or (N, T, m); a row of NaN is a missed detection
    (predict-only). ``scans=True``: z is a sequence of scans, (T, K, m) or (N, T, K, m), each
    scan's K rows its returns (unused rows NaN), for a filter of scans (``filters.pdaf``,
    ``nearest_neighbour``, ``strongest_neighbour``, ``ipda``). ``x0, P0`` is the prior one
    sample period before ``z[0]``, in the filter's own state order (its ``layout``): (n,) and (n, n), or per recording (N, n) and
    (N, n, n) with N that of ``z``; each step predicts, then updates with ``z[k]``. ``params``:
    the filter's parameters (None: ``flt.params``). ``dt``: the sample period. ``precision``:
    "float64" (whatever JAX's global 64-bit mode) or "float32"; the parameters and inputs are
    cast to it (a filter's own constants follow the mode it was built in: build it inside
    ``jax.enable_x64(False)`` for single precision throughout).

    Refused before anything compiles, in one line naming the argument: ``flt`` not a
    ``tracklab.Filter`` (``TypeError``); ``z`` with a ±inf (NaN is a missed detection), of
    the wrong shape, or with m components where the filter measures another number (the
    filter traced on shapes alone, with z's m and, when that fails, with other sizes); ``x0``
    not finite; ``P0`` (each of a batch) not finite, not symmetric (to
    1e-9 of its largest entry) or not positive definite; ``dt`` not a finite number > 0;
    ``precision`` neither "float64" nor "float32"; a filter that does not trace at these shapes
    (``ValueError``).
    """
    where = "tracklab.run_filter"
    check_filter(where, "flt", flt)
    precision = check_precision(where, precision)
    dt = check_positive(where, "dt", dt)
    z = check_measurements(where, "z", z)
    lead = 1 if scans else 0  # a scan's axis of returns
    if z.ndim - lead not in (2, 3):
        raise ValueError(f"{where}: z has shape {z.shape}: expected "
                         + ("(T, K, m) or (N, T, K, m) (scans)" if scans else
                            "(T, m) or (N, T, m) (scans of K returns: scans=True, with z (T, K, m) or (N, T, K, m))"))
    xs, Ps = numeric(where, "x0", x0).shape, numeric(where, "P0", P0).shape
    n = xs[-1] if xs else 0
    if len(xs) not in (1, 2) or len(Ps) not in (2, 3) or Ps[-2:] != (n, n):
        raise ValueError(f"{where}: x0 {xs} and P0 {Ps}: expected (n,) or (N, n), and (n, n) "
                         f"or (N, n, n), in the filter's own state order")
    batched = z.ndim - lead == 3
    runs = z.shape[0] if batched else None
    for name, shape in (("x0", xs[:-1]), ("P0", Ps[:-2])):
        if shape and shape[0] != runs:
            raise ValueError(f"{where}: {name} has shape {xs if name == 'x0' else Ps}, z {z.shape}: a prior per "
                             f"recording needs z as (N, T, m) with the same N")
    check_finite(where, "x0", x0)
    check_covariance(where, "P0", P0)
    m = z.shape[-1]
    returns = z.shape[-2] if scans else None
    why = trace_problem(flt, n, m, params, precision, outputs=False, returns=returns)
    if why:
        takes = [] if scans else measurement_sizes(flt, n, [k for k in range(1, max(MEASUREMENT_SIZES, m) + 1)
                                                            if k != m], params, precision, outputs=False)
        if takes:
            raise refuse(where, "z", shape_of(z), f"has m = {m} components per measurement, the filter takes "
                         f"{' or '.join(map(str, takes))} (z is (T, m) or (N, T, m))")
        raise ValueError(f"{where}: the filter {why}")
    with jax.enable_x64(precision == "float64"):
        dtype = jnp.float64 if precision == "float64" else jnp.float32
        params = in_precision(flt.params if params is None else params, precision)
        z, x0, P0 = (jnp.asarray(a, dtype) for a in (z, x0, P0))
        out = _run_filter_jit(flt.init, flt.step, params, z, x0, P0, dt, batched)
    return FilterResult(*out, layout=flt.layout)


def _run_filter_impl(init, step, params, z, x0, P0, dt, batched):
    if not batched:  # one run: a batch of one, unbatched at the end
        return jax.tree_util.tree_map(lambda a: a[0], _run_filter_impl(init, step, params, z[None], x0, P0, dt, True))
    N, T = z.shape[0], z.shape[1]
    x0 = jnp.broadcast_to(x0, (N,) + x0.shape[-1:])
    P0 = jnp.broadcast_to(P0, (N,) + P0.shape[-2:])
    state = jax.vmap(init, in_axes=(None, 0))(params, Prior(x0, P0))
    step = jax.vmap(step, in_axes=(None, 0, 0))
    t = dt * jnp.arange(1, T + 1, dtype=z.dtype)

    def body(s, inp):
        z_k, t_k = inp
        new, out = step(params, s, Meas(z_k, jnp.full((N,), t_k), jnp.ones((N,), bool)))
        return like(new, s), out  # the state in its own precision

    _, out = jax.lax.scan(body, state, (jnp.swapaxes(z, 0, 1), t))
    return tuple(jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), out))


_run_filter_jit = jax.jit(_run_filter_impl, static_argnums=(0, 1, 6, 7))
