"""The open-loop tracking world: simulate -> measure -> filter -> per-step sums.

A chunk of runs is one ``lax.scan`` over the steps that carries every run's
truth and every filter's state: at each step the runs' truths advance, their
measurements are made, every filter steps (``vmap`` over runs) and the errors
are reduced over the runs to per-step sums (and maxima). The random draws of
the whole chunk are made first, in float32 (``tracklab.random``), so nothing
of size (runs × steps) is kept in the working precision. One scan serves every
compared filter, and a filter state that is the same in every run (a linear
KF's covariance when the report pattern is) is carried once, not per run.
Filters whose errors have the same shapes are a group: their errors and
per-step sums are computed together along a leading filter axis.

Every number — scenario, sensors, prior, filters — is a leaf of
``TrackingParams``, an argument of the compiled program; ``TrackingStructure``
(the filters' kinds, models and views, the report windows, the chunk size) and
the params' pytree structure are what the program is compiled for. The runner
(``tracklab.montecarlo.runner``) drives the chunks: keys, devices, padding,
divergence, progress, timing and the host-side sums.

A run in which a filter produces NaN/inf or a covariance that is not positive
definite is *diverged* for that filter: it is counted and left out of that
filter's averages (the runner runs the chunk a second time without it); it
never stops the batch.
"""

from __future__ import annotations

import functools
import hashlib
import re
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab import random
from tracklab.filters import build
from tracklab.filters.core import Filter, Meas, Prior, trace_problem
from tracklab.filters.fusion import view_of
from tracklab.intervals import LEVEL, precision_reached
from tracklab.metrics import REPORT_WINDOW
from tracklab.linalg import mahalanobis2, mahalanobis2_logdet, norm, sum_elements
from tracklab.models import MODELS, cv, cv_index, interleaved
from tracklab.montecarlo import runner
from tracklab.pytree import like
from tracklab.sensors import SensorSuite


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
    trace to, the constants they close over included) with its label, kind, sensors and
    layout: two filters with the same code compile to the same program whatever their params'
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

    def _value(self):
        return (self.label, self.kind, tuple(self.sensors), self.layout, self.filter.layout, self.prior_extra_var,
                self.code)

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
        return (f"FilterSpec(label={self.label!r}, kind={self.kind!r}, sensors={tuple(self.sensors)!r}, "
                f"layout={self.layout or self.filter.layout!r}, prior_extra_var={self.prior_extra_var!r}, {what})")

    def with_code(self, scenario, sensor) -> "FilterSpec":
        """This filter as structure by value: its ``program_key`` at the experiment's shapes."""
        _, seen = self.sees(sensor)
        return replace(self, code=program_key(self.filter, self.report_layout(scenario.dim).n, seen.m))

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
        return trace_problem(flt, layout.n, seen.m)


def program_key(flt: Filter, n: int, m: int) -> str | None:
    """What a filter compiles to, as a digest: its ``init``, ``step`` and ``coast`` traced (float64)
    with a state of ``n`` and measurements of ``m`` components, each measurement with and without
    its report pattern — their jaxprs and every constant they close over — and the params'
    pytree. Filters with the same key compile to the same program whatever their params'
    values. None when it calls back into Python (nothing to identify it by but its identity)."""
    f64 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float64)  # noqa: E731
    h = hashlib.sha256()

    def add(closed):
        text = re.sub(r" at 0x[0-9a-f]+", "", str(closed.jaxpr))
        h.update(text.encode())
        for c in closed.consts:
            a = np.asarray(c)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
        return text

    with jax.enable_x64(True):
        params = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(
            np.shape(a), jnp.float64 if jnp.issubdtype(jnp.result_type(a), jnp.floating) else jnp.result_type(a)),
            flt.params)
        h.update(str(jax.tree_util.tree_structure(params)).encode())
        init, state = jax.make_jaxpr(flt.init, return_shape=True)(params, Prior(f64(n), f64(n, n)))
        texts = [add(init)]
        for present in (None, jax.ShapeDtypeStruct((m,), bool)):
            meas = Meas(f64(m), f64(), jax.ShapeDtypeStruct((), bool), present)
            for fn in (flt.step, flt.coast) if flt.coast is not None else (flt.step,):
                texts.append(add(jax.make_jaxpr(fn)(params, state, meas)))
    if any("callback" in t for t in texts):
        return None
    return h.hexdigest()


@dataclass(frozen=True)
class DeclaredFilter:
    """A filter of an experiment file, as structure: its kind, motion model, options and what it
    sees. Its numbers arrive as the params of the program, where ``realise`` builds it."""

    label: str
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
class TrackingStructure:
    """What an open-loop program is compiled for, besides the params' pytree structure."""

    filters: tuple  # DeclaredFilter or FilterSpec, one per compared filter
    windows: tuple = ()  # (name, (steps,) bools): where each run's largest prediction error is taken
    chunk: int = 1000  # runs per chunk

    @property
    def labels(self) -> list[str]:
        return [f.label for f in self.filters]

    def window_masks(self) -> dict:
        return {name: np.asarray(mask, bool) for name, mask in self.windows}


class TrackingParams(NamedTuple):
    """Every number of an open-loop experiment: the program's argument."""

    scenario: Any  # a scenario pytree (tracklab.scenarios)
    sensor: SensorSuite
    P0: Any  # (2d, 2d) prior covariance, CV layout
    prior_extra_var: Any  # prior variance of filter states beyond position/velocity
    filters: list  # each filter's parameter pytree


def with_report_window(masks: dict, steps: int) -> dict:
    """Named step masks with the report window first (all steps when none is named)."""
    masks = dict(masks)
    report = masks.pop(REPORT_WINDOW, np.ones(steps, bool))
    return {REPORT_WINDOW: np.asarray(report, bool)} | masks


