"""Interacting multiple model filter (Blom & Bar-Shalom) over CV, CA and coordinated-turn models.

Every model works on one common state, the CA layout plus the turn rate:
[x, ẋ, ẍ, y, ẏ, ÿ, (z, ż, z̈,) ω] (ω in rad/s, a turn in the x-y plane), so
that mixing is a plain weighted sum:

* ``cv`` — constant velocity (DWNA noise of variance q); accelerations reset to 0;
* ``ca`` — constant acceleration (DWPA noise of variance q);
* ``ct`` — coordinated turn at rate ω in the x-y plane (z: constant velocity),
  DWNA noise of variance q on positions and velocities, a random walk of variance
  ``q_turn`` per step on ω; its accelerations are the turn's, ẍ = −ω ẏ, ÿ = ω ẋ.

ω is carried by every model (a random walk of variance ``q_turn``), so a model
that ignores it does not erase it. Each model is an EKF (Jacobians of its
transition and of the sensor by ``jax.jacfwd``), so any sensor works. One cycle:

1. mixing: c_j = Σ_i π_ij μ_i, μ_i|j = π_ij μ_i / c_j, x₀ⱼ = Σ_i μ_i|j x_i,
   P₀ⱼ = Σ_i μ_i|j (P_i + (x_i − x₀ⱼ)(x_i − x₀ⱼ)ᵀ);
2. each model predicts and updates from its mixed prior; its likelihood is
   N(ν_j; 0, S_j) over the measurement components present;
3. μ_j ∝ c_j Λ_j; the output is the moment-matched mixture.

The mode probabilities are in ``Out.aux["mode_probabilities"]`` (``run_filter``'s
``.aux``). Parameters {q (one per model), q_turn, r, transition, mu0, turn_rate_sigma
(the prior's turn-rate std)}.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, ekf_update, predict
from tracklab.filters.core import Filter, Out, masked_meas
from tracklab.filters.kind import ANY_SENSOR, MEASUREMENT_NOISE, Entry, FilterKind
from tracklab.parameters import Param, positive, probabilities
from tracklab.linalg import jacobian, mahalanobis2_logdet, symmetrise
from tracklab.toml_fields import MAX_MAGNITUDE

IMM_MODELS = ("cv", "ca", "ct")


class ImmState(NamedTuple):
    x: jax.Array  # (r, n) per-model means
    P: jax.Array  # (r, n, n) per-model covariances
    mu: jax.Array  # (r,) mode probabilities


def _sin_over(w, T):
    """sin(ωT)/ω and (1 − cos ωT)/ω, smooth through ω = 0 (and differentiable there)."""
    small = jnp.abs(w) < 1e-6
    ws = jnp.where(small, 1.0, w)
    a = jnp.where(small, T - w**2 * T**3 / 6.0, jnp.sin(ws * T) / ws)
    b = jnp.where(small, w * T**2 / 2.0 - w**3 * T**4 / 24.0, (1.0 - jnp.cos(ws * T)) / ws)
    return a, b


def transition(kind: str, dim: int, T: float):
    """x' = f(x) on the common state of ``dim`` axes (3·dim + 1 components)."""
    o = 3

    def f(x):
        w = x[-1]
        out = []
        for a in range(dim):
            p, v, acc = x[a * o], x[a * o + 1], x[a * o + 2]
            if kind == "ca":
                out.append(jnp.stack([p + T * v + 0.5 * T**2 * acc, v + T * acc, acc]))
            else:  # cv, and the axes a turn leaves alone
                out.append(jnp.stack([p + T * v, v, jnp.zeros_like(acc)]))
        if kind == "ct":
            sw, cw = _sin_over(w, T)
            px, vx, py, vy = x[0], x[1], x[o], x[o + 1]
            c, s = jnp.cos(w * T), jnp.sin(w * T)
            vx2, vy2 = c * vx - s * vy, s * vx + c * vy
            out[0] = jnp.stack([px + sw * vx - cw * vy, vx2, -w * vy2])
            out[1] = jnp.stack([py + cw * vx + sw * vy, vy2, w * vx2])
        return jnp.concatenate(out + [w[None]])

    return f


