"""Measurement models of sensors at the origin, their timing, and sensor suites.

Kinds (z as a function of the position p):

* ``polar`` (2-D): [r, β], r = √(x²+y²), β = atan2(y, x) (paper 000 eqs. 5–7).
* ``spherical`` (3-D): [r, az, el], az = atan2(y, x), el = atan2(z, √(x²+y²))
  (docs/mathematics.md §4; paper 002's laser, eq. 13).
* ``angles`` (3-D): [az, el] (paper 002's infrared sensor, eq. 11).
* ``cartesian`` (1-, 2- or 3-D): the position itself (the linear-Gaussian case).
* ``mount``: an alt-azimuth mount's azimuth and elevation in degrees. It
  observes the truth in the mount frame (``scenarios.MountFrame``), whose
  "positions" are those angles, so its measurement is linear there; azimuth is
  continuous (an axis encoder's reading, never wrapped at ±180°).

Timing: a sensor reports at t = offset + j·period (j = 0, 1, …) on the
experiment's grid of steps t_k = k·dt (k = 1 … steps); between reports its
rows are NaN, which every filter treats as a predict-only step, as it treats a
missed detection (probability 1 − ``p_detect``).

A sensor holds the true noise; filters hold their own assumed R as parameters.
A ``SensorSuite`` stacks several sensors observing the same truth: its
measurement is the concatenation of theirs (NaN where a sensor has no report).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from tracklab import random
from tracklab.linalg import jacobian, mm, norm
from tracklab.parameters import Param, positive
from tracklab.pytree import static


def _horizontal_range(x, y):
    """√(x²+y²) (``linalg.norm``), not ``jnp.hypot``: hypot's guards against overflow (no range a
    sensor sees comes near 1e154 m) are selects and divisions in its derivative too, which every
    EKF step takes (the lidar EKF's step alone: 6.4 M runs·steps/s on a core with hypot, 8.0 M
    without; benchmarks/README.md)."""
    return norm(jnp.stack([x, y]))


def polar_h(p):
    x, y = p[..., 0], p[..., 1]
    return jnp.stack([_horizontal_range(x, y), jnp.arctan2(y, x)], axis=-1)


def spherical_h(p):
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    rho = _horizontal_range(x, y)
    return jnp.stack([jnp.sqrt(rho**2 + z**2), jnp.arctan2(y, x), jnp.arctan2(z, rho)], axis=-1)


def angles_h(p):
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return jnp.stack([jnp.arctan2(y, x), jnp.arctan2(z, _horizontal_range(x, y))], axis=-1)


def cartesian_h(p):
    return p


_H = {"polar": polar_h, "spherical": spherical_h, "angles": angles_h, "cartesian": cartesian_h, "mount": cartesian_h}
_NAMES = {"polar": ("r", "angle"), "spherical": ("r", "az", "el"), "angles": ("az", "el"), "mount": ("az_deg", "el_deg")}
LINEAR_KINDS = ("cartesian", "mount")  # the measurement is the (frame's) position itself
_ANGLES = ("angle", "az", "el")


def wrap(a):
    """An angle wrapped to (−π, π]: a + 2π⌊(π − a)/2π⌋, i.e. π − mod(π − a, 2π) with a floor,
    which XLA vectorises, where ``jnp.mod``'s fmod is a scalar library call per element."""
    return a + 2.0 * jnp.pi * jnp.floor((jnp.pi - a) / (2.0 * jnp.pi))


def measure_whole(sensor, key, pos):
    """A sensor's (or suite's) measurements of a whole position sequence (T, dim) -> (T, m):
    ``measure_step`` at every step, on that step's row of ``draws``."""
    T = pos.shape[0]
    return jax.vmap(lambda d, k, p: sensor.measure_step(d, k, T, p))(sensor.draws(key, T), jnp.arange(T), pos)


def epochs(steps: int, dt: float, period: float, offset: float) -> np.ndarray:
    """Boolean mask over steps k = 1 … steps: does a sensor report at t_k = k·dt?"""
    t = dt * np.arange(1, steps + 1)
    j = (t - offset) / period
    return (t >= offset - 1e-9 * dt) & (np.abs(j - np.round(j)) < 1e-6)


