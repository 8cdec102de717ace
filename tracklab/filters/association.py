"""Data association: a Gaussian filter made to track in clutter, as a combinator.

A cluttered sensor (``tracklab.sensors.Cluttered``) gives a *scan* per step: z of shape
(capacity, m), one row per return, NaN rows unused. ``nearest_neighbour(base, …)``,
``strongest_neighbour(base, …)``, ``pdaf(base, …)`` and ``ipda(base, …)`` take any filter ``base`` whose state is a Gaussian
(``blocks.Gaussian``, or any NamedTuple with x (n,) and P (n, n): every filter written with
``blocks.kalman_filter``, the built-in KF, EKF, CMKF, UKF, sequential EKF and polar KF) and
return a filter of scans, in the spirit of optax's ``chain``:

1. one hypothesis per return: the base's step on that return alone (``vmap`` over the rows;
   what does not depend on the measurement — the prediction, H, S, the gain — is computed
   once), and the base's prediction (no return);
2. the gate: return i is validated when its innovation's d²ᵢ = νᵢᵀ Sᵢ⁻¹ νᵢ ≤ γ (``gate``);
3. the rule:

   * **nearest neighbour**: the validated hypothesis of least d² (none: the prediction);
   * **strongest neighbour**: the validated return of greatest amplitude — the first validated
     row, for a sensor whose scans hold their returns in order of amplitude (a cluttered sensor
     with ``snr``; ``sensors.clutter``) — (none: the prediction);
   * **PDAF** (Bar-Shalom & Tse, Automatica 1975; the parametric form of Bar-Shalom, Daum &
     Huang, "The probabilistic data association filter", IEEE Control Systems Magazine 29(6),
     2009): weights β₀ ∝ λ(1 − P_D P_G), βᵢ ∝ P_D N(νᵢ; 0, Sᵢ) over the validated returns,
     λ the clutter density, P_G = P(χ²ₘ ≤ γ); the posterior is the weighted mixture of the
     prediction and the hypotheses reduced to its mean and covariance. Where the base's
     covariance does not depend on z (KF, EKF, UKF; found when tracing) that is the PDAF's
     gain form x = x⁻ + K ν̄, P = β₀P⁻ + (1 − β₀)P_c + K(Σβᵢνᵢνᵢᵀ − ν̄ν̄ᵀ)Kᵀ, computed so
     (the gain K by forward differentiation: the same numbers, fewer operations per return);
   * **IPDA** (Mušicki, Evans & Stanković, "Integrated probabilistic data association",
     IEEE Trans. Automatic Control 39(6), 1994): the PDAF's update and the probability ψ that
     the target exists, predicted ψ⁻ = p_S ψ (Markov chain, no birth) and updated
     ψ = (1 − δ)ψ⁻ / (1 − δψ⁻), δ = P_D P_G − Σᵢ P_D N(νᵢ; 0, Sᵢ)/λ (in ``Out.aux["existence"]``).

PDAF and IPDA are smooth in every number (gate, P_D, λ, the base's q and r), so ``tracklab
tune`` tunes them through the simulation. The nearest and strongest neighbours' choice is a hard
one: their numbers are not tuned (tune their PDAF relaxation).

A scan filter's ``Out.validated`` is the number of validated returns (NaN at a step with no
scan); its ν and S are the combined innovation (the chosen one for the nearest neighbour) and
the base's innovation covariance. A z of one measurement (m,) is a scan of one return.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.checks import check_count, check_filter, check_positive, refuse
from tracklab.filters.core import Filter, Meas, Out, select
from tracklab.filters.kind import ANY_SENSOR, MEASUREMENT_NOISE, PROCESS_NOISE, FilterKind
from tracklab.linalg import mahalanobis2_logdet, mm
from tracklab.montecarlo.statistics import chi2_quantile
from tracklab.parameters import Param, bounded, positive, unit_interval
from tracklab.sensors.clutter import cluttered_of


def gate_probability(gate, m: int):
    """P_G = P(χ²ₘ ≤ γ): the probability that the target's return passes a gate γ."""
    return jax.scipy.special.gammainc(m / 2.0, jnp.asarray(gate) / 2.0)


