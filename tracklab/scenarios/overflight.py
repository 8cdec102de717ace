"""A straight, level pass over an observation site (paper 004's scenario, our geometry).

The target flies at constant ``speed`` and ``altitude`` on a heading (degrees
clockwise from north) whose ground track passes the site at the horizontal
distance d = altitude / tan(max_elevation), so that the elevation seen from the
site peaks at ``max_elevation`` at t = ``t_closest``. Paper 004 reports only
"maximum elevation 74.947°, strong manoeuvre between 60 and 90 s" of its real
target; 8 km, 250 m/s and t = 75 s of a 150 s pass are our choice.
The truth, in CV layout [x, ẋ, y, ẏ, z, ż] (east, north, up; m), is the same
in every Monte-Carlo run.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from tracklab.parameters import Param, bounded, free, positive
from tracklab.pytree import static
from tracklab.scenarios.kind import Scenario, ScenarioKind


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Overflight(Scenario):
    dt: float = static()
    steps: int = static()
    altitude: float = 8000.0
    speed: float = 250.0
    max_elevation: float = 74.947  # degrees
    t_closest: float = 75.0  # s after the prior epoch t = 0
    heading: float = 90.0  # degrees clockwise from north

    dim = 3
    per_run = False  # the same truth in every run
    gaussian = False

    def truth(self):
        h = jnp.radians(self.heading)
        u = jnp.stack([jnp.sin(h), jnp.cos(h)])  # direction of flight (east, north)
        d = self.altitude / jnp.tan(jnp.radians(self.max_elevation))
        c = d * jnp.stack([-u[1], u[0]])  # closest point of the ground track, left of the track
        t = self.dt * jnp.arange(self.steps + 1) - self.t_closest
        xy = c[None, :] + self.speed * t[:, None] * u[None, :]
        one = jnp.ones_like(t)
        return jnp.stack([xy[:, 0], self.speed * u[0] * one, xy[:, 1], self.speed * u[1] * one, self.altitude * one,
                          0.0 * one], axis=-1)

    def linear_gaussian(self):
        return None

    def simulate(self, key):
        return self.truth()


OVERFLIGHT = ScenarioKind(
    "overflight", "straight level pass over the site (paper 004)",
    {"altitude": Param("flight altitude", positive, "m", 8000.0), "speed": Param("ground speed", positive, "m/s", 250.0),
     "max_elevation": Param("elevation at the closest point", bounded(0.0, 90.0), "deg", 74.947),
     "t_closest": Param("time of the closest point after the prior epoch", free, "s", 75.0),
     "heading": Param("track, clockwise from north", free, "deg", 90.0)},
    lambda context, n, fields: Overflight(dt=context.dt, steps=context.steps, **n))