def report_mask(sensor, steps: int) -> np.ndarray:
    """Which of the steps 1 … steps a sensor reports at (its ``period`` and ``offset``; every step
    when it has no period)."""
    if sensor.period <= 0:
        return np.ones(steps, bool)
    return epochs(steps, sensor.dt, sensor.period, sensor.offset)


def sensor_draws(key, steps, m, misses):
    """One run's draws of a sensor of ``m`` components, float32: standard-normal noise (steps, m)
    and, when it can miss (``misses``), uniforms (steps,) that decide its detections."""
    k_noise, k_det = jax.random.split(key)
    u = random.uniform(k_det, (steps,)) if misses else None  # float32
    return random.normal(k_noise, (steps, m)), u


def reported(sensor, z, k, steps, u):
    """A sensor's noisy measurement ``z`` at step k as reported: its angle components wrapped,
    NaN where it has no report at that step or misses the detection (``u`` ≥ p_detect)."""
    if any(sensor.angle_mask):
        z = jnp.where(jnp.asarray(sensor.angle_mask), wrap(z), z)
    present = jnp.asarray(report_mask(sensor, steps))[k]
    if u is not None:
        present = present & (u < sensor.p_detect)
    return jnp.where(present, z, jnp.nan)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Sensor:
    """A sensor: its numbers (``sigma``, ``p_detect``) are the leaves of a pytree, so they
    enter a compiled program as arguments; kind, timing and whether it can miss a
    detection are its structure."""

    kind: str = static()  # "polar" | "spherical" | "angles" | "cartesian" | "mount"
    dim: int = static()  # spatial dimension of the positions it observes
    sigma: tuple = ()  # true noise std per measurement component
    p_detect: float = 1.0
    name: str = static("")
    dt: float = static(0.0)  # the experiment's step; with period/offset, sets the report epochs
    period: float = static(0.0)  # 0: every step
    offset: float = static(0.0)
    misses: bool | None = static(None)  # draws detections (p_detect < 1); None: from p_detect

    def __post_init__(self):
        if self.misses is None:
            object.__setattr__(self, "misses", bool(self.p_detect < 1.0))

    @property
    def m(self) -> int:
        return len(self.sigma)

    @property
    def R(self):
        """Its true noise covariance: the variances of its components (uncorrelated)."""
        return jnp.diag(jnp.square(jnp.asarray(self.sigma)))

    @property
    def names(self) -> tuple[str, ...]:
        return _NAMES.get(self.kind) or ("x", "y", "z")[: self.dim]

    @property
    def angle_mask(self) -> tuple[bool, ...]:
        return tuple(n in _ANGLES for n in self.names)

    @property
    def linear(self) -> bool:
        return self.kind in LINEAR_KINDS

    @property
    def sensors(self) -> tuple["Sensor", ...]:
        return (self,)

    def h(self, p):
        """Noise-free measurement of positions ``p`` (..., dim)."""
        return _H[self.kind](p)

    def report_mask(self, steps: int) -> np.ndarray:
        return report_mask(self, steps)

    def draws(self, key, steps):
        return sensor_draws(key, steps, self.m, self.misses)

    def measure_step(self, draws_k, k, steps, p):
        """Step k's noisy measurement (m,) of the position ``p`` (dim,), from that step's draws."""
        noise, u = draws_k
        return reported(self, self.h(p) + noise.astype(p.dtype) * jnp.asarray(self.sigma, p.dtype), k, steps, u)

    def measure(self, key, pos):
        """Noisy measurements of a position sequence ``pos`` (T, dim) -> (T, m)."""
        return measure_whole(self, key, pos)

    def information(self, p):
        """Expected Fisher information of one report about the position: Pd·Hᵀ R⁻¹ H."""
        H = jacobian(self.h, p)
        return self.p_detect * mm(H.T / jnp.square(jnp.asarray(self.sigma, p.dtype)), H)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class SensorSuite:
    """Several sensors observing the same truth; z is their concatenation."""

    sensors: tuple[Sensor, ...]

    @property
    def kind(self) -> str:
        return "suite" if len(self.sensors) > 1 else self.sensors[0].kind

    @property
    def dim(self) -> int:
        return self.sensors[0].dim

    @property
    def m(self) -> int:
        return sum(s.m for s in self.sensors)

    @property
    def sigma(self) -> tuple[float, ...]:
        return sum((s.sigma for s in self.sensors), ())

    @property
    def names(self) -> tuple[str, ...]:
        return sum((s.names for s in self.sensors), ())

    @property
    def angle_mask(self) -> tuple[bool, ...]:
        return sum((s.angle_mask for s in self.sensors), ())

    @property
    def misses(self) -> bool:
        return any(s.misses for s in self.sensors)

    @property
    def linear(self) -> bool:
        return all(s.linear for s in self.sensors)

    def columns(self, names) -> np.ndarray:
        """Column indices of the named sensors in the suite's z."""
        cols, start = {}, 0
        for s in self.sensors:
            cols[s.name] = np.arange(start, start + s.m)
            start += s.m
        return np.concatenate([cols[n] for n in names])

    def subset(self, names) -> "SensorSuite":
        by = {s.name: s for s in self.sensors}
        return SensorSuite(tuple(by[n] for n in names))

    def h(self, p):
        return jnp.concatenate([s.h(p) for s in self.sensors], axis=-1)

    def draws(self, key, steps):
        keys = jax.random.split(key, len(self.sensors))
        return tuple(s.draws(k, steps) for s, k in zip(self.sensors, keys))

    def measure_step(self, draws_k, k, steps, p):
        return jnp.concatenate([s.measure_step(d, k, steps, p) for s, d in zip(self.sensors, draws_k)], axis=-1)

    def measure(self, key, pos):
        return measure_whole(self, key, pos)

    def information(self, pos):
        """Per-step expected position information (T, dim, dim), only at report epochs."""
        T = pos.shape[0]
        total = 0.0
        for s in self.sensors:
            info = jax.vmap(s.information)(pos)
            total = total + jnp.asarray(s.report_mask(T), pos.dtype)[:, None, None] * info
        return total


