"""Building blocks of a Gaussian (Kalman-type) filter: the predict/update algebra every
built-in Kalman filter is made of, for writing one's own.

The state is a ``Gaussian(x, P)``. One cycle::

    g = predict(g, F, Q)                          # x⁻ = F x, P⁻ = F P Fᵀ + Q
    u = update(g, z, H, R, angles=(False, True))  # Joseph form; NaN in z = absent
    g = u.posterior                               # u.nu, u.S: innovation and its covariance

``kalman_filter(params, time_update, measurement_update)`` assembles such halves into a
``Filter`` (its ``step``, a cheaper ``coast`` and the ``Out`` statistics). Everything here
is a pure function of arrays: it works under ``jax.jit``, ``jax.vmap``, ``jax.grad`` and
``jax.jacfwd``, in float32 and float64. Products are ``tracklab.linalg.mm`` (elementwise
under ``vmap``) and Jacobians ``tracklab.linalg.jacobian`` (forward mode).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tracklab.checks import check_columns
from tracklab.filters.core import Filter, Out, masked_meas, select
from tracklab.linalg import jacobian, mm, pick, spd_inverse, symmetrise
from tracklab.sensors.geometry import wrap

wrap_angle = wrap  # an angle wrapped to (-π, π]


class Gaussian(NamedTuple):
    """The state of every Kalman-type filter here: mean x (n,) and covariance P (n, n)."""

    x: jax.Array
    P: jax.Array


class Update(NamedTuple):
    """What ``update`` (and ``innovation_update``) gives: the posterior mean and covariance, the innovation ν = z − ẑ (m,)
    (0 where a component was not used), its covariance S = H P Hᵀ + R (m, m) (an unused
    component's row and column decoupled, with unit variance) and ``used`` (m,), which
    components entered the update."""

    x: jax.Array
    P: jax.Array
    nu: jax.Array
    S: jax.Array
    used: jax.Array

    @property
    def posterior(self) -> Gaussian:
        return Gaussian(self.x, self.P)


# --------------------------------------------------------------------------- predict


def predict(g: Gaussian, F, Q, *, f_x=None) -> Gaussian:
    """Prediction x⁻ = F x (or ``f_x``, a nonlinear f(x) already evaluated), P⁻ = F P Fᵀ + Q,
    symmetrised."""
    x = mm(F, g.x) if f_x is None else f_x
    return Gaussian(x, symmetrise(mm(mm(F, g.P), F.T) + Q))


def ekf_predict(g: Gaussian, f, Q) -> Gaussian:
    """Extended prediction: x⁻ = f(x), P⁻ = F P Fᵀ + Q with F = ∂f/∂x at x (autodiff)."""
    return predict(g, jacobian(f, g.x), Q, f_x=f(g.x))


# --------------------------------------------------------------------------- update


def innovation(z, z_pred, angles=None):
    """ν = z − ẑ, the components flagged in ``angles`` (a static tuple of bools) wrapped to (-π, π]."""
    nu = z - z_pred
    if angles is None or not any(angles):
        return nu
    return jnp.where(jnp.asarray(angles), wrap_angle(nu), nu)


def joseph_covariance(P, K, H, R, columns=None):
    """The covariance after an update with any gain K, in Joseph form:
    (I − K H) P (I − K H)ᵀ + K R Kᵀ, symmetrised (positive semi-definite whatever K).
    ``columns`` as ``innovation_update``'s: H holds only those columns of the state's."""
    if columns is None:
        IKH = jnp.eye(P.shape[-1], dtype=P.dtype) - mm(K, H)
        return symmetrise(mm(mm(IKH, P), IKH.T) + mm(mm(K, R), K.T))
    KH = mm(K, H)  # the columns of K H that are not zero
    A = _identity_minus(KH, columns, P)  # (I − K H) P
    return symmetrise(_identity_minus(KH, columns, A.T).T + mm(mm(K, R), K.T))  # A (I − K H)ᵀ


def _identity_minus(KH, columns, B):
    """(I − K H) B = B − Σ (K H)[:, k] B[k] over the k in ``columns``, K H being zero elsewhere
    (``KH``: those columns, (n, len(columns))): one outer product per column."""
    out = B
    for c, k in enumerate(columns):
        out = out - KH[:, c:c + 1] * B[k:k + 1]
    return out


def _check_shapes(where: str, g: Gaussian, columns=None, **arrays):
    """``ValueError`` when the arrays of an update do not fit one measurement of m components (H's
    rows) and the state of n = len(g.x): z, h_x, nu, present (m,), H (m, n) (with ``columns``:
    (m, len(columns))), R (m, m). Shapes are known when tracing, so a measurement of the wrong
    size is refused there instead of broadcast."""
    n = jnp.shape(g.x)[-1]
    check_columns(where, n, columns)
    n_h = n if columns is None else len(columns)
    shapes = {k: tuple(jnp.shape(a)) for k, a in arrays.items() if a is not None}
    if len(shapes["H"]) != 2 or shapes["H"][1] != n_h:
        what = f"a state of {n}" if columns is None else f"the columns {columns} of a state of {n}"
        raise ValueError(f"{where}: H has shape {shapes['H']}: expected (m, {n_h}) for {what}")
    m = shapes["H"][0]
    want = {"z": (m,), "h_x": (m,), "nu": (m,), "present": (m,), "H": (m, n_h), "R": (m, m)}
    if any(shape != want[k] for k, shape in shapes.items()):
        raise ValueError(f"{where}: {', '.join(f'{k} {s}' for k, s in shapes.items())}: expected "
                         f"{', '.join(f'{k} {want[k]}' for k in shapes)} (m = {m}, H's rows; n = {n})")


def innovation_update(g: Gaussian, nu, H, R, *, present=None, columns=None) -> Update:
    """The Kalman update of ``g`` on an innovation ν (m,) already formed: S = H P Hᵀ + R,
    K = P Hᵀ S⁻¹, x⁺ = x + K ν, P⁺ = (I − K H) P (I − K H)ᵀ + K R Kᵀ (Joseph form).

    Only the components ``present`` flags (default: all) are used: the others' rows of H and
    ν are zeroed and their R entries replaced by an uncoupled unit variance, so they change
    neither mean nor covariance (none used: the prior is kept).

    ``columns``: the state components the measurement depends on, increasing (a position
    sensor's: the positions), H then holding only their columns (m, len(columns)); the others
    are zero and cost nothing (P Hᵀ reads those columns of P, (I − K H) has the identity's
    columns elsewhere). The same update to the rounding.
    """
    _check_shapes("innovation_update", g, columns, nu=nu, H=H, R=R, present=present)
    if present is None:
        used = jnp.ones(jnp.shape(nu), bool)
    else:
        used = jnp.asarray(present)
        H = jnp.where(used[:, None], H, 0.0)
        nu = jnp.where(used, nu, 0.0)
        R = jnp.where(used[:, None] & used[None, :], R, jnp.eye(R.shape[-1], dtype=R.dtype))
    if columns is None:
        PHt = mm(g.P, H.T)
        S = mm(H, PHt) + R
    else:
        PHt = mm(pick(g.P, columns, axis=1), H.T)  # the columns of P that H reads
        S = mm(H, pick(PHt, columns)) + R
    K = mm(PHt, spd_inverse(S))
    return Update(g.x + mm(K, nu), joseph_covariance(g.P, K, H, R, columns), nu, S, used)


def update(g: Gaussian, z, H, R, *, h_x=None, angles=None, present=None, columns=None) -> Update:
    """Kalman measurement update of the prediction ``g`` with z (m,), H (m, n), R (m, m).

    ν = z − ẑ with ẑ = H x (or ``h_x``, a nonlinear h(x) already evaluated), the components
    flagged in ``angles`` wrapped to (-π, π] (``innovation``), then ``innovation_update``
    (Joseph form) with the components ``present`` flags, by default the finite ones of z
    (NaN = absent). ``present`` known without looking at z (a report pattern shared by
    every run) keeps the covariance independent of the measurement. ``columns`` as
    ``innovation_update``'s (H then holds those columns only; ẑ = H x over them).
    """
    _check_shapes("update", g, columns, z=z, H=H, h_x=h_x)
    if h_x is None:
        h_x = mm(H, g.x if columns is None else pick(g.x, columns))
    nu = innovation(z, h_x, angles)
    return innovation_update(g, nu, H, R, present=jnp.isfinite(z) if present is None else present, columns=columns)


def ekf_update(g: Gaussian, z, h, R, *, angles=None, present=None, columns=None) -> Update:
    """Extended update: ``update`` with ẑ = h(x) and H = ∂h/∂x at the prediction (autodiff).

    ``columns``: the state components h reads, increasing (the positions, for a sensor of the
    position): only their columns of H are computed, and the update skips the others, which
    are zero (``innovation_update``). h must not read any other component.
    """
    check_columns("ekf_update", jnp.shape(g.x)[-1], columns)
    return update(g, z, jacobian(h, g.x, columns), R, h_x=h(g.x), angles=angles, present=present, columns=columns)


# ------------------------------------------------------------------------- assembly


def kalman_filter(params, time_update, measurement_update, *, report=None, init=None, layout=None) -> Filter:
    """A ``Filter`` from its two halves.

    ``time_update(params, g) -> g⁻``; ``measurement_update(params, g⁻, z, present) -> Update``,
    where z has its absent components (NaN in the measurement) set to 0 and ``present`` flags
    the others (``core.masked_meas``); ``report(g) -> (x, P)`` in the reporting frame (identity
    by default); ``init(params, prior) -> g`` (the prior as a Gaussian by default); ``layout``
    as ``Filter``'s. A step with no component used keeps the prediction. ``Out`` holds x, P,
    x_pred, ν (0 where unused), S, valid (any component used) and dof (how many); ``coast``
    is the step with nothing present, without the update.
    """
    report = report or (lambda g: (g.x, g.P))
    init = init or (lambda params, prior: Gaussian(jnp.asarray(prior.x), jnp.asarray(prior.P)))

    def step(params, g, meas):
        z, present = masked_meas(meas)
        pred = time_update(params, g)
        u = measurement_update(params, pred, z, present)
        valid = jnp.any(u.used)
        post = select(valid, Gaussian(u.x, u.P), pred)
        x, P = report(post)
        x_pred, _ = report(pred)
        return post, Out(x=x, P=P, x_pred=x_pred, nu=jnp.where(u.used, u.nu, 0.0), S=u.S, valid=valid,
                         dof=jnp.sum(u.used))

    def coast(params, g, meas):
        pred = time_update(params, g)
        x, P = report(pred)
        u = jax.eval_shape(measurement_update, params, pred, *masked_meas(meas))
        none = jnp.zeros(u.used.shape, bool)
        return pred, Out(x=x, P=P, x_pred=x, nu=jnp.zeros(u.nu.shape, u.nu.dtype),
                         S=jnp.eye(u.S.shape[-1], dtype=u.S.dtype), valid=jnp.any(none), dof=jnp.sum(none))

    return Filter(init=init, step=step, params=params, coast=coast, layout=layout)
