"""The PDAF's expected covariance in steady state: the modified Riccati equation.

Fortmann, Bar-Shalom, Scheffé & Gelfand ("Detection thresholds for tracking in clutter — a
connection between estimation and signal processing", IEEE Trans. Automatic Control 30(3),
1985) average the PDAF's covariance update over the returns of a scan:

    P⁻ₖ₊₁ = F Pₖ Fᵀ + Q,    Pₖ = P⁻ₖ − q₂ Kₖ Sₖ Kₖᵀ,

with S = H P⁻ Hᵀ + R, K = P⁻ Hᵀ S⁻¹ and q₂ ∈ [0, P_D P_G] the expected reduction:
q₂ I = E[(1 − β₀) I − (Σᵢ βᵢ νᵢ νᵢᵀ − ν νᵀ)] in whitened innovation coordinates (S = I), over
the target's return (probability P_D, inside the gate) and the Poisson false alarms in the
gate (λ√det S of them per unit whitened volume). q₂ depends on S, so the equation is iterated
to its fixed point; q₂ is evaluated by Monte-Carlo integration with a fixed seed (the same
value for the same arguments).
"""

from __future__ import annotations

import math

import numpy as np

from tracklab.filters.association import gate_probability


def ball_volume(m: int, radius: float) -> float:
    return math.pi ** (m / 2) / math.gamma(m / 2 + 1) * radius**m


def pdaf_q2(density_w: float, p_detect: float, gate: float, m: int, scans: int = 40_000, seed: int = 0) -> float:
    """q₂ (see the module's doc) for whitened clutter density ``density_w``, P_D and gate γ."""
    rng = np.random.default_rng(seed)
    pg = float(gate_probability(gate, m))
    r = math.sqrt(gate)
    n = rng.poisson(density_w * ball_volume(m, r), scans)
    K = int(n.max(initial=0)) + 1
    # false alarms uniform in the gate's ball: directions on the sphere, radii r·u^(1/m)
    d = rng.standard_normal((scans, K, m))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    alarms = d * (r * rng.random((scans, K, 1)) ** (1.0 / m))
    valid = np.arange(K)[None, :] < n[:, None]
    target = rng.standard_normal((scans, 1, m))
    detected = (rng.random(scans) < p_detect) & (np.sum(target[:, 0] ** 2, axis=-1) <= gate)
    nu = np.concatenate([target, alarms], axis=1)
    valid = np.concatenate([detected[:, None], valid], axis=1)
    L = np.where(valid, p_detect * np.exp(-0.5 * np.sum(nu**2, -1)) / (2 * np.pi) ** (m / 2), 0.0)
    w0 = density_w * (1.0 - p_detect * pg)
    denom = w0 + L.sum(axis=1)
    none = denom <= 0  # no return and no clutter: the prediction kept
    denom = np.where(none, 1.0, denom)
    beta = L / denom[:, None]
    b0 = np.where(none, 1.0, w0 / denom)
    mean_nu = np.einsum("sk,skm->sm", beta, nu)
    spread = np.einsum("sk,ski,skj->sij", beta, nu, nu) - np.einsum("si,sj->sij", mean_nu, mean_nu)
    reduction = (1.0 - b0)[:, None, None] * np.eye(m) - spread
    return float(np.trace(reduction.mean(axis=0)) / m)


def _riccati(F, Q, H, R, q2, P_pred, iterations=2000):
    """The modified Riccati equation iterated to its fixed point with q₂ held: P⁻."""
    for _ in range(iterations):
        S = H @ P_pred @ H.T + R
        K = P_pred @ H.T @ np.linalg.inv(S)
        new = F @ (P_pred - q2 * K @ S @ K.T) @ F.T + Q
        if np.allclose(new, P_pred, rtol=1e-12, atol=0.0):
            return new
        P_pred = new
    return P_pred


def pdaf_steady_state(F, Q, H, R, p_detect: float, density: float, gate: float, rounds: int = 30):
    """(P, P⁻, q₂) of the modified Riccati equation at its fixed point; ``density`` λ per unit volume
    of the measurement space. Alternates the equation's fixed point at a q₂ and q₂ at its S."""
    F, Q, H, R = (np.asarray(a, float) for a in (F, Q, H, R))
    m = H.shape[0]
    P_pred = _riccati(F, Q, H, R, p_detect, Q + np.eye(len(Q)))
    q2 = p_detect
    for _ in range(rounds):
        S = H @ P_pred @ H.T + R
        new = pdaf_q2(density * math.sqrt(np.linalg.det(S)), p_detect, gate, m)
        P_pred = _riccati(F, Q, H, R, new, P_pred)
        if abs(new - q2) < 1e-6:
            q2 = new
            break
        q2 = new
    S = H @ P_pred @ H.T + R
    K = P_pred @ H.T @ np.linalg.inv(S)
    return P_pred - q2 * K @ S @ K.T, P_pred, q2
