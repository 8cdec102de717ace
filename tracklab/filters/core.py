"""The filter contract and the Kalman update shared by every Gaussian filter.

A filter is a small immutable bundle of pure functions over pytrees, in the
spirit of optax's ``GradientTransformation``::

    state = flt.init(params, prior)
    state, out = flt.step(params, state, meas)

``flt.params`` holds the default parameters (a pytree of arrays: what
``jax.grad`` and optax see). Static structure (dimensions, model choice) lives
in the closures.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from tracklab.linalg import mm, spd_inverse, symmetrise
from tracklab.sensors.geometry import wrap


class Prior(NamedTuple):
    """Gaussian prior one sample period before the first measurement."""

    x: jax.Array
    P: jax.Array


class Meas(NamedTuple):
    """One measurement: value, time and validity (False = missed detection).

    ``present`` (optional, one flag per component) says which components are
    there when that is known without looking at ``z``: the engine passes the
    sensors' report pattern when every sensor detects with probability one, so
    under ``vmap`` it is shared by all runs, and so is everything a filter computes
    from it alone (a linear KF's covariance and gain: once per step, not once per run).
    By default the components that are present are the finite ones.
    """

    z: jax.Array
    t: jax.Array
    valid: jax.Array
    present: jax.Array | None = None


class Out(NamedTuple):
    """What a filter reports after each step.

    ``x``/``P`` are the filtered mean and covariance in the reporting frame
    (Cartesian, in the layout of the filter's motion model); ``x_pred`` is the
    one-step prediction in the same frame; ``nu``/``S`` are the innovation and
    its covariance in the filter's measurement space (components not used are
    zero in ``nu`` and decoupled with unit variance in ``S``); ``valid`` says
    whether an update happened and ``dof`` how many innovation components it used.
    ``aux`` holds what a filter family adds (the strong tracking filter's fading
    factor, an IMM's mode probabilities); ``None`` for the others.
    """

    x: jax.Array
    P: jax.Array
    x_pred: jax.Array
    nu: jax.Array
    S: jax.Array
    valid: jax.Array
    dof: jax.Array
    aux: Any = None


class Filter(NamedTuple):
    init: Callable[[Any, Prior], Any]
    step: Callable[[Any, Any, Meas], tuple[Any, Out]]
    params: Any
    # coast(params, state, meas) -> (state, out): the step when no measurement is present
    # (equal to ``step`` with an absent measurement, cheaper); optional
    coast: Callable[[Any, Any, Meas], tuple[Any, Out]] | None = None


class Gaussian(NamedTuple):
    """The state of every Kalman-type filter here: mean and covariance."""

    x: jax.Array
    P: jax.Array


def kalman_update(x, P, nu, H, R):
    """Kalman measurement update in Joseph form; returns (x, P, S)."""
    PHt = mm(P, H.T)
    S = mm(H, PHt) + R
    K = mm(PHt, spd_inverse(S))  # K = P Hᵀ S⁻¹
    x = x + mm(K, nu)
    IKH = jnp.eye(P.shape[-1], dtype=P.dtype) - mm(K, H)
    P = mm(mm(IKH, P), IKH.T) + mm(mm(K, R), K.T)
    return x, symmetrise(P), S


def masked_kalman_update(x, P, nu, H, R, used):
    """Kalman update with only the ``used`` measurement components (a bool vector).

    Unused rows of H and components of ν are zeroed and their R entries replaced
    by an uncoupled unit variance, so they change neither the mean nor the
    covariance: a partial measurement (one sensor of several reporting) is an
    update with the components that are there.
    """
    H = jnp.where(used[:, None], H, 0.0)
    nu = jnp.where(used, nu, 0.0)
    R = jnp.where(used[:, None] & used[None, :], R, jnp.eye(R.shape[-1], dtype=R.dtype))
    x, P, S = kalman_update(x, P, nu, H, R)
    return x, P, nu, S


wrap_angle = wrap  # wrap to (-π, π]


def wrap_components(nu, angle_mask):
    """Wrap the innovation components flagged by a static boolean mask."""
    if angle_mask is None or not any(angle_mask):
        return nu
    mask = jnp.asarray(angle_mask)
    return jnp.where(mask, wrap_angle(nu), nu)


def select(valid, a, b):
    """Pytree-wise ``where(valid, a, b)`` (a missed detection keeps ``b``)."""
    return jax.tree_util.tree_map(lambda u, v: jnp.where(valid, u, v), a, b)


def masked_meas(meas: Meas):
    """Measurement with NaNs replaced by zeros, and which components are present."""
    present = meas.valid & (jnp.isfinite(meas.z) if meas.present is None else meas.present)
    return jnp.where(present, meas.z, 0.0), present
