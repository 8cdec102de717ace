"""Differentiable tuning: optax through the whole Monte-Carlo simulation.

The loss is a function of the per-step sums the engine computes for a batch of
runs, so its gradient with respect to the filters' parameters flows through
simulation, filtering and statistics. Each optimisation step draws a fresh
batch of runs; the result is evaluated on held-out runs.

Parameters are optimised in an unconstrained space, the one their kind's declaration
gives (``tracklab.filters.kind``: each parameter's constraint):

* positive ones (``q``, ``r``, ``lam``, ``b``, ``q_e``, ``r_e``, ``r_guide``, ``pw0``:
  variances, the tracking index, the STF's weakening factor): logarithms;
* ones in (0, 1] (``rho``, ``forget``: the STF's and the DEKF's forgetting factors): logit;
* free ones (``w0``, the DEKF's initial network weights): as they are;
* ``alpha``, ``beta`` (, ``gamma``): tuned together inside the α-β(-γ) stability
  region (Jury): α = 2σ(u), β = (4 − 2α)σ(v), γ = 4αβ/(2 − α)·σ(w), σ the logistic.

Which parameters may be tuned (``TUNABLE``) and how a tuned value is written back
into the experiment file are declared there too.

Losses (time-averaged over the report window). Each tuned filter has its own: the
optimiser follows the gradient of their sum, in which a filter's parameters reach only
its own term, so no filter's tuning is steered by another's error, and each filter's
loss is recorded and evaluated on its own:

* ``mse_pos`` — position mean-square error;
* ``pred_mse`` — one-step prediction mean-square error of the position;
* ``nll`` — innovation negative log-likelihood ½(νᵀS⁻¹ν + log det S) per
  update (needs no truth).

The closed loops tune through their own hooks (``tune_names``, ``tune_losses``,
``tune_selection``, ``tune_start``, ``with_tuned``, ``write_tuned`` of an airborne or
servo experiment): the airborne trackers' ``q_scale``, ``r_scale``, ``lam`` against the
true pointing error (``pointing``) or the LOS-rate error (``los_rate``); the servo
estimators' ``q`` against the tracking error (``track_mse``) or the rate error
(``rate_mse``); all positive, tuned in their logarithms, the gradient through the whole
closed loop (the estimate steers the antenna or the mount).

The gradient (``gradient``) is taken in forward mode (``jax.jacfwd``: one tangent per tuned
number carried through the scans, nothing kept per step) for up to ``FORWARD_UP_TO`` tuned
numbers, in reverse mode above. With two or three numbers, forward mode compiled in 0.3–0.85×
the time and stepped in 0.35–0.95× (``benchmarks/tune.md``; the airborne joint EKF: 17 s
against 50 s to compile); its cost grows with every number tuned, reverse mode's does not
(15 numbers: 2.8× slower a step).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from tracklab.config.writeback import write_back
from tracklab.worlds.tracking.experiment import declared_of
from tracklab.filters.kind import FilterKind
from tracklab.filters.registry import KINDS
from tracklab.montecarlo import runner
from tracklab.parameters import constraint_of, positive
from tracklab.pytree import named_leaves, with_leaves
from tracklab.worlds.tracking import errors, scan
from tracklab.worlds.tracking.errors import LOSSES
from tracklab.worlds.tracking.lanes import FilterSpec


def _constrained_together(kind: FilterKind, params: dict, names):
    """(constraint, the parameters it transforms together) for the named parameters of a filter."""
    groups = []
    for n in names:
        c = kind.params[n].constraint
        group = (c, tuple(m for m in c.members if m in params) if c.members else (n,))
        if group not in groups:
            groups.append(group)
    return groups


def encode(kind: FilterKind, params: dict, names) -> dict:
    """Unconstrained coordinates of the named parameters of a filter of ``kind``."""
    theta = {}
    for c, group in _constrained_together(kind, params, names):
        theta.update(c.encode({n: params[n] for n in group}))
    return theta


def decode(kind: FilterKind, theta: dict, params: dict) -> dict:
    """Parameters with the tuned ones replaced by their constrained values."""
    out = dict(params)
    for c, group in _constrained_together(kind, params, theta):
        out.update(c.decode({n: theta[n] for n in group}))
    return out


def acceptable(kind: FilterKind, params: dict, names) -> str | None:
    """Why the named parameter values could not be written into an experiment file that
    ``tracklab run`` accepts (None if they can)."""
    for n in names:
        p = kind.params[n]
        if n not in params or p.write is None:  # a file holds none
            continue
        v = np.asarray(params[n], float)
        if not np.all(np.isfinite(v)):
            return f"{n} is not finite"
        if not np.all(p.constraint.inside(v)):
            return f"{n} leaves {p.constraint.bounds}"
    return None


def unwritable(exp, chosen: dict) -> str | None:
    """Why the tuned values of ``chosen`` ({label: names}) could not be written back into the
    experiment file (None if they can): checked before tuning starts."""
    import copy

    if hasattr(exp, "write_tuned"):
        return None  # the closed loops' tuned numbers are [[tracker]] / [[estimator]] fields

    for fc, table in zip(exp.filters, exp.raw["filter"]):
        if isinstance(fc, FilterSpec):  # a factory's filter: a tuned value goes back as the keyword of that name
            missing = [n for n in chosen.get(fc.label, ()) if n not in table and n not in fc.declared]
            if missing:
                return (f"filter {fc.label!r}: {missing[0]} is no key of its [[filter]] table, so a tuned value "
                        f"has nowhere to go in the file (tune it from Python: tracklab.tune)")
            continue
        kind = KINDS[fc.kind]
        for n in chosen.get(fc.label, ()):
            p = kind.params[n]
            if p.write is None:
                return f"filter {fc.label!r}: {n} ({p.doc}) is tuned through the Python API; a file holds none"
            try:
                p.write(copy.deepcopy(table), n, fc.params[n], write_back(exp, fc))
            except ValueError as e:
                return f"filter {fc.label!r}: {e}"
    return None


FORWARD_UP_TO = 4  # tuned numbers: forward-mode gradient up to here, reverse mode above


def forward_mode(numbers: int) -> bool:
    """Whether a tuning of this many numbers takes its gradient in forward mode."""
    return numbers <= FORWARD_UP_TO


def gradient(total, numbers: int):
    """``jax.value_and_grad(total, has_aux=True)`` for ``total(theta, *args) -> (loss, aux)``,
    in forward mode (``jax.jacfwd``) for up to ``FORWARD_UP_TO`` tuned numbers, reverse above."""
    if not forward_mode(numbers):
        return jax.value_and_grad(total, has_aux=True)

    @functools.wraps(total)  # the compiled program keeps the loss's name
    def value_and_grad(theta, *args):
        def loss(th):
            value, aux = total(th, *args)
            return value, (value, aux)

        g, (value, aux) = jax.jacfwd(loss, has_aux=True)(theta)
        return (value, aux), g

    return value_and_grad


def numbers(theta) -> int:
    """How many numbers a tuning moves (each entry of a vector parameter counts)."""
    return sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(theta))


def tuned_numbers(exp, chosen: dict) -> int:
    """``numbers`` of a selection (``selection``), from the file's values, before anything is traced."""
    if hasattr(exp, "tune_start"):
        return numbers(exp.tune_start(chosen))
    base = dict(zip((fc.label for fc in exp.filters), exp.params().filters))
    own = {fc.label for fc in exp.filters if isinstance(fc, FilterSpec)}
    return numbers({l: [(named_leaves(base[l]) if l in own else base[l])[n] for n in ns] for l, ns in chosen.items()})