@functools.lru_cache(maxsize=64)
def chi2_gate(probability: float, m: int) -> float:
    """The gate γ with P(χ²ₘ ≤ γ) = ``probability``: the χ² quantile."""
    return float(chi2_quantile(probability, m))


def _gaussian(state, where: str):
    """``state`` if it is a Gaussian (a NamedTuple with x and P), else TypeError in one line."""
    if not (isinstance(state, tuple) and hasattr(state, "_replace") and hasattr(state, "x") and hasattr(state, "P")):
        raise TypeError(f"{where}: the base filter's state is {type(state).__name__}: association needs a Gaussian "
                        "state (x, P), as every filter written with tracklab.filters.kalman_filter has")
    return state


def _scan(meas: Meas, m: int):
    """(returns (K, m) with unused rows 0, which rows are returns (K,), whether the sensor scanned)."""
    Z = jnp.asarray(meas.z)
    if Z.ndim == 1:
        Z = Z[None]
    if Z.ndim != 2 or Z.shape[1] != m:
        raise ValueError(f"the filter associates scans of returns of {m} components: z has shape {jnp.shape(meas.z)}")
    finite = jnp.all(jnp.isfinite(Z), axis=1)
    scanned = jnp.asarray(meas.valid, bool) & (jnp.all(meas.present) if meas.present is not None else jnp.any(finite))
    returns = finite & scanned
    return jnp.where(returns[:, None], Z, 0.0), returns, scanned


def _mixture(weights, g0, gs, shared_P):
    """The mean and covariance of the mixture of ``g0`` (weight ``weights[0]``) and the hypotheses
    ``gs`` (x (K, n), P (K, n, n); weights ``weights[1:]``): (x, P). ``shared_P``: every
    hypothesis has the same P (an update whose covariance does not depend on z), added once."""
    # elementwise products and sums (a dot product under vmap is a library call per run on the CPU)
    w0, w = weights[0], weights[1:]
    x = w0 * g0.x + jnp.sum(w[:, None] * gs.x, axis=0)
    d0, d = g0.x - x, gs.x - x
    spread = jnp.sum(w[:, None, None] * (d[:, :, None] * d[:, None, :]), axis=0)
    own = jnp.sum(w) * gs.P[0] if shared_P else jnp.sum(w[:, None, None] * gs.P, axis=0)
    P = w0 * (g0.P + d0[:, None] * d0[None, :]) + own + spread
    return x, 0.5 * (P + P.T)


def _gain_form(one, z_bar, beta, nus, nu_bar, pred, out0):
    """The PDAF as Bar-Shalom & Tse write it, for an update affine in z with a covariance that does
    not depend on it: x = x⁻ + G ν̄ (the update on z̄, whose innovation is ν̄), P = β₀ P⁻ + (1 − β₀)
    P_c + G (Σ βᵢ νᵢ νᵢᵀ − ν̄ ν̄ᵀ) Gᵀ, with the gain G = ∂x/∂z by forward differentiation (m
    tangents of one update); the same in the reporting frame. ((x, P), (x_out, P_out))."""
    state_c, out_c = one(z_bar)
    G, G_out = jax.jacfwd(lambda z: (one(z)[0].x, one(z)[1].x))(z_bar)
    spread = (jnp.sum(beta[1:, None, None] * (nus[:, :, None] * nus[:, None, :]), axis=0)
              - nu_bar[:, None] * nu_bar[None, :])
    b0 = beta[0]

    def reduced(P_pred, P_c, G):
        P = b0 * P_pred + (1.0 - b0) * P_c + mm(mm(G, spread), G.T)
        return 0.5 * (P + P.T)

    return ((state_c.x, reduced(pred.P, state_c.P, G)), (out_c.x, reduced(out0.P, out_c.P, G_out)))


def _unbatched(fn, Z) -> bool:
    """Whether ``fn``'s output is the same for every row of ``Z`` (it does not depend on z): found
    when tracing, by asking ``vmap`` for an unmapped output (the probe itself computes nothing)."""
    try:
        jax.eval_shape(jax.vmap(fn, out_axes=None), Z)
    except ValueError:
        return False
    return True


def _out(out0: Out, x, P, nu, S, valid, dof, validated, aux=None) -> Out:
    return Out(x=x, P=P, x_pred=out0.x_pred, nu=nu, S=S, valid=valid, dof=dof, validated=validated, aux=aux)


