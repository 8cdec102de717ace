"""Kalman-family filters on Cartesian motion models (paper 000 §3.1, §3.3, §4.2).

* ``kf``            — linear Kalman filter (public: any F, H, Q, R).
* ``ekf``           — extended KF, Jacobians by autodiff (public: any f, h).
* ``cmkf``          — converted-measurement KF (plain / additive / unbiased).
* ``sequential_ekf``— paper 000 §4.2: angle innovations first, re-linearise at
  the intermediate estimate, then the range innovation.

Filters built for experiments (``model_*``) take parameters
``{"q": process-noise variance, "r": measurement-noise variances (m,)}``, so
noise levels can be swept and tuned; the public constructors take matrices.
The kinds an experiment file names (``KF``, ``EKF``, ``CMKF``, ``SEQUENTIAL_EKF``)
are declared at the end.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.checks import check_state_space
from tracklab.filters.blocks import Update, ekf_predict, ekf_update, kalman_filter, predict, update
from tracklab.filters.core import Filter
from tracklab.filters.kind import ANY_SENSOR, NOISE, Entry, FilterKind, noise, read_noise
from tracklab.sensors import CONVERSIONS


# --------------------------------------------------------------------------- public


def kf(F, H, Q, R) -> Filter:
    """Linear Kalman filter x' = F x + w, z = H x + v; params {F, H, Q, R}.

    Refused in one line naming the argument (``checks.check_state_space``): a matrix that is not
    numbers or not finite, F not (n, n), H not (m, n), Q not an (n, n) symmetric positive
    semi-definite matrix, R not an (m, m) symmetric positive definite one."""
    check_state_space("tracklab.filters.kf", F=F, H=H, Q=Q, R=R)
    params = {k: jnp.asarray(v) for k, v in dict(F=F, H=H, Q=Q, R=R).items()}

    def time_update(p, g):
        return predict(g, p["F"], p["Q"])

    def measurement_update(p, g, z, present):
        return update(g, z, p["H"], p["R"], present=present)

    return kalman_filter(params, time_update, measurement_update)


def ekf(f, h, Q, R, *, angle_mask=None, columns=None) -> Filter:
    """Extended Kalman filter for x' = f(x) + w, z = h(x) + v; params {Q, R}.

    Jacobians of f and h come from autodiff; innovation components flagged
    in ``angle_mask`` are wrapped to (-π, π]; ``columns``: the state components h reads, when
    it reads only some (``ekf_update``).

    Refused in one line naming the argument (``checks.check_state_space``): Q not an (n, n)
    finite symmetric positive semi-definite matrix, R not an (m, m) finite symmetric positive
    definite one, f or h not a function that traces on a state of n to (n,) and (m,),
    ``angle_mask`` not m flags, ``columns`` not increasing state components or leaving out one
    that h reads (∂h/∂x not zero outside them at three random states).
    """
    check_state_space("tracklab.filters.ekf", Q=Q, R=R, f=f, h=h, angle_mask=angle_mask, columns=columns)
    params = {"Q": jnp.asarray(Q), "R": jnp.asarray(R)}

    def time_update(p, g):
        return ekf_predict(g, f, p["Q"])

    def measurement_update(p, g, z, present):
        return ekf_update(g, z, h, p["R"], angles=angle_mask, present=present, columns=columns)

    return kalman_filter(params, time_update, measurement_update)


# ------------------------------------------------------------ experiment filters


def noise_params(q, r):
    return {"q": jnp.asarray(q, dtype=float), "r": jnp.asarray(r, dtype=float)}


def _model_predict(model):
    F = model.F  # NumPy: known when the filter is built inside a trace, so ``mm`` skips its zeros

    def time_update(p, g):
        return predict(g, F, model.Q(p["q"]))

    return time_update


def _h_state(model, sensor):
    pos = tuple(model.pos_idx)
    return lambda x: sensor.h(jnp.stack([x[i] for i in pos]))


def model_kf(model, sensor, params) -> Filter:
    """KF with linear sensors (each observes the frame's position; a suite stacks them)."""
    H = np.zeros((sensor.m, model.n))
    H[np.arange(sensor.m), np.array(model.pos_idx)[np.arange(sensor.m) % model.dim]] = 1.0

    def measurement_update(p, g, z, present):
        return update(g, z, H, jnp.diag(p["r"]), present=present)

    return kalman_filter(params, _model_predict(model), measurement_update)


def model_ekf(model, sensor, params) -> Filter:
    """EKF: H = ∂h/∂x at the prediction (paper 000 eq. 21); h reads the positions only, so only
    their columns of H are formed and used."""
    h = _h_state(model, sensor)

    def measurement_update(p, g, z, present):
        return ekf_update(g, z, h, jnp.diag(p["r"]), angles=sensor.angle_mask, present=present,
                          columns=model.pos_idx)

    return kalman_filter(params, _model_predict(model), measurement_update)


def model_cmkf(model, sensor, params, debias="plain") -> Filter:
    """Converted-measurement KF (paper 000 §3.1; docs/mathematics.md §4 variants)."""
    if debias == "additive" and sensor.m != 2:
        raise ValueError("the additive (Lerro & Bar-Shalom) conversion is 2-D only")
    convert = CONVERSIONS[debias]
    H = np.zeros((model.dim, model.n))
    H[np.arange(model.dim), np.array(model.pos_idx)] = 1.0

    def measurement_update(p, g, z, present):
        zc, Rc = convert(z, jnp.sqrt(p["r"]))
        used = jnp.broadcast_to(jnp.all(present), (model.dim,))  # a conversion needs every component
        return update(g, zc, H, Rc, present=used)

    return kalman_filter(params, _model_predict(model), measurement_update)


def model_sequential_ekf(model, sensor, params) -> Filter:
    """Sequential EKF (paper 000 §4.2, eqs. 31–34).

    Scalar EKF updates in the order angle(s) then range, each re-linearised at
    the estimate left by the previous one; an absent component is skipped. The innovations are reported in the
    sensor's component order with S = diag of the scalar innovation variances,
    so NIS is their sum (χ² with m degrees of freedom).
    """
    h = _h_state(model, sensor)
    m = sensor.m
    order = [i for i in range(m) if sensor.angle_mask[i]] + [i for i in range(m) if not sensor.angle_mask[i]]

    def measurement_update(p, g, z, present):
        nus, Ss = [None] * m, [None] * m
        for i in order:  # static loop over measurement components (m ≤ 5)
            hi = lambda s, i=i: h(s)[i]
            u = update(g, z[i][None], jax.grad(hi)(g.x)[None, :], p["r"][i][None, None], h_x=hi(g.x)[None],
                       angles=(sensor.angle_mask[i],), present=present[i][None])
            g = u.posterior
            nus[i], Ss[i] = u.nu[0], u.S[0, 0]
        return Update(g.x, g.P, jnp.stack(nus), jnp.diag(jnp.stack(Ss)), present)

    return kalman_filter(params, _model_predict(model), measurement_update)


# ------------------------------------------------------------------------- declarations


def _read_kf(e: Entry):
    if not e.meas.linear:
        raise e.error("kind", "kf", "needs linear sensors only (cartesian or mount): use ekf, ukf or stf")
    return read_noise(e)


def _read_cmkf(e: Entry):
    model = e.motion_model()
    debias = e.string("debias", "plain", choices=tuple(CONVERSIONS))
    if debias == "additive" and e.meas.kind != "polar":
        raise e.error("debias", debias, "the additive (Lerro) conversion is 2-D: use plain or unbiased with a spherical sensor")
    return model, noise(e, model), {"debias": debias}


KF = FilterKind(
    name="kf", doc="linear Kalman filter (needs a linear 'cartesian' or 'mount' sensor)",
    accepts=("cartesian", "mount", "suite"), params=NOISE, read=_read_kf,
    build=lambda model, sensor, params, options: model_kf(model, sensor, params))
EKF = FilterKind(
    name="ekf", doc="extended Kalman filter, Jacobians by autodiff", accepts=ANY_SENSOR, params=NOISE,
    read=read_noise, build=lambda model, sensor, params, options: model_ekf(model, sensor, params))
CMKF = FilterKind(
    name="cmkf", doc="converted-measurement KF; debias = plain | additive | unbiased", accepts=("polar", "spherical"),
    params=NOISE, read=_read_cmkf,
    build=lambda model, sensor, params, options: model_cmkf(model, sensor, params, options.get("debias", "plain")))
SEQUENTIAL_EKF = FilterKind(
    name="sequential_ekf", doc="sequential EKF: angles first, re-linearise, then range",
    accepts=("polar", "spherical", "angles", "custom", "suite"), params=NOISE, read=read_noise,
    build=lambda model, sensor, params, options: model_sequential_ekf(model, sensor, params))