def _window_mask(windows: dict) -> np.ndarray:
    """(steps, windows) bools: whether each step is in each of ``windows`` (``with_report_window``'s), in order."""
    return np.stack([np.asarray(m, bool) for m in windows.values()], axis=1)


def windows_of(masks: dict | None) -> tuple:
    """Named step masks as a hashable structure field."""
    return tuple((name, tuple(bool(b) for b in np.asarray(m))) for name, m in (masks or {}).items())


@dataclass
class MonteCarloResult:
    runs: int
    steps: int
    dt: float
    dim: int
    sums: dict[str, dict[str, np.ndarray]]  # label -> name -> (T, ...)
    pcrlb: np.ndarray | None  # (T, 2·dim, 2·dim) bound on the CV-layout state, or None
    wall_s: float
    compile_s: float
    labels: list[str]
    kinds: dict[str, str]
    example: dict = field(default_factory=dict)  # run 0: truth, z, and each filter's estimates
    axes: tuple[str, ...] = ("x", "y", "z")  # names of the reporting frame's position axes
    units: tuple[str, str] = ("m", "m/s")  # of position and velocity
    windows: list[str] = field(default_factory=list)  # named windows of the prediction-error maxima
    samples: Any = None  # the per-run samples' moments (montecarlo.samples.RunSamples), lanes in ``labels`` order
    sample_names: list = field(default_factory=list)  # (name, width) of each lane's samples (``sample_names``)
    report_window: tuple[int, int] | None = None  # 1-based steps the samples average over
    auto: dict | None = None  # runs chosen by a target precision: {target, max_runs, reached}


def _split_keys(keys):
    """A run's key -> its truth, measurement and prior keys."""
    split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
    return split[:, 0], split[:, 1], split[:, 2]


class _RunErrors(NamedTuple):
    """One filter's errors at one step, per run (under ``vmap`` with runs last: (…, runs))."""

    e: Any  # (2d,) estimate minus truth, CV layout
    nees: Any
    nis: Any  # 0 where no update
    valid: Any  # bool: an update happened
    dof: Any  # innovation components used
    bad: Any  # bool: NaN/inf estimate, NEES or NIS
    logdet_s: Any  # log det S, 0 where no update
    e_pred: Any  # (d,) one-step position prediction error
    var: Any  # (2d,) the filter's own variances of e (the diagonal of its covariance), CV layout

    @classmethod
    def zeros(cls, d, B, dtype):
        """In the place of the errors before the first step (the scan's first carry)."""
        z = lambda *shape: jnp.zeros(shape + (B,), dtype)
        no = jnp.zeros((B,), bool)
        return cls(z(2 * d), z(), z(), no, z(), no, z(), z(d), z(2 * d))


@dataclass(frozen=True)
class _Lane:
    """One filter inside a chunk's scan: its vmapped step and how its state is batched."""

    label: str
    init: Callable  # prior (2d,) of one run -> filter state
    body: Callable  # (state, (z_k, truth_k, t_k, present_k, reports_k)) -> (state, _ErrorInputs), one run
    view: Callable | None
    pattern: np.ndarray  # (T, m) which components of the filter's view are reported at each step
    present: Any  # (T, m) pattern as an array when it is the same in every run, else None
    reports: np.ndarray  # (T,) steps with some component reported


def _pick(a, idx, axis=0):
    """``a``'s entries ``idx`` (known at trace time) along ``axis`` by static slices, which fuse
    with what reads them (indexing by an index array is a gather, a kernel of its own)."""
    idx = [int(i) for i in idx]
    if idx == list(range(idx[0], idx[0] + len(idx))):
        return jax.lax.slice_in_dim(a, idx[0], idx[0] + len(idx), axis=axis)
    return jnp.stack([jax.lax.index_in_dim(a, i, axis, keepdims=False) for i in idx], axis=axis)


class _ErrorInputs(NamedTuple):
    """What a filter's output at one step gives its errors (one run): picked in the filter's
    step, turned into errors (``errors_of``) for all the filters of the same shapes at once."""

    e: Any  # (2d,) estimate minus truth, CV layout
    Pe: Any  # (2d, 2d) the filter's covariance of e
    x_sum: Any  # the sum of the state's entries (NaN/inf when any is)
    nu: Any  # innovation, or None
    S: Any  # its covariance, or None
    valid: Any  # bool: an update happened
    dof: Any  # innovation components used
    e_pred: Any  # (d,) one-step position prediction error (NaN when the filter reports none)


