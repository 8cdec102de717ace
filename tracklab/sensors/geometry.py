"""Measurement models of a sensor at the origin.

* ``polar`` (2-D): z = [r, β], r = √(x²+y²), β = atan2(y, x) (paper 000 eqs. 5–7).
* ``spherical`` (3-D): z = [r, az, el], az = atan2(y, x), el = atan2(z, √(x²+y²))
  (the convention of REFERENCE_MATH §4).
* ``cartesian`` (2-D or 3-D): z = position + noise (the linear-Gaussian case).

A sensor holds the true noise; filters hold their own assumed R as parameters.
Measurements are drawn with independent Gaussian noise per component; a missed
detection (probability 1 − ``p_detect``) is a row of NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np


def polar_h(p):
    x, y = p[..., 0], p[..., 1]
    return jnp.stack([jnp.hypot(x, y), jnp.arctan2(y, x)], axis=-1)


def spherical_h(p):
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    rho = jnp.hypot(x, y)
    return jnp.stack([jnp.sqrt(rho**2 + z**2), jnp.arctan2(y, x), jnp.arctan2(z, rho)], axis=-1)


def cartesian_h(p):
    return p


@dataclass(frozen=True)
class Sensor:
    kind: str  # "polar" | "spherical" | "cartesian"
    dim: int  # spatial dimension of the positions it observes
    sigma: tuple[float, ...]  # true noise std per measurement component
    p_detect: float = 1.0

    @property
    def m(self) -> int:
        return len(self.sigma)

    @property
    def names(self) -> tuple[str, ...]:
        return {
            "polar": ("r", "angle"),
            "spherical": ("r", "az", "el"),
            "cartesian": ("x", "y", "z")[: self.dim],
        }[self.kind]

    @property
    def angle_mask(self) -> tuple[bool, ...]:
        return tuple(n in ("angle", "az", "el") for n in self.names)

    @property
    def range_index(self) -> int | None:
        return 0 if self.kind in ("polar", "spherical") else None

    @property
    def linear(self) -> bool:
        return self.kind == "cartesian"

    def h(self, p):
        """Noise-free measurement of positions ``p`` (..., dim)."""
        return {"polar": polar_h, "spherical": spherical_h, "cartesian": cartesian_h}[self.kind](p)

    def R(self):
        return np.diag(np.square(self.sigma))

    def measure(self, key, pos):
        """Noisy measurements of a position sequence ``pos`` (T, dim) -> (T, m)."""
        k_noise, k_det = jax.random.split(key)
        noise = jax.random.normal(k_noise, pos.shape[:-1] + (self.m,), pos.dtype)
        z = self.h(pos) + noise * jnp.asarray(self.sigma, pos.dtype)
        if self.kind != "cartesian":
            z = z.at[..., 1].set(_wrap(z[..., 1]))
        if self.p_detect < 1.0:
            hit = jax.random.uniform(k_det, pos.shape[:-1]) < self.p_detect
            z = jnp.where(hit[..., None], z, jnp.nan)
        return z

    def position_information(self, p):
        """Fisher information of one measurement about the position: Hᵀ R⁻¹ H, (dim, dim)."""
        H = jax.jacfwd(self.h)(p)
        return self.p_detect * (H.T / jnp.asarray(np.square(self.sigma), p.dtype)) @ H


def _wrap(a):
    return jnp.pi - jnp.mod(jnp.pi - a, 2.0 * jnp.pi)


SENSOR_KINDS = {
    "polar": "2-D range and angle: sigma_r (m), sigma_angle (rad)",
    "spherical": "3-D range, azimuth, elevation: sigma_r (m), sigma_az, sigma_el (rad)",
    "cartesian": "2-D/3-D position: sigma (m), one value or one per axis",
}
