"""Constant-gain α-β and α-β-γ filters (paper 002 §1, REFERENCE_MATH §2).

Per Cartesian axis, x⁺ = x⁻ + K (z − x⁻_pos) with K = [α, β/T] (α-β, eq. 1) or
K = [α, β/T, γ/(2T²)] (α-β-γ; note the factor 2). The gains come from

* ``kalata``: the tracking index λ = σ_v T²/σ_w (eq. 5) in closed form
  (eqs. 6–7; α-β-γ through the real root of s³ + (λ/2 − 3)s² + (λ/2 + 3)s − 1 = 0);
  these are the steady-state Kalman gains of the DWNA (α-β) or DWPA (α-β-γ) model;
* ``growing_memory``: α_k = 2(2k−1)/(k(k+1)), β_k = 6/(k(k+1)) (eqs. 8–9), or
  the α-β-γ least-squares schedule, k counting the measurements processed
  (including the current one); optionally each gain stops shrinking at a floor
  (explicit values, or the Kalata gains);
* ``explicit``: α, β (, γ) given.

The gains are parameters (pytree leaves) or functions of parameters and of the
step count only, never of the measurements, so under ``vmap`` over runs they
are computed once per parameter set. The filter also propagates the error
covariance of its fixed-gain update under its model (Joseph form with the gain
actually used), so NEES is meaningful. Non-Cartesian sensors are first
converted to Cartesian positions (plain or unbiased conversion).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Filter, Out, masked_meas, select, symmetrise
from tracklab.linalg import mm
from tracklab.sensors import CONVERSIONS


def kalata_alpha_beta(lam):
    """Steady-state α, β of the DWNA model from the tracking index (eqs. 6–7)."""
    r = jnp.sqrt(lam**2 + 8 * lam)
    alpha = -(lam**2 + 8 * lam - (lam + 4) * r) / 8
    beta = (lam**2 + 4 * lam - lam * r) / 4
    return alpha, beta


def kalata_alpha_beta_gamma(lam):
    """Steady-state α, β, γ of the DWPA model (REFERENCE_MATH §2).

    s is the root in (0, 1) of s³ + (λ/2 − 3)s² + (λ/2 + 3)s − 1 = 0: Cardano's
    formula while the cubic has one real root, the trigonometric form when it
    has three (λ > 12√3).
    """
    b, c = lam / 2 - 3, lam / 2 + 3
    p = c - b**2 / 3
    q = 2 * b**3 / 27 - b * c / 3 - 1
    disc = q**2 + 4 * p**3 / 27
    one_root = disc >= 0
    z = jnp.cbrt((-q + jnp.sqrt(jnp.where(one_root, disc, 1.0))) / 2)
    s_cardano = z - p / (3 * z) - b / 3
    p_neg = jnp.where(one_root, -1.0, p)  # p < 0 whenever there are three real roots
    m = 2 * jnp.sqrt(-p_neg / 3)
    phi = jnp.arccos(jnp.clip(jnp.where(one_root, 0.0, 3 * q / (p_neg * m)), -1.0, 1.0)) / 3
    roots = [m * jnp.cos(phi - 2 * jnp.pi * j / 3) - b / 3 for j in range(3)]
    s_trig = roots[2]
    for r in roots[1::-1]:
        s_trig = jnp.where((r > 0) & (r < 1), r, s_trig)
    s = jnp.where(one_root, s_cardano, s_trig)
    return 1 - s**2, 2 * (1 - s) ** 2, 2 * lam * s


def growing_memory_alpha_beta(k):
    """Least-squares line-fit gains after k measurements (eqs. 8–9)."""
    k = jnp.maximum(k, 1.0)
    return 2 * (2 * k - 1) / (k * (k + 1)), 6 / (k * (k + 1))


def growing_memory_alpha_beta_gamma(k):
    """Least-squares parabola-fit gains after k measurements (γ in the γ/(2T²) convention)."""
    k = jnp.maximum(k, 1.0)
    den = k * (k + 1) * (k + 2)
    return 3 * (3 * k**2 - 3 * k + 2) / den, 18 * (2 * k - 1) / den, 120 / den


def gain_matrix(order, dim, T, gains):
    """K (dim·order, dim): per axis [α, β/T (, γ/(2T²))] in the interleaved layout."""
    scale = jnp.array([1.0, 1.0 / T, 1.0 / (2 * T**2)][:order])
    g = jnp.stack([jnp.broadcast_to(v, (dim,)) for v in gains[:order]], axis=-1)  # (dim, order)
    K = jnp.zeros((dim * order, dim), dtype=g.dtype)
    for a in range(dim):
        K = K.at[a * order:(a + 1) * order, a].set(g[a] * scale)
    return K


def tracking_index(sigma_v, sigma_w, T):
    """λ = σ_v T² / σ_w (eq. 5): process-noise std σ_v, measurement-noise std σ_w."""
    return sigma_v * T**2 / sigma_w


class ABState(NamedTuple):
    x: jax.Array
    P: jax.Array
    k: jax.Array  # measurements processed


def model_alpha_beta(model, sensor, params, gains="kalata", floor=None, conversion="plain") -> Filter:
    """α-β (CV model) or α-β-γ (CA model) filter.

    params: {"q", "r"} always (the covariance propagation and, for a converted
    measurement, its noise); {"lam": (dim,)} for Kalata gains or a Kalata floor;
    {"alpha", "beta"(, "gamma")} for explicit gains; {"floor": (order,)} for an
    explicit floor on growing-memory gains. The gains' T is the sensor's report period
    (the model's step when the sensor reports every step); between reports the
    filter predicts with its model.
    """
    order, dim = model.order, model.dim
    # the gains' T is the update interval: the sensor's period when it reports less often than every step
    T = float(getattr(sensor, "period", 0.0) or model.F[0, 1])
    F = jnp.asarray(model.F)
    H = np.zeros((dim, model.n))
    H[np.arange(dim), np.array(model.pos_idx)] = 1.0
    H = jnp.asarray(H)
    kalata = kalata_alpha_beta if order == 2 else kalata_alpha_beta_gamma
    growing = growing_memory_alpha_beta if order == 2 else growing_memory_alpha_beta_gamma
    convert = None if sensor.linear else CONVERSIONS[conversion]

    def current_gains(p, k):
        if gains == "kalata":
            return kalata(p["lam"])
        if gains == "explicit":
            return tuple(p[n] for n in ("alpha", "beta", "gamma")[:order])
        g = growing(k)
        if floor == "kalata":
            g = tuple(jnp.maximum(a, b) for a, b in zip(g, kalata(p["lam"])))
        elif floor is not None:
            g = tuple(jnp.maximum(a, p["floor"][i]) for i, a in enumerate(g))
        return g

    def init(p, prior):
        return ABState(jnp.asarray(prior.x), jnp.asarray(prior.P), jnp.zeros((), jnp.asarray(prior.x).dtype))

    def predict(p, s):
        return mm(F, s.x), symmetrise(mm(mm(F, s.P), F.T) + model.Q(p["q"]))

    def coast(p, s, meas):
        x_pred, P_pred = predict(p, s)
        none = jnp.zeros((dim,), bool)
        out = Out(x=x_pred, P=P_pred, x_pred=x_pred, nu=jnp.zeros((dim,), x_pred.dtype),
                  S=jnp.eye(dim, dtype=x_pred.dtype), valid=jnp.any(none), dof=jnp.sum(none))
        return ABState(x_pred, P_pred, s.k), out

    def step(p, s, meas):
        z, present = masked_meas(meas)
        x_pred, P_pred = predict(p, s)
        if convert is None:
            zc, Rc, used = z, jnp.diag(jnp.broadcast_to(p["r"], (dim,))), present
        else:
            zc, Rc = convert(z, jnp.sqrt(p["r"]))
            used = jnp.broadcast_to(jnp.all(present), (dim,))
        valid = jnp.any(used)
        k = s.k + valid
        K = gain_matrix(order, dim, T, current_gains(p, k)) * used[None, :]
        nu = jnp.where(used, zc - mm(H, x_pred), 0.0)
        x = x_pred + mm(K, nu)
        IKH = jnp.eye(model.n, dtype=x.dtype) - mm(K, H)
        Ru = jnp.where(used[:, None] & used[None, :], Rc, jnp.eye(dim, dtype=x.dtype))
        P = symmetrise(mm(mm(IKH, P_pred), IKH.T) + mm(mm(K, Ru), K.T))
        S = jnp.where(used[:, None] & used[None, :], mm(mm(H, P_pred), H.T) + Ru, Ru)
        post = select(valid, ABState(x, P, k), ABState(x_pred, P_pred, s.k))
        out = Out(x=post.x, P=post.P, x_pred=x_pred, nu=nu, S=S, valid=valid, dof=jnp.sum(used))
        return post, out

    return Filter(init=init, step=step, params=params, coast=coast)
