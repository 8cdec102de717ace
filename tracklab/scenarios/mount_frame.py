"""The truth as an alt-azimuth mount at the origin sees it (angle tracking, paper 004).

Wraps any 3-D scenario (east, north, up; m) and turns its truth into the mount
frame [az, ȧz, el, ėl] in degrees and degrees per second, with azimuth
measured clockwise from north, az = atan2(x, y), elevation
el = atan2(z, √(x² + y²)). Azimuth is unwrapped along the pass, as a mount's
axis encoder reads it. Rates are exact: the derivative of the angles along the
truth's velocity (a Jacobian-vector product), not finite differences.

Filters of an angle-tracking experiment work in this frame: their "positions"
are the two angles, so every error statistic is in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from tracklab.scenarios.kind import Scenario


def mount_angles(p):
    """[az, el] in radians of a position (east, north, up)."""
    x, y, z = p[0], p[1], p[2]
    return jnp.stack([jnp.arctan2(x, y), jnp.arctan2(z, jnp.hypot(x, y))])


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class MountFrame(Scenario):
    scenario: Any  # a 3-D scenario: simulate(key) -> (steps + 1, 6) in CV layout

    dim = 2
    axes = ("az", "el")
    units = ("deg", "deg/s")
    gaussian = False

    @property
    def per_run(self):
        return self.scenario.per_run

    @property
    def accel_sigma(self):
        return self.scenario.accel_sigma  # the 3-D truth's (m/s²)

    @property
    def dt(self):
        return self.scenario.dt

    @property
    def steps(self):
        return self.scenario.steps

    def linear_gaussian(self):
        return None

    def simulate(self, key):
        s = self.scenario.simulate(key)
        pos, vel = s[:, 0::2], s[:, 1::2]
        ang, rate = jax.vmap(lambda p, v: jax.jvp(mount_angles, (p,), (v,)))(pos, vel)
        az = jnp.unwrap(ang[:, 0])
        return jnp.degrees(jnp.stack([az, rate[:, 0], ang[:, 1], rate[:, 1]], axis=-1))