def noise_gain(kind: str, dim: int, T: float) -> np.ndarray:
    """(n, dim) gain of the per-axis noise: DWNA for cv/ct, DWPA for ca."""
    g = np.array([T**2 / 2, T, 1.0]) if kind == "ca" else np.array([T**2 / 2, T, 0.0])
    G = np.zeros((3 * dim + 1, dim))
    for a in range(dim):
        G[3 * a:3 * a + 3, a] = g
    return G


def model_imm(dim: int, dt: float, sensor, params, kinds=("cv", "ca", "ct")) -> Filter:
    """IMM over ``kinds`` for a sensor observing the ``dim`` position components."""
    if "ct" in kinds and dim < 2:
        raise ValueError("the coordinated-turn model needs at least 2 dimensions")
    n = 3 * dim + 1
    fs = [transition(k, dim, dt) for k in kinds]
    Gs = [jnp.asarray(noise_gain(k, dim, dt)) for k in kinds]
    e_w = jnp.zeros((n, n)).at[-1, -1].set(1.0)
    pos = tuple(3 * a for a in range(dim))

    def h(x):
        return sensor.h(jnp.stack([x[i] for i in pos]))

    def init(p, prior):
        x = jnp.concatenate([jnp.asarray(prior.x), jnp.zeros((1,), prior.x.dtype)])
        P = jnp.zeros((n, n), prior.x.dtype).at[:-1, :-1].set(prior.P).at[-1, -1].set(p["turn_rate_sigma"] ** 2)
        r = len(kinds)
        return ImmState(jnp.broadcast_to(x, (r, n)), jnp.broadcast_to(P, (r, n, n)), jnp.asarray(p["mu0"], x.dtype))

    def step(p, s, meas):
        z, present = masked_meas(meas)
        Pi = p["transition"]
        c = jnp.maximum(s.mu @ Pi, jnp.finfo(s.mu.dtype).tiny)  # predicted mode probabilities
        w = Pi * s.mu[:, None] / c[None, :]  # μ_i|j
        x0 = jnp.einsum("ij,in->jn", w, s.x)
        d = s.x[:, None, :] - x0[None, :, :]  # (i, j, n)
        P0 = jnp.einsum("ij,inm->jnm", w, s.P) + jnp.einsum("ij,ijn,ijm->jnm", w, d, d)
        # each model's prediction (its own transition), then one update for all of them (the same sensor)
        Fs, preds, Qs = [], [], []
        for j, f in enumerate(fs):  # static loop over the models (r ≤ 3)
            Fs.append(jacobian(f, x0[j]))
            preds.append(f(x0[j]))
            Qs.append((Gs[j] * p["q"][j]) @ Gs[j].T + p["q_turn"] * e_w)
        Fs, xps, Qs = jnp.stack(Fs), jnp.stack(preds), jnp.stack(Qs)
        pred = jax.vmap(lambda g, F, Q, fx: predict(g, F, Q, f_x=fx))(Gaussian(x0, P0), Fs, Qs, xps)

        def model_update(g):
            u = ekf_update(g, z, h, jnp.diag(p["r"]), angles=sensor.angle_mask, present=present)
            d2, logdet = mahalanobis2_logdet(u.S, u.nu)
            return u.x, u.P, u.nu, u.S, -0.5 * (d2 + logdet)

        xs, Ps, nus, Ss, ll = jax.vmap(model_update)(pred)
        mu = c * jnp.exp(ll - jnp.max(ll))
        mu = jnp.where(jnp.any(present), mu / jnp.sum(mu), c)
        x = mu @ xs
        dx = xs - x
        P = jnp.einsum("j,jnm->nm", mu, Ps) + jnp.einsum("j,jn,jm->nm", mu, dx, dx)
        x_pred = c @ xps
        nu = c @ nus
        dnu = nus - nu
        S = jnp.einsum("j,jab->ab", c, Ss) + jnp.einsum("j,ja,jb->ab", c, dnu, dnu)
        out = Out(x=x, P=symmetrise(P), x_pred=x_pred, nu=nu, S=S, valid=jnp.any(present), dof=jnp.sum(present),
                  aux={"mode_probabilities": mu})
        return ImmState(xs, Ps, mu), out

    return Filter(init=init, step=step, params=params)


