"""The air-to-air engagement of paper 001's simulation (our values: the paper gives none).

Inertial frame: x along the own aircraft's heading, y to its left, z up. The
own aircraft flies straight and level at ``own_speed`` from the origin (its
acceleration, zero here, is the INS input a_M of the model). The target starts
``target_range`` ahead, ``target_offset`` to the left and ``target_height``
above, flying level at ``target_speed`` on ``target_heading`` (degrees from x,
counter-clockwise). Between ``turn_start`` and ``turn_end`` it turns at
``turn_g`` g (to its left for ``turn_direction`` = +1).

The nominal target path is analytic (a line, a circular arc, a line), so its
velocity and acceleration are exact at any time. In Monte-Carlo runs a Singer
acceleration (σ_m, τ) on each axis is added; the perturbation's position,
velocity and acceleration are sampled exactly at the radar's sample period
(``singer_block``, docs/mathematics.md §1).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.linalg import host_expm

G0 = 9.80665  # m/s², one g


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Engagement:
    own_speed: float = 250.0
    target_range: float = 20_000.0
    target_offset: float = 3_000.0
    target_height: float = -500.0
    target_speed: float = 300.0
    target_heading: float = 180.0
    turn_g: float = 4.0
    turn_start: float = 20.0
    turn_end: float = 30.0
    turn_direction: float = 1.0
    singer_sigma: float = 30.0  # m/s², per axis, Monte-Carlo runs only
    singer_tau: float = 10.0  # s

    def own(self, t):
        """Own-aircraft position, velocity and acceleration at time(s) t, each (..., 3)."""
        t = jnp.asarray(t, float)
        z = jnp.zeros_like(t)
        p = jnp.stack([self.own_speed * t, z, z], -1)
        v = jnp.stack([z + self.own_speed, z, z], -1)
        return p, v, jnp.zeros_like(p)

    def target(self, t):
        """Nominal target position, velocity and acceleration at time(s) t, each (..., 3)."""
        t = jnp.asarray(t, float)
        V, psi0 = self.target_speed, jnp.radians(self.target_heading)
        ts, te = self.turn_start, self.turn_end
        omega = self.turn_direction * self.turn_g * G0 / V  # turn rate, rad/s
        before = jnp.minimum(t, ts)
        turning = jnp.clip(t - ts, 0.0, te - ts)
        after = jnp.maximum(t - te, 0.0)
        psi = psi0 + omega * turning
        c0, s0, c, s = jnp.cos(psi0), jnp.sin(psi0), jnp.cos(psi), jnp.sin(psi)
        straight = omega == 0.0  # no turn: the arc is a line
        w = jnp.where(straight, 1.0, omega)
        arc_x = jnp.where(straight, V * turning * c0, V / w * (s - s0))  # ∫ V (cos ψ, sin ψ) dt over the arc
        arc_y = jnp.where(straight, V * turning * s0, V / w * (c0 - c))
        x = self.target_range + V * before * c0 + arc_x + V * after * c
        y = self.target_offset + V * before * s0 + arc_y + V * after * s
        z = jnp.zeros_like(t) + self.target_height
        in_turn = (t > ts) & (t < te)
        a = jnp.where(in_turn, V * omega, 0.0)
        zero = jnp.zeros_like(t)
        return (jnp.stack([x, y, z], -1), jnp.stack([V * c, V * s, zero], -1),
                jnp.stack([-a * s, a * c, zero], -1))


def nominal_range(eng: Engagement, t) -> np.ndarray:
    """The nominal target's range from the own aircraft at the host times ``t`` (float64, one
    compiled program rather than an eager operation per step of ``target``)."""
    with jax.enable_x64(True):
        return np.asarray(_nominal_range(eng, jnp.asarray(t, jnp.float64)))


@jax.jit
def _nominal_range(eng, t):
    return jnp.linalg.norm(eng.target(t)[0] - eng.own(t)[0], axis=-1)


def singer_block(T, tau, sigma):
    """Exact discretisation (Φ, Q) of one Singer axis [p, v, a] over T, by Van Loan's method.

    The closed forms of docs/mathematics.md §1 agree (tested) but lose every digit to
    cancellation at the radar's sample period (T/τ = 10⁻³: Q₁₁ ~ T⁵).
    """
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0 / tau]])
    Qc = np.zeros((3, 3))
    Qc[2, 2] = 2.0 * sigma**2 / tau
    M = np.block([[-A, Qc], [np.zeros((3, 3)), A.T]]) * T
    E = host_expm(M)  # float64 on the host: constants, also when called under jit
    phi = E[3:, 3:].T
    Q = phi @ E[:3, 3:]
    return phi, 0.5 * (Q + Q.T)
