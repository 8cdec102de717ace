"""Differentiable tuning: optax through the whole Monte-Carlo simulation.

The loss is a function of the per-step sums the engine computes for a batch of
runs, so its gradient with respect to the filters' parameters flows through
simulation, filtering and statistics. Each optimisation step draws a fresh
batch of runs; the result is evaluated on held-out runs.

Every world tunes by one path (``objective``). The numbers a study names are the units'
declared ones (``Experiment.declared``: a filter kind's, a factory's ``tracklab.declare``,
an airborne tracker kind's, a servo estimator kind's), each optimised in the unconstrained
coordinates its constraint gives (``tracklab.parameters``):

* positive ones (variances, the tracking index, the STF's weakening factor, the trackers'
  ``q_scale``, ``r_scale``, ``lam``, the estimators' ``q``): logarithms;
* ones in (0, 1] (``rho``, ``forget``: forgetting factors): logit;
* free ones (``w0``, the DEKF's initial network weights): as they are;
* ``alpha``, ``beta`` (, ``gamma``): tuned together inside the α-β(-γ) stability
  region (Jury): α = 2σ(u), β = (4 − 2α)σ(v), γ = 4αβ/(2 − α)·σ(w), σ the logistic.

The values go into the params (``Experiment.with_values``, traced), the world runs a batch of
runs, and each tuned unit's loss is its lane's (``Experiment.tune_losses``; a servo estimator's,
the cases it feeds): the optimiser follows the gradient of their sum, in which a unit's numbers
reach only its own term, so no unit's tuning is steered by another's error. Open loop,
time-averaged over the report window: ``mse_pos`` (position MSE), ``pred_mse`` (one-step
prediction MSE), ``nll`` (innovation negative log-likelihood ½(νᵀS⁻¹ν + log det S) per update,
needing no truth); airborne: ``pointing`` (true pointing error), ``los_rate``; servo:
``track_mse`` (tracking error after settle), ``rate_mse`` — the gradient through the whole
closed loop (the estimate steers the antenna or the mount).

The gradient (``gradient``) is taken in forward mode (``jax.jacfwd``: one tangent per tuned
number carried through the scans, nothing kept per step) for up to ``FORWARD_UP_TO`` tuned
numbers, in reverse mode above. With two or three numbers, forward mode compiled in 0.3–0.85×
the time and stepped in 0.35–0.95× (``benchmarks/tune.md``; the airborne joint EKF: 17 s
against 50 s to compile); its cost grows with every number tuned, reverse mode's does not
(15 numbers: 2.8× slower a step).
"""

from __future__ import annotations

import copy
import functools
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from tracklab.checks import check_count, check_positive, refuse, wrong_type
from tracklab.montecarlo import runner
from tracklab.parameters import constraint_of, write_value
from tracklab.worlds.protocol import Experiment


def _groups(constraints: dict, have) -> list:
    """(constraint, the numbers it transforms together) for each named number: the α-β(-γ) gains
    go together (those of them in ``have``), every other number on its own."""
    out = []
    for n, c in constraints.items():
        g = (c, tuple(m for m in c.members if m in have) if c.members else (n,))
        if g not in out:
            out.append(g)
    return out


def encode(constraints: dict, values: dict) -> dict:
    """Unconstrained coordinates of the numbers named in ``constraints`` (name -> Constraint), from a
    unit's ``values`` (its jointly constrained numbers come along)."""
    theta = {}
    for c, group in _groups(constraints, values):
        theta.update(c.encode({n: values[n] for n in group}))
    return theta


def decode(constraints: dict, theta: dict) -> dict:
    """The constrained values at unconstrained coordinates ``theta``."""
    out = {}
    for c, group in _groups(constraints, theta):
        out.update(c.decode({n: theta[n] for n in group}))
    return out


def outside(constraints: dict, values: dict) -> str | None:
    """Why ``values`` leave their constraints (a number not finite, or outside), None if they do not."""
    for c, group in _groups(constraints, values):
        v = {n: np.asarray(values[n], float) for n in group}
        if not all(np.all(np.isfinite(x)) for x in v.values()):
            return f"{', '.join(group)} not finite"
        if not c.contains(v):
            return f"{', '.join(group)} leaves {c.bounds}"
    return None


