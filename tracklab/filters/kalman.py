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

from tracklab.filters.core import (
    Filter,
    Gaussian,
    Out,
    masked_kalman_update,
    masked_meas,
    select,
    symmetrise,
    wrap_components,
)
from tracklab.filters.kind import ANY_SENSOR, NOISE, Entry, FilterKind, noise, read_noise
from tracklab.linalg import jacobian, mm
from tracklab.sensors import CONVERSIONS


def gaussian_filter(params, predict, update, report=None, init=None) -> Filter:
    """Assemble a Filter from predict/update halves.

    predict(params, g) -> g⁻;  update(params, g⁻, z, present) -> (g⁺, ν, S, used)
    where ``present`` flags the measurement components that are there (NaN
    components, a missed detection or a sensor with no report, are absent) and
    ``used`` the innovation components the update used;
    report(g) -> (x, P) in the reporting frame (identity by default);
    init(params, prior) -> g (the prior as a Gaussian by default).
    A step with no component used keeps the prediction.
    """
    report = report or (lambda g: (g.x, g.P))
    init = init or (lambda params, prior: Gaussian(jnp.asarray(prior.x), jnp.asarray(prior.P)))

    def step(params, g, meas):
        z, present = masked_meas(meas)
        pred = predict(params, g)
        post, nu, S, used = update(params, pred, z, present)
        valid = jnp.any(used)
        post = select(valid, post, pred)
        x, P = report(post)
        x_pred, _ = report(pred)
        dof = jnp.sum(used)
        return post, Out(x=x, P=P, x_pred=x_pred, nu=jnp.where(used, nu, 0.0), S=S, valid=valid, dof=dof)

    def coast(params, g, meas):
        pred = predict(params, g)
        x, P = report(pred)
        _, nu, S, used = jax.eval_shape(update, params, pred, *masked_meas(meas))
        none = jnp.zeros(used.shape, bool)
        return pred, Out(x=x, P=P, x_pred=x, nu=jnp.zeros(nu.shape, nu.dtype), S=jnp.eye(S.shape[-1], dtype=S.dtype),
                         valid=jnp.any(none), dof=jnp.sum(none))

    return Filter(init=init, step=step, params=params, coast=coast)


def _linear_predict(F, Q, g):
    return Gaussian(mm(F, g.x), symmetrise(mm(mm(F, g.P), F.T) + Q))


# --------------------------------------------------------------------------- public


def kf(F, H, Q, R) -> Filter:
    """Linear Kalman filter x' = F x + w, z = H x + v; params {F, H, Q, R}."""
    params = {k: jnp.asarray(v) for k, v in dict(F=F, H=H, Q=Q, R=R).items()}

    def predict(p, g):
        return _linear_predict(p["F"], p["Q"], g)

    def update(p, g, z, present):
        nu = z - mm(p["H"], g.x)
        x, P, nu, S = masked_kalman_update(g.x, g.P, nu, p["H"], p["R"], present)
        return Gaussian(x, P), nu, S, present

    return gaussian_filter(params, predict, update)


def ekf(f, h, Q, R, *, angle_mask=None) -> Filter:
    """Extended Kalman filter for x' = f(x) + w, z = h(x) + v; params {Q, R}.

    Jacobians of f and h come from ``jax.jacfwd``; innovation components flagged
    in ``angle_mask`` are wrapped to (-π, π].
    """
    params = {"Q": jnp.asarray(Q), "R": jnp.asarray(R)}

    def predict(p, g):
        F = jacobian(f, g.x)
        return Gaussian(f(g.x), symmetrise(mm(mm(F, g.P), F.T) + p["Q"]))

    def update(p, g, z, present):
        H = jacobian(h, g.x)
        nu = wrap_components(z - h(g.x), angle_mask)
        x, P, nu, S = masked_kalman_update(g.x, g.P, nu, H, p["R"], present)
        return Gaussian(x, P), nu, S, present

    return gaussian_filter(params, predict, update)


# ------------------------------------------------------------ experiment filters


def noise_params(q, r):
    return {"q": jnp.asarray(q, dtype=float), "r": jnp.asarray(r, dtype=float)}


def _model_predict(model):
    F = jnp.asarray(model.F)

    def predict(p, g):
        return _linear_predict(F, model.Q(p["q"]), g)

    return predict


def _h_state(model, sensor):
    pos = tuple(model.pos_idx)
    return lambda x: sensor.h(jnp.stack([x[i] for i in pos]))


def model_kf(model, sensor, params) -> Filter:
    """KF with linear sensors (each observes the frame's position; a suite stacks them)."""
    H = np.zeros((sensor.m, model.n))
    H[np.arange(sensor.m), np.array(model.pos_idx)[np.arange(sensor.m) % model.dim]] = 1.0
    H = jnp.asarray(H)

    def update(p, g, z, present):
        nu = z - mm(H, g.x)
        x, P, nu, S = masked_kalman_update(g.x, g.P, nu, H, jnp.diag(p["r"]), present)
        return Gaussian(x, P), nu, S, present

    return gaussian_filter(params, _model_predict(model), update)


def model_ekf(model, sensor, params) -> Filter:
    """EKF: H = ∂h/∂x at the prediction (paper 000 eq. 21)."""
    h = _h_state(model, sensor)

    def update(p, g, z, present):
        H = jacobian(h, g.x)
        nu = wrap_components(z - h(g.x), sensor.angle_mask)
        x, P, nu, S = masked_kalman_update(g.x, g.P, nu, H, jnp.diag(p["r"]), present)
        return Gaussian(x, P), nu, S, present

    return gaussian_filter(params, _model_predict(model), update)


def model_cmkf(model, sensor, params, debias="plain") -> Filter:
    """Converted-measurement KF (paper 000 §3.1; REFERENCE_MATH §4 variants)."""
    if debias == "additive" and sensor.m != 2:
        raise ValueError("the additive (Lerro & Bar-Shalom) conversion is 2-D only")
    convert = CONVERSIONS[debias]
    H = np.zeros((model.dim, model.n))
    H[np.arange(model.dim), np.array(model.pos_idx)] = 1.0
    H = jnp.asarray(H)

    def update(p, g, z, present):
        zc, Rc = convert(z, jnp.sqrt(p["r"]))
        used = jnp.broadcast_to(jnp.all(present), (model.dim,))  # a conversion needs every component
        x, P, nu, S = masked_kalman_update(g.x, g.P, zc - mm(H, g.x), H, Rc, used)
        return Gaussian(x, P), nu, S, used

    return gaussian_filter(params, _model_predict(model), update)


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

    def update(p, g, z, present):
        x, P = g.x, g.P
        nus, Ss = [None] * m, [None] * m
        for i in order:  # static loop over measurement components (m ≤ 5)
            hi = lambda s, i=i: h(s)[i]
            Hi = jax.grad(hi)(x)[None, :]
            nu_i = z[i] - hi(x)
            if sensor.angle_mask[i]:
                nu_i = wrap_components(nu_i[None], (True,))[0]
            x, P, nu_i, S_i = masked_kalman_update(x, P, nu_i[None], Hi, p["r"][i][None, None], present[i][None])
            nus[i], Ss[i] = nu_i[0], S_i[0, 0]
        return Gaussian(x, P), jnp.stack(nus), jnp.diag(jnp.stack(Ss)), present

    return gaussian_filter(params, _model_predict(model), update)


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
