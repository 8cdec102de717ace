"""A Moose-type adaptive tracker (paper 001 Fig. 8; docs/mathematics.md §6).

Moose models a manoeuvre as a mean acceleration ("command") that jumps among
a few levels, plus a correlated random part. Here each of the model's three
target accelerations is u + a: a mean level u, one of ``levels`` (m/s²) per
channel (e, d, r), plus the model's Singer process a (``boresight.drift``'s
``levels``). A Markov chain (probability ``p_stay`` of
keeping the level over a filter period; a simplification of Moose's
semi-Markov sojourn times) carries each channel's level probabilities from
period to period.

The levels enter as known inputs, so every hypothesis shares the joint EKF's
covariance and gain; only the predicted mean moves, by Γ Δu, with Γ = ∂x̂/∂u
over the period (carried through the RK4 steps). Each period:

1. the prediction uses the merged level ū;
2. for each channel c and level i, the innovation is ν − H Γ_c (uᵢ − ū_c),
   its Gaussian likelihood (S of the shared update) weighs the level's
   Markov-predicted probability (the channels' posteriors are factorised);
3. the new mean level ū' moves the prediction by Γ (ū' − ū) before the
   Kalman update, and the spread of the levels adds Σ_c Var_c(u) d_c d_cᵀ,
   d_c = (I − K H) Γ_c, to the covariance (one merged Gaussian per period,
   GPB1-like, so the bank never grows).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.linalg import mm, spd_inverse, symmetrise
from tracklab.parameters import Constraint, Param, bounded
from tracklab.worlds.airborne.boresight import EPS, observation_matrix
from tracklab.worlds.airborne.cd_ekf import (
    CDParams,
    command,
    filter_numbers,
    predict_period,
)
from tracklab.worlds.airborne.tracker import FILTERING, Timing, Tracker, TrackerKind


class MooseParams(NamedTuple):
    base: CDParams  # the joint EKF's model (its σ_m the random part's), noise, gains and λ
    levels: jax.Array  # (N,) mean-acceleration levels, m/s², the same set for a_e, a_d and a_r
    p_stay: jax.Array  # probability of keeping a level over one filter period


class MooseState(NamedTuple):
    x: jax.Array
    P: jax.Array
    pred: jax.Array
    P_end: jax.Array
    refer: jax.Array
    gamma: jax.Array  # (9, 3) ∂x̂(end)/∂u over the period
    cmd: jax.Array
    zsum: jax.Array
    prob: jax.Array  # (3, N) level probabilities of a_e, a_d, a_r
    u: jax.Array  # (3,) merged levels used in the prediction
    spread: jax.Array  # (3,) the levels' variance under prob


def moose(timing: Timing) -> Tracker:
    n = timing.n

    def plan(params, x, P, w_a, prob):
        base = params.base
        u = mm(prob, params.levels)
        spread = jnp.sum(prob * (params.levels[None, :] - u[:, None]) ** 2, axis=1)
        cmd = command(x, base.lam)
        pred, P_end, refer, gamma = predict_period(x, P, w_a, cmd, timing, base.model, u)
        return MooseState(x, P, pred, P_end, refer, gamma, cmd, jnp.zeros(4, x.dtype), prob, u, spread)

    def start(params, x0, P0):
        N = params.levels.shape[0]
        prior = jnp.where(jnp.abs(params.levels) == jnp.min(jnp.abs(params.levels)), 1.0, 0.0)
        prob = jnp.broadcast_to(prior / jnp.sum(prior), (3, N)).astype(x0.dtype)
        return plan(params, x0, P0, jnp.zeros(2, x0.dtype), prob)

    def tick(params, s, i):
        return s.cmd, s.pred[i, 6:8]

    def sample(params, s, i, z):
        return s._replace(zsum=s.zsum + z)

    def update(params, s, w_a):
        base = params.base
        k = base.k
        N = params.levels.shape[0]
        z_hat = jnp.concatenate([k[:2] * jnp.mean(s.pred[:, jnp.array(EPS)], axis=0), jnp.zeros(2, s.x.dtype)])
        nu = s.zsum / n - z_hat
        H = mm(observation_matrix(k), s.refer)
        R = jnp.diag(base.r) / n
        P = s.P_end
        S = mm(mm(H, P), H.T) + R
        S_inv = spd_inverse(S)
        K = mm(mm(P, H.T), S_inv)
        HG = mm(H, s.gamma)  # (4, 3)
        # 2. each channel's level likelihoods, factorised
        du = params.levels[None, :] - s.u[:, None]  # (3, N)
        nus = nu[None, None, :] - HG.T[:, None, :] * du[:, :, None]  # (3, N, 4)
        loglik = -0.5 * jnp.sum(mm(nus.reshape(-1, 4), S_inv).reshape(nus.shape) * nus, axis=-1)
        stay = params.p_stay
        T = stay * jnp.eye(N, dtype=nu.dtype) + (1.0 - stay) / (N - 1) * (1.0 - jnp.eye(N, dtype=nu.dtype))
        prior = mm(s.prob, T)
        post = prior * jnp.exp(loglik - jnp.max(loglik, axis=1, keepdims=True))
        prob = post / jnp.sum(post, axis=1, keepdims=True)
        # 3. move to the new merged levels, update, add the levels' spread
        u_new = mm(prob, params.levels)
        shift = mm(s.gamma, u_new - s.u)
        x_pred = s.pred[-1] + shift
        x = x_pred + mm(K, nu - mm(H, shift))
        IKH = jnp.eye(9, dtype=P.dtype) - mm(K, H)
        P = mm(mm(IKH, P), IKH.T) + mm(mm(K, R), K.T)
        var = jnp.sum(prob * (params.levels[None, :] - u_new[:, None]) ** 2, axis=1)
        D = mm(IKH, s.gamma)
        P = symmetrise(P + mm(D * var, D.T))
        return plan(params, x, P, w_a, prob)

    def estimate(s):
        """The total accelerations (level + Singer part), the levels' spread added to their variances."""
        acc = jnp.array([2, 5, 8])
        return s.x.at[acc].add(s.u), s.P.at[acc, acc].add(s.spread)

    return Tracker(start, tick, sample, update, estimate)


def _numbers(setting, n):
    base, sd0 = filter_numbers(setting, n)
    return MooseParams(base, np.asarray(n["levels"], float), np.asarray(n["p_stay"], float)), sd0


_LEVELS = Constraint("2-21 distinct numbers (m/s²) of magnitude <= 1000",
                     lambda v: (v.ndim == 1) & (2 <= v.size <= 21) & (np.unique(v).size == v.size) & np.all(np.abs(v) <= 1000))
MOOSE = TrackerKind(
    "moose", "joint EKF with Markov-switching mean accelerations (Moose-type adaptive filter)",
    {**FILTERING, "levels": Param("mean-acceleration levels, the same set for a_e, a_d and a_r", _LEVELS, "m/s²",
                                  (-40.0, -20.0, 0.0, 20.0, 40.0)),
     "p_stay": Param("probability of keeping a level over one filter period", bounded(0.0, 1.0), "", 0.99)},
    lambda timing, choices: moose(timing), _numbers)
