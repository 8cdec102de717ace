"""Differentiable tuning: optax through the whole Monte-Carlo simulation.

The loss is a function of the per-step sums the engine computes for a batch of
runs, so its gradient with respect to the filters' parameters flows through
simulation, filtering and statistics. Each optimisation step draws a fresh
batch of runs; the result is evaluated on held-out runs.

Parameters are optimised in an unconstrained space:

* ``q``, ``r``, ``lam``, ``b``, ``q_e``, ``r_e``, ``r_guide`` (variances, the
  tracking index, the STF's weakening factor): logarithms;
* ``rho``, ``forget`` (the STF's and the DEKF's forgetting factors, in (0, 1)): logit;
* ``w0`` (the DEKF's initial network weights): as they are;
* ``alpha``, ``beta`` (, ``gamma``): tuned together inside the α-β(-γ) stability
  region (Jury): α = 2σ(u), β = (4 − 2α)σ(v), γ = 4αβ/(2 − α)·σ(w), σ the logistic.

Losses (time-averaged over the report window, summed over the tuned filters):

* ``mse_pos`` — position mean-square error;
* ``pred_mse`` — one-step prediction mean-square error of the position;
* ``nll`` — innovation negative log-likelihood ½(νᵀS⁻¹ν + log det S) per
  update (needs no truth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from tracklab.engine import make_chunk_fn

GAINS = ("alpha", "beta", "gamma")
POSITIVE = ("q", "r", "lam", "b", "q_e", "r_e", "r_guide", "pw0")
UNIT = ("rho", "forget")
FREE = ("w0",)  # unconstrained: the DEKF's initial network weights
TUNABLE = POSITIVE + UNIT + FREE + GAINS


def _window_mean(x, window):
    a, b = window
    return jnp.mean(x[a - 1:b])


def _safe_div(a, b):
    return a / jnp.maximum(b, 1.0)


LOSSES: dict[str, Callable] = {
    "mse_pos": lambda s, w: _window_mean(_safe_div(jnp.sum(s["sumsq_pos"], -1), s["count"]), w),
    "pred_mse": lambda s, w: _window_mean(_safe_div(jnp.sum(s["sumsq_pred"], axis=-1), s["count"]), w),
    "nll": lambda s, w: _window_mean(0.5 * _safe_div(s["sum_nis"] + s["sum_logdet_s"], s["count_nis"]), w),
}


def encode(params: dict, names) -> dict:
    """Unconstrained coordinates of the named parameters."""
    theta = {}
    for n in names:
        if n in POSITIVE:
            theta[n] = jnp.log(jnp.asarray(params[n], float))
        elif n in UNIT:
            theta[n] = jax.scipy.special.logit(jnp.minimum(jnp.asarray(params[n], float), 1.0 - 1e-6))
        elif n in FREE:
            theta[n] = jnp.asarray(params[n], float)
    gains = [g for g in GAINS if g in params]
    if any(g in names for g in GAINS):
        a = jnp.asarray(params["alpha"], float)
        b = jnp.asarray(params["beta"], float)
        theta["alpha"] = jax.scipy.special.logit(a / 2)
        theta["beta"] = jax.scipy.special.logit(b / (4 - 2 * a))
        if "gamma" in gains:
            g = jnp.asarray(params["gamma"], float)
            theta["gamma"] = jax.scipy.special.logit(g * (2 - a) / (4 * a * b))
    return theta


def decode(theta: dict, params: dict) -> dict:
    """Parameters with the tuned ones replaced by their constrained values."""
    out = dict(params)
    for n in POSITIVE:
        if n in theta:
            out[n] = jnp.exp(theta[n])
    for n in UNIT:
        if n in theta:
            out[n] = jax.nn.sigmoid(theta[n])
    for n in FREE:
        if n in theta:
            out[n] = theta[n]
    if "alpha" in theta:
        a = 2 * jax.nn.sigmoid(theta["alpha"])
        b = (4 - 2 * a) * jax.nn.sigmoid(theta["beta"])
        out["alpha"], out["beta"] = a, b
        if "gamma" in theta:
            out["gamma"] = 4 * a * b / (2 - a) * jax.nn.sigmoid(theta["gamma"])
    return out


MAX_MAGNITUDE = 1e15  # what an experiment file accepts (tracklab.config)


def acceptable(params: dict, names) -> str | None:
    """Why the named parameter values could not be written into an experiment file that
    ``tracklab run`` accepts (None if they can)."""
    for n in names:
        if n not in params or n in FREE:
            continue
        v = np.asarray(params[n], float)
        if not np.all(np.isfinite(v)):
            return f"{n} is not finite"
        if n in POSITIVE and not np.all((v >= 1e-300) & (v <= MAX_MAGNITUDE)):
            return f"{n} leaves [1e-300, {MAX_MAGNITUDE:g}]"
        if n in UNIT and not np.all((v > 0) & (v <= 1)):
            return f"{n} leaves (0, 1]"
        if n in GAINS and not np.all((v > 0) & (v < 4)):
            return f"{n} leaves (0, 4)"
    return None


def unwritable(exp, chosen: dict) -> str | None:
    """Why the tuned values of ``chosen`` ({label: names}) could not be written back into the
    experiment file (None if they can): checked before tuning starts."""
    for fc in exp.filters:
        names = chosen.get(fc.label, ())
        if "w0" in names:
            return f"filter {fc.label!r}: network weights (w0) are tuned through the Python API; a file holds none"
        if "r" in names and "r" not in exp.raw["filter"][exp.filters.index(fc)]:
            from tracklab.config import SENSOR_SIGMAS

            _, meas = exp.view(fc)
            if meas.kind not in SENSOR_SIGMAS:  # written back as the one sensor's sigmas
                return (f"filter {fc.label!r} sees several sensors: its r cannot be written back as sensor sigmas "
                        f"(give the filter r = [...] in the file to tune it)")
    return None


def memory_bytes(exp, runs_per_step, eval_runs=None) -> float:
    """A lower bound: the filter states reverse mode keeps for every run and step of a batch,
    and the held-out evaluation's random draws."""
    n = [(3 if fc.model == "ca" else 2) * exp.dim for fc in exp.filters]  # each filter's state dimension
    state = sum(k * (1 + k) for k in n)  # its mean and covariance
    n_eval = eval_runs or min(exp.runs, 2000)
    width = 2 * exp.dim + exp.sensor.m
    return runs_per_step * exp.steps * state * 8.0 + min(n_eval, 1000) * exp.steps * width * 4.0


