"""Error-space estimation for synergic targets (paper 004, Cen Ming et al., §2.3).

The target's observation Z is split into guide data L and guide error
e = Z − L̂ (eqs. 10, 13). Two Kalman filters run together:

* the guide-data filter: the target's motion model (eqs. 5–6) with L as its
  observation, giving the filtered L̂(k+1) (step 4; filtered, never predicted);
* the guide-error filter: its own model (eqs. 11–12) with e(k) as observation,
  giving the prediction ê(k+1, k) (step 3);

and the synthesis Ẑ(k+1, k) = L̂(k+1) + ê(k+1, k) (eq. 14, step 5) is the
one-step prediction that drives the instrument.

Guide data:

* ``"previous"`` (the paper's "equivalent synergic target", eq. 3):
  L(k+1) = Z(k), the instrument's own previous observation;
* an external stream: a second sensor of the experiment, L(k+1) = Z_g(k − d)
  (its reading d ≥ 0 periods old), e.g. a search radar handing over a noisier,
  later track.

Per step k, with L̂(k) and ê(k−1|k−1) carried from step k−1:

    Ẑ(k, k−1) = H L̂(k) + H F_e ê(k−1|k−1)           reported as the prediction
    e(k) = Z(k) − H L̂(k)                             (13)
    ê(k|k) = KF update of F_e ê(k−1|k−1) with e(k)
    L̂(k+1) = KF update of F L̂(k) with L(k+1)
    x̂(k|k) = L̂(k) + ê(k|k)                          reported estimate

Both filters work in the sensor's own (linear) coordinates: Cartesian
positions, or a mount's azimuth and elevation. As the guide error of a
guide delayed by n periods is e(t) = Z(t) − Z(t − nT), the error filter's state
[e, ė, ë] adds to the guide's state, which is how the estimate and its rate are
reported. Reported covariance: P_L + P_e (the two errors are correlated, which
the method ignores, so NEES/NIS of this filter are indicative only). Priors:
L̂ = F^{−(n−1)} x̂₀ and ê = (I − F^{−n}) x̂₀ from the experiment's prior, each
with the prior covariance P₀ (conservative). Parameters {q, r, q_e, r_e,
r_guide}: process and observation noise of the guide-data and the guide-error
filters, and the guide's observation noise.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, predict, update
from tracklab.filters.core import Filter, Out
from tracklab.filters.kind import NOISE, Entry, FilterKind, noise
from tracklab.parameters import Param, positive
from tracklab.linalg import mm


class ErrorSpaceState(NamedTuple):
    L: Gaussian  # guide-data filter: L̂(k), the estimate of the guide at the coming step
    E: Gaussian  # guide-error filter: ê(k−1|k−1)
    queue: jax.Array  # (d, m) guide readings not yet due (oldest first)


def model_error_space(model, m: int, params, guide: str = "previous", delay: int = 0) -> Filter:
    """Error-space estimator on a kinematic model observing its m position components.

    The measurement the filter sees is Z (m values), or [Z, Z_g] (2m values)
    with an external guide. ``delay``: how many periods older than the
    one-period hand-over the external guide's readings are.
    """
    if model.dim != m:
        raise ValueError(f"error_space needs a sensor observing the {model.dim} position components directly")
    if guide == "previous" and delay:
        raise ValueError("a delay applies to an external guide only")
    n_lag = 1 + int(delay)  # L(k) is the target n_lag periods earlier
    # the model's matrices in NumPy: known when built inside a trace (``mm`` skips their zeros)
    F = model.F
    H = np.zeros((m, model.n))
    H[np.arange(m), np.array(model.pos_idx)] = 1.0
    F_inv = np.linalg.inv(model.F)
    L_map = np.linalg.matrix_power(F_inv, n_lag - 1)
    E_map = np.eye(model.n) - np.linalg.matrix_power(F_inv, n_lag)

    def init(p, prior):
        x0, P0 = jnp.asarray(prior.x), jnp.asarray(prior.P)
        queue = jnp.full((int(delay), m), jnp.nan, x0.dtype)
        return ErrorSpaceState(Gaussian(mm(L_map, x0), P0), Gaussian(mm(E_map, x0), P0), queue)

    def step(p, s, meas):
        raw = jnp.where(meas.valid, meas.z, jnp.nan)
        z = raw[:m]
        present = jnp.isfinite(z)
        zm = jnp.where(present, z, 0.0)

        # guide-error filter (steps 2-3): e(k) = Z(k) − L̂(k), eq. (13)
        E_pred = predict(s.E, F, model.Q(p["q_e"]))
        x_pred = s.L.x + E_pred.x  # Ẑ(k, k−1) of eq. (14), made at step k−1
        # ν = Z(k) − H Ẑ(k, k−1) = e(k) − H ê(k|k−1)
        E = update(E_pred, zm, H, jnp.diag(p["r_e"]), h_x=mm(H, x_pred), present=present)

        # guide-data filter (step 4): L(k+1), filtered
        g_now = z if guide == "previous" else raw[m:2 * m]
        if delay:
            g, queue = s.queue[0], jnp.concatenate([s.queue[1:], g_now[None]])
        else:
            g, queue = g_now, s.queue
        g_present = jnp.isfinite(g)
        L_pred = predict(s.L, F, model.Q(p["q"]))
        r_guide = p["r"] if guide == "previous" else p["r_guide"]
        L = update(L_pred, jnp.where(g_present, g, 0.0), H, jnp.diag(r_guide), present=g_present)
        out = Out(x=s.L.x + E.x, P=s.L.P + E.P, x_pred=x_pred, nu=E.nu, S=E.S,
                  valid=jnp.any(present), dof=jnp.sum(present))
        return ErrorSpaceState(L.posterior, E.posterior, queue), out

    return Filter(init=init, step=step, params=params)


# ------------------------------------------------------------------------- declarations


def _read(e: Entry):
    """q_e, r_e; with a guide sensor r_guide and guide_delay; q and r as every kind."""
    model = e.motion_model()
    params = noise(e, model)
    params["q_e"] = e.number("q_e", params["q"], positive=True)
    params["r_e"] = e.sigmas("r_e", e.meas.m, required=False) or params["r"]
    options = {}
    if e.guide is not None:
        r_g = e.sigmas("r_guide", e.meas.m, required=False)
        params["r_guide"] = tuple(v**2 for v in e.guide.sigma) if r_g is None else r_g
        options["guide_delay"] = e.integer("guide_delay", 0, lo=0, hi=10_000)
    elif e.has("guide_delay"):
        raise e.error("guide_delay", e.get("guide_delay"), "applies to an external guide sensor only")
    return model, params, options


def _build(model, sensor, params, options):
    guide = options.get("guide", "previous")
    m = sensor.m if guide == "previous" else sensor.m // 2
    return model_error_space(model, m, params, "previous" if guide == "previous" else "external",
                             options.get("guide_delay", 0))


ERROR_SPACE = FilterKind(
    name="error_space", doc="error-space estimator (paper 004): guide-data and guide-error KFs; guide = previous | a sensor",
    accepts=("cartesian", "mount"), guided=True,
    params={**NOISE,
            "q_e": Param("guide-error process noise; default q", positive, "(m/s²)²", tune=True, sweep=True),
            "r_e": Param("guide-error observation noise; default r", positive, "sensor units²", tune=True, sweep=True),
            "r_guide": Param("guide sensor's observation noise; default its sigmas²", positive, "sensor units²",
                             tune=True, sweep=True)},
    read=_read, build=_build)