def associate(base: Filter, rule: str, split, m: int, *, wrap_state=False) -> Filter:
    """A filter of scans from ``base`` by ``rule`` ("nn", "snf", "pdaf", "ipda"); ``split(params) ->
    (base params, association params {gate, p_detect, clutter_density[, p_survive, existence0]})``."""

    def hypotheses(params, state, meas):
        bp, ap = split(params)
        Z, returns, scanned = _scan(meas, m)
        step0 = base.coast or base.step
        absent = Meas(jnp.zeros((m,), Z.dtype), meas.t, jnp.asarray(True), jnp.zeros((m,), bool))
        pred, out0 = step0(bp, state, absent)
        every = jnp.ones((m,), bool)
        one = lambda z: base.step(bp, state, Meas(z, meas.t, jnp.asarray(True), every))  # noqa: E731
        states, outs = jax.vmap(one)(Z)
        shared = (_unbatched(lambda z: one(z)[1].S, Z), _unbatched(lambda z: _gaussian(one(z)[0], "association").P, Z),
                  _unbatched(lambda z: one(z)[1].P, Z))
        if shared[0]:  # S is the same for every return (a KF's, an EKF's): its factor once
            d2, logdet = jax.vmap(mahalanobis2_logdet, in_axes=(None, 0))(outs.S[0], outs.nu)
        else:
            d2, logdet = jax.vmap(mahalanobis2_logdet)(outs.S, outs.nu)
        gated = returns & (d2 <= ap["gate"])
        return ap, pred, out0, states, outs, d2, logdet, gated, scanned, shared, one, Z

    def weights(ap, d2, logdet, gated, shared_S):
        """Log-weights (K + 1,) — the prediction's, then each hypothesis' (−inf where not validated) —
        and a bound on them all: the prediction's or that of a return with d² = 0 (with one S for
        every return no reduction over them; a validated return's weight is within e^(−γ/2) of it,
        so none underflows)."""
        pd, lam = ap["p_detect"], ap["clutter_density"]
        log_w0 = jnp.log(lam) + jnp.log1p(-pd * gate_probability(ap["gate"], m))
        log_peak = jnp.log(pd) - 0.5 * (logdet + m * math.log(2.0 * math.pi))
        log_w = jnp.where(gated, log_peak - 0.5 * d2, -jnp.inf)
        return jnp.concatenate([log_w0[None], log_w]), jnp.maximum(log_w0, log_peak[0] if shared_S else jnp.max(log_peak))

    def step(params, state, meas):
        inner = state[0] if wrap_state else state
        ap, pred, out0, states, outs, d2, logdet, gated, scanned, shared, one, Z = hypotheses(params, inner, meas)
        _gaussian(pred, "association")
        n_valid = jnp.sum(gated)
        any_valid = n_valid > 0
        validated = jnp.where(scanned, n_valid.astype(out0.x.dtype), jnp.nan)
        eye = jnp.eye(m, dtype=out0.x.dtype)
        if rule in HARD_RULES:  # one return chosen: the nearest, or the first (strongest) validated
            i = jnp.argmin(jnp.where(gated, d2, jnp.inf)) if rule == "nn" else jnp.argmax(gated)
            chosen = jax.tree_util.tree_map(lambda a: a[i], states)
            oc = jax.tree_util.tree_map(lambda a: a[i], outs)
            new = select(any_valid, chosen, pred)
            out = _out(out0, jnp.where(any_valid, oc.x, out0.x), jnp.where(any_valid, oc.P, out0.P),
                       jnp.where(any_valid, oc.nu, 0.0), jnp.where(any_valid, oc.S, eye), any_valid,
                       jnp.where(any_valid, oc.dof, 0), validated)
            return new, out
        lw, top = weights(ap, d2, logdet, gated, shared[0])
        top = jnp.where(jnp.isfinite(top), top, 0.0)
        e = jnp.exp(lw - top)
        total = jnp.sum(e)
        beta = jnp.where(total > 0, e / jnp.where(total > 0, total, 1.0), jnp.arange(len(e)) == 0)  # none: keep x⁻
        nu = jnp.sum(beta[1:, None] * outs.nu, axis=0)
        if shared[1] and shared[2]:  # the update's covariance does not depend on z (KF, EKF, UKF): the gain form
            (x, P), (ox, oP) = _gain_form(one, Z[0] - outs.nu[0] + nu, beta, outs.nu, nu, pred, out0)
        else:  # the mixture of the hypotheses reduced to its mean and covariance
            x, P = _mixture(beta, pred, states, shared[1])
            ox, oP = _mixture(beta, Out(out0.x, out0.P), Out(outs.x, outs.P), shared[2])
        new = pred._replace(x=x, P=P)
        out = _out(out0, ox, oP, nu, outs.S[0], any_valid, jnp.where(any_valid, outs.dof[0], 0), validated)
        if rule == "pdaf":
            return new, out
        # IPDA: the target's existence
        psi_pred = ap["p_survive"] * state[1]
        # 1 − δ = (λ(1 − P_D P_G) + Σ P_D Nᵢ)/λ
        one_minus_delta = jnp.exp(top + jnp.log(total) - jnp.log(ap["clutter_density"]))
        psi = one_minus_delta * psi_pred / (1.0 - psi_pred + one_minus_delta * psi_pred)
        psi = jnp.where(scanned, psi, psi_pred)
        return (new, psi), out._replace(aux={"existence": psi})

    def coast(params, state, meas):
        inner = state[0] if wrap_state else state
        bp, ap = split(params)
        absent = Meas(jnp.zeros((m,), jnp.result_type(meas.z)), meas.t, jnp.asarray(True), jnp.zeros((m,), bool))
        pred, out0 = (base.coast or base.step)(bp, inner, absent)
        out = out0._replace(validated=jnp.full((), jnp.nan, out0.x.dtype))
        if not wrap_state:
            return pred, out
        psi = ap["p_survive"] * state[1]
        return (pred, psi), out._replace(aux={"existence": psi})

    def init(params, prior):
        bp, ap = split(params)
        g = base.init(bp, prior)
        return (g, jnp.asarray(ap["existence0"], g.x.dtype)) if wrap_state else g

    return Filter(init=init, step=step, params=None, coast=coast, layout=base.layout)