def memory_bytes(exp, runs_per_step, eval_runs=None, tuned=FORWARD_UP_TO + 1) -> float:
    """A lower bound on one tuning step of ``tuned`` numbers (tuning runs in float64). Reverse
    mode: the filter states it keeps for every run and step of a batch; forward mode, which keeps
    no step's states: the batch's random draws for every step and the current step's filter
    states with one tangent per tuned number (a closed loop: its per-period outputs). Plus the
    held-out evaluation's draws."""
    if hasattr(exp, "tune_memory_bytes"):
        if forward_mode(tuned):
            return runs_per_step * exp.run_bytes
        return exp.tune_memory_bytes(runs_per_step)
    n = [fc.report_layout(exp.dim).n if isinstance(fc, FilterSpec) else (3 if fc.model == "ca" else 2) * exp.dim
         for fc in exp.filters]  # each filter's state dimension
    state = sum(k * (1 + k) for k in n)  # its mean and covariance
    n_eval = eval_runs or min(exp.runs, 2000)
    width = 2 * exp.dim + exp.sensor.m
    held_out = min(n_eval, 1000) * exp.steps * width * 4.0
    if forward_mode(tuned):
        return runs_per_step * (exp.steps * width + state * (1 + tuned)) * 8.0 + held_out
    return runs_per_step * exp.steps * state * 8.0 + held_out