def error_inputs(out, truth_k, pv, dtype) -> _ErrorInputs:
    """One run's ``_ErrorInputs`` at one step from a filter's output ``out`` (an ``Out``), the
    true state ``truth_k`` (2d,) in CV layout and ``pv``, the indices of [x, ẋ, y, ẏ, …] in its state."""
    e = _pick(out.x, pv) - truth_k
    Pe = _pick(_pick(out.P, pv), pv, axis=1)
    nu = S = None
    valid, dof = jnp.asarray(False), jnp.asarray(0.0, dtype)
    if out.nu is not None and out.S is not None:
        nu, S = out.nu, out.S
        valid = jnp.asarray(True if out.valid is None else out.valid, bool)
        dof = jnp.asarray(out.nu.shape[-1] if out.dof is None else out.dof, dtype)
    if out.x_pred is not None:
        e_pred = _pick(out.x_pred, pv[0::2]) - truth_k[0::2]
    else:  # no prediction reported: its statistics are NaN, shown as missing
        e_pred = jnp.full((len(pv) // 2,), jnp.nan, dtype)
    return _ErrorInputs(e, Pe, sum_elements(out.x), nu, S, valid, dof, e_pred)


def errors_of(a: _ErrorInputs, dtype) -> _RunErrors:
    """One run's errors from its ``_ErrorInputs``."""
    nees = mahalanobis2(a.Pe, a.e)  # NaN when P is not positive definite
    bad = ~jnp.isfinite(nees + a.x_sum)
    if a.nu is not None:
        nis, logdet_s = mahalanobis2_logdet(a.S, a.nu)
        nis = jnp.where(a.valid, nis, 0.0)
        logdet_s = jnp.where(a.valid, logdet_s, 0.0)
        bad = bad | (a.valid & ~jnp.isfinite(nis))
    else:  # no innovation reported: no NIS (its columns are empty)
        nis, logdet_s = 0.0, 0.0
    # fixed dtypes, so that the scan's carry is known without tracing the step (_RunErrors.zeros)
    f = lambda v: jnp.asarray(v, dtype)
    return _RunErrors(f(a.e), f(nees), f(nis), jnp.asarray(a.valid, bool), f(a.dof), bad, f(logdet_s), f(a.e_pred),
                      f(jnp.diagonal(a.Pe)))


def run_errors(out, truth_k, pv, dtype) -> _RunErrors:
    """One run's errors at one step from a filter's output ``out`` (see ``error_inputs``)."""
    return errors_of(error_inputs(out, truth_k, pv, dtype), dtype)


def _lane(label, real: Realised, params, P0_cv, pattern, detect_all, dtype) -> _Lane:
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
    return _Lane(label, init, body, real.view, pattern, present, reports)


def _view_pattern(view, pattern, dtype):
    """The report pattern of a view of the sensors: where it is not NaN given the sensors' pattern."""
    if view is None:
        return pattern
    with jax.ensure_compile_time_eval():
        template = jnp.where(jnp.asarray(pattern), jnp.ones((), dtype), jnp.nan)
        return np.isfinite(np.asarray(view(template)))


# a step's sums over the runs and maxima over the runs, each one vector per filter inside the
# scan (one reduction each, one output each), cut into the named quantities after it
_SUMS = ("count", "sum_pos", "sum_vel", "sumsq_pos", "sumsq_vel", "sum_nees", "sum_nis", "count_nis", "dof_nis",
         "sum_logdet_s", "sum_pred", "sumsq_pred", "sum4_pos", "sum4_vel", "sumsq2_pos", "sumsq2_vel")
_MAXIMA = ("max_abs_pos", "max_abs_vel", "max_err_pos", "max_err_vel")
_PER_RUN_SCALARS = {"count", "sum_nees", "sum_nis", "count_nis", "dof_nis", "sum_logdet_s", "max_err_pos", "max_err_vel",
                    "sumsq2_pos", "sumsq2_vel"}


def sample_names(d: int, windows) -> list[tuple[str, int]]:
    """The per-run samples of a filter (name, width), in order: over the report window its
    mean-square position and velocity error (total, then per axis), mean error per axis
    (position, velocity), mean NEES, mean NIS and updates per step (the NIS is their ratio);
    per named window the mean-square one-step prediction error (total, per axis); then per
    named window the run's largest prediction error (per axis, then the norm)."""
    names = [("sq_pos", 1), ("sq_vel", 1), ("sq_pos_axes", d), ("err_pos", d), ("err_vel", d), ("nees", 1),
             ("nis", 1), ("updates", 1)]
    for w in windows:
        names += [(f"sq_pred@{w}", 1), (f"sq_pred_axes@{w}", d)]
    return names + [(f"max_pred@{w}", d + 1) for w in windows]


def _accumulated_lengths(d: int, windows: dict) -> np.ndarray:
    """Per accumulated sample (all of ``sample_names`` but the maxima), the steps of its window:
    what a run's window sum is divided by."""
    names = [(n, w) for n, w in sample_names(d, windows) if not n.startswith("max_pred@")]
    return np.concatenate([np.full(w, windows[n.split("@")[1] if "@" in n else REPORT_WINDOW].sum()) for n, w in names])


def _run_samples(r: _RunErrors, w_k):
    """One step's contributions (Q, B) to each run's sums of the accumulated samples (all of
    ``sample_names`` but the maxima): ``w_k`` (windows,) whether the step is in each named
    window, the report window first (``with_report_window``)."""
    w_report = w_k[0]
    ep, ev = r.e[0::2], r.e[1::2]
    upd = r.valid.astype(ep.dtype)
    sq_pred = r.e_pred**2
    report = jnp.concatenate([jnp.sum(ep**2, 0)[None], jnp.sum(ev**2, 0)[None], ep**2, ep, ev, r.nees[None],
                              (r.nis * upd)[None], upd[None]])
    rows = [w_report * report]
    for j in range(w_k.shape[0]):
        rows.append(w_k[j] * jnp.concatenate([jnp.sum(sq_pred, 0)[None], sq_pred]))
    return jnp.concatenate(rows)


def _lane_sums(r: _RunErrors, ok, runmax, w_k, dtype):
    """One step's sums over the runs ``ok`` (B,) of one filter's per-run errors (runs last): the
    vectors of ``_SUMS`` and of ``_MAXIMA`` (see ``_named``), and the updated per-run maxima."""
    okf = ok.astype(dtype)
    e = jnp.where(ok, r.e, 0.0)  # (2d, B)
    ep, ev = e[0::2], e[1::2]
    e_pred = jnp.where(ok, r.e_pred, 0.0)  # (d, B)
    updf = (r.valid & ok).astype(dtype)
    a_pred = jnp.concatenate([jnp.abs(e_pred), norm(e_pred)[None]])  # (d + 1, B)
    runmax = jnp.where(w_k[:, None, None], jnp.maximum(runmax, a_pred[None]), runmax)
    add = {
        "count": okf[None],
        "sum_pos": ep,
        "sum_vel": ev,
        "sumsq_pos": ep**2,
        "sumsq_vel": ev**2,
        "sum_nees": jnp.where(ok, r.nees, 0.0)[None],
        "sum_nis": (jnp.where(ok, r.nis, 0.0) * updf)[None],
        "count_nis": updf[None],
        "dof_nis": (r.dof * updf)[None],
        "sum_logdet_s": (jnp.where(ok, r.logdet_s, 0.0) * updf)[None],
        "sum_pred": e_pred,  # one-step prediction error, per axis
        "sumsq_pred": e_pred**2,
        "sum4_pos": ep**4,  # for the per-step RMSE's interval
        "sum4_vel": ev**4,
        "sumsq2_pos": jnp.sum(ep**2, 0)[None] ** 2,
        "sumsq2_vel": jnp.sum(ev**2, 0)[None] ** 2,
    }
    top = {
        "max_abs_pos": jnp.abs(ep),
        "max_abs_vel": jnp.abs(ev),
        "max_err_pos": norm(ep)[None],
        "max_err_vel": norm(ev)[None],
    }
    sums = _sum_over_runs([add[n] for n in _SUMS])
    maxima = jnp.max(jnp.where(ok, jnp.concatenate([top[n] for n in _MAXIMA]), -jnp.inf), axis=-1)
    return sums, maxima, runmax


@jax.custom_jvp
def _sum_over_runs(rows):
    """``rows`` (each (k, B)) summed over the runs, concatenated: (Σk,). One variadic reduction
    per row height, into which XLA fuses the arithmetic that makes the rows: a reduction of
    their concatenation would first write every row out, a kernel each. (A variadic reduction
    has no derivative rule of its own: the tangents are summed row by row.)"""
    by_height: dict = {}
    for i, a in enumerate(rows):
        by_height.setdefault(a.shape[0], []).append(i)
    out = [None] * len(rows)
    for idx in by_height.values():
        zeros = tuple(jnp.zeros((), rows[i].dtype) for i in idx)
        summed = jax.lax.reduce(tuple(rows[i] for i in idx), zeros,
                                lambda a, b: tuple(jax.lax.add(x, y) for x, y in zip(a, b)), (1,))
        for i, v in zip(idx, summed):
            out[i] = v
    return jnp.concatenate(out)


@_sum_over_runs.defjvp
def _sum_over_runs_jvp(primals, tangents):
    (rows,), (d_rows,) = primals, tangents
    return _sum_over_runs(rows), jnp.concatenate([jnp.sum(t, axis=-1) for t in d_rows])


def _named(v, names, d):
    """Vectors (..., width) of ``_lane_sums`` cut into the named quantities along the last axis
    (a per-run scalar's sum one column, the others d columns)."""
    out, i = {}, 0
    for name in names:
        if name in _PER_RUN_SCALARS:
            out[name], i = v[..., i], i + 1
        else:
            out[name], i = v[..., i:i + d], i + d
    return out


def simulate_runs(scenario, sensor, P0_cv, key, idx):
    """Runs ``idx`` as the tracking world simulates them: (truth (B, T+1, 2d), z (B, T, M), prior (B, 2d)).

    Run i's truth, measurements and prior mean come from ``fold_in(key, i)`` (the runner's keys);
    ``P0_cv`` is the prior covariance (CV layout). The world draws the same values step by step
    inside its scan; this gives them whole.
    """
    k_truth, k_meas, k_prior = _split_keys(runner.run_keys(key, idx))
    truth = jax.vmap(scenario.simulate)(k_truth)  # (B, T+1, 2d)
    z = jax.vmap(sensor.measure)(k_meas, truth[:, 1:, 0::2])  # (B, T, M)
    return truth, z, _prior_means(truth[:, 0], k_prior, jnp.linalg.cholesky(jnp.asarray(P0_cv)))


def _prior_means(truth0, k_prior, L0):
    """Run i's prior mean: its truth at the prior epoch plus a N(0, L0 L0ᵀ) draw."""
    w = jax.vmap(lambda k: random.normal(k, (L0.shape[0],), L0.dtype))(k_prior)
    return truth0 + w @ L0.T


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


def _run_dependence(init, body, prior, z_k, truth_k, fixed, may_share):
    """How a filter's step depends on the run: (for its state, a pytree of whether each leaf is the same in
    every run, i.e. depends neither on a run's prior mean nor on its measurements: a linear KF's
    covariance when the report pattern is the same in every run, looked for only when
    ``may_share``; per leaf of its error inputs, whether it may differ between runs; the error
    inputs' shapes; the step as its jaxpr replayed, for the chunk's ``vmap``). The step is traced
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


def _with_errors(body, dtype):
    """A filter's one-run step returning its errors (``errors_of``) instead of their inputs."""

    def step(state, inp):
        state, inputs = body(state, inp)
        return state, errors_of(inputs, dtype)

    return step


def _streams(scenario, views) -> bool:
    """Whether the chunk can draw truth and measurements step by step inside its scan: the
    truth is the same in every run or has a one-step ``advance``, and every filter sees each
    step's measurement alone (a view that registers one sensor's reports in time needs them all)."""
    truth_ok = not scenario.per_run or hasattr(scenario, "advance")
    return truth_ok and all(v is None or getattr(v, "rowwise", False) for v in views)


def _stand_in(tree):
    """A concrete copy of a (traced) pytree with every leaf 1: for what depends on structure alone."""
    return jax.tree_util.tree_map(lambda a: np.ones(np.shape(a)), tree)


def _chunk(structure: TrackingStructure):
    """The tracking world's chunk: (params, keys, live, exclude) -> sums (packed; see ``unpack``)."""
    def local(params: TrackingParams, keys, live, exclude):  # the runs of ``keys`` on one device
        scenario, sensor = params.scenario, params.sensor
        d, T, dt = scenario.dim, scenario.steps, scenario.dt
        windows = with_report_window(structure.window_masks(), T)
        names = list(windows)  # the report window, then the prediction-error windows
        lengths = _accumulated_lengths(d, windows)
        n_acc = len(lengths)
        P0_cv = params.P0
        L0 = jnp.linalg.cholesky(P0_cv)
        dtype = L0.dtype
        pattern = np.concatenate([np.repeat(s.report_mask(T)[:, None], s.m, axis=1) for s in sensor.sensors],
                                 axis=1)  # (steps, M): which components each sensor reports at each step
        report_masks = np.stack([s.report_mask(T) for s in sensor.sensors], axis=1)  # (steps, sensors)
        detect_all = not sensor.misses
        with_bound = scenario.gaussian  # no PCRLB, no information to gather
        stand_in = _stand_in(sensor)
        views = [f.view_for(stand_in) for f in structure.filters]
        stream = _streams(scenario, views)
        k_truth, k_meas, k_prior = _split_keys(keys)
        B = keys.shape[0]
        t = dt * jnp.arange(1, T + 1, dtype=dtype)
        if stream and not scenario.per_run:  # one truth for every run: a table
            table = jnp.asarray(scenario.simulate(None), dtype)  # (T+1, 2d)
            truth0, src = table[0], None
        elif stream:  # each run's truth advanced step by step
            truth0 = jnp.broadcast_to(jnp.asarray(scenario.initial_state(), dtype), (B, 2 * d))
            src = None
        else:  # drawn whole, read step by step (time-major)
            truth_all = jax.vmap(scenario.simulate, out_axes=1)(k_truth).astype(dtype)  # (T+1, B, 2d)
            z_all = jax.vmap(sensor.measure, in_axes=(0, 1), out_axes=1)(k_meas, truth_all[1:, :, 0::2])
            truth0, src = truth_all[0], (truth_all[1:], z_all)
        prior = _prior_means(truth0, k_prior, L0.astype(dtype))
        n_live = jnp.sum(live.astype(dtype))
        reports_by_sensor = jnp.asarray(report_masks, dtype)  # (steps, sensors)
        if stream:  # every draw of the chunk made at once (float32, cheap), read step by step (time-major)
            meas_draws = jax.vmap(lambda k: sensor.draws(k, T), out_axes=1)(k_meas)
            accel = jax.vmap(scenario.draws, out_axes=1)(k_truth) if scenario.per_run else None

        lanes = []
        for f, p, view in zip(structure.filters, params.filters, views):
            real = f.realise(scenario, sensor, p, params.prior_extra_var)
            lanes.append(_lane(f.label, real, p, P0_cv, _view_pattern(view, pattern, dtype), detect_all, dtype))
        z_views = []
        if not stream:  # a view of the whole sequence per run, time-major
            z_views = [z_all if ln.view is None else jax.vmap(ln.view, in_axes=1, out_axes=1)(z_all)
                       for ln in lanes]
        truth_batched = scenario.per_run or not stream
        state_axes, states0, err_axes, kinds, bodies = [], [], [], [], []
        for ln in lanes:
            fixed = (t, ln.present, jnp.asarray(ln.reports))
            m_f = ln.pattern.shape[1]
            z_ex, truth_ex = jnp.zeros((m_f,), dtype), jnp.zeros((2 * d,), dtype)
            shared, varies, inputs, body = _run_dependence(ln.init, ln.body, prior[0], z_ex, truth_ex, fixed,
                                                           may_share=ln.present is not None)
            bodies.append(body)
            state_axes.append(jax.tree_util.tree_map(lambda s: None if s else 0, shared))
            states0.append(jax.vmap(ln.init, out_axes=state_axes[-1])(prior))
            # the error inputs that differ between runs carry the runs last; the others (a shared
            # covariance's Pe and S) once
            in_tree = jax.tree_util.tree_structure(inputs)
            err_axes.append(jax.tree_util.tree_unflatten(in_tree, [-1 if v else None for v in varies]))
            kinds.append((in_tree, tuple((a.shape, a.dtype) for a in jax.tree_util.tree_leaves(inputs)), tuple(varies)))
        # filters whose error inputs have the same shapes form a group: their errors, per-step sums
        # and per-run samples are computed together, one set of kernels for the group. A filter
        # alone has its errors made inside its own vmap over the runs, where XLA fuses them with
        # the filter's arithmetic (its scan step as fast as before grouping; benchmarks/compile.md)
        groups: dict = {}
        for i, kind in enumerate(kinds):
            groups.setdefault(kind, []).append(i)
        groups = list(groups.values())
        steps = [None] * len(lanes)
        for g in groups:
            for i in g:
                alone = len(g) == 1
                body, out_axes = (_with_errors(bodies[i], dtype), -1) if alone else (bodies[i], err_axes[i])
                steps[i] = jax.vmap(body, in_axes=(state_axes[i], (0, 0 if truth_batched else None, None, None, None)),
                                    out_axes=(state_axes[i], out_axes))
        carries = []
        for g in groups:
            L = len(g)
            no_errors = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (L,) + a.shape), _RunErrors.zeros(d, B, dtype))
            nothing = (no_errors, jnp.zeros((L, 4 * d), dtype))
            carries.append((tuple(states0[i] for i in g), nothing, jnp.zeros((L, B), bool),
                            (jnp.zeros((L, len(names), d + 1, B), dtype), jnp.zeros((L, n_acc, B), dtype))))

        def group_errors(g, outs):
            """The errors (lanes, …, runs) of a group's filters from their steps' outputs: their
            error inputs, or for a filter alone the errors it made in its step."""
            if len(g) == 1:
                return jax.tree_util.tree_map(lambda a: a[None], outs[0])
            stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *outs)
            per_run = jax.vmap(lambda a: errors_of(a, dtype), in_axes=(err_axes[g[0]],), out_axes=-1)
            return jax.vmap(per_run)(stacked)

        def group_stats(g, pending, w_k, bad_any, per_run_acc):  # w_k: the step before's windows
            r, first = pending
            runmax, acc = per_run_acc
            bad_any = bad_any | r.bad
            ok = live & ~_pick(exclude, g) & ~bad_any
            sums, maxima, runmax = jax.vmap(lambda r, ok, m: _lane_sums(r, ok, m, w_k, dtype))(r, ok, runmax)
            acc = acc + jax.vmap(lambda r: _run_samples(r, w_k.astype(dtype)))(r)
            return (sums, maxima, first), bad_any, (runmax, acc)

        def scan_step(carry, inp):
            truth_prev, w_prev, group_carries = carry
            k, t_k, src_k, zv_k, lane_in, w_k = inp
            if not stream:
                truth_k, z_k = src_k
            else:
                accel_k, meas_k = src_k
                truth_k = jax.vmap(scenario.advance)(truth_prev, accel_k) if scenario.per_run else table[k + 1]
                z_k = jax.vmap(sensor.measure_step, in_axes=(0, None, None, 0 if truth_batched else None))(
                    meas_k, k, T, truth_k[..., 0::2])
            out = {"_example": {"truth": truth_k[0] if truth_batched else truth_k, "z": z_k[0]}}
            if with_bound:  # expected measurement information at the true positions, for the PCRLB
                pos_k = truth_k[..., 0::2]
                info = 0.0
                for j, s in enumerate(sensor.sensors):
                    if truth_batched:
                        I = jnp.sum(jnp.where(live[:, None, None], jax.vmap(s.information)(pos_k), 0.0), axis=0)
                    else:
                        I = n_live * s.information(pos_k)
                    info = info + reports_by_sensor[k, j] * I
                out["_info"] = info
            new_carries = []
            for g, (states, pending, bad_any, per_run_acc) in zip(groups, group_carries):
                # the sums of the step before, from its per-run errors held in the carry: a loop
                # variable is computed once, where XLA would otherwise recompute the filter's
                # arithmetic inside every reduction that reads it
                (sums, maxima, first), bad_any, per_run_acc = group_stats(g, pending, w_prev, bad_any, per_run_acc)
                for j, i in enumerate(g):
                    out[lanes[i].label] = (sums[j], maxima[j], first[j])
                new_states, outs = [], []
                for i, state in zip(g, states):
                    present_k, reports_k = lane_in[i]
                    z_f = zv_k[i] if not stream else (z_k if lanes[i].view is None else lanes[i].view(z_k))
                    state, out_i = steps[i](state, (z_f, truth_k, t_k, present_k, reports_k))
                    new_states.append(state)
                    outs.append(out_i)
                r = group_errors(g, outs)
                x_first = r.e[:, :, 0] + (truth_k[0] if truth_batched else truth_k)  # run 0's estimate
                first = jnp.concatenate([x_first, r.var[:, :, 0]], axis=1)  # and its variances
                new_carries.append((tuple(new_states), (r, first), bad_any, per_run_acc))
            return (truth_k if (stream and scenario.per_run) else None, w_k, new_carries), out

        lanes_in = [(ln.present, jnp.asarray(ln.reports)) for ln in lanes]
        if stream:
            src = (accel, meas_draws)
        # T + 1 iterations: iteration k adds up step k - 1's errors (held in the carry), so the
        # statistics are written once, inside the loop. Iteration 0 adds up nothing; iteration T
        # reads step T - 1's inputs again, and its simulation and filter steps are not kept
        carry0 = (truth0 if (stream and scenario.per_run) else None, jnp.zeros((len(names),), bool), carries)
        again = lambda a: jnp.concatenate([a, a[-1:]])
        w_masks = jnp.asarray(_window_mask(windows))  # (T, windows)
        xs = jax.tree_util.tree_map(again, (jnp.arange(T), t, src, z_views, lanes_in, w_masks))
        (_, _, finals), out = jax.lax.scan(scan_step, carry0, xs)
        out["_example"]["truth"] = jnp.concatenate([(truth0[0] if truth_batched else truth0)[None],
                                                    out["_example"]["truth"][:T]])
        out["_example"]["z"] = out["_example"]["z"][:T]
        out["_info"] = out["_info"][:T] if with_bound else jnp.zeros((T, d, d), dtype)
        n = len(lanes)
        flags, values, oks = [None] * n, [None] * n, [None] * n
        for g, (_, _, bad_any, (runmax, acc)) in zip(groups, finals):
            for j, i in enumerate(g):
                ln = lanes[i]
                sums, maxima, first = (a[1:] for a in out[ln.label])
                out[ln.label] = {"sums": sums, "maxima": maxima, "example_x": first[:, :2 * d],
                                 "example_var": first[:, 2 * d:]}  # cut by _unpack
                ok = live & ~exclude[i] & ~bad_any[j]
                for w, name in enumerate(names):  # sum over runs of each run's largest |error| (per axis, then norm)
                    out[ln.label][f"runmax_pred@{name}"] = jnp.sum(jnp.where(ok, runmax[j, w], 0.0), axis=-1)
                out[ln.label]["diverged"] = jnp.sum((live & bad_any[j]).astype(dtype))
                flags[i] = live & bad_any[j]
                values[i] = jnp.concatenate([acc[j] / jnp.asarray(lengths, dtype)[:, None], runmax[j].reshape(-1, B)])
                oks[i] = ok
        # (filters, B): the runner runs the chunk again without them
        out["diverged_runs"] = jnp.stack(flags) if flags else jnp.zeros((0, B), bool)
        if values:  # each run's time-averaged samples, for intervals and paired comparisons
            values = jnp.stack(values)
            out["per_run"] = {"values": values, "ok": jnp.stack(oks), "kept": jnp.sqrt(values[:, :1])}
        return out


    return local


