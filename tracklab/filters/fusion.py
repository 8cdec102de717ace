"""What a filter sees of a sensor suite: a selection, or laser + infrared fusion.

Paper 002 §2: the infrared sensor (azimuth, elevation) and the laser (range,
azimuth, elevation) sample at different periods. Their measurements are first
registered to common epochs — the laser's — by interpolating the infrared
angles between the infrared samples around each laser epoch (eq. 19, linear;
extrapolation from the two nearest samples at the ends), then fused: range from
the laser, each angle the inverse-variance weighted mean of the two (eqs. 20–21).
The fused stream is a spherical measurement at the laser's epochs, so any
filter of a spherical sensor can sit behind it (including a conversion to
Cartesian for the α-β filters).

The report epochs of every sensor are fixed by its period and offset, so the
registration indices and weights are computed once, with NumPy, at trace time.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from tracklab.sensors.geometry import Sensor, SensorSuite, wrap


def registration_weights(src_mask, target_mask, method="interpolate"):
    """For each step: indices (a, b) of source epochs and weight w, z = z_a + w (z_b − z_a).

    ``method = "interpolate"`` uses the source epochs around each target epoch (eq. 19),
    extrapolating from the first or last two at the ends; ``"none"`` takes the latest
    source epoch at or before the target epoch (the first one before any exists).
    """
    src = np.flatnonzero(src_mask)
    k = np.arange(len(target_mask))
    if len(src) == 0:
        raise ValueError("the source sensor never reports")
    if method == "none" or len(src) == 1:
        a = src[np.clip(np.searchsorted(src, k, side="right") - 1, 0, len(src) - 1)]
        return a, a, np.zeros(len(k))
    j = np.clip(np.searchsorted(src, k, side="right") - 1, 0, len(src) - 2)
    a, b = src[j], src[j + 1]
    w = (k - a) / (b - a)
    exact = np.isin(k, src)  # a target epoch that is a source epoch takes it as is
    a = np.where(exact, k, a)
    w = np.where(exact, 0.0, w)
    return a, b, w


def register(z_src, src_mask, target_mask, angle_mask=None, method="interpolate"):
    """Source measurements (T, m) registered to the target epochs (NaN elsewhere)."""
    a, b, w = registration_weights(np.asarray(src_mask), np.asarray(target_mask), method)
    za, zb = z_src[a], z_src[b]
    d = zb - za
    if angle_mask is not None and any(angle_mask):
        d = jnp.where(jnp.asarray(angle_mask), wrap(d), d)
    z = za + jnp.asarray(w, z_src.dtype)[:, None] * d
    if angle_mask is not None and any(angle_mask):
        z = jnp.where(jnp.asarray(angle_mask), wrap(z), z)
    return jnp.where(jnp.asarray(target_mask)[:, None], z, jnp.nan)


def fuse_angles(theta_a, var_a, theta_b, var_b):
    """Inverse-variance weighted mean of two angle measurements (eqs. 20–21)."""
    var = var_a * var_b / (var_a + var_b)
    return wrap(theta_a + (var / var_b) * wrap(theta_b - theta_a)), var


@dataclass(frozen=True)
class Select:
    """The named sensors of a suite, as they are."""

    suite: SensorSuite
    names: tuple[str, ...]
    rowwise = True  # each step's measurement on its own (the engine may draw them step by step)

    @property
    def model(self):
        sub = self.suite.subset(self.names)
        return sub.sensors[0] if len(sub.sensors) == 1 else sub

    def __call__(self, z):
        return z[..., self.suite.columns(self.names)]


@dataclass(frozen=True)
class LaserIrFusion:
    """Laser range + fused laser/infrared angles at the laser's epochs (paper 002 §2.2–2.3)."""

    suite: SensorSuite
    laser: str
    infrared: str
    registration: str = "interpolate"  # or "none"

    def _sensors(self):
        by = {s.name: s for s in self.suite.sensors}
        return by[self.laser], by[self.infrared]

    @property
    def model(self) -> Sensor:
        L, I = self._sensors()
        s_az = (L.sigma[1] ** 2 * I.sigma[0] ** 2 / (L.sigma[1] ** 2 + I.sigma[0] ** 2)) ** 0.5
        s_el = (L.sigma[2] ** 2 * I.sigma[1] ** 2 / (L.sigma[2] ** 2 + I.sigma[1] ** 2)) ** 0.5
        return Sensor("spherical", 3, (L.sigma[0], s_az, s_el), L.p_detect, name=f"{self.laser}+{self.infrared}",
                      dt=L.dt, period=L.period, offset=L.offset, misses=L.misses)

    def __call__(self, z):
        L, I = self._sensors()
        T = z.shape[-2]
        zl = z[:, self.suite.columns([self.laser])]
        zi = z[:, self.suite.columns([self.infrared])]
        zi = register(zi, I.report_mask(T), L.report_mask(T), (True, True), self.registration)
        az, _ = fuse_angles(zl[:, 1], L.sigma[1] ** 2, zi[:, 0], I.sigma[0] ** 2)
        el, _ = fuse_angles(zl[:, 2], L.sigma[2] ** 2, zi[:, 1], I.sigma[1] ** 2)
        return jnp.stack([zl[:, 0], az, el], axis=-1)


def view_of(suite: SensorSuite, names, fusion=None):
    """(view function or None, measurement model) of what a filter sees of a sensor suite: the
    named sensors (all when ``names`` is empty), laser + infrared fused when ``fusion`` is given."""
    names = tuple(names) or tuple(s.name for s in suite.sensors)
    if fusion is not None:
        sub = suite.subset(names)
        laser = next(s.name for s in sub.sensors if s.kind == "spherical")
        ir = next(s.name for s in sub.sensors if s.kind == "angles")
        v = LaserIrFusion(suite, laser, ir, fusion)
        return v, v.model
    if names == tuple(s.name for s in suite.sensors):
        return None, suite.sensors[0] if len(suite.sensors) == 1 else suite
    v = Select(suite, names)
    return v, v.model