def selection(exp, names, labels=None) -> dict:
    """Which parameters of which filters (trackers, estimators) are tuned: {label: names}.

    ``names``: parameter names (every selected built-in filter that declares one, tunable,
    has it tuned), or {label: names} naming each filter's own: for a built-in kind a list of
    its declared parameters, for a filter of one's own (``FilterSpec``) {leaf name:
    constraint} over its params pytree (``tracklab.pytree.named_leaves``; constraints
    "positive", "unit", "free" or (lo, hi)). ``ValueError`` in one line for a label, name or
    constraint that does not fit."""
    if hasattr(exp, "tune_selection"):
        return exp.tune_selection([n for n in names if n in exp.tune_names], labels)
    if isinstance(names, dict):
        return _named_selection(exp, names)
    chosen = {}
    for fc in exp.filters:
        if labels and fc.label not in labels:
            continue
        if isinstance(fc, FilterSpec):  # a factory's declared numbers, each in its constraint's coordinates
            have = {n: fc.declared[n].constraint for n in names if n in fc.declared and fc.declared[n].tune}
        else:
            have = tuple(n for n in names if n in declared_of(fc) and declared_of(fc)[n].tune)
        if have:
            chosen[fc.label] = have
    return chosen


def _named_selection(exp, names: dict) -> dict:
    by_label = {fc.label: fc for fc in exp.filters}
    chosen = {}
    for label, wanted in names.items():
        if label not in by_label:
            raise ValueError(f"tune: no filter labelled {label!r} (filters: {', '.join(by_label)})")
        fc = by_label[label]
        if isinstance(fc, FilterSpec):
            if not isinstance(wanted, dict):  # declared numbers, by name: their declared constraints
                undeclared = [n for n in wanted if n not in fc.declared or not fc.declared[n].tune]
                if undeclared:
                    raise ValueError(f"tune: filter {label!r} declares no tunable {undeclared[0]!r} (declared: "
                                     f"{', '.join(n for n, p in fc.declared.items() if p.tune) or 'none'}); give "
                                     f"each leaf of its params its constraint, e.g. {{{label!r}: {{'q': 'positive'}}}}")
                wanted = {n: fc.declared[n].constraint for n in wanted}
            leaves = named_leaves(fc.filter.params)
            picked = {}
            for n, spec in wanted.items():
                if n not in leaves:
                    raise ValueError(f"tune: filter {label!r} has no parameter {n!r} (its parameters: "
                                     f"{', '.join(k or '(the params itself)' for k in leaves)})")
                if not jnp.issubdtype(jnp.result_type(leaves[n]), jnp.floating):
                    raise ValueError(f"tune: filter {label!r}: {n} is {jnp.result_type(leaves[n]).name}, not a "
                                     f"floating-point number: it cannot be differentiated")
                try:
                    c = constraint_of(spec)
                except ValueError as e:
                    raise ValueError(f"tune: filter {label!r}: {n}: {e}") from None
                if not np.all(np.asarray(c.inside(np.asarray(leaves[n], float)))):
                    raise ValueError(f"tune: filter {label!r}: {n} = {np.asarray(leaves[n]).tolist()} is outside "
                                     f"its constraint {c.bounds}")
                picked[n] = c
            if picked:
                chosen[label] = picked
            continue
        kind = KINDS[fc.kind]
        wanted = list(wanted)
        for n in wanted:
            if not (n in declared_of(fc) and declared_of(fc)[n].tune):
                ok = [k for k, p in declared_of(fc).items() if p.tune]
                raise ValueError(f"tune: filter {label!r} ({kind.name}) has no tunable parameter {n!r} "
                                 f"(tunable: {', '.join(ok) or 'none'})")
        if wanted:
            chosen[label] = tuple(wanted)
    return chosen


@dataclass
class Objective:
    """losses(theta, key, idx, live) -> {label: loss} for the selected parameters of an experiment
    (any world): each tuned filter's (tracker's, case's) own loss."""

    losses: Callable
    theta0: dict  # label -> unconstrained coordinates of its tuned parameters
    values: Callable  # theta -> {label: {name: value}}, the tuned parameters' constrained values
    chosen: dict  # label -> names
    why_not: Callable  # {label: {name: value}} -> why a file could not hold them (None if it can)
    compiler_options: dict | None = None  # XLA options of the world's programs (``runner.World``)

    @property
    def initial(self) -> dict:
        return self.values(self.theta0)