def recorded_sums(out, truth, layout, windows: dict | None = None) -> dict:
    """One filter's per-step sums over recorded runs, as a chunk's scan makes them (named as
    ``unpack`` names them): ``out`` an ``Out`` of arrays (N, T, …) (``run_filter``'s), ``truth``
    (N, T, 2·dim) in CV layout at the same steps, ``layout`` where position and velocity sit in
    the filter's state. A run with a NaN/inf estimate or a covariance that is not positive
    definite at any step is diverged and left out of every sum, as in a simulation."""
    pv = tuple(int(i) for i in cv_index(layout))
    truth = jnp.asarray(truth)
    windows = with_report_window(windows or {}, truth.shape[1])
    lengths = _accumulated_lengths(len(pv) // 2, windows)
    out = jax.tree_util.tree_map(jnp.asarray, out)
    res = _recorded_sums(out, truth, jnp.asarray(_window_mask(windows)), jnp.asarray(lengths, truth.dtype), pv,
                         tuple(windows))
    return jax.tree_util.tree_map(np.asarray, res)


@functools.partial(jax.jit, static_argnums=(4, 5))
def _recorded_sums(out, truth, wmask, lengths, pv, names):
    """``recorded_sums`` as one program (compiled once per shape)."""
    pv = np.asarray(pv)
    dtype = truth.dtype
    N = truth.shape[0]
    d = len(pv) // 2
    xs = (jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), out), jnp.swapaxes(truth, 0, 1), wmask)
    errors = jax.vmap(lambda o, t: run_errors(o, t, pv, dtype), out_axes=-1)  # over the runs, runs last

    def bad_of(bad_any, inp):
        return bad_any | errors(inp[0], inp[1]).bad, None

    diverged, _ = jax.lax.scan(bad_of, jnp.zeros((N,), bool), xs)

    def step(carry, inp):
        runmax, acc = carry
        out_k, truth_k, w_k = inp
        r = errors(out_k, truth_k)
        sums, maxima, runmax = _lane_sums(r, ~diverged, runmax, w_k, dtype)
        acc = acc + _run_samples(r, w_k.astype(dtype))
        return (runmax, acc), (sums, maxima)

    carry0 = (jnp.zeros((len(names), d + 1, N), dtype), jnp.zeros((lengths.shape[0], N), dtype))
    (runmax, acc), (sums, maxima) = jax.lax.scan(step, carry0, xs)
    res = _named(sums, _SUMS, d) | _named(maxima, _MAXIMA, d)
    for j, name in enumerate(names):
        res[f"runmax_pred@{name}"] = jnp.sum(jnp.where(~diverged, runmax[j], 0.0), axis=-1)
    res["diverged"] = jnp.sum(diverged.astype(dtype))
    res["example_x"] = out.x[0][:, pv]
    res["example_var"] = jnp.diagonal(out.P[0][:, pv[:, None], pv[None, :]], axis1=-2, axis2=-1)
    values = jnp.concatenate([acc / lengths[:, None], runmax.reshape(-1, N)])
    res["per_run"] = {"values": values, "ok": ~diverged, "kept": jnp.sqrt(values[:1])}
    return res


