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
import numpy as np

from tracklab.filters.blocks import Gaussian, innovation_update
from tracklab.linalg import mm, solve
from tracklab.worlds.airborne.boresight import (
    EPS,
    OMEGA,
    ModelParams,
    antenna_motion,
    antenna_rate_at,
    drift,
    observation_matrix,
    process_noise,
)
from tracklab.worlds.airborne.tracker import (
    FILTERING,
    Setting,
    Timing,
    Tracker,
    TrackerKind,
    prior_sd,
)


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
    """One classical Runge–Kutta step of ẏ = f(s, y) over [0, h]."""
    k1 = f(0.0, y)
    k2 = f(h / 2, y + h / 2 * k1)
    k3 = f(h / 2, y + h / 2 * k2)
    k4 = f(h, y + h * k3)
    return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _rk4_packed(Y, w0, cmd, dt, lag, mp: ModelParams, u, du):
    """``rk4_tick`` on the packed columns Y = [x̂ | P | tangent columns] (9 × K+1); ``du`` (3, K) the
    columns' tangents of u (zero but for Moose's G columns)."""
    GQG = process_noise(mp)
    n, K = Y.shape[0], Y.shape[1] - 1
    a_m = jnp.zeros((3, 1), Y.dtype)
    u_columns = jnp.broadcast_to(u[:, None], (3, K))

    def deriv(s, Y):
        x = Y[:, 0]
        w = antenna_rate_at(w0, cmd, s, lag)[:, None]
        f = lambda z, v: drift(z, w, a_m, mp, v)
        # the drift's tangent map on every column at once: each state component a row of K columns
        _, FC = jax.jvp(f, (jnp.broadcast_to(x[:, None], (n, K)), u_columns), (Y[:, 1:], du))
        FP = FC[:, :n]
        return jnp.concatenate([f(x[:, None], u[:, None]), FP + FP.T + GQG, FC[:, n:]], axis=1)

    return _rk4(deriv, Y, dt)


def rk4_tick(x, P, w0, cmd, dt, lag, mp: ModelParams, u=None, M=None, G=None):
    """Mean and covariance over one sample period (eqs. 10–11), RK4 on them together, and with
    them the transition's tangent columns: M ↦ J_x M and, given G, G ↦ J_x G + J_u for
    J = ∂x(t+dt)/∂(x, u) of the mean's RK4 step. Returns (x, P, M, G).

    F P is the drift's tangent map (``jax.jvp``) applied to P's columns, and P Fᵀ its transpose, P
    being symmetric (each stage adds F P + (F P)ᵀ, so a symmetric P stays exactly symmetric). M
    and G ride in the same stages as Ṁ = F M and Ġ = F G + ∂f/∂u: RK4 applied to these
    variational equations is exactly the tangent map of RK4's step, so the drift is linearised
    once per stage for all. The step works on one packed array [x̂ | P | M | G], every
    operation elementwise on its rows (``predict_period`` carries it packed from tick to tick)."""
    n = x.shape[0]
    u = jnp.zeros(3, x.dtype) if u is None else u
    M = jnp.zeros((n, 0), x.dtype) if M is None else M
    m = M.shape[1]
    Y = _rk4_packed(_pack(x, P, M, G), w0, cmd, dt, lag, mp, u, _u_tangents(n + m, G is not None, x.dtype))
    return Y[:, 0], Y[:, 1:n + 1], Y[:, n + 1:n + 1 + m], (None if G is None else Y[:, n + 1 + m:])


def _pack(x, P, M, G=None):
    """The packed columns [x̂ | P | M | G] (G: None, none)."""
    return jnp.concatenate([x[:, None], P, M] + ([] if G is None else [G]), axis=1)


def _u_tangents(columns, with_g, dtype):
    """∂u of each packed tangent column: zero for P's and M's, the identity for G's (∂f/∂u)."""
    du = jnp.zeros((3, columns), dtype)
    return jnp.concatenate([du, jnp.eye(3, dtype=dtype)], axis=1) if with_g else du


def command(x, lam):
    """Eq. 1: ω_AC = ω̂ + λ ε̂ (e and d channels)."""
    return x[jnp.array(OMEGA)] + lam * x[jnp.array(EPS)]


def predict_period(x, P, w_a, cmd, timing: Timing, mp: ModelParams, u=None):
    """Predictions at the n samples of the next period, the covariance at its end, the averaged samples'
    referral to the end (``CDState.refer``) and, with mean levels u (Moose), the end state's
    sensitivity to them (9 × 3; None without)."""
    n = x.shape[0]
    du = _u_tangents(2 * n, u is not None, x.dtype)
    levels = jnp.zeros(3, x.dtype) if u is None else u

    def step(carry, _):
        Y, w = carry  # Y = [x̂ | P | M | G], M = Φ(tᵢ, t_start)
        Y = _rk4_packed(Y, w, cmd, timing.dt, timing.lag, mp, levels, du)
        w, _ = antenna_motion(w, cmd, timing.dt, timing.lag)
        return (Y, w), Y

    Y0 = _pack(x, P, jnp.eye(n, dtype=x.dtype), None if u is None else jnp.zeros((n, 3), x.dtype))
    (Y_end, _), Ys = jax.lax.scan(step, (Y0, w_a), None, length=timing.n)
    M_end = Y_end[:, n + 1:2 * n + 1]
    refer = solve(M_end.T, jnp.mean(Ys[:, :, n + 1:2 * n + 1], axis=0).T).T  # (1/n Σ Mᵢ) M_end⁻¹
    return Ys[:, :, 0], Y_end[:, 1:n + 1], refer, (None if u is None else Y_end[:, 2 * n + 1:])


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
        u = innovation_update(Gaussian(s.pred[-1], s.P_end), nu, H, jnp.diag(params.r) / n)
        return plan(params, u.x, u.P, w_a)

    def estimate(s: CDState):
        return s.x, s.P

    return Tracker(start, tick, sample, update, estimate)


def filter_numbers(setting: Setting, n) -> tuple[CDParams, np.ndarray]:
    """A filtering tracker's params from its table's numbers (``FILTERING``): the model's Singer σ's
    scaled by √q_scale (Q ∝ σ²), R = r_scale·(k σ)² of the error signals, λ; and its prior
    standard deviations. Traceable in q_scale, r_scale and lam (what tuning varies)."""
    q = n["q_scale"] ** 0.5
    mp = ModelParams(q * np.asarray(n["sigma_m"], float), np.asarray(n["tau"], float), q * np.asarray(n["sigma_r"], float),
                     np.asarray(n["tau_r"], float))
    k = np.asarray(setting.gains, float)
    r = n["r_scale"] * (k * np.asarray(setting.noise, float)) ** 2
    return CDParams(mp, r, k, n["lam"] * np.ones((), float)), prior_sd(setting, n["sigma_m"], n["sigma_r"])


CD_EKF = TrackerKind("cd_ekf", "joint continuous-discrete EKF on the 9-state boresight model, antenna command eq. 1",
                     FILTERING, lambda timing, choices: cd_ekf(timing), filter_numbers)