def objective(exp, names, loss="mse_pos", labels=None) -> Objective:
    losses = getattr(exp, "tune_losses", LOSSES)
    if loss not in losses:
        raise ValueError(f"tune: loss {loss!r}: must be one of {', '.join(losses)}")
    chosen = selection(exp, names, labels)
    if not chosen:
        raise ValueError(f"no filter has any of the parameters {', '.join(names)}")
    if hasattr(exp, "tune_selection"):
        return _closed_loop_objective(exp, chosen, loss)
    structure = exp.structure()
    world = scan.world(structure)
    fn = runner.sharded(world)
    params = exp.params()
    base = params.filters
    labels_all = structure.labels
    entries = dict(zip(labels_all, exp.filters))
    at = {l: labels_all.index(l) for l in chosen}
    loss_fn = LOSSES[loss]
    window = exp.window

    def own(label):  # a filter of one's own: {name: constraint}
        return isinstance(entries[label], FilterSpec)

    def encode_one(l):
        if own(l):
            leaves = named_leaves(base[at[l]])
            return {n: c.to_free(jnp.asarray(leaves[n], float)) for n, c in chosen[l].items()}
        return encode(KINDS[entries[l].kind], base[at[l]], chosen[l])

    def decode_one(l, theta_l, p):
        if own(l):
            return with_leaves(p, {n: c.from_free(theta_l[n]) for n, c in chosen[l].items()})
        return decode(KINDS[entries[l].kind], theta_l, p)

    theta0 = {l: encode_one(l) for l in chosen}

    def filters(theta):
        return [decode_one(l, theta[l], f) if l in theta else f for l, f in zip(labels_all, base)]

    def per_filter(theta, key, idx, live):
        p = params._replace(filters=filters(theta))
        sums = errors.unpack(fn(p, key, idx, live, jnp.zeros((len(labels_all), idx.shape[0]), bool)), exp.dim)
        return {l: loss_fn(sums[l], window) for l in chosen}

    def values(theta):
        f = filters(theta)
        return {l: {n: (named_leaves(f[at[l]])[n] if own(l) else f[at[l]][n]) for n in ns} for l, ns in chosen.items()}

    def why_not(vals):
        for l, v in vals.items():
            if own(l):
                why = next((f"{n} leaves {chosen[l][n].bounds}" for n, x in v.items()
                            if not np.all(np.isfinite(np.asarray(x))) or not chosen[l][n].contains({n: x})), None)
            else:
                why = acceptable(KINDS[entries[l].kind], v, chosen[l])
            if why:
                return why
        return None

    return Objective(per_filter, theta0, values, {l: tuple(ns) for l, ns in chosen.items()}, why_not,
                     runner.world_compiler_options(world))


def _closed_loop_objective(exp, chosen, loss) -> Objective:
    """The airborne or servo world's: every tuned number is positive (tuned in its logarithm)."""
    structure = exp.structure()
    world = exp.world(structure)
    fn = runner.sharded(world)
    params = exp.params()
    lanes = getattr(exp, "tune_lanes", lambda c: list(c))(chosen)
    loss_fn = exp.tune_losses[loss]
    theta0 = {l: positive.encode(vals) for l, vals in exp.tune_start(chosen).items()}

    def values(theta):
        return {l: positive.decode(t) for l, t in theta.items()}

    def per_lane(theta, key, idx, live):
        p = exp.with_tuned(params, values(theta))
        sums = fn(p, key, idx, live, jnp.zeros((len(structure.labels), idx.shape[0]), bool))
        return {l: loss_fn(sums[l]) for l in lanes}

    def why_not(vals):
        return next((f"{l}: {n} leaves {positive.bounds}" for l, v in vals.items() for n, x in v.items()
                     if not positive.contains({n: x})), None)

    return Objective(per_lane, theta0, values, chosen, why_not, runner.world_compiler_options(world))


@dataclass
class TuneResult:
    params: dict  # label -> tuned parameters (floats / lists)
    initial: dict  # label -> starting parameters
    history: list = field(default_factory=list)  # (step, {label: its loss on that step's runs}, gradient norm)
    eval_initial: dict = field(default_factory=dict)  # label -> its loss on the held-out runs, before
    eval_tuned: dict = field(default_factory=dict)  # label -> … after
    stopped: str = ""
    loss: str = ""  # which loss
    runs_per_step: int = 0
    eval_runs: int = 0
    wall_s: float = 0.0  # the whole tuning, compiling and the held-out evaluations included


