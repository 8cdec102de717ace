"""The decoupled linear tracker of Pearson and Shibata (paper 001 §2, remark 2; docs/mathematics.md §1).

Three 3-state channels filtered separately: elevation [ε_e, ω_e, a_e], azimuth
[ε_d, ω_d, a_d] and range [r, ṙ, a_r]. Each channel is linear once the other
channels' estimates are frozen as known coefficients for the period: the
angle channels take r̂ and ṙ̂ from the range channel,

    A = [[0, 1, 0], [0, −2ṙ̂/r̂, 1/r̂], [0, 0, −1/τ]],   input −ω_A into ε̇,

and the range channel takes the centripetal term r̂(ω̂_e² + ω̂_d²) as a known
input to r̈. Each period the channels are discretised at the sample period by
Van Loan's method (``linalg.expm``, channel by channel), the antenna's turn over each
sample (``boresight.antenna_motion``) entering the ε rows exactly.

``separate=True`` splits the range channel as a classical radar does: a range
loop [r, ṙ, a_r] on the range discriminator alone and a velocity loop [ṙ, a_r]
on the velocity discriminator alone (paper 001's third comparison: the single
range loop against the cross-coupled range–velocity channel of Fig. 5).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import block_diag

from tracklab.filters.blocks import Gaussian, innovation_update
from tracklab.linalg import expm, mm, symmetrise
from tracklab.worlds.airborne.boresight import EPS, OMEGA, antenna_motion
from tracklab.worlds.airborne.cd_ekf import command, filter_numbers
from tracklab.worlds.airborne.tracker import FILTERING, Timing, Tracker, TrackerKind


class DecoupledState(NamedTuple):
    x: jax.Array  # (m,) 9, or 11 with the separate velocity loop [ṙ, a_r] at 9, 10
    P: jax.Array  # block diagonal
    pred: jax.Array  # (n, m)
    P_end: list  # each channel's covariance at the period's end
    refer: list  # each channel's (1/n) Σᵢ Φ^{i−n}: the averaged samples' errors from the error at the period's end (cd_ekf)
    cmd: jax.Array
    zsum: jax.Array


class Channel(NamedTuple):
    """One channel's model with the other channels' estimates frozen: ẋ_c = A x_c + b + w, E[w wᵀ] = Q_c."""

    A: jax.Array
    b: jax.Array | None  # None: no input
    Qc: jax.Array


CHANNELS = ((0, 3), (3, 6), (6, 9), (9, 11))  # elevation, azimuth, range, the separate velocity loop
# each channel's error signals (rows of z: ε_em, ε_dm, range, velocity) and the states they read
SIGNALS = {False: (((0,), (0,)), ((1,), (0,)), ((2, 3), (0, 1))),
           True: (((0,), (0,)), ((1,), (0,)), ((2,), (0,)), ((3,), (0,)))}


def channel_matrices(x, mp, separate):
    """The channels with the coefficients frozen at x, in the state's order: elevation, azimuth (the
    same channel object), range and, ``separate``, the velocity loop."""
    r, rdot = x[6], (x[9] if separate else x[7])
    z = jnp.zeros((), x.dtype)
    one = jnp.ones((), x.dtype)
    A_angle = jnp.stack([jnp.stack([z, one, z]), jnp.stack([z, -2.0 * rdot / r, 1.0 / r]), jnp.stack([z, z, -1.0 / mp.tau])])
    Q_angle = jnp.diag(jnp.stack([z, z, 2.0 * mp.sigma_m**2 / mp.tau]))
    qr = 2.0 * mp.sigma_r**2 / mp.tau_r
    centripetal = r * jnp.sum(x[jnp.array(OMEGA)] ** 2)
    A_range = jnp.stack([jnp.stack([z, one, z]), jnp.stack([z, z, one]), jnp.stack([z, z, -1.0 / mp.tau_r])])
    angle = Channel(A_angle, None, Q_angle)
    out = [angle, angle, Channel(A_range, jnp.stack([z, centripetal, z]), jnp.diag(jnp.stack([z, z, qr])))]
    if separate:
        out.append(Channel(jnp.stack([jnp.stack([z, one]), jnp.stack([z, -1.0 / mp.tau_r])]),
                           jnp.stack([centripetal, z]), jnp.diag(jnp.stack([z, qr]))))
    return out


def _van_loan(c: Channel, T):
    """(Φ, γ = ∫Φ b, Q_d, Φ⁻¹) of one channel over T. Q_d is linear in Q_c, which is scaled to unit
    size first, so that A·T alone sets the exponential's squarings; Φ⁻¹ = e^{−AT} is the exponential's
    other diagonal block."""
    k = c.A.shape[0]
    scale = jnp.maximum(jnp.max(jnp.abs(c.Qc)), jnp.finfo(c.A.dtype).tiny)
    M = jnp.zeros((2 * k, 2 * k), c.A.dtype).at[:k, :k].set(-c.A).at[:k, k:].set(c.Qc / scale).at[k:, k:].set(c.A.T)
    E = expm(M * T)
    phi = E[k:, k:].T
    Qd = scale * symmetrise(mm(phi, E[:k, k:]))
    if c.b is None:  # no input
        return phi, jnp.zeros(k, c.A.dtype), Qd, E[:k, :k]
    Mb = jnp.zeros((k + 1, k + 1), c.A.dtype).at[:k, :k].set(c.A).at[:k, k].set(c.b)
    return phi, expm(Mb * T)[:k, k], Qd, E[:k, :k]


def van_loan(channels, T):
    """Each channel's (Φ, γ = ∫Φ b, Q_d, Φ⁻¹) over T by Van Loan's method, in the state's order (a
    channel whose model is another's, the azimuth's, is not computed twice). The whole state's are
    these blocks on the diagonal."""
    done = {}
    for c in channels:
        if id(c) not in done:
            done[id(c)] = _van_loan(c, T)
    return [done[id(c)] for c in channels]


def decoupled(timing: Timing, separate=False) -> Tracker:
    n, m = timing.n, (11 if separate else 9)
    rdot_i = 9 if separate else 7
    view = jnp.array([0, 1, 2, 3, 4, 5, 6, 9, 10] if separate else list(range(9)))
    signals = SIGNALS[separate]
    bounds = CHANNELS[:len(signals)]
    # per channel, which of the antenna's turns enters it, and at which of its rows: the ε rows (EPS)
    turned = [next(((t, e - a) for t, e in enumerate(EPS) if a <= e < b), None) for a, b in bounds]

    def plan(params, x, P, w_a):
        cmd = command(x, params.lam)
        blocks = van_loan(channel_matrices(x, params.model, separate), timing.dt)

        def step(carry, _):  # channel by channel: P is block diagonal, and so is every product here
            xs, Ps, w = carry
            w_next, turn = antenna_motion(w, cmd, timing.dt, timing.lag)
            xs = [mm(phi, xc) + gam for (phi, gam, _, _), xc in zip(blocks, xs)]
            xs = [xc if on is None else xc.at[on[1]].add(-turn[on[0]]) for xc, on in zip(xs, turned)]
            Ps = [symmetrise(mm(mm(phi, Pc), phi.T) + Qd) for (phi, _, Qd, _), Pc in zip(blocks, Ps)]
            return (xs, Ps, w_next), jnp.concatenate(xs)

        init = ([x[a:b] for a, b in bounds], [P[a:b, a:b] for a, b in bounds], w_a)
        (_, P_end, _), pred = jax.lax.scan(step, init, None, length=n)
        refer = []
        for _, _, _, phi_inv in blocks:
            back = [jnp.eye(phi_inv.shape[0], dtype=x.dtype)]  # Φ^{i−n}, i = n … 1
            for _ in range(n - 1):
                back.append(mm(back[-1], phi_inv))
            refer.append(sum(back) / n)
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

    def update(params, s, w_a):  # channel by channel, each on the error signals it reads
        k = params.k
        z_hat = jnp.concatenate([k[:2] * jnp.mean(s.pred[:, jnp.array(EPS)], axis=0), jnp.zeros(2, s.x.dtype)])
        nu = s.zsum / n - z_hat
        xs, Ps = [], []
        for (a, b), (rows, states), P_end, refer in zip(bounds, signals, s.P_end, s.refer):
            rows = np.asarray(rows)
            H = jnp.zeros((len(rows), b - a), s.x.dtype).at[np.arange(len(rows)), np.asarray(states)].set(k[rows])
            u = innovation_update(Gaussian(s.pred[-1, a:b], P_end), nu[rows], mm(H, refer), jnp.diag(params.r[rows]) / n)
            xs.append(u.x)
            Ps.append(u.P)
        return plan(params, jnp.concatenate(xs), block_diag(*Ps), w_a)

    def estimate(s):
        return s.x[view], s.P[view][:, view]

    def _block_diagonal(P):
        return block_diag(*(P[a:b, a:b] for a, b in bounds))

    return Tracker(start, tick, sample, update, estimate)


DECOUPLED = TrackerKind("decoupled", "Pearson/Shibata: e, d and range channels filtered separately (range_velocity "
                        "coupled | separate)", FILTERING,
                        lambda timing, choices: decoupled(timing, choices["range_velocity"] == "separate"), filter_numbers,
                        {"range_velocity": ("coupled", "separate")})
