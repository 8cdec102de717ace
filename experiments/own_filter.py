"""A filter of one's own for experiments/own_filter.toml (kind = "own_filter:converted_kf").

A converted-measurement Kalman filter on the state [x, y, ẋ, ẏ] (not tracklab's interleaved
layout), written with tracklab's building blocks: the range-bearing measurement is turned
into a Cartesian position with the covariance J R Jᵀ linearised at the measurement (Zhang
Yujun et al., "Study on high accuracy tracking target in lidar", eq. 12), then ``update``
does the rest (Joseph form). Its two numbers are declared (``tracklab.declare``): they arrive
in ``params``, and ``tracklab tune --params accel_var`` and ``tracklab sweep --grid
"filter[CMKF (own code)].accel_var=…"`` name them. Its maths is the built-in ``cmkf``'s; the
documentation's "Your own filter" (docs/own-filter.md) shows it run from Python and tuned.
"""

import jax.numpy as jnp
import numpy as np

import tracklab
from tracklab import Layout, Param
from tracklab.filters import kalman_filter, predict, update


@tracklab.declare(  # its numbers: inputs of the compiled program, tuned and swept by name
    accel_var=Param(doc="acceleration noise variance", unit="(m/s²)²", constraint="positive",
                    default=lambda context: context.accel_sigma**2),
    r=Param(doc="range and bearing noise variances", unit="m², rad²", constraint="positive",
            default=lambda context: np.diag(context.R)))
def converted_kf(context):
    """A CMKF for one 2-D range-bearing sensor; params {"accel_var", "r"} (default: the
    scenario's σ_a² and the sensor's variances)."""
    if context.dim != 2 or context.m != 2:
        raise ValueError("converted_kf needs a 2-D scenario and one range-bearing sensor (r, bearing)")
    dt = context.dt
    F = jnp.array([[1.0, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])
    G = jnp.array([[dt**2 / 2, 0], [0, dt**2 / 2], [dt, 0], [0, dt]])
    H = jnp.eye(2, 4)

    def time_update(params, g):  # g: Gaussian(x, P)
        return predict(g, F, params["accel_var"] * G @ G.T)

    def measurement_update(params, g, z, present):  # z = (range, bearing), an absent component 0
        rng, brg = z
        J = jnp.array([[jnp.cos(brg), -rng * jnp.sin(brg)], [jnp.sin(brg), rng * jnp.cos(brg)]])
        pos = jnp.array([rng * jnp.cos(brg), rng * jnp.sin(brg)])
        both = jnp.full(2, jnp.all(present))  # the conversion needs range and bearing
        return update(g, pos, H, J @ jnp.diag(params["r"]) @ J.T, present=both)

    return kalman_filter({}, time_update, measurement_update, layout=Layout(n=4, pos_idx=(0, 1), vel_idx=(2, 3)))
