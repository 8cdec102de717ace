"""Dual extended Kalman filter with a neural motion model (paper 003, Yang Hongtao et al., eqs. 4–15).

Motion model (eq. 4): a single-hidden-layer network on the state x = [θ, θ̇, θ̈],

    u = x / s                     (input scaling: s = typical angle, rate, acceleration)
    h = tanh(W₁ u + b₁)           (``hidden`` units, 4 in the paper)
    F(x, w) = s ⊙ (W₂ h + b₂)                 reading "literal": the network outputs x_{k+1}
    F(x, w) = Φ_CA x + T s ⊙ (W₂ h + b₂)      reading "residual": it corrects the CA prediction

with w = [vec W₁, b₁, vec W₂, b₂] and T the sample period (the residual is a
correction per step, so its scale is s·T). Both readings are faithful to the
paper's text. The residual one starts as the CA model exactly (W₂ = 0, b₂ = 0;
W₁, b₁ random); the literal one starts near it through the linear part of tanh
(tiny first-layer weights, large second-layer ones), which leaves it
ill-conditioned: a 10⁻³ relative model error on an 80° angle is already 0.3′
per step.

Two EKFs run together in one step (our reading of the garbled eqs. 6–15, the
classical dual EKF of Wan & Nelson):

* weights, a random walk with forgetting: ŵ⁻ = ŵ, P_w⁻ = P_w / λ, λ ∈ (0, 1];
* state: x⁻ = F(x̂, ŵ⁻), A = ∂F/∂x at (x̂, ŵ⁻), P⁻ = A P Aᵀ + Q;
* one innovation for both, ν = y − C x⁻ (C = [1, 0, 0], θ measured);
* state update: K = P⁻Cᵀ(C P⁻ Cᵀ + R)⁻¹, x̂ = x⁻ + Kν, P = (I − KC)P⁻ (Joseph form);
* weight update (eqs. 13–15): C_w = C ∂F(x̂, w)/∂w at ŵ⁻ (x̂ held fixed: the
  "static" derivative), K_w = P_w⁻ C_wᵀ (C_w P_w⁻ C_wᵀ + Rᵉ)⁻¹, ŵ = ŵ⁻ + K_w ν,
  P_w = (I − K_w C_w) P_w⁻, with Rᵉ = 0.5 by default.

A step with no measurement predicts the state and inflates P_w only. Parameters
{q (state noise: variance of the acceleration increment, the CA model's DWPA),
r, forget (λ), r_e, w0 (initial weights), pw0 (initial weight variance)} are a pytree: λ
and the initial weights can be trained by gradient through whole Monte-Carlo runs. An
experiment filter (kind ``dekf``) also carries the network's scaling s there (``scale``),
an input of the compiled program like every number of its file.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, innovation_update, predict
from tracklab.filters.core import Filter, Out, masked_meas
from tracklab.filters.kind import MEASUREMENT_NOISE, PROCESS_NOISE, Entry, FilterKind, noise
from tracklab.parameters import Param, free, positive, unit_interval
from tracklab.linalg import mm


class Network(NamedTuple):
    """Static shape and scaling of the motion network."""

    hidden: int
    scale: tuple[float, float, float]  # typical |θ|, |θ̇|, |θ̈| (input and output scaling)
    dt: float
    residual: bool

    @property
    def n_weights(self) -> int:
        return 3 * self.hidden + self.hidden + self.hidden * 3 + 3

    def unpack(self, w):
        k = self.hidden
        W1 = w[: 3 * k].reshape(k, 3)
        b1 = w[3 * k: 4 * k]
        W2 = w[4 * k: 7 * k].reshape(3, k)
        b2 = w[7 * k: 7 * k + 3]
        return W1, b1, W2, b2

    def phi(self):
        T = self.dt
        return jnp.array([[1.0, T, T * T / 2], [0.0, 1.0, T], [0.0, 0.0, 1.0]])

    def __call__(self, x, w):
        """F(x, w): the next state."""
        W1, b1, W2, b2 = self.unpack(w)
        s = jnp.asarray(self.scale, x.dtype)
        h = jnp.tanh(W1 @ (x / s) + b1)
        if self.residual:
            return mm(self.phi().astype(x.dtype), x) + self.dt * s * (W2 @ h + b2)
        return s * (W2 @ h + b2)


def initial_weights(net: Network, key, spread=0.5):
    """Residual reading: random first layer, zero second layer (F = Φ_CA at the start)."""
    k = net.hidden
    w = jnp.zeros((net.n_weights,))
    return w.at[: 4 * k].set(spread * jax.random.normal(key, (4 * k,)))


def ca_weights(net: Network, key, spread=1e-3):
    """Literal reading: weights that make F ≈ Φ_CA near the origin (tanh linear for small inputs).

    W₁ = a·I-like (3 of the hidden units carry the scaled state), W₂ = Φ_CA-scaled / a; the rest small.
    """
    k = net.hidden
    a = 1e-3
    s = np.asarray(net.scale)
    W1 = np.zeros((k, 3))
    W1[:3, :3] = a * np.eye(3)
    W2 = np.zeros((3, k))
    W2[:, :3] = (np.asarray(net.phi()) * s[None, :] / s[:, None]) / a
    w = np.concatenate([W1.ravel(), np.zeros(k), W2.ravel(), np.zeros(3)])
    return jnp.asarray(w) + spread * jax.random.normal(key, w.shape) * (np.abs(w) > 0)


class DekfState(NamedTuple):
    x: jax.Array
    P: jax.Array
    w: jax.Array
    Pw: jax.Array


def dual_ekf(net: Network, params) -> Filter:
    """The dual EKF on one angle channel; the measurement is θ (m = 1). With ``scale`` in the
    parameters, the network's scaling is that parameter (otherwise ``net.scale``)."""
    C = jnp.array([[1.0, 0.0, 0.0]])
    G = jnp.array([net.dt**2 / 2, net.dt, 1.0])  # DWPA gain of the state noise

    def init(p, prior):
        x = jnp.asarray(prior.x)
        nw = net.n_weights
        return DekfState(x, jnp.asarray(prior.P), jnp.asarray(p["w0"], x.dtype),
                         p["pw0"] * jnp.eye(nw, dtype=x.dtype))

    def step(p, s, meas):
        net_p = net._replace(scale=p["scale"]) if "scale" in p else net
        z, present = masked_meas(meas)
        Pw_pred = s.Pw / p["forget"]  # forgetting
        x_pred = net_p(s.x, s.w)
        A = jax.jacfwd(net_p, argnums=0)(s.x, s.w)
        pred = predict(Gaussian(s.x, s.P), A, p["q"] * jnp.outer(G, G), f_x=x_pred)
        nu = z - mm(C, pred.x)
        u = innovation_update(pred, nu, C, jnp.reshape(p["r"], (1, 1)), present=present)
        # weight filter, on the same innovation (eqs. 13-15)
        Cw = mm(C, jax.jacfwd(net_p, argnums=1)(s.x, s.w))  # (1, n_w)
        uw = innovation_update(Gaussian(s.w, Pw_pred), nu, Cw, jnp.reshape(p["r_e"], (1, 1)), present=present)
        out = Out(x=u.x, P=u.P, x_pred=pred.x, nu=u.nu, S=u.S, valid=jnp.any(present), dof=jnp.sum(present),
                  aux={"weights": uw.x})
        return DekfState(u.x, u.P, uw.x, uw.P), out

    return Filter(init=init, step=step, params=params)


