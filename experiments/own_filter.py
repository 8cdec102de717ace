"""A filter of one's own for experiments/own_filter.toml (kind = "own_filter:converted_kf").

A converted-measurement Kalman filter written from scratch with jax.numpy, on the state
[x, y, ẋ, ẏ] (not tracklab's interleaved layout): the range-bearing measurement is turned
into a Cartesian position with the covariance J R Jᵀ linearised at the measurement (Zhang
Yujun et al., "Study on high accuracy tracking target in lidar", eq. 12), and the update is
in Joseph form. Its maths is the built-in ``cmkf``'s; the README's "Your own filter"
shows it run from Python and tuned.
"""

import jax.numpy as jnp
import numpy as np

from tracklab import Filter, Layout, Out


def converted_kf(context, accel_var=None, r=None):
    """A CMKF for one 2-D range-bearing sensor; params {"accel_var", "r"} (default: the
    scenario's σ_a² and the sensor's variances)."""
    if context.dim != 2 or context.m != 2:
        raise ValueError("converted_kf needs a 2-D scenario and one range-bearing sensor (r, bearing)")
    dt = context.dt
    params = {"accel_var": jnp.asarray(context.accel_sigma**2 if accel_var is None else accel_var, float),
              "r": jnp.asarray(np.diag(context.R) if r is None else r, float)}
    F = jnp.array([[1.0, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])
    G = jnp.array([[dt**2 / 2, 0], [0, dt**2 / 2], [dt, 0], [0, dt]])
    H = jnp.eye(2, 4)

    def init(params, prior):  # the prior arrives in this filter's layout
        return prior.x, prior.P

    def step(params, state, meas):
        x, P = state
        x_pred = F @ x
        P_pred = F @ P @ F.T + params["accel_var"] * G @ G.T
        have = meas.valid & jnp.all(jnp.isfinite(meas.z))
        rng, brg = jnp.where(have, meas.z, jnp.array([1.0, 0.0]))
        J = jnp.array([[jnp.cos(brg), -rng * jnp.sin(brg)], [jnp.sin(brg), rng * jnp.cos(brg)]])
        Rc = J @ jnp.diag(params["r"]) @ J.T
        nu = jnp.array([rng * jnp.cos(brg), rng * jnp.sin(brg)]) - H @ x_pred
        S = H @ P_pred @ H.T + Rc
        K = jnp.linalg.solve(S, H @ P_pred).T  # P Hᵀ S⁻¹ (S and P symmetric)
        A = jnp.eye(4) - K @ H
        x_new = jnp.where(have, x_pred + K @ nu, x_pred)
        P_new = jnp.where(have, A @ P_pred @ A.T + K @ Rc @ K.T, P_pred)
        out = Out(x=x_new, P=P_new, x_pred=x_pred, nu=jnp.where(have, nu, 0.0), S=S, valid=have,
                  dof=jnp.where(have, 2, 0))
        return (x_new, P_new), out

    return Filter(init, step, params, layout=Layout(n=4, pos_idx=(0, 1), vel_idx=(2, 3)))