def selection(exp, names, labels=None) -> dict[str, tuple[str, ...]]:
    """Which parameters of which filters are tuned: {label: names}."""
    chosen = {}
    for fc in exp.filters:
        if labels and fc.label not in labels:
            continue
        have = tuple(n for n in names if n in fc.params)
        if have:
            chosen[fc.label] = have
    return chosen


@dataclass
class Objective:
    """loss(theta, key, idx, live) for the selected parameters of an experiment."""

    loss: Callable
    theta0: dict
    base: list  # each filter's parameters (pytree)
    labels: list
    chosen: dict

    def params(self, theta):
        return [decode(theta[l], p) if l in theta else p for l, p in zip(self.labels, self.base)]


def objective(exp, names, loss="mse_pos", labels=None) -> Objective:
    specs = exp.filter_specs()
    chosen = selection(exp, names, labels)
    if not chosen:
        raise ValueError(f"no filter has any of the parameters {', '.join(names)}")
    # products as outer-product sums: element by element, the gradient compiles slowly
    fn = make_chunk_fn(exp.scenario, exp.sensor, specs, exp.prior_covariance(), exp.dt, elementwise=False)
    base = [s.filter.params for s in specs]
    labels_all = [s.label for s in specs]
    theta0 = {l: encode(base[labels_all.index(l)], ns) for l, ns in chosen.items()}
    loss_fn = LOSSES[loss]
    window = exp.window

    def total(theta, key, idx, live):
        params_list = [decode(theta[l], p) if l in theta else p for l, p in zip(labels_all, base)]
        sums = fn(params_list, key, idx, live)
        return sum(loss_fn(sums[l], window) for l in chosen)

    return Objective(total, theta0, base, labels_all, chosen)


@dataclass
class TuneResult:
    params: dict  # label -> tuned parameters (floats / lists)
    initial: dict  # label -> starting parameters
    history: list = field(default_factory=list)  # (step, loss, gradient norm)
    eval_initial: float = math.nan
    eval_tuned: float = math.nan
    stopped: str = ""


def _floats(p, names):
    return {n: np.asarray(p[n]).tolist() for n in names}