def dekf_params(net: Network, q, r, lam=0.999, r_e=0.5, w0=None, pw0=1e-4, key=None):
    if w0 is None:
        key = jax.random.key(0) if key is None else key
        w0 = initial_weights(net, key) if net.residual else ca_weights(net, key)
    return {"q": jnp.asarray(q, float), "r": jnp.asarray(r, float), "forget": jnp.asarray(lam, float),
            "r_e": jnp.asarray(r_e, float), "w0": jnp.asarray(w0, float), "pw0": jnp.asarray(pw0, float)}


def predict_ahead(net: Network, x, w, n: int):
    """n applications of the network (eq. 17: from the delayed estimate to now)."""
    for _ in range(n):
        x = net(x, w)
    return x


def model_dekf(model, sensor, params, hidden=4, reading="residual") -> Filter:
    """The dual EKF as an experiment filter: one angle channel, CA-layout state [θ, θ̇, θ̈];
    params {q, r, forget, r_e, w0, pw0, scale}."""
    if model.dim != 1 or model.order != 3 or sensor.m != 1:
        raise ValueError("dekf tracks one channel: a 1-D scenario, the ca model and a 1-D linear sensor")
    net = Network(int(hidden), params["scale"], float(model.F[0, 1]), reading == "residual")
    return dual_ekf(net, params)


# ------------------------------------------------------------------------- declarations


def _read(e: Entry):
    """hidden, reading, scale, forget, weights_seed (-> w0), r_e, pw0; q (accel_increment_sigma) and r as every kind."""
    if e.dim != 1 or e.meas.m != 1:
        raise e.error("kind", "dekf", "dekf tracks one angle channel: a 1-D scenario and a 1-D cartesian sensor")
    if e.get("model", "ca") != "ca":
        raise e.error("model", e.get("model"), "dekf works on the ca state [theta, rate, acceleration]")
    params = noise(e, "ca")
    options = {"hidden": e.integer("hidden", 4, lo=1, hi=256),
               "reading": e.string("reading", "residual", choices=("residual", "literal"))}
    scale = e.sigmas("scale", 3, default=list(e.default("scale")))
    forget = e.number("forget", e.default("forget"))
    if not 0.0 < forget <= 1.0:
        raise e.error("forget", forget, "the forgetting factor must be in (0, 1]")
    seed = e.integer("weights_seed", 0, lo=0, hi=2**32 - 1)
    net = Network(options["hidden"], scale, 1.0, options["reading"] == "residual")
    p = dekf_params(net, q=params["q"], r=params["r"][0], lam=forget, r_e=e.number("r_e", e.default("r_e"), positive=True),
                    pw0=e.number("pw0", e.default("pw0"), positive=True), key=jax.random.key(seed))
    params.update({k: np.asarray(v).tolist() for k, v in p.items() if k not in ("q", "r")}, scale=scale)
    return "ca", params, options


DEKF = FilterKind(
    name="dekf", doc="dual EKF with a neural motion model (paper 003); one angle channel, 1-D linear sensor",
    accepts=("cartesian",),
    params={"q": PROCESS_NOISE, "r": MEASUREMENT_NOISE,
            "forget": Param("weight forgetting factor λ", unit_interval, default=0.999, tune=True),
            "r_e": Param("weight filter's innovation variance Rᵉ", positive, "sensor units²", default=0.5, tune=True,
                         sweep=True),
            "pw0": Param("initial weight variance", positive, default=1e-4, tune=True),
            "w0": Param("initial network weights; a file gives weights_seed", free, tune=True, write=None),
            "scale": Param("network scaling: typical |θ|, |θ̇|, |θ̈|", positive, "angle, /s, /s²",
                           default=(100.0, 50.0, 30.0))},
    read=_read,
    build=lambda model, sensor, params, options: model_dekf(
        model, sensor, params, options.get("hidden", 4), options.get("reading", "residual")))
