"""The azimuth axis of paper 003's theodolite: double loop, velocity-lag compensation, on-axis tracking.

Blocks (paper 003 §3; docs/mathematics.md §7), in the same angular unit throughout:

* plant G_s(s) = 0.763 / ((0.663s + 1)(0.008s + 1)) from the drive command to the
  axis rate ω, θ = ∫ω, and the velocity corrector
  G_vc(s) = 3200(0.16s + 1)(0.008s + 1) / ((8.8s + 1)(0.0025s + 1)) closing the rate
  loop around it: one continuous subsystem (velocity reference → ω, θ);
* position corrector G_pc(s) = 4050(0.45s + 1)² / (6.75s + 1)² and velocity-lag
  compensator G_c(s) = 0.9 / (0.325s + 1).

Each is discretised at the 1 kHz tick by Tustin (default; ``method = "zoh"``
holds the velocity reference over the tick instead). Tustin blocks pass part of
their input straight through, so the position loop closed at the tick is an
algebraic loop: it is solved exactly each tick (a scalar equation), which makes
the discrete closed loop the Tustin image of the continuous one — within 0.02 %
(frequency warping) of it below 50 rad/s.

Per 1 kHz tick: ω_cmd = G_pc(e_pos); the velocity subsystem follows ω_cmd + ω_ff.
The camera exposes once per frame (100 Hz, the frame's first tick); its miss
distance Δθ = θ_target − θ + noise reaches the servo ``delay`` frames later
(two in the paper) and is held for the frame. Modes:

* ``double_loop`` — e_pos = the delivered miss distance; no feed-forward;
* ``velocity_lag`` — the same e_pos, plus ω_ff = G_c(ω̂) (the estimator's target rate
  through the compensator) into the velocity loop;
* ``on_axis`` — e_pos = θ̂ − θ (the estimator's target angle, extrapolated to the
  tick, minus the encoder), and ω_ff = ω̂ + k_a·α̂ (the predicted rate, and the
  acceleration times ``accel_ff``; 0 in the paper) into the velocity loop.

The estimator sees the measured target angle θ_m = Δθ + θ_encoder at exposure
(paper 003 eq. 16), ``delay`` frames late; it estimates at the exposure frame and
predicts ``delay`` frames ahead (eq. 17). ``closed_position_loop`` is the same
loop driven by a reference angle directly (no camera), for checking the
discretisation against the continuous transfer functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Meas
from tracklab.worlds.servo.estimators import Estimator
from tracklab.worlds.servo.transfer import (
    TransferFunction,
    discretise,
    discretise_state_space,
)

G_S = TransferFunction.lead_lag(0.763, (), (0.663, 0.008))
G_VC = TransferFunction.lead_lag(3200.0, (0.16, 0.008), (8.8, 0.0025))
G_PC = TransferFunction.lead_lag(4050.0, (0.45, 0.45), (6.75, 6.75))
G_COMP = TransferFunction.lead_lag(0.9, (), (0.325,))
MODES = ("double_loop", "velocity_lag", "on_axis")


@dataclass(frozen=True)
class AzimuthAxis:
    dt: float = 1e-3  # encoder / servo tick (1 kHz)
    plant: TransferFunction = G_S
    velocity_corrector: TransferFunction = G_VC
    position_corrector: TransferFunction = G_PC
    compensator: TransferFunction = G_COMP
    method: str = "bilinear"  # discretisation of the velocity subsystem: bilinear | zoh

    def velocity_subsystem(self):
        """Continuous (A, B, C, D): velocity reference → [ω, θ], the rate loop closed (G_s strictly proper)."""
        Av, Bv, Cv, Dv = self.velocity_corrector.state_space()
        As, Bs, Cs, Ds = self.plant.state_space()
        if abs(Ds[0, 0]) > 0:
            raise ValueError("the plant must be strictly proper")
        nv, ns = Av.shape[0], As.shape[0]
        n = nv + ns + 1
        A = np.zeros((n, n))
        B = np.zeros((n, 1))
        A[:nv, :nv], A[:nv, nv:nv + ns], B[:nv] = Av, -Bv @ Cs, Bv  # corrector driven by v − ω
        A[nv:nv + ns, :nv] = Bs @ Cv
        A[nv:nv + ns, nv:nv + ns] = As - Bs @ Dv @ Cs
        B[nv:nv + ns] = Bs @ Dv
        A[n - 1, nv:nv + ns] = Cs[0]  # θ' = ω
        C = np.zeros((2, n))
        C[0, nv:nv + ns], C[1, n - 1] = Cs[0], 1.0
        return A, B, C, np.zeros((2, 1))

    def blocks(self):
        """(velocity subsystem [ω, θ], G_pc, G_c) discretised at the tick."""
        vel = discretise_state_space(*self.velocity_subsystem(), self.dt, self.method)
        return (vel, discretise(self.position_corrector, self.dt, "bilinear"),
                discretise(self.compensator, self.dt, "bilinear"))

    def open_position_loop(self) -> TransferFunction:
        """L(s) = G_pc Φ_v / s with Φ_v = G_vc G_s / (1 + G_vc G_s), continuous."""
        phi_v = (self.velocity_corrector * self.plant).feedback()
        return self.position_corrector * phi_v * TransferFunction.integrator()

    def delay_margin(self):
        """(seconds, phase margin in degrees, gain crossover in rad/s) of the position loop: the
        largest pure delay inside it that keeps it stable, phase margin / crossover."""
        L = self.open_position_loop()
        w = np.logspace(-3, 5, 80001)
        mag = np.abs(L(1j * w))
        k = int(np.nonzero(mag >= 1.0)[0][-1])  # the last crossing of unit gain
        lo, hi = w[k], w[min(k + 1, len(w) - 1)]
        for _ in range(60):
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if abs(L(1j * mid)) >= 1.0 else (lo, mid)
        wc = lo
        phase = np.unwrap(np.angle(L(1j * np.append(w[w < wc], wc))))[-1]
        pm = np.pi + phase
        return float(pm / wc), float(np.degrees(pm)), float(wc)


def _tick(blocks, x, w_ff, *, e_pos=None, reference=None):
    """One tick. Either the position-loop input ``e_pos`` is given (a held miss distance) or the
    loop is closed at the tick on ``reference`` − θ (solved with the blocks' feed-through).
    Returns the new states and (θ, ω) at the tick."""
    vel, pc, _ = blocks
    xv, xpc = x
    y0 = jnp.asarray(vel.C) @ xv  # [ω, θ] without this tick's input
    d = vel.D[:, 0]
    if e_pos is None:  # v = C_pc x_pc + D_pc (r − y0_θ − d_θ v) + ω_ff
        v = ((jnp.asarray(pc.C) @ xpc)[0] + pc.D[0, 0] * (reference - y0[1]) + w_ff) / (1.0 + pc.D[0, 0] * d[1])
        theta = y0[1] + d[1] * v
        e_pos = reference - theta
    else:
        v = pc.output(xpc, e_pos) + w_ff
    w, theta = y0[0] + d[0] * v, y0[1] + d[1] * v
    return (vel.advance(xv, v), pc.advance(xpc, e_pos)), (theta, w)


def _zeros(blocks, dtype=None):
    vel, pc, _ = blocks
    return (jnp.zeros((vel.order,), dtype), jnp.zeros((pc.order,), dtype))


def closed_position_loop(axis: AzimuthAxis, reference):
    """Encoder angle θ per tick of the position loop closed on ``reference`` − θ (no camera, no feed-forward)."""
    blocks = axis.blocks()

    def body(x, r):
        x, (theta, _) = _tick(blocks, x, 0.0, reference=r)
        return x, theta

    _, theta = jax.lax.scan(body, _zeros(blocks), jnp.asarray(reference, float))
    return theta


def track(axis: AzimuthAxis, mode: str, target: Callable, frames: int, key, *, estimator: Estimator | None = None,
          prior=None, frame_ticks: int = 10, delay: int = 2, noise: float = 0.0, accel_ff: float = 0.0,
          perfect: bool = False, estimator_params=None):
    """Simulate ``frames`` camera frames of the axis following ``target(t) -> (θ, θ̇, θ̈)``.

    The camera exposes at each frame's first tick (target and boresight at the
    same instant); the exposure is delivered ``delay`` ≥ 1 frames later.
    ``perfect``: the estimator is replaced by the true target angle, rate and
    acceleration at each tick (the ideal feed-forward). Returns per tick
    {t, target, encoder, error (target − encoder)} and per frame the estimator's
    ``rate_error`` (its predicted rate at the frame's first tick, minus the true one).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}")
    if delay < 1:
        raise ValueError("the camera's miss distance arrives at least one frame late (delay >= 1)")
    blocks = axis.blocks()
    comp = blocks[2]
    T = axis.dt
    noise_all = noise * jax.random.normal(key, (frames,))
    flt = None if estimator is None else estimator.filter
    params = None if estimator is None else (
        estimator_params if estimator_params is not None
        else estimator.params if estimator.params is not None else flt.params)
    if flt is None and mode != "double_loop" and not perfect:
        raise ValueError(f"mode {mode} needs an estimator (or perfect = True)")
    est0 = flt.init(params, prior) if flt is not None else jnp.zeros(())
    queue0 = jnp.zeros((delay, 2))  # (Δθ, encoder) of the exposures not yet delivered, oldest first

    def frame_step(carry, j):
        x, xc, est, queue, held, pred = carry
        t0 = j * frame_ticks * T
        # delivery of the exposure `delay` frames ago: miss distance and the encoder then (eq. 16)
        d_miss, d_enc = queue[0]
        delivered = j >= delay
        held = jnp.where(delivered, d_miss, held)
        if flt is not None:
            z = jnp.where(delivered, d_miss + d_enc, jnp.nan)[None]
            est, out = flt.step(params, est, Meas(z, t0, jnp.asarray(True)))
            pred = estimator.ahead(params, est, out, delay)  # (θ̂, ω̂, α̂) at this frame's first tick (eq. 17)
        rate_err = (pred[1] - target(t0)[1]) if flt is not None else jnp.zeros(())

        def tick(c, i):
            x, xc = c
            t = t0 + i * T
            tg = target(t)
            dt_ = i * T
            if perfect:
                est_th, est_w, est_a = tg[0], tg[1], tg[2]
            else:
                est_th = pred[0] + pred[1] * dt_ + 0.5 * pred[2] * dt_**2
                est_w, est_a = pred[1] + pred[2] * dt_, pred[2]
            if mode == "on_axis":
                x, (th, _) = _tick(blocks, x, est_w + accel_ff * est_a, reference=est_th)
            else:
                w_ff = 0.0
                if mode == "velocity_lag":
                    w_ff = comp.output(xc, est_w)
                    xc = comp.advance(xc, est_w)
                x, (th, _) = _tick(blocks, x, w_ff, e_pos=held)
            return (x, xc), (t, tg[0], th, tg[0] - th)

        (x, xc), ticks = jax.lax.scan(tick, (x, xc), jnp.arange(frame_ticks))
        exposure = jnp.stack([ticks[3][0] + noise_all[j], ticks[2][0]])  # at the first tick: Δθ + noise, encoder
        queue = jnp.concatenate([queue[1:], exposure[None]])
        return (x, xc, est, queue, held, pred), (ticks, rate_err)

    carry0 = (_zeros(blocks), jnp.zeros((comp.order,)), est0, queue0, jnp.zeros(()), jnp.zeros(3))
    _, (ticks, rate_err) = jax.lax.scan(frame_step, carry0, jnp.arange(frames))
    t, tg, enc, err = (a.reshape(-1) for a in ticks)
    return {"t": t, "target": tg, "encoder": enc, "error": err, "rate_error": rate_err}


def sine_target(amplitude, omega):
    """θ = A sin(ωt) (paper 003: 83.33° sin 0.6t), with its rate and acceleration."""

    def target(t):
        return jnp.stack([amplitude * jnp.sin(omega * t), amplitude * omega * jnp.cos(omega * t),
                          -amplitude * omega**2 * jnp.sin(omega * t)])

    return target