def _split_nested(params):
    return params["base"], params


def _check_probability(where, name, value, *, upper_open=False):
    """``value`` as a float if it is a probability in (0, 1] (``upper_open``: (0, 1))."""
    v = check_positive(where, name, value)
    if v > 1.0 or (upper_open and v == 1.0):
        raise refuse(where, name, value, f"must be a probability in (0, 1{')' if upper_open else ']'}")
    return v


def _numbers(where, base, gate, p_detect, clutter_density, m):
    """An association's arguments checked (``tracklab.checks``: one line each) as its params."""
    check_filter(where, "base", base)
    m = check_count(where, "m", m)
    gate = chi2_gate(0.99, m) if gate is None else check_positive(where, "gate", gate)
    return {"gate": jnp.asarray(gate), "p_detect": jnp.asarray(_check_probability(where, "p_detect", p_detect)),
            "clutter_density": jnp.asarray(check_positive(where, "clutter_density", clutter_density))}


def nearest_neighbour(base: Filter, m: int, *, gate: float | None = None) -> Filter:
    """``base`` updated with the validated return of least d² (see the module's doc); ``m``: the
    components of a return; ``gate`` γ (default: P_G = 0.99). params {"base", "gate"}."""
    numbers = _numbers("tracklab.filters.nearest_neighbour", base, gate, 1.0, 1.0, m)
    flt = associate(base, "nn", _split_nested, m)
    return flt._replace(params={"base": base.params, "gate": numbers["gate"]})


def strongest_neighbour(base: Filter, m: int, *, gate: float | None = None) -> Filter:
    """``base`` updated with the first validated return of its scan: the strongest, for scans whose
    returns are in order of amplitude (``sensors.Cluttered`` with ``snr``); see the module's doc.
    ``m``: the components of a return; ``gate`` γ (default: P_G = 0.99). params {"base", "gate"}."""
    numbers = _numbers("tracklab.filters.strongest_neighbour", base, gate, 1.0, 1.0, m)
    flt = associate(base, "snf", _split_nested, m)
    return flt._replace(params={"base": base.params, "gate": numbers["gate"]})