def selection(exp: Experiment, names, labels=None) -> dict:
    """Which numbers of which units (filters, trackers, estimators) are tuned: {label: {name: constraint}}.

    ``names``: names every selected unit that declares them tunable has tuned (``labels``: the units
    selected, default all); or {label: names} naming each unit's own — a list of its declared names,
    or for a filter of one's own {leaf name: constraint} over its params pytree
    (``tracklab.pytree.named_leaves``; constraints "positive", "unit", "free" or (lo, hi)).
    ``ValueError`` in one line for a label, name or constraint that does not fit."""
    declared = exp.declared()
    names = [names] if isinstance(names, str) else names
    if isinstance(names, dict):
        names = {label: [w] if isinstance(w, str) else w for label, w in names.items()}
    if not isinstance(names, dict):
        return {l: picked for l, d in declared.items() if not labels or l in labels
                if (picked := {n: d[n].constraint for n in names if n in d and d[n].tune})}
    values = exp.values(exp.params())
    chosen = {}
    for label, wanted in names.items():
        if label not in declared and label not in values:
            raise ValueError(f"tune: no filter labelled {label!r} (filters: {', '.join(values)})")
        d = declared.get(label, {})
        if not isinstance(wanted, dict):  # declared numbers, by name: their declared constraints
            undeclared = [n for n in wanted if n not in d or not d[n].tune]
            if undeclared:
                ok = [n for n, q in d.items() if q.tune]
                raise ValueError(f"tune: filter {label!r} declares no tunable {undeclared[0]!r} (tunable: "
                                 f"{', '.join(ok) or 'none'}); give a filter of one's own each leaf of its params "
                                 f"with its constraint, e.g. {{{label!r}: {{'q': 'positive'}}}}")
            picked = {n: d[n].constraint for n in wanted}
        else:
            leaves, picked = values[label], {}
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
    return chosen


def unwritable(exp: Experiment, chosen: dict) -> str | None:
    """Why the tuned values of ``chosen`` could not be written back into the experiment file (None
    if they can): each written where its declaration says, on a copy of the file's tables, before
    tuning starts."""
    section, labels = exp.tables()
    declared, values = exp.declared(), exp.values(exp.params())
    for label, table in zip(labels, exp.raw.get(section, [])):
        for n in chosen.get(label, ()):
            p = declared.get(label, {}).get(n)
            if p is None and n not in table:  # a leaf of one's own filter goes back under its name: a keyword
                return (f"filter {label!r}: {n} is no key of its [[filter]] table, so a tuned value has nowhere to "
                        f"go in the file (tune it from Python: tracklab.tune)")
            if p is not None and p.write is None:
                return f"{label!r}: {n} ({p.doc}) is tuned through the Python API; a file holds none"
            try:
                (p.write if p is not None else write_value)(copy.deepcopy(table), n, values[label][n],
                                                            exp.write_where(label))
            except ValueError as e:
                return f"filter {label!r}: {e}"
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


def tuned_numbers(exp: Experiment, chosen: dict) -> int:
    """``numbers`` of a selection (``selection``), from the file's values, before anything is traced."""
    values = exp.values(exp.params())
    return numbers({l: encode(c, values[l]) for l, c in chosen.items()})


def memory_bytes(exp: Experiment, runs_per_step, tuned=FORWARD_UP_TO + 1) -> float:
    """A lower bound on one tuning step of ``tuned`` numbers (tuning runs in float64; the world's
    ``tune_memory_bytes``, in forward or reverse mode as ``tuned`` decides)."""
    return exp.tune_memory_bytes(runs_per_step, tuned, forward_mode(tuned))


@dataclass
class Objective:
    """losses(theta, key, idx, live) -> {lane: loss} for the selected numbers of an experiment (any
    world): each tuned unit's own loss (a servo estimator's: the cases it feeds)."""

    losses: Callable
    theta0: dict  # label -> unconstrained coordinates of its tuned numbers
    values: Callable  # theta -> {label: {name: value}}, the tuned numbers' constrained values
    chosen: dict  # label -> {name: constraint}
    why_not: Callable  # {label: {name: value}} -> why a file could not hold them (None if it can)
    compiler_options: dict | None = None  # XLA options of the world's programs (``runner.World``)

    @property
    def initial(self) -> dict:
        return self.values(self.theta0)


def objective(exp: Experiment, names, loss=None, labels=None) -> Objective:
    """The one tuning path, for every world: the selected numbers' constraints give the coordinates
    Adam moves in (``encode``/``decode``); their values go into the params (``with_values``), the
    world runs a batch, and each lane's loss is the experiment's ``tune_losses[loss]`` of its sums."""
    losses = exp.tune_losses
    loss = loss or next(iter(losses))
    if loss not in losses:
        raise ValueError(f"tune: loss {loss!r}: must be one of {', '.join(losses)}")
    chosen = selection(exp, names, labels)
    if not chosen:
        wanted = named(names)
        raise ValueError(f"tune: no filter has any of the parameters {', '.join(map(str, wanted))}" if wanted
                         else "tune: no parameter named: name at least one")
    structure = exp.structure()
    world = exp.world(structure)
    fn = runner.sharded(world)
    params = exp.params()
    start = exp.values(params)
    lanes = exp.tune_lanes(chosen)
    loss_fn = losses[loss]
    theta0 = {l: encode(c, start[l]) for l, c in chosen.items()}

    def values(theta):
        return {l: decode(chosen[l], theta[l]) for l in theta}

    def per_lane(theta, key, idx, live):
        sums = runner.labelled(fn(exp.with_values(params, values(theta)), key, idx, live,
                                  jnp.zeros((world.lanes, idx.shape[0]), bool)), structure.labels)
        return {lane: loss_fn(sums, lane) for lane in lanes}

    def why_not(vals):
        return next((f"{l}: {why}" for l, v in vals.items() if (why := outside(chosen[l], v))), None)

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


