"""Straight-line crossing target (paper 000 §5).

The target starts at (start_x, offset[, altitude]) with velocity (speed, 0[, 0])
one sample period before the first measurement and moves as a constant-velocity
target driven by discrete white acceleration of std ``accel_sigma`` per axis
(paper 000 eqs. 1–4). The paper's case: 400 m/s, crossing distance 20 km, from
x = −20 km to +20 km, T = 0.5 s, σ_a = 1 m/s².
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.models import cv


@dataclass(frozen=True)
class Crossing:
    dt: float
    steps: int
    speed: float = 400.0
    offset: float = 20000.0
    start_x: float = -20000.0
    accel_sigma: float = 1.0
    altitude: float | None = None  # set for a 3-D crossing at constant height

    @property
    def dim(self) -> int:
        return 2 if self.altitude is None else 3

    @property
    def model(self):
        return cv(self.dim, self.dt)

    def initial_state(self) -> np.ndarray:
        s = [self.start_x, self.speed, self.offset, 0.0]
        if self.dim == 3:
            s += [self.altitude, 0.0]
        return np.array(s)

    def linear_gaussian(self):
        """(F, Q) of the truth's dynamics, for the PCRLB."""
        m = self.model
        return m.F, np.asarray(m.Q(self.accel_sigma**2))

    def simulate(self, key):
        """Truth states (steps + 1, 2·dim) in CV layout; row 0 is the prior epoch."""
        m = self.model
        F, G = jnp.asarray(m.F), jnp.asarray(m.G)
        s0 = jnp.asarray(self.initial_state())
        w = self.accel_sigma * jax.random.normal(key, (self.steps, self.dim), s0.dtype)

        def advance(s, wk):
            s = F @ s + G @ wk
            return s, s

        _, path = jax.lax.scan(advance, s0, w)
        return jnp.concatenate([s0[None], path])
