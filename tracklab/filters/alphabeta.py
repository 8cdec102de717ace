"""Constant-gain α-β and α-β-γ filters (paper 002 §1, docs/mathematics.md §2).

Per Cartesian axis, x⁺ = x⁻ + K (z − x⁻_pos) with K = [α, β/T] (α-β, eq. 1) or
K = [α, β/T, γ/(2T²)] (α-β-γ; note the factor 2). The gains come from

* ``kalata``: the tracking index λ = σ_v T²/σ_w (eq. 5) in closed form
  (eqs. 6–7; α-β-γ through the real root of s³ + (λ/2 − 3)s² + (λ/2 + 3)s − 1 = 0);
  these are the steady-state Kalman gains of the DWNA (α-β) or DWPA (α-β-γ) model;
* ``growing_memory``: α_k = 2(2k−1)/(k(k+1)), β_k = 6/(k(k+1)) (eqs. 8–9), or
  the α-β-γ least-squares schedule, k counting the measurements processed
  (including the current one); optionally each gain stops shrinking at a floor
  (explicit values, or the Kalata gains);
* ``explicit``: α, β (, γ) given.

The gains are parameters (pytree leaves) or functions of parameters and of the
step count only, never of the measurements, so under ``vmap`` over runs they
are computed once per parameter set. The filter also propagates the error
covariance of its fixed-gain update under its model (Joseph form with the gain
actually used), so NEES is meaningful. Non-Cartesian sensors are first
converted to Cartesian positions (plain or unbiased conversion).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.blocks import Gaussian, joseph_covariance, predict
from tracklab.filters.core import Filter, Out, masked_meas, select
from tracklab.filters.kind import NOISE, Entry, FilterKind, noise
from tracklab.parameters import Constraint, Param, positive, stable_gains, write_value
from tracklab.linalg import mm
from tracklab.sensors import CONVERSIONS


def kalata_alpha_beta(lam):
    """Steady-state α, β of the DWNA model from the tracking index (eqs. 6–7)."""
    r = jnp.sqrt(lam**2 + 8 * lam)
    alpha = -(lam**2 + 8 * lam - (lam + 4) * r) / 8
    beta = (lam**2 + 4 * lam - lam * r) / 4
    return alpha, beta


def kalata_alpha_beta_gamma(lam):
    """Steady-state α, β, γ of the DWPA model (docs/mathematics.md §2).

    s is the root in (0, 1) of s³ + (λ/2 − 3)s² + (λ/2 + 3)s − 1 = 0: Cardano's
    formula while the cubic has one real root, the trigonometric form when it
    has three (λ > 12√3).
    """
    b, c = lam / 2 - 3, lam / 2 + 3
    p = c - b**2 / 3
    q = 2 * b**3 / 27 - b * c / 3 - 1
    disc = q**2 + 4 * p**3 / 27
    one_root = disc >= 0
    z = jnp.cbrt((-q + jnp.sqrt(jnp.where(one_root, disc, 1.0))) / 2)
    s_cardano = z - p / (3 * z) - b / 3
    p_neg = jnp.where(one_root, -1.0, p)  # p < 0 whenever there are three real roots
    m = 2 * jnp.sqrt(-p_neg / 3)
    phi = jnp.arccos(jnp.clip(jnp.where(one_root, 0.0, 3 * q / (p_neg * m)), -1.0, 1.0)) / 3
    roots = [m * jnp.cos(phi - 2 * jnp.pi * j / 3) - b / 3 for j in range(3)]
    s_trig = roots[2]
    for r in roots[1::-1]:
        s_trig = jnp.where((r > 0) & (r < 1), r, s_trig)
    s = jnp.where(one_root, s_cardano, s_trig)
    return 1 - s**2, 2 * (1 - s) ** 2, 2 * lam * s


def growing_memory_alpha_beta(k):
    """Least-squares line-fit gains after k measurements (eqs. 8–9)."""
    k = jnp.maximum(k, 1.0)
    return 2 * (2 * k - 1) / (k * (k + 1)), 6 / (k * (k + 1))


def growing_memory_alpha_beta_gamma(k):
    """Least-squares parabola-fit gains after k measurements (γ in the γ/(2T²) convention)."""
    k = jnp.maximum(k, 1.0)
    den = k * (k + 1) * (k + 2)
    return 3 * (3 * k**2 - 3 * k + 2) / den, 18 * (2 * k - 1) / den, 120 / den


def gain_matrix(order, dim, T, gains):
    """K (dim·order, dim): per axis [α, β/T (, γ/(2T²))] in the interleaved layout."""
    scale = jnp.array([1.0, 1.0 / T, 1.0 / (2 * T**2)][:order])
    g = jnp.stack([jnp.broadcast_to(v, (dim,)) for v in gains[:order]], axis=-1)  # (dim, order)
    K = jnp.zeros((dim * order, dim), dtype=g.dtype)
    for a in range(dim):
        K = K.at[a * order:(a + 1) * order, a].set(g[a] * scale)
    return K


def tracking_index(sigma_v, sigma_w, T):
    """λ = σ_v T² / σ_w (eq. 5): process-noise std σ_v, measurement-noise std σ_w."""
    return sigma_v * T**2 / sigma_w


class ABState(NamedTuple):
    x: jax.Array
    P: jax.Array
    k: jax.Array  # measurements processed


def model_alpha_beta(model, sensor, params, gains="kalata", floor=None, conversion="plain") -> Filter:
    """α-β (CV model) or α-β-γ (CA model) filter.

    params: {"q", "r"} always (the covariance propagation and, for a converted
    measurement, its noise); {"lam": (dim,)} for Kalata gains or a Kalata floor;
    {"alpha", "beta"(, "gamma")} for explicit gains; {"floor": (order,)} for an
    explicit floor on growing-memory gains. The gains' T is the sensor's report period
    (the model's step when the sensor reports every step); between reports the
    filter predicts with its model.
    """
    order, dim = model.order, model.dim
    # the gains' T is the update interval: the sensor's period when it reports less often than every step
    T = float(getattr(sensor, "period", 0.0) or model.F[0, 1])
    F = model.F  # F and H in NumPy: known when built inside a trace (``mm`` skips their zeros)
    H = np.zeros((dim, model.n))
    H[np.arange(dim), np.array(model.pos_idx)] = 1.0
    kalata = kalata_alpha_beta if order == 2 else kalata_alpha_beta_gamma
    growing = growing_memory_alpha_beta if order == 2 else growing_memory_alpha_beta_gamma
    convert = None if sensor.linear else CONVERSIONS[conversion]

    def current_gains(p, k):
        if gains == "kalata":
            return kalata(p["lam"])
        if gains == "explicit":
            return tuple(p[n] for n in ("alpha", "beta", "gamma")[:order])
        g = growing(k)
        if floor == "kalata":
            g = tuple(jnp.maximum(a, b) for a, b in zip(g, kalata(p["lam"])))
        elif floor is not None:
            g = tuple(jnp.maximum(a, p["floor"][i]) for i, a in enumerate(g))
        return g

    def init(p, prior):
        return ABState(jnp.asarray(prior.x), jnp.asarray(prior.P), jnp.zeros((), jnp.asarray(prior.x).dtype))

    def time_update(p, s):
        return predict(Gaussian(s.x, s.P), F, model.Q(p["q"]))

    def coast(p, s, meas):
        x_pred, P_pred = time_update(p, s)
        none = jnp.zeros((dim,), bool)
        out = Out(x=x_pred, P=P_pred, x_pred=x_pred, nu=jnp.zeros((dim,), x_pred.dtype),
                  S=jnp.eye(dim, dtype=x_pred.dtype), valid=jnp.any(none), dof=jnp.sum(none))
        return ABState(x_pred, P_pred, s.k), out

    def step(p, s, meas):
        z, present = masked_meas(meas)
        x_pred, P_pred = time_update(p, s)
        if convert is None:
            zc, Rc, used = z, jnp.diag(jnp.broadcast_to(p["r"], (dim,))), present
        else:
            zc, Rc = convert(z, jnp.sqrt(p["r"]))
            used = jnp.broadcast_to(jnp.all(present), (dim,))
        valid = jnp.any(used)
        k = s.k + valid
        K = gain_matrix(order, dim, T, current_gains(p, k)) * used[None, :]
        nu = jnp.where(used, zc - mm(H, x_pred), 0.0)
        x = x_pred + mm(K, nu)
        Ru = jnp.where(used[:, None] & used[None, :], Rc, jnp.eye(dim, dtype=x.dtype))
        P = joseph_covariance(P_pred, K, H, Ru)  # with the gain actually used
        S = jnp.where(used[:, None] & used[None, :], mm(mm(H, P_pred), H.T) + Ru, Ru)
        post = select(valid, ABState(x, P, k), ABState(x_pred, P_pred, s.k))
        out = Out(x=post.x, P=post.P, x_pred=x_pred, nu=nu, S=S, valid=valid, dof=jnp.sum(used))
        return post, out

    return Filter(init=init, step=step, params=params, coast=coast)


# ------------------------------------------------------------------------- declarations

GAIN_NAMES = ("alpha", "beta", "gamma")


def _gain(e: Entry, key):
    """An explicit gain: a number, or one per axis, in (0, 4)."""
    v = e.get(key)
    if v is None:
        raise e.error(key, None, "is required for explicit gains")
    vals = v if isinstance(v, list) else [v]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 < x < 4 for x in vals):
        raise e.error(key, v, "must be a number (or one per axis) in (0, 4)")
    return tuple(float(x) for x in vals) if isinstance(v, list) else float(v)


def _reader(order):
    kind, need = ("alpha_beta", "cv") if order == 2 else ("alpha_beta_gamma", "ca")
    names = GAIN_NAMES[:order]

    def read(e: Entry):
        model = e.motion_model(need)
        if model != need:
            raise e.error("model", model, f"{kind} works on the {need} model")
        params = noise(e, model)
        options = {}
        explicit = any(e.has(g) for g in names)
        gains = e.string("gains", "explicit" if explicit else "kalata", choices=("kalata", "growing_memory", "explicit"))
        if e.meas.kind != "cartesian":
            options["conversion"] = e.string("conversion", "plain", choices=("plain", "unbiased"))
        if gains == "explicit":
            for g in names:
                params[g] = _gain(e, g)
        elif explicit:
            raise e.error("gains", gains, 'explicit alpha/beta/gamma need gains = "explicit" (or no gains field)')
        floor = e.get("floor") if gains == "growing_memory" else None
        if gains == "growing_memory" and floor is not None:
            if floor == "kalata":
                options["floor"] = "kalata"
            elif isinstance(floor, list) and len(floor) == order and all(
                not isinstance(v, bool) and isinstance(v, (int, float)) and 0 <= v < 4 for v in floor
            ):
                options["floor"] = "explicit"
                params["floor"] = tuple(float(v) for v in floor)
            else:
                raise e.error("floor", floor, f'must be "kalata" or {order} gains [{", ".join(names)}] in [0, 4)')
        options["gains"] = gains
        if gains == "kalata" or options.get("floor") == "kalata":
            lam = e.sigmas("tracking_index", e.dim, required=False)
            if lam is None:
                sw = e.get("sigma_w")
                if sw is None and e.meas.kind != "cartesian":
                    raise e.error("sigma_w", None, "is required (position-noise std per axis, m) for Kalata gains behind "
                                  "a non-Cartesian sensor, unless tracking_index is given")
                sigma_w = e.sigmas("sigma_w", e.dim) if sw is not None else tuple(np.sqrt(params["r"]))
                T = getattr(e.meas, "period", 0.0) or e.dt  # the update interval
                lam = tuple(tracking_index(math.sqrt(params["q"]), w, T) for w in sigma_w)
            elif e.has("sigma_w"):
                raise e.error("sigma_w", e.get("sigma_w"), "give either tracking_index or sigma_w, not both")
            params["lam"] = lam
        return model, params, options

    return read


def _write_gain(table, name, value, where):
    """Explicit gains replace Kalata's and the growing-memory schedule."""
    write_value(table, name, value, where)
    table["gains"] = "explicit"
    for k in ("tracking_index", "sigma_w", "floor"):
        table.pop(k, None)


def _write_tracking_index(table, name, value, where):
    table["tracking_index"] = list(np.atleast_1d(value).tolist())
    table.pop("sigma_w", None)


_FLOOR = Constraint("[0, 4)", lambda v: (v >= 0) & (v < 4))


def _params(order):
    gain = {"alpha": "position gain α", "beta": "velocity gain β", "gamma": "acceleration gain γ"}
    return {
        **NOISE,
        **{g: Param(gain[g] + " (gains = explicit; jointly stable)", stable_gains, tune=True, sweep=True, write=_write_gain)
           for g in GAIN_NAMES[:order]},
        "lam": Param("Kalata's tracking index λ per axis (eq. 5), field tracking_index; default σ_v T²/σ_w", positive,
                     tune=True, sweep=True, write=_write_tracking_index),
        "floor": Param("growing-memory gain floor [α, β(, γ)] (floor = [...])", _FLOOR),
    }


_build = lambda model, sensor, params, options: model_alpha_beta(  # noqa: E731
    model, sensor, params, options.get("gains", "kalata"), options.get("floor"), options.get("conversion", "plain"))
_ACCEPTS = ("cartesian", "mount", "polar", "spherical")

ALPHA_BETA = FilterKind(
    name="alpha_beta", doc="α-β filter; gains = kalata | growing_memory | explicit alpha, beta", accepts=_ACCEPTS,
    params=_params(2), read=_reader(2), build=_build)
ALPHA_BETA_GAMMA = FilterKind(
    name="alpha_beta_gamma", doc="α-β-γ filter; gains = kalata | growing_memory | explicit", accepts=_ACCEPTS,
    params=_params(3), read=_reader(3), build=_build)
