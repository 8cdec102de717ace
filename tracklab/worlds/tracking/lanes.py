"""What a compared filter is to the open-loop world: structure, realisation and sharing.

A filter of an experiment file is a ``DeclaredFilter`` (its kind, model, options and what it
sees: built inside the program from the traced params); one of one's own is a ``FilterSpec``
(structure by what it traces to: ``program_key``). Inside a chunk's scan each is a ``Lane``:
its one-run step, with the error inputs its output gives, and how its state is batched — a
state leaf that depends neither on a run's prior mean nor on its measurements (a linear KF's
covariance when the report pattern is the same in every run) is carried once for all runs
(``run_dependence``: the step traced once, its dependence read off the jaxpr, which the chunk
then batches, the runs last in every array (``batching.runs_last``), without running the filter's
Python again).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab.filters import build
from tracklab.filters.core import Filter, Meas, Prior, trace_problem
from tracklab.filters.fusion import view_of
from tracklab.models import MODELS, cv, cv_index, interleaved
from tracklab.pytree import like, traced_key
from tracklab.sensors.clutter import cluttered_of
from tracklab.worlds.tracking.errors import MAY_BE_SHARED, RunErrors, error_inputs, errors_of


class Realised(NamedTuple):
    """A filter as one chunk's scan runs it (built inside the program, from traced numbers)."""

    filter: Filter
    model: Any  # where position and velocity sit in its state: a Layout or a motion model (pos_idx, vel_idx, embed)
    view: Callable | None  # what the filter sees of the sensors' z: (T, M) -> (T, m); None: all of it
    prior_extra_var: Any  # prior variance of states beyond position/velocity