def tune(exp, names, *, steps=200, lr=0.05, loss=None, runs_per_step=None, eval_runs=None, seed=None,
         labels=None, every=10, progress=None) -> TuneResult:
    """Adam (optax) on the named parameters (see ``selection``); a fresh batch of runs every step.

    ``exp``: an experiment of any world (``tracklab.experiment``, ``tracklab.load_experiment``);
    ``steps``: Adam steps; ``lr``: its learning rate (in the unconstrained coordinates);
    ``loss``: one of the world's (default its first); ``runs_per_step``: fresh runs per step
    (default the experiment's runs, 256 at most); ``eval_runs``: the held-out runs (default the
    experiment's, 2000 at most); ``seed``: default the experiment's; ``labels``: the units tuned
    (default every one with the parameters); ``progress(step, losses, gradient norm)`` every
    ``every`` steps. Runs in float64 whatever JAX's global mode (``tracklab.runtime``).

    Refused before anything compiles, in one line naming the argument: ``exp`` not an experiment
    or ``names`` not a name, a list of names or a dict of them (``TypeError``); ``names`` naming
    no parameter (``{}``, ``[]``, ``""``, ``{label: []}``); ``steps``, ``every``,
    ``runs_per_step``, ``eval_runs`` not integers >= 1; ``lr`` not a finite number > 0; ``seed``
    not an integer in [0, 2³² − 1]; ``labels`` naming no unit of the experiment; ``progress``
    not callable; a name, label, loss or constraint ``selection``/``objective`` refuses."""
    _check(exp, names, steps=steps, lr=lr, runs_per_step=runs_per_step, eval_runs=eval_runs, seed=seed,
           labels=labels, every=every, progress=progress)
    with jax.enable_x64(True):
        return _tune(exp, names, steps=steps, lr=lr, loss=loss, runs_per_step=runs_per_step, eval_runs=eval_runs,
                     seed=seed, labels=labels, every=every, progress=progress)


def _check(exp, names, *, steps, lr, runs_per_step, eval_runs, seed, labels, every, progress):
    """``tune``'s refusals of its arguments (see its doc)."""
    where = "tracklab.tune"
    if not isinstance(exp, Experiment):
        raise wrong_type(where, "exp", exp, "must be an experiment (tracklab.experiment(…) or "
                         "tracklab.load_experiment(path))")
    allowed = "must be a parameter name, a list of names, or {label: a name, a list of names or {leaf: constraint}}"
    if not isinstance(names, (str, dict)) and not _name_list(names):
        raise wrong_type(where, "names", names, allowed)
    for label, wanted in (names.items() if isinstance(names, dict) else ()):
        if not isinstance(wanted, (str, dict)) and not _name_list(wanted):
            raise wrong_type(where, f"names[{label!r}]", wanted, "must be a parameter name, a list of names, or "
                             "{leaf: constraint}")
        if isinstance(wanted, dict) and not all(isinstance(n, str) for n in wanted):
            raise wrong_type(where, f"names[{label!r}]", wanted, "must be {leaf name: constraint}, leaf names as "
                             "tracklab.pytree.named_leaves spells them")
    if not named(names):
        raise refuse(where, "names", names, f"names no parameter: {allowed}")
    check_count(where, "steps", steps)
    check_positive(where, "lr", lr)
    check_count(where, "runs_per_step", runs_per_step, optional=True)
    check_count(where, "eval_runs", eval_runs, optional=True)
    check_count(where, "seed", seed, 0, 2**32 - 1, optional=True)
    check_count(where, "every", every)
    if labels is not None:
        known = exp.tables()[1]
        if (isinstance(labels, str) or not isinstance(labels, (list, tuple, set, frozenset)) or not labels
                or any(l not in known for l in labels)):
            raise refuse(where, "labels", labels, f"must be None or a list of labels from: {', '.join(map(str, known))}")
    if progress is not None and not callable(progress):
        raise wrong_type(where, "progress", progress, "must be None or a function progress(step, losses, gradient norm)")


def named(names) -> list[str]:
    """The parameter names ``names`` holds: a name, a list of them, or {label: a name, a list of
    them, or {leaf: constraint}}."""
    if isinstance(names, str):
        return [names] if names else []
    if isinstance(names, dict):  # a leaf's name may be "" (the params themselves), a declared name not
        return [n for w in names.values() for n in (list(w) if isinstance(w, dict) else named(w))]
    return [n for n in names if n]


def _name_list(names) -> bool:
    """Whether ``names`` is a list (tuple, set) of parameter names."""
    return isinstance(names, (list, tuple, set, frozenset)) and all(isinstance(n, str) for n in names)


def _tune(exp, names, *, steps, lr, loss, runs_per_step, eval_runs, seed, labels, every, progress) -> TuneResult:
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
    loss = loss or next(iter(exp.tune_losses))
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
