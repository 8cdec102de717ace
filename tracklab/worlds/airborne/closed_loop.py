"""One closed-loop engagement: truth, antenna, radar error signals and a tracker, as one scan.

Every tick (the radar's sample period) the tracker's rate command drives the
gyro-stabilised antenna (first-order lag, ``boresight.antenna_motion``), the
target moves (the nominal path plus, in Monte-Carlo runs, the exactly sampled
Singer perturbation), and the radar forms its four error signals (eq. 4)
against the tracker's gates:

    ε_em = k_e·clip(ε_e) + v_e,  ε_dm = k_d·clip(ε_d) + v_d,
    z_r = k_r·clip(r − r_gate) + v_r,  z_ṙ = k_ṙ·clip(ṙ − ṙ_gate) + v_ṙ,

each clipped to its discriminator's linear range (the beam's and the gates'
half-widths); a run whose target leaves the beam or a gate has lost lock and
is counted, not averaged. Every ``n`` ticks the tracker updates and the true
9-state at that instant is compared with its estimate. An optional jolt turns
the antenna by a fixed angle about its d axis at one instant (a large error
the trackers must recover from).

``engage`` is one run of every tracker (pure, ``vmap`` over keys); ``sums`` reduces a batch of runs to per-period sums for
streaming statistics, ``run_samples`` to each run's time averages over the
report windows (the samples behind the intervals). Every random draw is made in
single precision and then cast, so a float32 run sees the very same target
paths and noise as a float64 one. The small products are ``linalg.mm``: under
``vmap`` on the CPU a batched 3 × 3 or 9 × 9 ``dot`` is a call per run.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.linalg import mahalanobis2, mm
from tracklab.worlds.airborne.boresight import (
    antenna_motion,
    los_frame,
    los_state,
    rotate,
)
from tracklab.worlds.airborne.engagement import Engagement, singer_block
from tracklab.worlds.airborne.tracker import Timing, Tracker

MRAD = 1e-3  # rad: the unit of the reported angles
SAMPLE_QUANTITIES = ("pointing", "pointing_estimate", "los_rate", "range", "range_rate", "nees")


class LoopConfig(NamedTuple):
    timing: Timing
    periods: int
    k: tuple  # detector gains k_e, k_d, k_r, k_ṙ
    sigma: tuple  # per-sample noise std of the four error signals (rad, rad, m, m/s, before the gains)
    limits: tuple  # half-widths: beam (rad), range gate (m), velocity gate (m/s)
    acquisition: tuple  # designation errors (std): ε (rad), ω (rad/s), r (m), ṙ (m/s)
    jolt_tick: int = -1  # tick at which the antenna is jolted (-1: never)
    jolt: float = 0.0  # rad, about the d axis
    singer: bool = True  # add the Singer perturbation to the nominal path
    singer_phi: object = None  # (3, 3) one tick's Singer transition; None: from the engagement
    singer_L: object = None  # (3, 3) Cholesky factor of one tick's Singer noise (zeros without it)


def singer_tick(eng: Engagement, dt, singer=True):
    """(Φ, L) of one tick of the Singer perturbation, computed in float64 on the host
    (``singer_block``): the transition and the Cholesky factor of its noise (zeros when off)."""
    phi, Q = singer_block(dt, float(eng.singer_tau), float(eng.singer_sigma))
    return phi, (np.linalg.cholesky(Q) if singer else np.zeros((3, 3)))


def truth(eng: Engagement, t, s):
    """Relative position, velocity, target and own accelerations at t (s: Singer state, axis × [p, v, a])."""
    p_t, v_t, a_t = eng.target(t)
    p_m, v_m, a_m = eng.own(t)
    return p_t + s[:, 0] - p_m, v_t + s[:, 1] - v_m, a_t + s[:, 2], a_m


def engage(eng: Engagement, trackers: list[Tracker], params: list, cfg: LoopConfig, sd0: list, key):
    """One run of every tracker on the same target path and noise: per filter period, each
    estimate's error (9), its NEES, the true pointing error and range (a dict per tracker).

    The trackers share one scan: the Singer perturbation, the target's geometry and the random
    draws are made once a tick for all of them; each tracker has its own antenna, gates and lock."""
    tm = cfg.timing
    dt, n = tm.dt, tm.n
    dtype = jnp.result_type(float)
    phi, L = (cfg.singer_phi, cfg.singer_L) if cfg.singer_phi is not None else singer_tick(eng, dt, cfg.singer)
    phi, L = jnp.asarray(phi, dtype), jnp.asarray(L, dtype)
    k = jnp.asarray(cfg.k, dtype)
    sigma = jnp.asarray(cfg.sigma, dtype)
    beam, gate_r, gate_v = cfg.limits
    lo = -jnp.asarray([beam, beam, gate_r, gate_v], dtype)
    zero = jnp.zeros((), dtype)

    normal = lambda k, shape: jax.random.normal(k, shape, jnp.float32).astype(dtype)
    k0, k1, k2, key = jax.random.split(key, 4)
    a0 = normal(k0, (3,)) * (eng.singer_sigma if cfg.singer else 0.0)
    s = jnp.zeros((3, 3), dtype).at[:, 2].set(a0)
    rel_p, rel_v, a_t, a_m = truth(eng, jnp.zeros((), dtype), s)
    eps0, dx0 = normal(k1, (2,)), normal(k2, (9,))  # the designation's errors in units of each prior's std
    on_los = los_frame(rel_p)
    loops = []
    for tracker, p, sd in zip(trackers, params, sd0):
        sd = jnp.asarray(sd, dtype)
        C = rotate(on_los, jnp.stack([zero, eps0[1] * sd[0], eps0[0] * sd[0]]))
        x_true0, _ = los_state(rel_p, rel_v, a_t, a_m, C)
        x0 = x_true0 + dx0 * sd
        x0 = x0.at[jnp.array([0, 3])].set(0.0).at[jnp.array([2, 5, 8])].set(0.0)  # ε̂ = 0: the antenna points at the designation
        loops.append((tracker.start(p, x0, jnp.diag(sd**2)), C, jnp.zeros(2, dtype), jnp.zeros((), bool)))

    def one_tick(carry, inp):
        loops, s = carry
        i, j, xi = inp
        s = mm(s, phi.T) + mm(xi[:9].reshape(3, 3), L.T)
        rel_p, rel_v, a_t, a_m = truth(eng, j * dt, s)
        out, xs = [], []
        for tracker, p, (ts, C, w, lost) in zip(trackers, params, loops):
            cmd, gates = tracker.tick(p, ts, i)
            w_next, turn = antenna_motion(w, cmd, dt, tm.lag)
            C = rotate(C, jnp.stack([zero, turn[1], turn[0]]))
            if cfg.jolt_tick >= 0:  # static: runs without a jolt trace no rotation for it
                C = jnp.where(j == cfg.jolt_tick, rotate(C, jnp.asarray([0.0, cfg.jolt, 0.0], dtype)), C)
            x, _ = los_state(rel_p, rel_v, a_t, a_m, C)
            clean = jnp.stack([x[0], x[3], x[6] - gates[0], x[7] - gates[1]])
            lost = lost | jnp.any(jnp.abs(clean) > -lo)
            z = k * jnp.clip(clean, lo, -lo) + sigma * xi[9:]
            out.append((tracker.sample(p, ts, i, z), C, w_next, lost))
            xs.append(x)
        return (out, s), xs

    def one_period(carry, p):
        noise = normal(jax.random.fold_in(key, p), (n, 13))
        ticks = jnp.arange(n)
        (loops, s), xs = jax.lax.scan(one_tick, carry, (ticks, p * n + ticks + 1, noise))
        out, errors = [], []
        for tracker, prm, (ts, C, w, lost), x in zip(trackers, params, loops, xs):
            ts = tracker.update(prm, ts, w)
            x_hat, P = tracker.estimate(ts)
            e = x_hat - x[-1]
            out.append((ts, C, w, lost))
            errors.append((e, mahalanobis2(P, e), jnp.hypot(x[-1, 0], x[-1, 3]), x[-1, 6]))
        return (out, s), errors

    (loops, _), errors = jax.lax.scan(one_period, (loops, s), jnp.arange(cfg.periods))
    return [{"err": e, "nees": nees, "point": point, "range": r, "lost": lost}
            for (_, _, _, lost), (e, nees, point, r) in zip(loops, errors)]


def _squares(runs_out):
    """Per run and period, the squares of the reported errors (B, periods, 5): the true pointing
    error and the pointing-error estimate's error (mrad²), the LOS-rate estimate's error
    ((mrad/s)², both axes), the range's (m²) and the range rate's ((m/s)²)."""
    e2 = runs_out["err"] ** 2
    return jnp.stack([runs_out["point"] ** 2 / MRAD**2, (e2[..., 0] + e2[..., 3]) / MRAD**2,
                      (e2[..., 1] + e2[..., 4]) / MRAD**2, e2[..., 6], e2[..., 7]], -1)


def sums(runs_out, live):
    """Per-period sums over the runs in lock (``live`` masks padding): the streaming statistics'
    inputs; ``sum4`` the sums of the squares in ``_squares`` squared (the per-period RMS bands)."""
    keep = live & ~runs_out["lost"]
    w = keep[:, None].astype(runs_out["err"].dtype)
    e = jnp.where(keep[:, None, None], runs_out["err"], 0.0)
    nees = runs_out["nees"]
    finite = keep[:, None] & jnp.isfinite(nees)
    sq = _squares(runs_out)
    sq4 = sq[..., jnp.array([0, 2, 3, 4])] ** 2
    return {
        "n": jnp.sum(w, axis=0),
        "sum_e": jnp.sum(e, axis=0),
        "sum_e2": jnp.sum(e**2, axis=0),
        "sum_point2": jnp.sum(jnp.where(keep[:, None], runs_out["point"] ** 2, 0.0), axis=0),
        "sum4": jnp.sum(jnp.where(keep[:, None, None], sq4, 0.0), axis=0),
        "sum_nees": jnp.sum(jnp.where(finite, nees, 0.0), axis=0),
        "n_nees": jnp.sum(finite, axis=0).astype(w.dtype),
        "lost": jnp.sum(live & runs_out["lost"]),
    }


def run_samples(runs_out, live, weights):
    """Each run's time averages over the report windows, the samples of the intervals:
    ``weights`` (W, periods) each window's averaging weights. Returns ``values`` (W·6, B): per
    window the mean squares of ``_squares`` and the mean NEES (``SAMPLE_QUANTITIES``); ``ok`` (B,)
    the runs in lock; ``kept`` (W, B) each run's RMS true pointing error per window (mrad)."""
    q = jnp.concatenate([_squares(runs_out), runs_out["nees"][..., None]], -1)  # (B, periods, 6)
    values = jnp.einsum("wp,bpq->wqb", weights.astype(q.dtype), q)
    return values.reshape(-1, values.shape[-1]), live & ~runs_out["lost"], jnp.sqrt(values[:, 0])
