"""One angle following θ(t) = A sin(ωt + φ) (paper 003's equivalent sine target, 83.33° sin 0.6t).

A 1-D truth in CV layout [θ, θ̇] (degrees, degrees per second), the same in every
run; the measurement noise and the prior make the runs differ.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from tracklab.parameters import Param, free, positive
from tracklab.pytree import static
from tracklab.scenarios.kind import Scenario, ScenarioKind


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Sine(Scenario):
    dt: float = static()
    steps: int = static()
    amplitude: float = 83.33
    omega: float = 0.6
    phase: float = 0.0  # rad

    dim = 1
    per_run = False  # the same truth in every run
    gaussian = False
    axes = ("angle",)
    units = ("deg", "deg/s")

    def truth(self):
        t = self.dt * jnp.arange(self.steps + 1)
        arg = self.omega * t + self.phase
        return jnp.stack([self.amplitude * jnp.sin(arg), self.amplitude * self.omega * jnp.cos(arg)], -1)

    def linear_gaussian(self):
        return None

    def simulate(self, key):
        return self.truth()


SINE = ScenarioKind(
    "sine", "one angle, A sin(omega t + phase) (paper 003's equivalent target)",
    {"amplitude": Param("A", positive, "deg", 83.33), "omega": Param("ω", positive, "rad/s", 0.6),
     "phase": Param("φ", free, "rad", 0.0)},
    lambda context, n, fields: Sine(dt=context.dt, steps=context.steps, **n))