@dataclass(frozen=True, eq=False)
class FilterSpec:
    """A filter of one's own among an experiment's filters: its label and its ``Filter``.

    The filter's ``params`` pytree is an input of the compiled program (``tracklab.tune``
    may name its leaves; ``declared`` are the numbers its factory declares, by name: what
    ``tracklab tune --params`` and the sweeps name); where position and velocity sit in its
    state is ``layout``, by default the filter's own (``Filter.layout``), else
    [x, ẋ, y, ẏ(, z, ż)]. It sees the sensors named in ``sensors`` (default all: their
    measurements concatenated in the experiment's order; a component is NaN when its sensor
    has no report). ``kind`` is what the tables call it.

    As structure of a program it is its ``code`` (``program_key``: what its init and step
    trace to, the constants they close over included) with its kind, sensors and layout (its
    label names it in the tables only): two filters with the same code compile to the same program whatever their params'
    values, and one whose code changed (a number its factory baked in, an edited module)
    compiles anew. Without a ``code`` it is structure by identity: a new object compiles anew.
    """

    label: str
    filter: Filter = field(repr=False)
    kind: str = "user"
    sensors: tuple[str, ...] = ()
    layout: Any = None  # a Layout (or a motion model); None: the filter's own
    view: Callable | None = field(default=None, repr=False)  # what it sees of z (T, M) -> (T, m), when not a selection
    prior_extra_var: float | None = None  # prior variance of states beyond position/velocity; None: the experiment's
    declared: Mapping = field(default_factory=dict, repr=False)  # name -> Param: its factory's declared numbers
    code: str | None = None  # program_key of its filter; None: structure by identity

    def __post_init__(self):
        if not isinstance(self.label, str):
            raise TypeError(f"tracklab.FilterSpec: label = {self.label!r}: must be a string (the filter's name in the "
                            f"tables)")
        if not isinstance(self.filter, Filter):
            hint = " (build one with tracklab.filters.build)" if isinstance(self.filter, str) else ""
            raise TypeError(f"tracklab.FilterSpec: filter = {self.filter!r}: must be a tracklab.Filter{hint}")
        if not self.declared and self.filter.declared:  # what its factory declares (tracklab.declare)
            object.__setattr__(self, "declared", dict(self.filter.declared))

    def _value(self):
        return (self.kind, tuple(self.sensors), self.layout, self.filter.layout, self.prior_extra_var, self.code)

    def _by_value(self) -> bool:
        return self.code is not None and self.view is None

    def __eq__(self, other):
        if not isinstance(other, FilterSpec):
            return NotImplemented
        if not (self._by_value() and other._by_value()):
            return self is other
        return self._value() == other._value()

    def __hash__(self):
        return hash(self._value()) if self._by_value() else id(self)

    def __repr__(self):
        what = f"code={self.code!r}" if self._by_value() else "<by identity>"  # '<': never kept on disk
        return (f"FilterSpec(kind={self.kind!r}, sensors={tuple(self.sensors)!r}, "
                f"layout={self.layout or self.filter.layout!r}, prior_extra_var={self.prior_extra_var!r}, {what})")

    def with_code(self, scenario, sensor) -> "FilterSpec":
        """This filter as structure by value: its ``program_key`` at the experiment's shapes."""
        _, seen = self.sees(sensor)
        return replace(self, code=program_key(self.filter, self.report_layout(scenario.dim).n, seen.m,
                                              scan_returns(seen)))

    def report_layout(self, dim: int):
        return self.layout or self.filter.layout or interleaved(dim)

    @property
    def params(self):
        return self.filter.params

    def sees(self, sensor):
        """(view function or None, measurement model) of what the filter sees of the sensors."""
        if self.view is not None:
            return self.view, sensor
        if self.sensors and tuple(self.sensors) != tuple(s.name for s in sensor.sensors):
            return view_of(sensor, tuple(self.sensors), None)
        return None, sensor

    def view_for(self, sensor):
        return self.sees(sensor)[0]

    def realise(self, scenario, sensor, params, extra_var) -> Realised:
        extra = extra_var if self.prior_extra_var is None else self.prior_extra_var
        return Realised(self.filter, self.report_layout(scenario.dim), self.view_for(sensor), extra)

    def problem(self, scenario, sensor) -> str | None:
        """Why this filter cannot run in an experiment of ``scenario`` and ``sensor`` (None if it
        can): checked by tracing ``init`` and ``step`` on shapes alone, before anything compiles."""
        flt = self.filter
        if not isinstance(flt, Filter) or not callable(flt.init) or not callable(flt.step):
            return f"is {type(flt).__name__}, not a tracklab Filter(init, step, params)"
        layout = self.report_layout(scenario.dim)
        why = layout.check(scenario.dim) if hasattr(layout, "check") else None
        if why:
            return f"layout {why}"
        _, seen = self.sees(sensor)
        return trace_problem(flt, layout.n, seen.m, returns=scan_returns(seen))

def scan_returns(sensor) -> int | None:
    """A cluttered sensor's scan capacity (its z is (returns, m)); None for a sensor without clutter."""
    c = cluttered_of(sensor)
    return None if c is None else c.max_returns

def program_key(flt: Filter, n: int, m: int, returns: int | None = None) -> str | None:
    """What a filter compiles to, as a digest (``pytree.traced_key``): its ``init``, ``step`` and
    ``coast`` traced (float64) with a state of ``n`` and measurements of ``m`` components, each
    measurement with and without its report pattern, and the params' pytree. Filters with the same
    key compile to the same program whatever their params' values; None when one calls back into
    Python."""
    f64 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float64)  # noqa: E731
    with jax.enable_x64(True):
        params = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(
            np.shape(a), jnp.float64 if jnp.issubdtype(jnp.result_type(a), jnp.floating) else jnp.result_type(a)),
            flt.params)
        state = jax.eval_shape(flt.init, params, Prior(f64(n), f64(n, n)))
        calls = [(flt.init, (params, Prior(f64(n), f64(n, n))))]
        for present in (None, jax.ShapeDtypeStruct((m,), bool)):
            meas = Meas(f64(m) if returns is None else f64(returns, m), f64(), jax.ShapeDtypeStruct((), bool), present)
            calls += [(fn, (params, state, meas)) for fn in (flt.step, flt.coast) if fn is not None]
        key = traced_key(calls)
    return None if key is None else f"{jax.tree_util.tree_structure(params)} {key}"


