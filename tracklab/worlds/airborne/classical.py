"""The classical tracker paper 001 compares against: a fixed angle loop and an α-β-γ range loop.

Angle loop (eq. 17): the open-loop transfer function from pointing error to
antenna angle is

    G(s) = 125 (s/2.09 + 1) / (s (s/0.104 + 1)(s/20 + 1)).

The antenna is a rate servo (first-order lag τ_a) behind an integrator, so
the compensator from the error signal to the rate command is
D(s) = G(s)·s·(τ_a s + 1) = 125 (s/2.09 + 1)(τ_a s + 1) / ((s/0.104 + 1)(s/20 + 1)),
proper, and the loop with our antenna has eq. 17 as its open loop exactly.
D is discretised by Tustin at the radar's sample period and acts on every
(10 ms) error-signal sample, each channel on its own. Holding its output y_k
over the next sample would delay it by half a sample (a 1.4 % closed-loop
error at 4 rad/s against the continuous loop); the held command is the
half-sample prediction 1.5 y_k − 0.5 y_{k−1}, which brings the sampled loop
within 0.2 % of G/(1 + G) up to the crossover (6.26 rad/s; tested).

Range and velocity loops, independent as in the radars the paper starts from
(§1: two angle loops, a range loop and a velocity loop): an α-β-γ tracker
[r, ṙ, r̈] on the pre-averaged range discriminator sets the range gate, and an
α-β tracker [ṙ, r̈] on the pre-averaged velocity discriminator sets the
velocity gate, both every filter period. Their gains are fixed, the steady
states of the matching models (Kalata's index, docs/mathematics.md §2): σ_v is the
Singer acceleration's increment per period for the range loop (Wiener-process
acceleration) and that increment divided by the period for the velocity loop
(piecewise-constant acceleration rate), ``loop_gains``. The range estimate is
the range loop's, the range-rate estimate the velocity loop's.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.alphabeta import kalata_alpha_beta, kalata_alpha_beta_gamma
from tracklab.linalg import mm
from tracklab.worlds.airborne.tracker import (
    Setting,
    Timing,
    Tracker,
    TrackerKind,
    prior_sd,
)
from tracklab.worlds.servo.transfer import TransferFunction, discretise


def open_loop() -> TransferFunction:
    """Eq. 17."""
    return TransferFunction.lead_lag(125.0, (1 / 2.09,), (1 / 0.104, 1 / 20.0)) * TransferFunction.integrator()


def compensator(lag) -> TransferFunction:
    """D(s): error signal → antenna rate command, so that D(s)/(s(τ_a s + 1)) = G(s)."""
    return TransferFunction.lead_lag(125.0, (1 / 2.09, lag), (1 / 0.104, 1 / 20.0))


def crossover(tf: TransferFunction, lo=1e-3, hi=1e4):
    """The gain-crossover frequency |G(jω)| = 1 (rad/s), by bisection on a log scale."""
    for _ in range(200):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if abs(tf(1j * mid)) > 1 else (lo, mid)
    return float(np.sqrt(lo * hi))


class ClassicalParams(NamedTuple):
    k: jax.Array  # (4,) detector gains
    range_gains: jax.Array  # (3,) α, β, γ of the range loop
    velocity_gains: jax.Array  # (2,) α, β of the velocity loop


class ClassicalState(NamedTuple):
    comp: jax.Array  # (2, order) compensator states, e and d channels
    cmd: jax.Array  # (2,) rate command held over the next sample
    y: jax.Array  # (2,) the compensator's last output
    eps: jax.Array  # (2,) the last error-signal sample (the loop's pointing-error "estimate")
    rng: jax.Array  # (3,) r, ṙ, r̈ of the range loop at the period's start
    vel: jax.Array  # (2,) ṙ, r̈ of the velocity loop
    zsum: jax.Array


def loop_gains(sigma_m, tau, sigma_range, sigma_velocity, timing: Timing):
    """Kalata gains of the range (α, β, γ) and velocity (α, β) loops on the pre-averaged discriminators."""
    T = timing.dt * timing.n
    increment = sigma_m * np.sqrt(1.0 - np.exp(-2.0 * T / tau))  # Singer acceleration's change per period
    lam_r = increment * T**2 / (sigma_range / np.sqrt(timing.n))
    lam_v = increment / T * T**2 / (sigma_velocity / np.sqrt(timing.n))
    with jax.enable_x64(True):  # numbers of the experiment: float64 whatever JAX's global mode
        return (np.asarray(jnp.stack(kalata_alpha_beta_gamma(jnp.asarray(lam_r, jnp.float64)))),
                np.asarray(jnp.stack(kalata_alpha_beta(jnp.asarray(lam_v, jnp.float64)))))


def classical(timing: Timing) -> Tracker:
    n, T = timing.n, timing.dt * timing.n
    D = discretise(compensator(timing.lag), timing.dt, "bilinear")
    A, B, C, Dd = (jnp.asarray(a) for a in (D.A, D.B, D.C, D.D))

    def start(params, x0, P0):
        z2 = jnp.zeros(2, x0.dtype)
        return ClassicalState(jnp.zeros((2, D.order), x0.dtype), z2, z2, z2, x0[6:9], x0[7:9], jnp.zeros(4, x0.dtype))

    def tick(params, s, i):
        dt = (i + 1) * timing.dt
        r, rd, rdd = s.rng
        return s.cmd, jnp.stack([r + rd * dt + 0.5 * rdd * dt**2, s.vel[0] + s.vel[1] * dt])

    def sample(params, s, i, z):
        u = z[:2] / params.k[:2]
        y = mm(s.comp, C[0]) + Dd[0, 0] * u
        comp = mm(s.comp, A.T) + u[:, None] * B[:, 0]
        return s._replace(comp=comp, cmd=1.5 * y - 0.5 * s.y, y=y, eps=u, zsum=s.zsum + z)

    def update(params, s, w_a):
        # the gates sat on the predictions: each averaged discriminator is the prediction error
        nu_r, nu_v = s.zsum[2] / n / params.k[2], s.zsum[3] / n / params.k[3]
        r, rd, rdd = s.rng
        a, b, g = params.range_gains
        rng = jnp.stack([r + rd * T + 0.5 * rdd * T**2, rd + rdd * T, rdd]) + jnp.stack([a, b / T, g / (2 * T**2)]) * nu_r
        av, bv = params.velocity_gains
        vel = jnp.stack([s.vel[0] + s.vel[1] * T, s.vel[1]]) + jnp.stack([av, bv / T]) * nu_v
        return s._replace(rng=rng, vel=vel, zsum=jnp.zeros_like(s.zsum))

    def estimate(s):
        z = jnp.zeros((), s.rng.dtype)
        x = jnp.stack([s.eps[0], s.y[0], z, s.eps[1], s.y[1], z, s.rng[0], s.vel[0], s.vel[1]])
        return x, jnp.full((9, 9), jnp.nan, s.rng.dtype)

    return Tracker(start, tick, sample, update, estimate)


def _numbers(setting: Setting, n):
    """Its loops' gains from the engagement's Singer model and the noise (its table has no numbers)."""
    eng, noise = setting.engagement, setting.noise
    g_r, g_v = loop_gains(eng.singer_sigma, eng.singer_tau, noise[2], noise[3], setting.timing)
    return (ClassicalParams(np.asarray(setting.gains, float), np.asarray(g_r, float), np.asarray(g_v, float)),
            prior_sd(setting, eng.singer_sigma, eng.singer_sigma))


CLASSICAL = TrackerKind("classical", "eq. 17 angle loop, alpha-beta-gamma range loop, alpha-beta velocity loop", {},
                        lambda timing, choices: classical(timing), _numbers)
