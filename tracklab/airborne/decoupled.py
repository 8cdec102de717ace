"""The decoupled linear tracker of Pearson and Shibata (paper 001 §2, remark 2; REFERENCE_MATH §1).

Three 3-state channels filtered separately: elevation [ε_e, ω_e, a_e], azimuth
[ε_d, ω_d, a_d] and range [r, ṙ, a_r]. Each channel is linear once the other
channels' estimates are frozen as known coefficients for the period: the
angle channels take r̂ and ṙ̂ from the range channel,

    A = [[0, 1, 0], [0, −2ṙ̂/r̂, 1/r̂], [0, 0, −1/τ]],   input −ω_A into ε̇,

and the range channel takes the centripetal term r̂(ω̂_e² + ω̂_d²) as a known
input to r̈. Each period the channels are discretised at the sample period by
Van Loan's method (``jax.scipy.linalg.expm``), the antenna's turn over each
sample (``boresight.antenna_motion``) entering the ε rows exactly.

``separate=True`` splits the range channel as a classical radar does: a range
loop [r, ṙ, a_r] on the range discriminator alone and a velocity loop [ṙ, a_r]
on the velocity discriminator alone (comparison 3 of PAPERS.md: the single
range loop against the cross-coupled range–velocity channel of Fig. 5).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import expm

from tracklab.airborne.boresight import EPS, OMEGA, antenna_motion
from tracklab.airborne.cd_ekf import command
from tracklab.airborne.tracker import Timing, Tracker
from tracklab.filters.core import kalman_update, symmetrise


class DecoupledState(NamedTuple):
    x: jax.Array  # (m,) 9, or 11 with the separate velocity loop [ṙ, a_r] at 9, 10
    P: jax.Array  # block diagonal
    pred: jax.Array  # (n, m)
    P_end: jax.Array
    refer: jax.Array  # (1/n) Σᵢ Φ^{i−n}: the averaged samples' errors from the error at the period's end (cd_ekf)
    cmd: jax.Array
    zsum: jax.Array


def channel_matrices(x, mp, separate):
    """(A, b, Q_c) of the channels with the coefficients frozen at x."""
    m = 11 if separate else 9
    r, rdot = x[6], (x[9] if separate else x[7])
    A = jnp.zeros((m, m), x.dtype)
    for e, w, a in ((0, 1, 2), (3, 4, 5)):
        A = A.at[e, w].set(1.0).at[w, w].set(-2.0 * rdot / r).at[w, a].set(1.0 / r).at[a, a].set(-1.0 / mp.tau)
    A = A.at[6, 7].set(1.0).at[7, 8].set(1.0).at[8, 8].set(-1.0 / mp.tau_r)
    centripetal = r * jnp.sum(x[jnp.array(OMEGA)] ** 2)
    b = jnp.zeros(m, x.dtype).at[7].set(centripetal)
    q = jnp.zeros(m, x.dtype).at[jnp.array([2, 5])].set(2.0 * mp.sigma_m**2 / mp.tau).at[8].set(2.0 * mp.sigma_r**2 / mp.tau_r)
    if separate:
        A = A.at[9, 10].set(1.0).at[10, 10].set(-1.0 / mp.tau_r)
        b = b.at[9].set(centripetal)
        q = q.at[10].set(2.0 * mp.sigma_r**2 / mp.tau_r)
    return A, b, jnp.diag(q)


def van_loan(A, b, Qc, T):
    """Φ, the constant input's response γ = ∫Φ b, and Q_d over T."""
    m = A.shape[0]
    M = jnp.zeros((2 * m, 2 * m), A.dtype).at[:m, :m].set(-A).at[:m, m:].set(Qc).at[m:, m:].set(A.T)
    E = expm(M * T)
    phi = E[m:, m:].T
    Mb = jnp.zeros((m + 1, m + 1), A.dtype).at[:m, :m].set(A).at[:m, m].set(b)
    return phi, expm(Mb * T)[:m, m], symmetrise(phi @ E[:m, m:])


def decoupled(timing: Timing, separate=False) -> Tracker:
    n, m = timing.n, (11 if separate else 9)
    rdot_i = 9 if separate else 7
    view = jnp.array([0, 1, 2, 3, 4, 5, 6, 9, 10] if separate else list(range(9)))
    H_rows = jnp.array([0, 3, 6, rdot_i])

    def plan(params, x, P, w_a):
        cmd = command(x, params.lam)
        phi, gam, Qd = van_loan(*channel_matrices(x, params.model, separate), timing.dt)

        def step(carry, _):
            x, P, w = carry
            w_next, turn = antenna_motion(w, cmd, timing.dt, timing.lag)
            x = phi @ x + gam
            x = x.at[jnp.array(EPS)].add(-turn)
            return (x, symmetrise(phi @ P @ phi.T + Qd), w_next), x

        (_, P_end, _), pred = jax.lax.scan(step, (x, P, w_a), None, length=n)
        powers = [jnp.eye(m, dtype=x.dtype)]
        for _ in range(n):
            powers.append(phi @ powers[-1])
        refer = jnp.linalg.solve(powers[-1].T, sum(powers[1:]).T / n).T
        return DecoupledState(x, P, pred, P_end, refer, cmd, jnp.zeros(4, x.dtype))

    def start(params, x0, P0):
        x = x0 if not separate else jnp.concatenate([x0, x0[7:9]])
        if separate:
            P = jnp.zeros((m, m), x0.dtype).at[:9, :9].set(P0).at[9:, 9:].set(P0[7:9, 7:9])
        else:
            P = P0
        return plan(params, x, _block_diagonal(P), jnp.zeros(2, x0.dtype))

    def tick(params, s, i):
        return s.cmd, jnp.stack([s.pred[i, 6], s.pred[i, rdot_i]])

    def sample(params, s, i, z):
        return s._replace(zsum=s.zsum + z)

    def update(params, s, w_a):
        k = params.k
        H = jnp.zeros((4, m), s.x.dtype).at[jnp.arange(4), H_rows].set(k)
        z_hat = jnp.concatenate([k[:2] * jnp.mean(s.pred[:, jnp.array(EPS)], axis=0), jnp.zeros(2, s.x.dtype)])
        x, P, _ = kalman_update(s.pred[-1], s.P_end, s.zsum / n - z_hat, H @ s.refer, jnp.diag(params.r) / n)
        return plan(params, x, P, w_a)

    def estimate(s):
        return s.x[view], s.P[view][:, view]

    def _block_diagonal(P):
        blocks = [(0, 3), (3, 6), (6, 9)] + ([(9, 11)] if separate else [])
        out = jnp.zeros_like(P)
        for a, b in blocks:
            out = out.at[a:b, a:b].set(P[a:b, a:b])
        return out

    return Tracker(start, tick, sample, update, estimate)