def _floats(values: dict) -> dict:
    """{label: {name: value}} as plain numbers (and lists)."""
    return {l: {n: np.asarray(v).tolist() for n, v in vals.items()} for l, vals in values.items()}


def tune(exp, names, *, steps=200, lr=0.05, loss="mse_pos", runs_per_step=None, eval_runs=None, seed=None,
         labels=None, every=10, progress=None) -> TuneResult:
    """Adam (optax) on the named parameters (see ``selection``); a fresh batch of runs every step.

    Runs in float64 whatever JAX's global mode (``tracklab.runtime``)."""
    with jax.enable_x64(True):
        return _tune(exp, names, steps=steps, lr=lr, loss=loss, runs_per_step=runs_per_step, eval_runs=eval_runs,
                     seed=seed, labels=labels, every=every, progress=progress)


def _tune(exp, names, *, steps, lr, loss, runs_per_step, eval_runs, seed, labels, every, progress) -> TuneResult:
    import time

    t0 = time.perf_counter()
    obj = objective(exp, names, loss, labels)
    B = int(runs_per_step or min(exp.runs, 256))
    n_eval = int(eval_runs or min(exp.runs, 2000))
    key = jax.random.key(exp.seed if seed is None else seed)
    train_key, eval_key = jax.random.fold_in(key, 1), jax.random.fold_in(key, 2)  # held-out runs
    idx = jnp.arange(B, dtype=jnp.uint32)
    live = jnp.ones((B,), bool)

    def total(theta, key, idx, live):  # a filter's parameters reach only its own term
        losses = obj.losses(theta, key, idx, live)
        return sum(losses.values()), losses

    value_and_grad = jax.jit(gradient(total, numbers(obj.theta0)), compiler_options=obj.compiler_options)
    held_out = jax.jit(obj.losses, compiler_options=obj.compiler_options)
    opt = optax.adam(lr)
    # the parameters go in as host arrays at every step (jax.device_get): an update made of the
    # program's outputs lives where they do (committed to the devices), and a compiled program is
    # found again only for arguments placed as before
    theta = jax.device_get(obj.theta0)
    state = opt.init(theta)
    result = TuneResult(params={}, initial=_floats(obj.initial), loss=loss, runs_per_step=B, eval_runs=n_eval)

    def evaluate(th):
        e_idx = jnp.arange(n_eval, dtype=jnp.uint32)
        return {l: float(v) for l, v in held_out(th, eval_key, e_idx, jnp.ones((n_eval,), bool)).items()}

    result.eval_initial = evaluate(theta)
    last_finite = theta  # the last parameters whose loss was finite (the start until one is seen)
    for k in range(steps):  # optimisation steps; each one is a whole batched simulation
        (val, per), g = value_and_grad(theta, jax.random.fold_in(train_key, k), idx, live)
        val, per = float(val), {l: float(v) for l, v in per.items()}
        if k == 0:
            dead = [f"{l}: {n}" for l, gl in g.items() for n, gn in gl.items() if not np.any(np.asarray(gn))]
            if dead:
                raise ValueError(f"tune: the loss does not depend on {', '.join(dead)} (its gradient is exactly 0): "
                                 f"is it used by the filter's step?")
        gnorm = float(jnp.sqrt(sum(jnp.vdot(x, x) for x in jax.tree_util.tree_leaves(g))))
        if not math.isfinite(val):
            theta = last_finite
            bad = ", ".join(l for l, v in per.items() if not math.isfinite(v))
            result.stopped = (f"stopped at step {k}: non-finite loss ({bad}); kept the parameters of step "
                              f"{k - 1 if k else 0} (the last with a finite loss)")
            break
        last_finite = theta
        if not math.isfinite(gnorm):
            result.stopped = f"stopped at step {k}: non-finite gradient; kept the parameters of step {k}"
            break
        result.history.append((k, per, gnorm))
        if progress and (k % every == 0 or k == steps - 1):
            progress(k, per, gnorm)
        updates, new_state = opt.update(g, state, theta)
        new_theta = optax.apply_updates(theta, updates)
        why = obj.why_not(obj.values(new_theta))
        if why:  # the step would leave what an experiment file accepts
            result.stopped = f"stopped after step {k}: the next step's {why}; kept the parameters of step {k}"
            break
        theta, state = jax.device_get(new_theta), new_state
    result.params = _floats(obj.values(theta))
    result.eval_tuned = evaluate(theta)
    result.wall_s = time.perf_counter() - t0
    return result
