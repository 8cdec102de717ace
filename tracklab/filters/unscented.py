"""Unscented Kalman filter (Julier & Uhlmann; Wan & van der Merwe's scaled sigma points).

2n + 1 sigma points x̂ ± √((n + λ)P) columns, λ = α²(n + κ) − n, weights
W_m0 = λ/(n + λ), W_c0 = W_m0 + 1 − α² + β, W_i = 1/(2(n + λ)). The prediction
propagates the sigma points through the motion model; the update draws new ones
from the prediction, maps them through h, and forms the innovation covariance
S = Σ W_c (Z − ẑ)(Z − ẑ)ᵀ + R and the cross-covariance C = Σ W_c (X − x̂)(Z − ẑ)ᵀ.
Angle components are averaged and differenced on the circle. Absent measurement
components are left out of the update, as in the other filters.

Defaults α = 1, β = 2, κ = 0 (λ = 0: the symmetric set, W_m0 = 0). A small α
(say 10⁻³) keeps the points close to the mean but multiplies rounding errors by
weights of order 1/α²: with coordinates of 10⁴ m that costs about 10⁻⁹ in
relative accuracy in float64.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Gaussian, symmetrise, wrap_angle
from tracklab.filters.kalman import gaussian_filter
from tracklab.linalg import cholesky, mm, spd_inverse


def sigma_weights(n, alpha, beta, kappa):
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 1.0 / (2 * (n + lam)))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + 1 - alpha**2 + beta
    return n + lam, wm, wc


def sigma_points(x, P, scale):
    L = cholesky(P) * jnp.sqrt(scale)
    return jnp.concatenate([x[None], x[None] + L.T, x[None] - L.T])  # (2n+1, n)


def model_ukf(model, sensor, params, alpha=1.0, beta=2.0, kappa=0.0):
    """UKF on a linear motion model (sigma points through F) and any sensor h."""
    n = model.n
    scale, wm, wc = sigma_weights(n, alpha, beta, kappa)
    wm, wc = jnp.asarray(wm), jnp.asarray(wc)
    F = jnp.asarray(model.F)
    pos = np.array(model.pos_idx)
    angles = jnp.asarray(sensor.angle_mask)

    def predict(p, g):
        X = sigma_points(g.x, g.P, scale) @ F.T
        x = X[0] + wm[1:] @ (X[1:] - X[0])  # deviation form: no cancellation of large weights
        d = X - x
        return Gaussian(x, symmetrise(mm((d * wc[:, None]).T, d) + model.Q(p["q"])))

    def update(p, g, z, present):
        X = sigma_points(g.x, g.P, scale)
        Z = sensor.h(jnp.stack([X[:, i] for i in pos], axis=-1))  # (2n+1, m)
        dZ = jnp.where(angles, wrap_angle(Z - Z[0]), Z - Z[0])
        z_hat = Z[0] + wm @ dZ
        dZ = jnp.where(angles, wrap_angle(Z - z_hat), Z - z_hat)
        dX = X - g.x
        used = present
        both = used[:, None] & used[None, :]
        R = jnp.diag(p["r"])
        S = jnp.where(both, mm((dZ * wc[:, None]).T, dZ) + R, jnp.eye(len(used), dtype=R.dtype))
        C = jnp.where(used[None, :], mm((dX * wc[:, None]).T, dZ), 0.0)
        nu = jnp.where(used, z - z_hat, 0.0)
        nu = jnp.where(angles, wrap_angle(nu), nu)
        K = mm(C, spd_inverse(S))
        x = g.x + mm(K, nu)
        P = symmetrise(g.P - mm(mm(K, S), K.T))
        return Gaussian(x, P), nu, S, used

    return gaussian_filter(params, predict, update)