@dataclass(frozen=True)
class DeclaredFilter:
    """A filter of an experiment file, as structure: its kind, motion model, options and what it
    sees. Its numbers arrive as the params of the program, where ``realise`` builds it. Its label
    names it in the tables, no part of what is compiled."""

    label: str = field(compare=False, repr=False)
    kind: str
    model: str  # "cv" | "ca"
    options: tuple = ()  # sorted (name, value) pairs, hashable
    sensors: tuple[str, ...] = ()  # the sensors it sees (all when empty)
    fusion: str | None = None  # laser + infrared fusion view: "interpolate" | "none"

    @property
    def option_dict(self) -> dict:
        return dict(self.options)

    def sees(self, sensor):
        """(view function or None, measurement model) of what the filter sees of the sensors."""
        names = self.sensors
        guide = self.option_dict.get("guide", "previous")
        if guide != "previous":  # error_space: [main, guide]
            names = tuple(names) + (guide,)
        return view_of(sensor, names, self.fusion)

    def view_for(self, sensor):
        return self.sees(sensor)[0]

    def realise(self, scenario, sensor, params, extra_var) -> Realised:
        model = MODELS[self.model](scenario.dim, scenario.dt)
        view, meas = self.sees(sensor)
        flt = build(self.kind, model, meas, params, self.option_dict)
        report = cv(scenario.dim, scenario.dt) if self.kind == "polar_kf" else model
        return Realised(flt, report, view, extra_var)

def hashable(v):
    """Lists (and nested lists) as tuples, so that a filter's options can be part of a structure."""
    if isinstance(v, (list, tuple)):
        return tuple(hashable(x) for x in v)
    if isinstance(v, dict):
        return tuple(sorted((k, hashable(x)) for k, x in v.items()))
    return v

@dataclass(frozen=True)
class Lane:
    """One filter inside a chunk's scan: its one-run step and how its state is batched."""

    init: Callable  # prior (2d,) of one run -> filter state
    body: Callable  # (state, (z_k, truth_k, t_k, present_k, reports_k)) -> (state, ErrorInputs), one run
    view: Callable | None
    pattern: np.ndarray  # (T, m) which components of the filter's view are reported at each step
    present: Any  # (T, m) pattern as an array when it is the same in every run, else None
    reports: np.ndarray  # (T,) steps with some component reported

def lane(real: Realised, params, P0_cv, pattern, detect_all, dtype) -> Lane:
    """Set up one filter for the chunk's scan (``pattern``: the report pattern (T, m) of what it sees)."""
    flt = real.filter
    pv = cv_index(real.model)
    reports = pattern.any(axis=-1)
    coast = flt.coast if (flt.coast is not None and not reports.all()) else None

    def init(prior_r):
        x0, P0 = real.model.embed(prior_r, P0_cv, real.prior_extra_var)
        return flt.init(params, Prior(x0, P0))

    def body(state, inp):  # one run, one step: filter, then what that run's errors are made of
        z_k, truth_k, t_k, present_k, reports_k = inp
        meas = Meas(z_k, t_k, jnp.asarray(True), present_k)
        if coast is None:
            new, out = flt.step(params, state, meas)
        else:  # no sensor reports at this step (between reports): predict only
            new, out = jax.lax.cond(reports_k, flt.step, coast, params, state, meas)
        # in the state's own precision: a filter of one's own built in float64 (its constants) keeps a
        # float32 run's state float32 (for the built-in kinds, built inside the program, a no-op)
        return like(new, state), error_inputs(out, truth_k, pv, dtype)

    present = jnp.asarray(pattern) if detect_all else None
    return Lane(init, body, real.view, pattern, present, reports)

def view_pattern(view, pattern, dtype):
    """The report pattern of a view of the sensors: where it is not NaN given the sensors' pattern."""
    if view is None:
        return pattern
    with jax.ensure_compile_time_eval():
        template = jnp.where(jnp.asarray(pattern), jnp.ones((), dtype), jnp.nan)
        return np.isfinite(np.asarray(view(template)))

