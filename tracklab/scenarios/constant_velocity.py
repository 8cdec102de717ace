"""Constant-velocity truth driven by discrete white acceleration (any dimension).

The state, in CV layout [x, ẋ, (y, ẏ, (z, ż))], starts at ``initial`` one sample
period before the first measurement and moves as x_{k+1} = F x_k + G w_k with
w_k ~ N(0, accel_sigma² I) (paper 000 eqs. 1–4; paper 002 eqs. 14–18).

``crossing`` is the straight pass of paper 000 §5: start (start_x, offset[,
altitude]) with velocity (speed, 0[, 0]) — 400 m/s, crossing distance 20 km,
x from −20 km to +20 km, T = 0.5 s, σ_a = 1 m/s² in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tracklab import random
from tracklab.linalg import mm
from tracklab.models import cv
from tracklab.parameters import Param, free, nonnegative
from tracklab.pytree import static
from tracklab.scenarios.kind import Scenario, ScenarioKind, numbers


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class ConstantVelocity(Scenario):
    dt: float = static()
    steps: int = static()
    initial: tuple = ()  # CV layout, 2·dim values
    accel_sigma: float = 0.0

    gaussian = True  # a linear-Gaussian motion model: the PCRLB applies

    @property
    def dim(self) -> int:
        return len(self.initial) // 2

    @property
    def model(self):
        return cv(self.dim, self.dt)

    def initial_state(self):
        return jnp.stack([jnp.asarray(v) for v in self.initial])

    def linear_gaussian(self):
        """(F, Q) of the truth's dynamics, for the PCRLB."""
        m = self.model
        return m.F, np.asarray(m.Q(self.accel_sigma**2))

    per_run = True  # every run draws its own truth

    def draws(self, key):
        """One run's standard-normal accelerations (steps, dim), float32."""
        return random.normal(key, (self.steps, self.dim))

    def advance(self, s, w):
        """The truth one step after ``s`` given that step's standard-normal draws ``w`` (dim,)."""
        m = self.model
        return mm(np.asarray(m.F), s) + mm(np.asarray(m.G), self.accel_sigma * w.astype(s.dtype))

    def simulate(self, key):
        """Truth states (steps + 1, 2·dim) in CV layout; row 0 is the prior epoch."""
        s0 = jnp.asarray(self.initial_state())

        def advance(s, w):
            s = self.advance(s, w)
            return s, s

        _, path = jax.lax.scan(advance, s0, self.draws(key))
        return jnp.concatenate([s0[None], path])


def Crossing(dt, steps, speed=400.0, offset=20000.0, start_x=-20000.0, accel_sigma=1.0, altitude=None):
    """The straight crossing pass of paper 000 §5 (3-D at constant ``altitude`` if given)."""
    initial = (start_x, speed, offset, 0.0) + (() if altitude is None else (altitude, 0.0))
    return ConstantVelocity(dt=dt, steps=steps, initial=tuple(float(v) for v in initial), accel_sigma=accel_sigma)


def _crossing(context, n, fields):
    return Crossing(context.dt, context.steps, n["speed"], n["offset"], n["start_x"], n["accel_sigma"],
                    fields.number("altitude", None))


def _constant_velocity(context, n, fields):
    init = numbers(fields.get("initial"), (2, 4, 6))
    if init is None:
        raise fields.error("initial", fields.get("initial"), "must be 2, 4 or 6 finite numbers [x, vx(, y, vy(, z, vz))]")
    return ConstantVelocity(dt=context.dt, steps=context.steps, initial=init, accel_sigma=n["accel_sigma"])


CROSSING = ScenarioKind(
    "crossing", "straight crossing pass, CV with white acceleration (paper 000); altitude (m) makes it 3-D",
    {"speed": Param("speed along x", free, "m/s", 400.0), "offset": Param("crossing distance (y)", free, "m", 20000.0),
     "start_x": Param("x one period before the first measurement", free, "m", -20000.0),
     "accel_sigma": Param("white acceleration noise", nonnegative, "m/s²", 1.0)}, _crossing)
CONSTANT_VELOCITY = ScenarioKind(
    "constant_velocity", "CV with white acceleration from initial = [x, vx(, y, vy(, z, vz))], 1-3 D (paper 002 §3)",
    {"accel_sigma": Param("white acceleration noise", nonnegative, "m/s²", 0.0)}, _constant_velocity)
