"""What a filter factory named in an experiment file receives: ``FilterContext``.

A ``[[filter]]`` table with ``kind = "package.module:factory"`` calls
``factory(context, **the table's other keys)``, which returns a ``Filter``. The context
holds what the experiment fixes and a filter needs to know:

* ``dt`` (s), ``steps``, ``dim`` (spatial dimensions of the truth: 2 or 3);
* ``model``: the constant-velocity motion model of that dimension and period
  (``tracklab.models.Kinematic``: ``F``, noise gain ``G``, ``Q(q)``; its state is the
  interleaved [x, ẋ, y, ẏ(, z, ż)]), and ``accel_sigma``, the scenario's acceleration
  noise (m/s², 0 when the truth has none), the usual default of a filter's q = σ²;
* ``sensors``: what the filter sees, one ``SensorModel`` per sensor in the order of its
  measurement vector: ``name``, ``h`` (position (dim,) -> (m,), ``jax.numpy``), ``R``
  (the sensor's true noise covariance, (m, m)), ``angles`` (which components are angles
  in radians, to be wrapped), ``period``, ``offset`` and ``p_detect``;
* ``h``, ``R``, ``angles``, ``m``: the same for all of them stacked (R block-diagonal).

A component of the measurement is NaN when its sensor has no report at that step.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

from tracklab.models import Kinematic, cv
from tracklab.sensors import CustomSensor, Sensor, SensorSuite


class SensorModel(NamedTuple):
    name: str
    h: Callable  # position (dim,) -> (m,)
    R: np.ndarray  # (m, m) true noise covariance
    angles: tuple[bool, ...]  # which components are angles (radians, wrapped to (−π, π])
    period: float  # s between reports (the step when every step)
    offset: float  # s, time of the first report
    p_detect: float

    @property
    def m(self) -> int:
        return self.R.shape[0]


class FilterContext(NamedTuple):
    dt: float
    steps: int
    dim: int
    model: Kinematic  # constant velocity, interleaved state [x, ẋ, y, ẏ(, z, ż)]
    accel_sigma: float  # the scenario's acceleration noise (m/s²), the usual default of q = σ²
    sensors: tuple[SensorModel, ...]  # what the filter sees, in the order of its measurement vector

    @property
    def m(self) -> int:
        return sum(s.m for s in self.sensors)

    @property
    def R(self) -> np.ndarray:
        """The stacked sensors' noise covariance, block-diagonal (m, m)."""
        R = np.zeros((self.m, self.m))
        i = 0
        for s in self.sensors:
            R[i:i + s.m, i:i + s.m] = s.R
            i += s.m
        return R

    @property
    def angles(self) -> tuple[bool, ...]:
        return sum((s.angles for s in self.sensors), ())

    def h(self, p):
        """The stacked sensors' measurement function of the position (dim,) -> (m,)."""
        return jnp.concatenate([jnp.atleast_1d(s.h(p)) for s in self.sensors])


def sensor_model(sensor) -> SensorModel:
    """A sensor (built-in or custom) as a filter factory sees it."""
    R = np.asarray(sensor.R, float)
    return SensorModel(sensor.name, sensor.h, R, tuple(sensor.angle_mask), float(sensor.period or sensor.dt),
                       float(sensor.offset), float(sensor.p_detect))


def filter_context(scenario, seen, accel_sigma: float | None = None) -> FilterContext:
    """The context of a filter that sees the sensors ``seen`` (a sensor, a suite or a sequence) of
    ``scenario``; ``accel_sigma`` by default the scenario's (0 when its truth has none)."""
    sensors = seen.sensors if isinstance(seen, SensorSuite) else (seen,) if isinstance(seen, (Sensor, CustomSensor)) else seen
    if accel_sigma is None:
        accel_sigma = float(np.asarray(scenario.accel_sigma))
    return FilterContext(float(scenario.dt), int(scenario.steps), int(scenario.dim), cv(scenario.dim, scenario.dt),
                         float(accel_sigma), tuple(sensor_model(s) for s in sensors))


__all__ = ["FilterContext", "SensorModel", "filter_context", "sensor_model"]