@dataclass(frozen=True)
class SensorKind:
    """A kind of sensor a [sensor] table may name: what it measures, the dimension of the truth it
    observes (None: any), and its noise standard deviations (``params``: field -> ``Param``, in the
    order of its measurement vector), each read and checked as declared. Its timing and detection
    (``period``, ``offset``, ``p_detect``) are every sensor's."""

    name: str
    doc: str
    dim: int | None
    params: Mapping[str, Param]


_RANGE = Param("range noise std", positive, "m")
SENSORS: dict[str, SensorKind] = {k.name: k for k in (
    SensorKind("polar", "2-D range and bearing", 2,
               {"sigma_r": _RANGE, "sigma_angle": Param("bearing noise std", positive, "rad")}),
    SensorKind("spherical", "3-D range, azimuth, elevation (a laser)", 3,
               {"sigma_r": _RANGE, "sigma_az": Param("azimuth noise std", positive, "rad"),
                "sigma_el": Param("elevation noise std", positive, "rad")}),
    SensorKind("angles", "3-D azimuth and elevation (an infrared sensor)", 3,
               {"sigma_az": Param("azimuth noise std", positive, "rad"),
                "sigma_el": Param("elevation noise std", positive, "rad")}),
    SensorKind("cartesian", "1-/2-/3-D position", None,
               {"sigma": Param("position noise std, one value or one per axis", positive, "m")}),
    SensorKind("mount", "alt-azimuth mount: azimuth and elevation of a 3-D truth, filters working in (az, el)", 3,
               {"sigma_az": Param("azimuth noise std", positive, "deg"),
                "sigma_el": Param("elevation noise std", positive, "deg")}),
)}
SENSOR_SIGMAS = {k.name: tuple(k.params) for k in SENSORS.values()}  # each kind's noise fields, in z's order