def _traced(fn, args):
    """``fn``'s closed jaxpr at the shapes of ``args`` and its outputs' shapes (``ShapeDtypeStruct``)."""
    args = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), args)
    return jax.make_jaxpr(fn, return_shape=True)(*args)

def _replayed(closed, args, shapes):
    """A function of arguments shaped as ``args`` that evaluates the jaxpr ``closed`` traced from them
    (outputs shaped as ``shapes``): the traced function again without running its Python."""
    in_tree = jax.tree_util.tree_structure(args)
    avals = [(jnp.shape(a), jnp.result_type(a)) for a in jax.tree_util.tree_leaves(args)]
    out_tree = jax.tree_util.tree_structure(shapes)
    run = jax.extend.core.jaxpr_as_fun(closed)

    def replay(*given):
        flat, tree = jax.tree_util.tree_flatten(given)
        got = [(jnp.shape(a), jnp.result_type(a)) for a in flat]
        if tree != in_tree or got != avals:
            raise TypeError(f"replayed with {tree} {got}, traced with {in_tree} {avals}")
        return jax.tree_util.tree_unflatten(out_tree, run(*flat))

    return replay

def _tainted(jaxpr, flags):
    """Which outputs of ``jaxpr`` depend on the inputs flagged in ``flags`` (one per input).

    A conservative reading: an equation with any dependent input makes all its outputs
    dependent (nested jaxprs included).
    """
    dep = {v for v, f in zip(jaxpr.invars, flags) if f}
    for eqn in jaxpr.eqns:
        if any(not isinstance(v, jax.extend.core.Literal) and v in dep for v in eqn.invars):
            dep.update(eqn.outvars)
    return [not isinstance(v, jax.extend.core.Literal) and v in dep for v in jaxpr.outvars]

def errors_dependence(inputs, varies, dtype) -> RunErrors:
    """Per field of a filter's errors (``errors_of`` of error inputs shaped as ``inputs``, whose leaves
    flagged in ``varies`` differ between runs): True where it is the same in every run, for the
    fields of ``MAY_BE_SHARED`` (the others are always taken as per run)."""
    closed, _ = _traced(lambda a: errors_of(a, dtype), (inputs,))
    depends = _tainted(closed.jaxpr, list(varies))
    return RunErrors(*[not dep and name in MAY_BE_SHARED for name, dep in zip(RunErrors._fields, depends)])

def run_dependence(init, body, prior, z_k, truth_k, fixed, may_share):
    """How a filter's step depends on the run: (for its state, a pytree of whether each leaf is the same in
    every run, i.e. depends neither on a run's prior mean nor on its measurements: a linear KF's
    covariance when the report pattern is the same in every run, looked for only when
    ``may_share``; per leaf of its error inputs, whether it may differ between runs; the error
    inputs' shapes; the step as its jaxpr replayed, for the chunk's batching). The step is traced
    once: its dependence is iterated on that jaxpr, and the chunk batches the jaxpr rather than
    tracing the filter's Python again."""
    leaves = jax.tree_util.tree_leaves
    fixed_k = jax.tree_util.tree_map(lambda a: a[0], fixed)
    init_closed, state = _traced(init, (prior,))
    n_state = len(leaves(state))
    example = (state, (z_k, truth_k) + tuple(fixed_k))
    step, shapes = _traced(body, example)
    state_flags = [True] * n_state
    if may_share:
        state_flags = _tainted(init_closed.jaxpr, [True] * len(leaves(prior)))
    for _ in range(n_state + 1):  # to the fixed point: a dependent leaf stays dependent
        # the inputs that differ between runs: the state's dependent leaves, the measurements and the truth
        flags = state_flags + [True] * len(leaves((z_k, truth_k))) + [False] * len(leaves(fixed_k))
        out = _tainted(step.jaxpr, flags)
        new = [a or b for a, b in zip(out[:n_state], state_flags)]
        if new == state_flags:
            break
        state_flags = new
    shared = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(state), [not f for f in state_flags])
    return shared, out[n_state:], shapes[1], _replayed(step, example, shapes)
