"""Strong tracking filter with Zhou's suboptimal fading factor (docs/mathematics.md §3).

Per step, from x̂(k|k), P(k|k) and the measurement z(k+1):

1. x̂(k+1|k) = f(x̂(k|k)); γ = z(k+1) − h(x̂(k+1|k))  (the residual does not depend on λ)
2. V = γγᵀ on the first measurement, then V = (ρ V + γγᵀ) / (1 + ρ), 0 < ρ ≤ 1
3. N = V − H Q Hᵀ − b R              (b, the weakening factor: larger b, gentler fading)
4. M = H F P Fᵀ Hᵀ
5. λ = max(1, tr N / tr M)           (tr M guarded against zero)
6. P(k+1|k) = λ F P Fᵀ + Q           (the fading factor multiplies F P Fᵀ only)
7. the Kalman update (Joseph form).

Only traces of N and M enter λ, so V is kept as its diagonal (one running mean
per measurement component, started by that component's first report). With a
partial measurement the traces run over the components present; with none, λ = 1
and V is unchanged. F and H are Jacobians (``jax.jacfwd``) at x̂(k|k) and
x̂(k+1|k): on a linear model and a linear sensor this is the linear STF, on a
nonlinear sensor the extended one. Parameters {q, r, rho, b} are a pytree, so
ρ and b can be tuned by gradient like Q and R.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tracklab.checks import check_positive, check_state_space, is_real, is_traced, refuse, wrong_type
from tracklab.filters.blocks import Gaussian, innovation, innovation_update
from tracklab.filters.core import Filter, Out, masked_meas
from tracklab.filters.kind import ANY_SENSOR, NOISE, Entry, FilterKind, noise
from tracklab.parameters import Param, positive, unit_interval
from tracklab.linalg import jacobian, mm, symmetrise


class StfState(NamedTuple):
    x: jax.Array
    P: jax.Array
    v: jax.Array  # running mean of γ² per measurement component (the diagonal of V)
    seen: jax.Array  # per component: has V been started?


def _stf(f, h, Q_of, R_of, angle_mask, params) -> Filter:
    """Build the STF from f(x), h(x) and Q(params), R(params) (full matrices)."""

    def init(p, prior):
        x = jnp.asarray(prior.x)
        m = jax.eval_shape(h, x).shape[0]
        return StfState(x, jnp.asarray(prior.P), jnp.zeros((m,), x.dtype), jnp.zeros((m,), bool))

    def predict_parts(p, s):
        F = jacobian(f, s.x)
        return f(s.x), symmetrise(mm(mm(F, s.P), F.T)), Q_of(p)

    def step(p, s, meas):
        z, present = masked_meas(meas)
        x_pred, FPF, Q = predict_parts(p, s)
        R = R_of(p)
        H = jacobian(h, x_pred)
        gamma = innovation(z, h(x_pred), angle_mask)
        g2 = jnp.where(present, gamma**2, 0.0)
        v = jnp.where(present, jnp.where(s.seen, (p["rho"] * s.v + g2) / (1.0 + p["rho"]), g2), s.v)
        HQH = jnp.diagonal(mm(mm(H, Q), H.T))
        M = jnp.diagonal(mm(mm(H, FPF), H.T))
        trN = jnp.sum(jnp.where(present, v - HQH - p["b"] * jnp.diagonal(R), 0.0))
        trM = jnp.sum(jnp.where(present, M, 0.0))
        floor = 1e-12 * jnp.sum(jnp.where(present, jnp.diagonal(R), 0.0)) + jnp.finfo(trM.dtype).tiny
        lam = jnp.where(jnp.any(present), jnp.maximum(1.0, trN / jnp.maximum(trM, floor)), 1.0)
        P_pred = lam * FPF + Q
        u = innovation_update(Gaussian(x_pred, P_pred), gamma, H, R, present=present)
        out = Out(x=u.x, P=u.P, x_pred=x_pred, nu=u.nu, S=u.S, valid=jnp.any(present), dof=jnp.sum(present),
                  aux={"fading": lam})
        return StfState(u.x, u.P, v, s.seen | present), out

    def coast(p, s, meas):  # no measurement: a plain prediction (λ = 1)
        x_pred, FPF, Q = predict_parts(p, s)
        P = FPF + Q
        m = s.v.shape[0]
        none = jnp.zeros((m,), bool)
        out = Out(x=x_pred, P=P, x_pred=x_pred, nu=jnp.zeros((m,), x_pred.dtype), S=jnp.eye(m, dtype=P.dtype),
                  valid=jnp.any(none), dof=jnp.sum(none), aux={"fading": jnp.ones((), P.dtype)})
        return s._replace(x=x_pred, P=P), out

    return Filter(init=init, step=step, params=params, coast=coast)


def strong_tracking(f, h, Q, R, *, rho=0.95, b=1.0, angle_mask=None) -> Filter:
    """Strong tracking filter for x' = f(x) + w, z = h(x) + v; params {Q, R, rho, b}.

    ``f`` and ``h`` may be linear (``lambda x: F @ x``) or not; innovation
    components flagged in ``angle_mask`` are wrapped to (-π, π].

    Refused in one line naming the argument: Q, R, f, h or ``angle_mask`` as ``tracklab.filters.ekf``
    refuses them (``checks.check_state_space``); ``rho`` not in (0, 1]; ``b`` not a finite number > 0.
    """
    where = "tracklab.filters.strong_tracking"
    check_state_space(where, Q=Q, R=R, f=f, h=h, angle_mask=angle_mask)
    if not is_traced(rho) and not (is_real(rho) and 0 < float(rho) <= 1):
        raise (refuse if is_real(rho) else wrong_type)(where, "rho", rho, "must be a forgetting factor in (0, 1]")
    if not is_traced(b):
        check_positive(where, "b", b)
    params = {"Q": jnp.asarray(Q), "R": jnp.asarray(R), "rho": jnp.asarray(rho, float), "b": jnp.asarray(b, float)}
    return _stf(f, h, lambda p: p["Q"], lambda p: p["R"], angle_mask, params)


def model_stf(model, sensor, params) -> Filter:
    """The STF on a kinematic model and an experiment's sensor; params {q, r, rho, b}."""
    F = model.F  # NumPy: known when built inside a trace (``mm`` skips its zeros)
    pos = tuple(model.pos_idx)

    def h(x):
        return sensor.h(jnp.stack([x[i] for i in pos]))

    return _stf(lambda x: mm(F, x), h, lambda p: model.Q(p["q"]), lambda p: jnp.diag(p["r"]), sensor.angle_mask, params)


def _read(e: Entry):
    model = e.motion_model()
    params = noise(e, model)
    params["rho"] = e.number("rho", e.default("rho"))
    if not 0.0 < params["rho"] <= 1.0:
        raise e.error("rho", params["rho"], "the forgetting factor must be in (0, 1]")
    params["b"] = e.number("b", e.default("b"), positive=True)
    return model, params, {}


STF = FilterKind(
    name="stf", doc="strong tracking filter (Zhou): fading factor, forgetting rho, weakening b; extended on nonlinear sensors",
    accepts=ANY_SENSOR,
    params={**NOISE,
            "rho": Param("forgetting factor ρ of the residual's running mean", unit_interval, default=0.95, tune=True,
                         sweep=True),
            "b": Param("weakening factor (larger: gentler fading)", positive, default=1.0, tune=True, sweep=True)},
    read=_read, build=lambda model, sensor, params, options: model_stf(model, sensor, params))