def pdaf(base: Filter, m: int, *, clutter_density: float, p_detect: float = 1.0, gate: float | None = None) -> Filter:
    """The PDAF of ``base`` (see the module's doc): ``m`` the components of a return,
    ``clutter_density`` λ (per unit volume of the measurement space), ``p_detect`` P_D, ``gate``
    γ (default: P_G = 0.99). params {"base", "gate", "p_detect", "clutter_density"}."""
    numbers = _numbers("tracklab.filters.pdaf", base, gate, p_detect, clutter_density, m)
    return associate(base, "pdaf", _split_nested, m)._replace(params={"base": base.params, **numbers})


def ipda(base: Filter, m: int, *, clutter_density: float, p_detect: float = 1.0, gate: float | None = None,
         p_survive: float = 0.98, existence0: float = 0.9) -> Filter:
    """The IPDA of ``base``: the PDAF's update and the target's existence probability (see the
    module's doc), ``p_survive`` p_S per step, ``existence0`` its prior. params as ``pdaf``'s
    and {"p_survive", "existence0"}."""
    where = "tracklab.filters.ipda"
    numbers = _numbers(where, base, gate, p_detect, clutter_density, m)
    numbers["p_survive"] = jnp.asarray(_check_probability(where, "p_survive", p_survive))
    numbers["existence0"] = jnp.asarray(_check_probability(where, "existence0", existence0, upper_open=True))
    return associate(base, "ipda", _split_nested, m, wrap_state=True)._replace(params={"base": base.params, **numbers})


# ------------------------------------------------------------------------- declarations

GATE = Param("validation gate γ on d² = νᵀS⁻¹ν; default: the gate a target return passes with probability 0.99",
             positive, "", tune=True)
ASSUMED_P_DETECT = Param("the detection probability the filter assumes; default the sensor's", unit_interval, "",
                         tune=True)
ASSUMED_DENSITY = Param("the clutter density λ the filter assumes; default the sensor's", positive,
                        "per unit measurement volume", tune=True, sweep=True)
P_SURVIVE = Param("probability that the target goes on existing from one step to the next", bounded(0.0, 1.0), "",
                  0.98, tune=True)
EXISTENCE0 = Param("the target's existence probability before the first scan", bounded(0.0, 1.0), "", 0.9, tune=True)


HARD_RULES = ("nn", "snf")  # rules that choose one return: no gradient, their numbers not tuned
ASSOCIATION_FIELDS = ("base", "gate", "p_detect", "clutter_density", "p_survive", "existence0")


def association_numbers(e, rule: str) -> dict:
    """An association's own numbers from its [[filter]] table (``e``: a ``kind.Entry``): the gate
    (default: P_G = 0.99), and for the PDAF and IPDA the P_D and λ they assume (default the
    sensor's), for the IPDA p_S and the prior existence; each checked in one line."""
    m = e.meas.m
    clutter = cluttered_of(e.meas)
    if rule == "snf" and (clutter is None or clutter.snr is None):
        raise e.error("kind", "snf", "needs the returns in order of amplitude: give the [sensor] the target's mean SNR, "
                      "snr = … (dB)")
    out = {"gate": e.number("gate", chi2_gate(0.99, m), positive=True)}
    if rule not in HARD_RULES:
        pd = e.number("p_detect", float(np.asarray(e.meas.sensors[0].p_detect)))
        if not 0.0 < pd <= 1.0:
            raise e.error("p_detect", pd, "must be a probability in (0, 1]")
        out["p_detect"] = pd
        density = None if clutter is None else float(np.asarray(clutter.density))
        lam = e.number("clutter_density", density, nonneg=True)
        if lam is None:
            raise e.error("clutter_density", None, "is required: the sensor has no clutter to take it from "
                          "(false alarms per unit volume of the measurement space)")
        if rule == "ipda" and lam <= 0:
            raise e.error("clutter_density", lam, "must be > 0 for the IPDA (its existence update divides by it): "
                          + ("give the filter its own clutter_density, or the sensor one > 0" if
                             not e.has("clutter_density") else "the λ the IPDA assumes"))
        out["clutter_density"] = lam
    if rule == "ipda":
        out["p_survive"] = e.number("p_survive", P_SURVIVE.default, lo=0.0, hi=1.0)
        out["existence0"] = e.number("existence0", EXISTENCE0.default, lo=0.0, hi=1.0)
        if not 0.0 < out["p_survive"] <= 1.0:
            raise e.error("p_survive", out["p_survive"], "must be a probability in (0, 1]")
        if not 0.0 < out["existence0"] < 1.0:
            raise e.error("existence0", out["existence0"], "must be a probability in (0, 1)")
    return out