def _window_mean(x, window):
    a, b = window
    return jnp.mean(x[a - 1:b])


def _safe_div(a, b):
    return a / jnp.maximum(b, 1.0)


# what tuning may minimise, from one chunk's sums, time-averaged over the report window ``w``
LOSSES: dict[str, Callable] = {
    "mse_pos": lambda s, w: _window_mean(_safe_div(jnp.sum(s["sumsq_pos"], -1), s["count"]), w),
    "pred_mse": lambda s, w: _window_mean(_safe_div(jnp.sum(s["sumsq_pred"], axis=-1), s["count"]), w),
    "nll": lambda s, w: _window_mean(0.5 * _safe_div(s["sum_nis"] + s["sum_logdet_s"], s["count_nis"]), w),
}


@functools.lru_cache(maxsize=64)
def world(structure: TrackingStructure) -> runner.World:
    """The tracking world of a structure (one per structure: its compiled programs are shared)."""
    return runner.World(structure, _chunk(structure), len(structure.filters), structure.chunk)


def unpack(out, d):
    """Each filter's per-step sums and maxima as named arrays, from the two vectors per step that
    the scan writes (``_lane_sums``); the leading axes (steps, grid points) are kept. Cut after
    the compiled chunk, each part is not an output buffer and a kernel of its own."""
    res = dict(out)
    for label, v in out.items():
        if isinstance(v, dict) and "sums" in v:
            v = dict(v)
            res[label] = _named(v.pop("sums"), _SUMS, d) | _named(v.pop("maxima"), _MAXIMA, d) | v
    return res


