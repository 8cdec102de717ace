"""Converted measurements: polar/spherical to Cartesian with their covariances.

Three conversions (docs/mathematics.md §4):

* ``plain`` — x = r cos β, … with the linearised covariance J R Jᵀ at the
  measurement (paper 000 eqs. 8 and 12).
* ``additive`` — Lerro & Bar-Shalom (1993): subtract the bias of the plain
  conversion, with its covariance (2-D only).
* ``unbiased`` — Mo et al. (1998): multiply by λ⁻¹ = e^{σ²/2}, with the
  covariance conditioned on the measurement (2-D and 3-D).

Each function takes z (..., m) and the noise std ``sigma`` of the filter's
measurement model and returns (position (..., dim), covariance (..., dim, dim)).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tracklab.linalg import mm


def _plain_position(z):
    if z.shape[-1] == 2:
        r, b = z[..., 0], z[..., 1]
        return jnp.stack([r * jnp.cos(b), r * jnp.sin(b)], axis=-1)
    r, az, el = z[..., 0], z[..., 1], z[..., 2]
    return jnp.stack([r * jnp.cos(el) * jnp.cos(az), r * jnp.cos(el) * jnp.sin(az), r * jnp.sin(el)], axis=-1)


def plain(z, sigma):
    """Paper 000 eq. (8) with R_T = J R Jᵀ at the measurement (eq. 12 in 2-D)."""
    J = jax.jacfwd(_plain_position)(z)
    return _plain_position(z), mm(J * jnp.square(sigma), J.T)


def additive(z, sigma):
    """Lerro & Bar-Shalom debiased conversion (2-D)."""
    r, b = z[0], z[1]
    sr2, sb2 = sigma[0] ** 2, sigma[1] ** 2
    c, s = jnp.cos(b), jnp.sin(b)
    mu = r * (jnp.exp(-sb2) - jnp.exp(-sb2 / 2))
    pos = jnp.stack([r * c - mu * c, r * s - mu * s])
    e2 = jnp.exp(-2 * sb2)
    ch2, ch1, sh2, sh1 = jnp.cosh(2 * sb2), jnp.cosh(sb2), jnp.sinh(2 * sb2), jnp.sinh(sb2)
    R11 = r**2 * e2 * (c**2 * (ch2 - ch1) + s**2 * (sh2 - sh1)) + sr2 * e2 * (
        c**2 * (2 * ch2 - ch1) + s**2 * (2 * sh2 - sh1)
    )
    R22 = r**2 * e2 * (s**2 * (ch2 - ch1) + c**2 * (sh2 - sh1)) + sr2 * e2 * (
        s**2 * (2 * ch2 - ch1) + c**2 * (2 * sh2 - sh1)
    )
    R12 = s * c * jnp.exp(-4 * sb2) * (sr2 + (r**2 + sr2) * (1 - jnp.exp(sb2)))
    return pos, jnp.array([[R11, R12], [R12, R22]])


def unbiased(z, sigma):
    """Mo et al. unbiased conversion, covariance conditioned on the measurement."""
    if z.shape[-1] == 2:
        return _unbiased_2d(z, sigma)
    return _unbiased_3d(z, sigma)


def _unbiased_2d(z, sigma):
    # Mo et al.'s covariance, rearranged so that no two r²-sized terms cancel (in float32 they
    # would leave rounding noise larger than the r²σ²-sized result): with λ = e^{−σ_β²/2},
    # λ⁻² − 2 = E − 1 and λ′ = e^{−2σ_β²} = 1 + δ, E = expm1(σ_β²), δ = expm1(−2σ_β²).
    r, b = z[0], z[1]
    sr2, sb2 = sigma[0] ** 2, sigma[1] ** 2
    lam = jnp.exp(-sb2 / 2)
    E, d = jnp.expm1(sb2), jnp.expm1(-2 * sb2)
    c, s = jnp.cos(b), jnp.sin(b)
    pos = jnp.stack([r * c, r * s]) / lam
    h = 0.5 * (r**2 + sr2)
    c2b = jnp.cos(2 * b)
    R11 = E * r**2 * c**2 + sr2 * c**2 + h * d * c2b
    R22 = E * r**2 * s**2 + sr2 * s**2 - h * d * c2b
    R12 = (E * r**2 + sr2 + (r**2 + sr2) * d) * s * c
    return pos, jnp.array([[R11, R12], [R12, R22]])


def _unbiased_3d(z, sigma):
    # Mo et al.'s 3-D covariance, rearranged as in 2-D: E = expm1(σ_β² + σ_ε²) = (λ_β λ_ε)⁻² − 1,
    # E_ε = expm1(σ_ε²), δ_β = expm1(−2σ_β²) = λ′_β − 1, δ_ε = expm1(−2σ_ε²) = λ′_ε − 1.
    r, be, ep = z[0], z[1], z[2]  # range, azimuth β, elevation ε
    sr2, sb2, se2 = sigma[0] ** 2, sigma[1] ** 2, sigma[2] ** 2
    lb, le = jnp.exp(-sb2 / 2), jnp.exp(-se2 / 2)
    E, Ee = jnp.expm1(sb2 + se2), jnp.expm1(se2)
    db, de = jnp.expm1(-2 * sb2), jnp.expm1(-2 * se2)
    Cb, Sb, Ce, Se = jnp.cos(be), jnp.sin(be), jnp.cos(ep), jnp.sin(ep)
    C2b, S2b, C2e = jnp.cos(2 * be), jnp.sin(2 * be), jnp.cos(2 * ep)
    pos = jnp.stack([r * Ce * Cb / (lb * le), r * Ce * Sb / (lb * le), r * Se / le])
    r2 = r**2
    q = 0.25 * (r2 + sr2)
    base = E * r2 + sr2
    R11 = base * Cb**2 * Ce**2 + q * (2 * Cb**2 * de * C2e + 2 * Ce**2 * db * C2b + db * de * C2b * C2e)
    R22 = base * Sb**2 * Ce**2 + q * (2 * Sb**2 * de * C2e - 2 * Ce**2 * db * C2b - db * de * C2b * C2e)
    R33 = (Ee * r2 + sr2) * Se**2 - 2 * q * de * C2e
    R12 = base * Sb * Cb * Ce**2 + q * S2b * (2 * db * Ce**2 + (1 + db) * de * C2e)
    k = (r2 * jnp.exp(sb2 / 2) * Ee + r2 * lb * de + sr2 * lb * (1 + de)) * Se * Ce
    R13, R23 = k * Cb, k * Sb
    R = jnp.array([[R11, R12, R13], [R12, R22, R23], [R13, R23, R33]])
    return pos, R


CONVERSIONS = {"plain": plain, "additive": additive, "unbiased": unbiased}