def associated(flt: Filter, rule: str, numbers: dict, m: int) -> Filter:
    """A filter of one's own (params a dict) under the association ``rule`` with its ``numbers``
    (``association_numbers``), their params side by side: what ``base = "module:factory"`` gives."""
    if not isinstance(flt.params, dict):
        raise TypeError(f"its params are {type(flt.params).__name__}: an association in a file needs them as a dict "
                        "(tracklab.declare's numbers are)")
    keys = tuple(flt.params)
    clash = sorted(set(keys) & set(numbers))
    if clash:
        raise TypeError(f"its params hold {clash[0]!r}, which the association sets: name it otherwise")
    split = lambda p: ({k: p[k] for k in keys}, p)  # noqa: E731
    out = associate(flt, rule, split, m, wrap_state=rule == "ipda")
    return out._replace(params={**flt.params, **{k: jnp.asarray(v) for k, v in numbers.items()}})


def association_kinds(bases: Mapping) -> tuple:
    """The kinds ``nn``, ``pdaf`` and ``ipda`` over the Gaussian filter kinds ``bases`` (name ->
    FilterKind): a [[filter]] table names its base with ``base = "ekf"`` and holds the base's
    fields (q or accel_sigma, r or the sensor's sigmas, …) beside the association's."""

    def reader(rule):
        def read(e):
            name = e.string("base", "ekf")
            if name not in bases:
                raise e.error("base", name, f"must be one of {', '.join(bases)}, or \"package.module:factory\" (a "
                              "filter of one's own whose state is a Gaussian (x, P))")
            base = bases[name]
            if e.meas.kind not in base.accepts:
                raise e.error("base", name, f"sees a '{e.meas.kind}' sensor: a base of kind "
                              f"{' or '.join(n for n, b in bases.items() if e.meas.kind in b.accepts)}")
            inner = type(e)(e.fields, base, e.meas, dim=e.dim, dt=e.dt, accel_sigma=e.accel_sigma,
                            sigma_fields=e.sigma_fields)
            model, params, options = base.read(inner)
            return model, {**params, **association_numbers(e, rule)}, {"base": name, **options}

        return read

    def builder(rule):
        def build(model, sensor, params, options):
            options = dict(options)
            base = bases[options.pop("base")]
            flt = base.build(model, sensor, base.with_defaults(params), options)
            return associate(flt, rule, lambda p: (p, p), sensor.m, wrap_state=rule == "ipda")._replace(params=params)

        return build

    common = {"q": PROCESS_NOISE, "r": MEASUREMENT_NOISE}
    pda = {"gate": GATE, "p_detect": ASSUMED_P_DETECT, "clutter_density": ASSUMED_DENSITY}
    # a hard choice of one return has no gradient: the nearest and strongest neighbours' numbers are not tuned
    hard = {n: dataclasses.replace(p, tune=False) for n, p in (common | {"gate": GATE}).items()}
    kinds = (
        FilterKind("nn", "nearest neighbour: the validated return of least d² (base = ekf, kf, …)", ANY_SENSOR,
                   hard, reader("nn"), builder("nn"), scans=True),
        FilterKind("snf", "strongest neighbour: the validated return of greatest amplitude (needs the sensor's snr; "
                   "base = ekf, kf, …)", ANY_SENSOR, hard, reader("snf"), builder("snf"), scans=True),
        FilterKind("pdaf", "probabilistic data association filter (base = ekf, kf, …)", ANY_SENSOR, common | pda,
                   reader("pdaf"), builder("pdaf"), scans=True),
        FilterKind("ipda", "integrated PDA: the PDAF with the target's existence probability (base = ekf, kf, …)",
                   ANY_SENSOR, common | pda | {"p_survive": P_SURVIVE, "existence0": EXISTENCE0}, reader("ipda"),
                   builder("ipda"), scans=True),
    )
    return kinds