def default_chunk(scenario, sensor, budget=2**28, runs=None) -> int:
    """Runs per chunk when the experiment does not say: 1 000 per device (with several filters
    in the scan, larger shares run slower on the CPU: their states no longer stay in cache),
    fewer if a chunk's per-step arrays (truth and measurements of every run and step, 8 bytes
    a value) would pass ``budget`` bytes (256 MiB), but at least 64; and no more than ``runs`` need,
    rounded up to a power of two per device (every run of a chunk is computed, live or not), so
    that nearby run counts, and any count from 1 000 per device up, share one compiled program."""
    devices = jax.device_count()
    width = 2 * scenario.dim + sensor.m
    chunk = int(np.clip(budget // (8 * scenario.steps * width), 64, 1000 * devices))
    if runs:
        per_device = -(-int(runs) // devices)
        chunk = min(chunk, devices * (1 << (per_device - 1).bit_length()))
    return chunk


def run(structure: TrackingStructure, params: TrackingParams, runs: int, key, *, progress=None,
        precision: str = "float64", points: int | None = None, target: float | None = None, level: float = LEVEL):
    """Per-step error statistics of the structure's filters over ``runs`` Monte-Carlo runs: a
    ``MonteCarloResult``, or with ``points`` (params stacked along a leading axis, as a sweep's
    grid) a list of them, one per parameter set, all on the same runs. With ``target``, chunks
    run until ``precision_reached`` (``runs`` at most): the result's ``auto`` says how it went."""
    enough = None
    if target is not None and points is None:
        enough = lambda sums, samples, done: precision_reached(samples, target, level)
    out = runner.run(world(structure), params, runs, key, precision=precision, points=points, progress=progress,
                     enough=enough)
    if points is None:
        res = result(structure, params, out.sums, out)
        if target is not None:
            res.auto = {"target": target, "max_runs": runs, "reached": precision_reached(out.samples, target, level)}
        return res
    return [result(structure, runner.pick(params, j), runner.pick(out.sums, j), out, j) for j in range(points)]


def result(structure, params, sums, out: runner.Outcome, point: int | None = None) -> MonteCarloResult:
    """The ``MonteCarloResult`` of one parameter set's sums (the runner's, for ``out.runs`` runs;
    ``point``: which grid point's samples, when the run had several)."""
    scenario = params.scenario
    sums = unpack(sums, scenario.dim)
    info = sums.pop("_info")
    ex = sums.pop("_example")
    example = {"truth": np.asarray(ex["truth"]), "z": np.asarray(ex["z"])}
    example["x"] = {label: np.asarray(sums[label].pop("example_x")) for label in structure.labels}
    example["var"] = {label: np.asarray(sums[label].pop("example_var")) for label in structure.labels}
    windows = with_report_window(structure.window_masks(), scenario.steps)
    report = np.flatnonzero(windows[REPORT_WINDOW])
    samples = out.samples if (point is None or out.samples is None) else out.samples.point(point)
    return MonteCarloResult(
        runs=out.runs, steps=scenario.steps, dt=float(scenario.dt), dim=scenario.dim,
        sums={label: sums[label] for label in structure.labels},
        pcrlb=_pcrlb64(scenario, np.asarray(params.P0, np.float64), info / out.runs) if scenario.gaussian else None,
        wall_s=out.wall_s, compile_s=out.compile_s, labels=structure.labels,
        kinds={f.label: f.kind for f in structure.filters}, example=example,
        axes=tuple(getattr(scenario, "axes", ("x", "y", "z")[: scenario.dim])),
        units=tuple(getattr(scenario, "units", ("m", "m/s"))), windows=[n for n, _ in structure.windows],
        samples=samples, sample_names=sample_names(scenario.dim, windows),
        report_window=(int(report[0]) + 1, int(report[-1]) + 1))


def monte_carlo(
    scenario,
    sensor,
    specs: Sequence[FilterSpec],
    runs: int,
    key,
    P0_cv,
    *,
    chunk: int | None = None,
    params: Sequence[Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    precision: str = "float64",
    windows: dict[str, np.ndarray] | None = None,
) -> MonteCarloResult:
    """Per-step error statistics of several filters over ``runs`` Monte-Carlo runs.

    ``P0_cv`` is the prior covariance in CV layout: run i's prior mean is the
    truth one period before the first measurement plus a N(0, P0) draw, shared
    by all filters in that run. ``precision = "float32"`` traces and runs the
    simulation and the filters in single precision (JAX's 64-bit mode off for
    them); sums are accumulated on the host in float64 either way, and the
    random draws are the same (made in float32 in both). ``windows`` (name -> (steps,)
    bool mask) are where each run's largest one-step prediction error is taken.
    """
    if not isinstance(sensor, SensorSuite):
        sensor = SensorSuite((sensor,))
    chunk = int(chunk or default_chunk(scenario, sensor, runs=runs))
    structure = TrackingStructure(tuple(specs), windows_of(windows), chunk)
    filter_params = list(params) if params is not None else [s.filter.params for s in specs]
    p = TrackingParams(scenario, sensor, np.asarray(P0_cv, float), 0.0, filter_params)
    return run(structure, p, runs, key, progress=progress, precision=precision)


def _pcrlb64(scenario, P0_cv, info_pos):
    with jax.enable_x64(True):
        return pcrlb(scenario, P0_cv, info_pos)


def pcrlb(scenario, P0_cv, info_pos):
    """Tichavský et al. recursion (REFERENCE_MATH §5) for linear-Gaussian dynamics.

    J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + E[H̃ᵀ R⁻¹ H̃], the expectation averaged over
    the simulated truths (``info_pos``, (T, dim, dim), position block); J_0 = P0⁻¹.
    ``F`` is one matrix, or one per step (T, n, n): the Jacobians of a deterministic
    truth's motion along it, with Q = 0 (the bound of a known, manoeuvring path).
    Returns J⁻¹ per measurement step, or None when the truth has no Gaussian model.
    """
    lg = scenario.linear_gaussian()
    if lg is None:
        return None
    F, Q = (np.asarray(a, float) for a in lg)
    pos = np.arange(scenario.dim) * 2
    Jz = np.zeros((len(info_pos),) + np.shape(P0_cv))
    Jz[:, pos[:, None], pos[None, :]] = np.asarray(info_pos)
    Fs = F if F.ndim == 3 else np.broadcast_to(F, (len(info_pos),) + F.shape)
    return np.asarray(_pcrlb_recursion(np.asarray(P0_cv, float), Q, Fs, Jz))


@jax.jit
def _pcrlb_recursion(P0, Q, Fs, Jz):
    """J⁻¹ per step (compiled once per shape, not per call; its inputs built on the host)."""

    def step(Jinv, inp):
        Jz_k, F_k = inp
        Jinv = jnp.linalg.inv(jnp.linalg.inv(Q + F_k @ Jinv @ F_k.T) + Jz_k)
        return Jinv, Jinv

    return jax.lax.scan(step, P0, (Jz, Fs))[1]
