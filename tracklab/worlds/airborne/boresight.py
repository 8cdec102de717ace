"""The boresight-frame model of the four-coordinate tracker (paper 001, eqs. 2–4).

The paper's state equation (2) is lost in the scan; docs/mathematics.md §1 rebuilds
it from line-of-sight kinematics. Antenna axes: x_A the boresight, y_A the "d"
axis, z_A the "e" axis; the antenna is gyro-stabilised with no roll about its
boresight (ω_Ax = 0), so the transport terms ω_Ax·ω of §1 vanish.

State (9): [ε_e, ω_e, a_e, ε_d, ω_d, a_d, r, ṙ, a_r]

* ε_e, ε_d — pointing errors, the rotation from boresight to the line of sight
  (LOS) about z_A and y_A: ε_e = atan2(u·y_A, u·x_A), ε_d = −atan2(u·z_A, u·x_A);
* ω_e, ω_d — the LOS rate ω = u × Ṙ / r resolved on z_A and y_A;
* a_e, a_d — the target's acceleration across the LOS, as (u × a_T)·z_A and
  (u × a_T)·y_A: the terms that drive ω (Singer processes in the model);
* r, ṙ, a_r — range, range rate and the target's acceleration along the LOS.

Drift, with the antenna rate (ω_Ae, ω_Ad) and the own-ship acceleration a_M
(same components) as known inputs:

    ε̇ = ω − ω_A                     ω̇ = −2(ṙ/r) ω + (a − a_M)/r
    ȧ = −a/τ + w                    r̈ = r(ω_e² + ω_d²) + a_r − a_Mr,  ȧ_r = −a_r/τ_r + w_r

These hold exactly (inertial ω̇ = −2(ṙ/r)ω + u×a/r, r̈ = r|ω|² + u·a) when the
boresight is on the LOS, and to first order in ε otherwise.

Observations (eq. 4): the four error signals ε_em = k_e ε_e, ε_dm = k_d ε_d,
the range discriminator k_r (r − r_gate) and the velocity discriminator
k_ṙ (ṙ − ṙ_gate), each with additive white noise; the gates are set from the
tracker's predictions, so they are known (the y of eq. 4).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tracklab.linalg import mm, norm, sum_elements

STATE = ("eps_e", "omega_e", "a_e", "eps_d", "omega_d", "a_d", "r", "rdot", "a_r")
EPS = (0, 3)  # ε_e, ε_d
OMEGA = (1, 4)
ACC = (2, 5)
R, RDOT, AR = 6, 7, 8
OBSERVED = (0, 3, 6, 7)  # rows of H (eq. 4)


class ModelParams(NamedTuple):
    """The filter's target model (a pytree: tunable)."""

    sigma_m: jax.Array  # m/s², Singer σ of the across-LOS accelerations a_e, a_d
    tau: jax.Array  # s
    sigma_r: jax.Array  # m/s², Singer σ of a_r
    tau_r: jax.Array  # s


def drift(x, w_a, a_m, mp: ModelParams, levels=None):
    """ẋ = f(x, u) (eq. 3 without noise); w_a = (ω_Ae, ω_Ad), a_m = (a_Me, a_Md, a_Mr).

    ``levels`` u = (u_e, u_d, u_r) are Moose's manoeuvre commands: mean
    accelerations added to the Singer ones where they drive ω and r̈.

    Component by component, so that x may carry trailing axes (x: (9, ...), the inputs broadcasting
    against them): ``cd_ekf`` pushes a state's tangent columns through it that way.
    """
    u = jnp.zeros(3, x.dtype) if levels is None else levels
    r, rdot = x[R], x[RDOT]
    omega_e, omega_d = x[OMEGA[0]], x[OMEGA[1]]
    damping = -2.0 * rdot / r
    return jnp.stack([omega_e - w_a[0], damping * omega_e + (x[ACC[0]] + u[0] - a_m[0]) / r, -x[ACC[0]] / mp.tau,
                      omega_d - w_a[1], damping * omega_d + (x[ACC[1]] + u[1] - a_m[1]) / r, -x[ACC[1]] / mp.tau,
                      rdot, r * (omega_e**2 + omega_d**2) + x[AR] + u[2] - a_m[2], -x[AR] / mp.tau_r])