def tune(exp, names, *, steps=200, lr=0.05, loss="mse_pos", runs_per_step=None, eval_runs=None, seed=None,
         labels=None, every=10, progress=None) -> TuneResult:
    """Adam (optax) on the named parameters; a fresh batch of runs every step."""
    obj = objective(exp, names, loss, labels)
    B = int(runs_per_step or min(exp.runs, 256))
    n_eval = int(eval_runs or min(exp.runs, 2000))
    key = jax.random.key(exp.seed if seed is None else seed)
    train_key, eval_key = jax.random.fold_in(key, 1), jax.random.fold_in(key, 2)  # held-out runs
    idx = jnp.arange(B, dtype=jnp.uint32)
    live = jnp.ones((B,), bool)
    value_and_grad = jax.jit(jax.value_and_grad(obj.loss))
    opt = optax.adam(lr)
    theta = obj.theta0
    state = opt.init(theta)
    result = TuneResult(params={}, initial={l: _floats(obj.base[obj.labels.index(l)], n) for l, n in obj.chosen.items()})

    def evaluate(th):
        e_idx = jnp.arange(n_eval, dtype=jnp.uint32)
        return float(jax.jit(obj.loss)(th, eval_key, e_idx, jnp.ones((n_eval,), bool)))

    result.eval_initial = evaluate(theta)
    last_finite = theta  # the last parameters whose loss was finite (the start until one is seen)
    for k in range(steps):  # optimisation steps; each one is a whole batched simulation
        val, g = value_and_grad(theta, jax.random.fold_in(train_key, k), idx, live)
        val = float(val)
        gnorm = float(jnp.sqrt(sum(jnp.vdot(x, x) for x in jax.tree_util.tree_leaves(g))))
        if not math.isfinite(val):
            theta = last_finite
            result.stopped = (f"stopped at step {k}: non-finite loss; kept the parameters of step "
                              f"{k - 1 if k else 0} (the last with a finite loss)")
            break
        last_finite = theta
        if not math.isfinite(gnorm):
            result.stopped = f"stopped at step {k}: non-finite gradient; kept the parameters of step {k}"
            break
        result.history.append((k, val, gnorm))
        if progress and (k % every == 0 or k == steps - 1):
            progress(k, val, gnorm)
        updates, new_state = opt.update(g, state, theta)
        new_theta = optax.apply_updates(theta, updates)
        why = next((acceptable(p, obj.chosen[l]) for l, p in zip(obj.labels, obj.params(new_theta))
                    if l in obj.chosen and acceptable(p, obj.chosen[l])), None)
        if why:  # the step would leave what an experiment file accepts
            result.stopped = f"stopped after step {k}: the next step's {why}; kept the parameters of step {k}"
            break
        theta, state = new_theta, new_state
    tuned = obj.params(theta)
    result.params = {l: _floats(tuned[obj.labels.index(l)], n) for l, n in obj.chosen.items()}
    result.eval_tuned = evaluate(theta)
    return result


def tuned_document(exp, result: TuneResult, out_path) -> dict:
    """The experiment file with the tuned values written into its filters."""
    import copy
    import os
    from pathlib import Path

    from tracklab.config import SENSOR_SIGMAS

    doc = copy.deepcopy(exp.raw)
    doc.pop("study", None)  # the tuned file is a result: its studies stay with the original
    doc["experiment"]["name"] = f"{exp.name}_tuned"
    out_dir = Path(out_path).resolve().parent
    sc = doc.get("scenario", {})
    if "path" in sc:  # keep the trajectory reachable from the new file's folder
        sc["path"] = os.path.relpath(Path(exp.scenario.path), out_dir)
    for fc, table in zip(exp.filters, doc["filter"]):
        tuned = result.params.get(fc.label)
        if not tuned:
            continue
        table["label"] = f"{fc.label}, tuned"
        if "q" in tuned:
            if "q" in table:
                table["q"] = float(tuned["q"])
            else:
                key = "accel_sigma" if fc.model == "cv" else "accel_increment_sigma"
                table[key] = math.sqrt(float(tuned["q"]))
        for k in ("rho", "b", "q_e", "forget", "pw0"):
            if k in tuned:
                table[k] = float(tuned[k])
        if "w0" in tuned:
            raise ValueError(f"filter {fc.label!r}: tuned network weights cannot be written into an experiment file")
        for k in ("r_e", "r_guide"):
            if k in tuned:
                table[k] = [float(v) for v in np.atleast_1d(tuned[k])]
        if "r" in tuned and "r" in table:
            table["r"] = [float(v) for v in np.atleast_1d(tuned["r"])]
        elif "r" in tuned:
            _, meas = exp.view(fc)
            sig = [math.sqrt(v) for v in np.atleast_1d(tuned["r"])]
            if meas.kind == "cartesian":
                table["sigma"] = sig
            elif meas.kind in SENSOR_SIGMAS:
                table.update(dict(zip(SENSOR_SIGMAS[meas.kind], sig)))
            else:
                raise ValueError(f"filter {fc.label!r} sees several sensors: its R cannot be written back")
        if any(g in tuned for g in GAINS):
            for g in GAINS:
                if g in tuned:
                    table[g] = tuned[g]
            table["gains"] = "explicit"
            for k in ("tracking_index", "sigma_w", "floor"):
                table.pop(k, None)
        if "lam" in tuned:
            table["tracking_index"] = list(np.atleast_1d(tuned["lam"]).tolist())
            table.pop("sigma_w", None)
    return doc
