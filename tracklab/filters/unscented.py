"""Unscented Kalman filter (Julier & Uhlmann; Wan & van der Merwe's scaled sigma points).

2n + 1 sigma points x̂ ± √((n + λ)P) columns, λ = α²(n + κ) − n, weights
W_m0 = λ/(n + λ), W_c0 = W_m0 + 1 − α² + β, W_i = 1/(2(n + λ)). The prediction
propagates the sigma points through the motion model; the update draws new ones
from the prediction, maps them through h, and forms the innovation covariance
S = Σ W_c (Z − ẑ)(Z − ẑ)ᵀ + R and the cross-covariance C = Σ W_c (X − x̂)(Z − ẑ)ᵀ.
Angle components are averaged and differenced on the circle. Absent measurement
components are left out of the update, as in the other filters.

α, β, κ are parameters (``ut_alpha``, ``ut_beta``, ``ut_kappa``: inputs of the compiled
program, like q and r). Defaults α = 1, β = 2, κ = 0 (λ = 0: the symmetric set, W_m0 = 0). A small α
(say 10⁻³) keeps the points close to the mean but multiplies rounding errors by
weights of order 1/α²: with coordinates of 10⁴ m that costs about 10⁻⁹ in
relative accuracy in float64.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, Update, innovation, kalman_filter
from tracklab.filters.kind import ANY_SENSOR, NOISE, Entry, FilterKind, noise
from tracklab.parameters import Param, interval, nonnegative
from tracklab.linalg import cholesky, mm, spd_inverse, symmetrise


def sigma_weights(n, alpha, beta, kappa):
    """(n + λ, W_m, W_c) of the 2n + 1 sigma points; α, β, κ may be traced."""
    lam = alpha**2 * (n + kappa) - n
    w = jnp.broadcast_to(1.0 / (2 * (n + lam)), (2 * n,))
    wm0 = lam / (n + lam)
    wm = jnp.concatenate([jnp.reshape(wm0, (1,)), w])
    wc = jnp.concatenate([jnp.reshape(wm0 + 1 - alpha**2 + beta, (1,)), w])
    return n + lam, wm, wc


def sigma_points(x, P, scale):
    L = cholesky(P) * jnp.sqrt(scale)
    return jnp.concatenate([x[None], x[None] + L.T, x[None] - L.T])  # (2n+1, n)


def model_ukf(model, sensor, params):
    """UKF on a linear motion model (sigma points through F) and any sensor h;
    params {q, r, ut_alpha, ut_beta, ut_kappa}."""
    n = model.n
    F = jnp.asarray(model.F)
    pos = np.array(model.pos_idx)

    def weights(p):
        return sigma_weights(n, p["ut_alpha"], p["ut_beta"], p["ut_kappa"])

    def time_update(p, g):
        scale, wm, wc = weights(p)
        X = sigma_points(g.x, g.P, scale) @ F.T
        x = X[0] + wm[1:] @ (X[1:] - X[0])  # deviation form: no cancellation of large weights
        d = X - x
        return Gaussian(x, symmetrise(mm((d * wc[:, None]).T, d) + model.Q(p["q"])))

    def measurement_update(p, g, z, present):
        scale, wm, wc = weights(p)
        X = sigma_points(g.x, g.P, scale)
        Z = sensor.h(jnp.stack([X[:, i] for i in pos], axis=-1))  # (2n+1, m)
        dZ = innovation(Z, Z[0], sensor.angle_mask)  # angles differenced on the circle
        z_hat = Z[0] + wm @ dZ
        dZ = innovation(Z, z_hat, sensor.angle_mask)
        dX = X - g.x
        used = present
        both = used[:, None] & used[None, :]
        R = jnp.diag(p["r"])
        S = jnp.where(both, mm((dZ * wc[:, None]).T, dZ) + R, jnp.eye(len(used), dtype=R.dtype))
        C = jnp.where(used[None, :], mm((dX * wc[:, None]).T, dZ), 0.0)
        nu = jnp.where(used, innovation(z, z_hat, sensor.angle_mask), 0.0)
        K = mm(C, spd_inverse(S))
        x = g.x + mm(K, nu)
        P = symmetrise(g.P - mm(mm(K, S), K.T))
        return Update(x, P, nu, S, used)

    return kalman_filter(params, time_update, measurement_update)


def _read(e: Entry):
    model = e.motion_model()
    params = noise(e, model)
    params["ut_alpha"] = e.number("ut_alpha", e.default("ut_alpha"), lo=1e-4, hi=1.0)
    params["ut_beta"] = e.number("ut_beta", e.default("ut_beta"), nonneg=True)
    params["ut_kappa"] = e.number("ut_kappa", e.default("ut_kappa"), nonneg=True)
    return model, params, {}


UKF = FilterKind(
    name="ukf", doc="unscented KF; ut_alpha, ut_beta, ut_kappa (default 1, 2, 0)", accepts=ANY_SENSOR,
    params={**NOISE,
            "ut_alpha": Param("spread of the sigma points, α", interval(1e-4, 1.0), default=1.0),
            "ut_beta": Param("prior-distribution weight, β (2: Gaussian)", nonnegative, default=2.0),
            "ut_kappa": Param("secondary scaling, κ", nonnegative, default=0.0)},
    read=_read, build=lambda model, sensor, params, options: model_ukf(model, sensor, params))
