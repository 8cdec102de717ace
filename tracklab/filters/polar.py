"""Polar-state Kalman filter (paper 000 §3.2, eqs. 13–17).

State [r, ṙ, β, β̇]: two decoupled constant-velocity filters, one for range and
one for angle. The Cartesian acceleration noise is mapped into each channel
through the noise gains of eqs. (15)–(16), evaluated at the current estimate
(r̂_k, β̂_k); the cross-channel term is dropped, as in the paper. The filter
reports in the Cartesian CV frame [x, ẋ, y, ẏ] (covariance mapped through the
Jacobian of the polar→Cartesian map).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, kalman_filter, predict, update
from tracklab.filters.core import Prior
from tracklab.filters.kind import NOISE, Entry, FilterKind, noise
from tracklab.linalg import jacobian, mm, symmetrise


def polar_to_cartesian(s):
    r, rd, b, bd = s[0], s[1], s[2], s[3]
    c, sn = jnp.cos(b), jnp.sin(b)
    return jnp.stack([r * c, rd * c - r * bd * sn, r * sn, rd * sn + r * bd * c])


def cartesian_to_polar(x):
    px, vx, py, vy = x[0], x[1], x[2], x[3]
    r = jnp.hypot(px, py)
    return jnp.stack([r, (px * vx + py * vy) / r, jnp.arctan2(py, px), (px * vy - py * vx) / r**2])


def model_polar_kf(dt, sensor, params):
    T = dt
    # F and H in NumPy: known when built inside a trace (``mm`` skips their zeros)
    F = np.array([[1.0, T, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, T], [0, 0, 0, 1.0]])
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])

    def init(p, prior: Prior):
        J = jacobian(cartesian_to_polar, prior.x)
        P = symmetrise(J @ prior.P @ J.T)
        P = P.at[:2, 2:].set(0.0).at[2:, :2].set(0.0)  # decoupled channels
        return Gaussian(cartesian_to_polar(prior.x), P)

    def time_update(p, g):
        r, b = g.x[0], g.x[2]
        c, s = jnp.cos(b), jnp.sin(b)
        q = jnp.broadcast_to(p["q"], (2,))
        Gr = jnp.array([[T**2 / 2 * c, T**2 / 2 * s], [T * c, T * s]])  # eq. (15)
        Gb = jnp.array([[-(T**2) * s / (2 * r), T**2 * c / (2 * r)], [-T * s / r, T * c / r]])  # eq. (16)
        Q = jnp.zeros((4, 4))
        Q = Q.at[:2, :2].set(mm(Gr * q, Gr.T)).at[2:, 2:].set(mm(Gb * q, Gb.T))
        return predict(g, F, Q)

    def measurement_update(p, g, z, present):  # z = [r, β]: the bearing innovation wrapped
        return update(g, z, H, jnp.diag(p["r"]), angles=(False, True), present=present)

    def report(g):
        J = jacobian(polar_to_cartesian, g.x)
        return polar_to_cartesian(g.x), symmetrise(mm(mm(J, g.P), J.T))

    return kalman_filter(params, time_update, measurement_update, report=report, init=init)


def _read(e: Entry):
    model = e.motion_model()
    if model != "cv":
        raise e.error("model", model, 'polar_kf has its own polar CV state: use model = "cv"')
    return model, noise(e, model), {}


POLAR_KF = FilterKind(
    name="polar_kf", doc="polar-state KF [r, ṙ, β, β̇], two decoupled channels (2-D)", accepts=("polar",),
    params=NOISE, read=_read, build=lambda model, sensor, params, options: model_polar_kf(model.F[0, 1], sensor, params))
