"""The joint continuous–discrete EKF on the 9-state boresight model (paper 001 §3, eqs. 10–15).

Between updates the mean and the covariance are integrated together by RK4
at the radar's sample period (eqs. 10–11):

    dx̂/dt = f(x̂, u),    dP/dt = F P + P Fᵀ + G Q Gᵀ,    F = ∂f/∂x at x̂ (``jax.linearize``)

with the antenna's rate between samples known exactly (its command is held
and its lag is known, ``boresight.antenna_rate_at``). The predictions at
each sample set the range and velocity gates and the expected angle error
signals. At the period's end the pre-averaged error signals update the
estimate (eqs. 13–15; Joseph form). The innovation is the averaged signal less
the average of the predicted ones; it measures the average of the state's
errors at the n samples, which the linearised transitions refer to the
period's end: H_eff = H · (1/n) Σᵢ Φ(tᵢ, t_k). (Without it the averaged
velocity discriminator reads ṙ some 20 ms early, the unknown a_r shifts it by
up to 0.6 m/s, and the NEES sits 20 % above its band.)
The antenna is then commanded ω_AC = ω̂ + λ ε̂ per channel (eq. 1).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tracklab.airborne.boresight import EPS, OMEGA, ModelParams, antenna_motion, antenna_rate_at, drift, observation_matrix, process_noise
from tracklab.airborne.tracker import Timing, Tracker
from tracklab.filters.core import kalman_update, symmetrise
from tracklab.linalg import mm, solve


class CDParams(NamedTuple):
    model: ModelParams
    r: jax.Array  # (4,) per-sample noise variances of the error signals (in signal units)
    k: jax.Array  # (4,) detector gains k_e, k_d, k_r, k_ṙ
    lam: jax.Array  # 1/s, the antenna command's gain on ε̂ (eq. 1)


class CDState(NamedTuple):
    x: jax.Array  # x̂(k|k)
    P: jax.Array
    pred: jax.Array  # (n, 9) x̂ predicted at the period's samples
    P_end: jax.Array  # P(k+1|k)
    refer: jax.Array  # (1/n) Σᵢ Φ(tᵢ, t_end): the averaged samples' errors from the error at the period's end
    cmd: jax.Array  # (2,) antenna rate command held over the period
    zsum: jax.Array  # (4,) error signals summed over the period


def _rk4(f, y, h):
    """One classical Runge–Kutta step of ẏ = f(s, y) over [0, h], y a pytree."""
    axpy = lambda a, k, y: jax.tree.map(lambda yi, ki: yi + a * ki, y, k)
    k1 = f(0.0, y)
    k2 = f(h / 2, axpy(h / 2, k1, y))
    k3 = f(h / 2, axpy(h / 2, k2, y))
    k4 = f(h, axpy(h, k3, y))
    return jax.tree.map(lambda yi, a, b, c, d: yi + h / 6 * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4)


def rk4_tick(x, P, w0, cmd, dt, lag, mp: ModelParams, u=None, M=None, G=None):
    """Mean and covariance over one sample period (eqs. 10–11), RK4 on them together, and with
    them the transition's tangent columns: M ↦ J_x M and, given G, G ↦ J_x G + J_u for
    J = ∂x(t+dt)/∂(x, u) of the mean's RK4 step. Returns (x, P, M, G).

    F P is the drift's tangent map applied to P's columns (``jax.linearize``: only its nonzero
    partial derivatives), and P Fᵀ its transpose, P being symmetric. M and G ride in the same
    stages as Ṁ = F M and Ġ = F G + ∂f/∂u: RK4 applied to these variational equations is
    exactly the tangent map of RK4's step, so the drift is linearised once per stage for all."""
    GQG = process_noise(mp)
    a_m = jnp.zeros(3, x.dtype)
    u = jnp.zeros(3, x.dtype) if u is None else u
    n = x.shape[0]
    M = jnp.zeros((n, 0), x.dtype) if M is None else M
    du = jnp.zeros((3, n + M.shape[1]), x.dtype)
    if G is not None:  # G's columns move u as well (∂f/∂u)
        du = jnp.concatenate([du, jnp.eye(3, dtype=x.dtype)], axis=1)

    def deriv(s, y):
        x, P, C = y
        w = antenna_rate_at(w0, cmd, s, lag)
        fx, f_lin = jax.linearize(lambda z, v: drift(z, w, a_m, mp, v), x, u)
        FC = jax.vmap(f_lin, in_axes=(1, 1), out_axes=1)(jnp.concatenate([P, C], axis=1), du)
        FP = FC[:, :n]
        return fx, FP + FP.T + GQG, FC[:, n:]

    columns = M if G is None else jnp.concatenate([M, G], axis=1)
    x, P, C = _rk4(deriv, (x, P, columns), dt)
    m = M.shape[1]
    return x, symmetrise(P), C[:, :m], (None if G is None else C[:, m:])


def command(x, lam):
    """Eq. 1: ω_AC = ω̂ + λ ε̂ (e and d channels)."""
    return x[jnp.array(OMEGA)] + lam * x[jnp.array(EPS)]


def predict_period(x, P, w_a, cmd, timing: Timing, mp: ModelParams, u=None):
    """Predictions at the n samples of the next period, the covariance at its end, the averaged samples'
    referral to the end (``CDState.refer``) and, with mean levels u (Moose), the end state's
    sensitivity to them (9 × 3; None without)."""

    def step(carry, _):
        x, P, w, M, G = carry
        x, P, M, G = rk4_tick(x, P, w, cmd, timing.dt, timing.lag, mp, u, M, G)  # M: Φ(tᵢ, t_start)
        w, _ = antenna_motion(w, cmd, timing.dt, timing.lag)
        return (x, P, w, M, G), (x, M)

    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    init = (x, P, w_a, eye, None if u is None else jnp.zeros((9, 3), x.dtype))
    (_, P_end, _, M_end, G_end), (pred, Ms) = jax.lax.scan(step, init, None, length=timing.n)
    refer = solve(M_end.T, jnp.mean(Ms, axis=0).T).T  # (1/n Σ Mᵢ) M_end⁻¹
    return pred, P_end, refer, G_end


def cd_ekf(timing: Timing) -> Tracker:
    n = timing.n

    def plan(params, x, P, w_a):
        cmd = command(x, params.lam)
        pred, P_end, refer, _ = predict_period(x, P, w_a, cmd, timing, params.model)
        return CDState(x, P, pred, P_end, refer, cmd, jnp.zeros(4, x.dtype))

    def start(params, x0, P0):
        return plan(params, x0, P0, jnp.zeros(2, x0.dtype))

    def tick(params, s: CDState, i):
        return s.cmd, s.pred[i, 6:8]

    def sample(params, s: CDState, i, z):
        return s._replace(zsum=s.zsum + z)

    def update(params, s: CDState, w_a):
        k = params.k
        z_hat = jnp.concatenate([k[:2] * jnp.mean(s.pred[:, jnp.array(EPS)], axis=0), jnp.zeros(2, s.x.dtype)])
        nu = s.zsum / n - z_hat  # the range and velocity gates sat on the predictions
        H = mm(observation_matrix(k), s.refer)
        x, P, _ = kalman_update(s.pred[-1], s.P_end, nu, H, jnp.diag(params.r) / n)
        return plan(params, x, P, w_a)

    def estimate(s: CDState):
        return s.x, s.P

    return Tracker(start, tick, sample, update, estimate)