def process_noise(mp: ModelParams):
    """G Q Gᵀ of eq. 3: white noise 2σ²/τ on ȧ_e, ȧ_d, ȧ_r."""
    q = 2.0 * mp.sigma_m**2 / mp.tau
    qr = 2.0 * mp.sigma_r**2 / mp.tau_r
    d = jnp.zeros(9).at[jnp.array(ACC)].set(q).at[AR].set(qr)
    return jnp.diag(d)


def observation_matrix(k):
    """H of eq. 4 (4 × 9): gains k = (k_e, k_d, k_r, k_ṙ) on ε_e, ε_d, r, ṙ."""
    return jnp.zeros((4, 9)).at[jnp.arange(4), jnp.array(OBSERVED)].set(k)


def _dot(a, b):
    """a · b of two 3-vectors, as elementwise arithmetic (under ``vmap``, a batched dot is slow on CPU)."""
    return sum_elements(a * b)


def los_state(rel_p, rel_v, a_t, a_m, C):
    """The true 9-state from the relative geometry and the antenna axes C = [x_A y_A z_A] (columns).

    Also returns a_M's components (a_Me, a_Md, a_Mr), the model's known input.
    """
    r = norm(rel_p)
    u = rel_p / r
    rdot = _dot(u, rel_v)
    omega = jnp.cross(u, rel_v) / r
    x_a, y_a, z_a = C[:, 0], C[:, 1], C[:, 2]
    ux, uy, uz = _dot(u, x_a), _dot(u, y_a), _dot(u, z_a)
    eps_e, eps_d = jnp.arctan2(uy, ux), -jnp.arctan2(uz, ux)
    ua_t, ua_m = jnp.cross(u, a_t), jnp.cross(u, a_m)
    x = jnp.stack([eps_e, _dot(omega, z_a), _dot(ua_t, z_a), eps_d, _dot(omega, y_a), _dot(ua_t, y_a),
                   r, rdot, _dot(u, a_t)])
    return x, jnp.stack([_dot(ua_m, z_a), _dot(ua_m, y_a), _dot(u, a_m)])


def los_frame(rel_p, up=(0.0, 0.0, 1.0)):
    """Antenna axes with the boresight on the LOS and y_A horizontal (zero pointing error)."""
    u = rel_p / norm(rel_p)
    y = jnp.cross(jnp.asarray(up, u.dtype), u)
    y = y / norm(y)
    return jnp.stack([u, y, jnp.cross(u, y)], -1)


def rotate(C, phi):
    """C · exp([φ]×): the antenna axes after a rotation φ (antenna components), by Rodrigues' formula."""
    theta2 = jnp.sum(phi**2)
    theta = jnp.sqrt(theta2 + 1e-300)
    small = theta2 < 1e-12
    s = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    c = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.maximum(theta2, 1e-300))
    K = jnp.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]], dtype=C.dtype)
    return mm(C, jnp.eye(3, dtype=C.dtype) + s * K + c * mm(K, K))


def antenna_motion(w0, w_cmd, dt, lag):
    """The gyro-stabilised antenna over dt: its rate follows the held command through a first-order lag.

    Returns (rate at the end, angle turned): w(s) = c + (w0 − c)e^{−s/τ}, ∫w ds exactly.
    """
    e = jnp.exp(-dt / lag)
    return w_cmd + (w0 - w_cmd) * e, w_cmd * dt + (w0 - w_cmd) * lag * (1.0 - e)


def antenna_rate_at(w0, w_cmd, s, lag):
    """The antenna's rate s seconds into a tick (the model's known input between samples)."""
    return w_cmd + (w0 - w_cmd) * jnp.exp(-s / lag)