def imm_params(kinds, q, q_turn, r, p_stay=0.95, transition_matrix=None, mu0=None, turn_rate_sigma=0.1):
    """Parameter pytree: per-model q, q_turn, r, the Markov transition matrix, initial probabilities and
    the prior's turn-rate std."""
    k = len(kinds)
    if transition_matrix is None:
        off = (1.0 - p_stay) / (k - 1) if k > 1 else 0.0
        transition_matrix = np.full((k, k), off) + np.eye(k) * (p_stay - off if k > 1 else 1.0)
    mu0 = np.full(k, 1.0 / k) if mu0 is None else np.asarray(mu0, float)
    return {"q": jnp.asarray(q, float), "q_turn": jnp.asarray(q_turn, float), "r": jnp.asarray(r, float),
            "transition": jnp.asarray(transition_matrix, float), "mu0": jnp.asarray(mu0, float),
            "turn_rate_sigma": jnp.asarray(turn_rate_sigma, float)}


# ------------------------------------------------------------------------- declarations


def _read(e: Entry):
    """models, q (one per model), q_turn, turn_rate_sigma, p_stay or transition; r as every kind."""
    if e.has("model"):
        raise e.error("model", e.get("model"), 'imm has its own models: use models = ["cv", "ca", "ct"]')
    r = e.measurement_noise()
    models = e.get("models", list(IMM_MODELS) if e.dim >= 2 else ["cv", "ca"])
    if not isinstance(models, list) or not models or any(m not in IMM_MODELS for m in models) or len(set(models)) != len(models):
        raise e.error("models", models, f"must be a list of distinct models from: {', '.join(IMM_MODELS)}")
    if "ct" in models and e.dim < 2:
        raise e.error("models", models, "the coordinated turn (ct) needs a 2-D or 3-D scenario")
    cv_q = e.accel_sigma**2 if e.accel_sigma > 0 else 1.0
    q = e.get("q", [cv_q if m != "ca" else 0.1 * cv_q for m in models])
    if (not isinstance(q, list) or len(q) != len(models)
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE for v in q)):
        raise e.error("q", q, f"must be {len(models)} process-noise variances > 0, one per model")
    q_turn = e.number("q_turn", e.default("q_turn"), positive=True)
    turn_sigma = e.number("turn_rate_sigma", e.default("turn_rate_sigma"), positive=True)
    k = len(models)
    if e.has("transition"):
        if e.has("p_stay"):
            raise e.error("p_stay", e.get("p_stay"), "give either p_stay or transition, not both")
        tm = e.get("transition")
        ok = isinstance(tm, list) and len(tm) == k and all(
            isinstance(row, list) and len(row) == k
            and all(not isinstance(v, bool) and isinstance(v, (int, float)) and 0 <= v <= 1 for v in row)
            and abs(sum(row) - 1.0) < 1e-9 for row in tm)
        if not ok:
            raise e.error("transition", tm, f"must be a {k}x{k} matrix of probabilities whose rows sum to 1")
        matrix = np.array(tm, float)
    else:
        p_stay = e.number("p_stay", 0.95)
        if not 0.0 < p_stay <= 1.0 or (k > 1 and p_stay == 1.0):
            raise e.error("p_stay", p_stay, "must be a probability in (0, 1) (1 with one model)")
        matrix = None
    params = imm_params(models, q, q_turn, r, p_stay=p_stay if matrix is None else 0.95, transition_matrix=matrix,
                        turn_rate_sigma=turn_sigma)
    return "ca", {n: np.asarray(v).tolist() for n, v in params.items()}, {"models": tuple(models)}


IMM = FilterKind(
    name="imm", doc="interacting multiple models over cv / ca / ct (coordinated turn); mode probabilities in aux",
    accepts=ANY_SENSOR,
    params={"q": Param("process-noise variance per model; default the scenario's (ca: a tenth)", positive, "(m/s²)²",
                       tune=True, sweep=True),
            "r": MEASUREMENT_NOISE,
            "q_turn": Param("turn-rate random-walk variance per step", positive, "(rad/s)²", default=1e-4),
            "transition": Param("Markov transition matrix (from p_stay = 0.95, or transition = [[...]])", probabilities),
            "mu0": Param("initial mode probabilities (equal)", probabilities),
            "turn_rate_sigma": Param("prior turn-rate std", positive, "rad/s", default=0.1)},
    read=_read,
    build=lambda model, sensor, params, options: model_imm(
        model.dim, float(model.F[0, 1]), sensor, params, tuple(options.get("models", IMM_MODELS))))
