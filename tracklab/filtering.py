"""A filter run over a user's own measurements (no simulation): ``run_filter``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Filter, Meas, Prior


@dataclass(frozen=True)
class FilterResult:
    x: jax.Array  # (..., T, n) filtered means
    P: jax.Array  # (..., T, n, n) filtered covariances
    x_pred: jax.Array  # (..., T, n) one-step predictions
    nu: jax.Array  # (..., T, m) innovations (0 where not used)
    S: jax.Array  # (..., T, m, m) innovation covariances
    valid: jax.Array  # (..., T) update happened
    dof: jax.Array  # (..., T) innovation components used
    aux: Any = None  # what the filter family adds (e.g. the STF's fading factor), per step


def run_filter(flt: Filter, z, *, x0, P0, params=None, dt: float = 1.0) -> FilterResult:
    """Run a filter over a user's measurements.

    ``z`` is (T, m) or (N, T, m); a row of NaN is a missed detection
    (predict-only). ``x0, P0`` is the prior one sample period before ``z[0]``;
    each step predicts, then updates with ``z[k]``. For single precision, build
    the filter and call this inside ``with jax.enable_x64(False):`` with float32 inputs.
    """
    params = flt.params if params is None else params
    z = jnp.asarray(z)
    batched = z.ndim == 3
    zb = z if batched else z[None]
    N = zb.shape[0]
    x0 = jnp.broadcast_to(jnp.asarray(x0, zb.dtype), (N,) + np.shape(x0)[-1:])
    P0 = jnp.broadcast_to(jnp.asarray(P0, zb.dtype), (N,) + np.shape(P0)[-2:])
    out = _run_filter_jit(flt.init, flt.step, params, zb, x0, P0, float(dt))
    if not batched:
        out = jax.tree_util.tree_map(lambda a: a[0], out)
    return FilterResult(*out)


def _run_filter_impl(init, step, params, z, x0, P0, dt):
    N, T = z.shape[0], z.shape[1]
    state = jax.vmap(init, in_axes=(None, 0))(params, Prior(x0, P0))
    step = jax.vmap(step, in_axes=(None, 0, 0))
    t = dt * jnp.arange(1, T + 1, dtype=z.dtype)

    def body(s, inp):
        z_k, t_k = inp
        s, out = step(params, s, Meas(z_k, jnp.full((N,), t_k), jnp.ones((N,), bool)))
        return s, out

    _, out = jax.lax.scan(body, state, (jnp.swapaxes(z, 0, 1), t))
    return tuple(jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), out))


_run_filter_jit = jax.jit(_run_filter_impl, static_argnums=(0, 1, 6))
