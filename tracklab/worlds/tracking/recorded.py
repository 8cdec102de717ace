"""Filters run over recorded measurements, judged against the recorded truth: the same
statistics, tables and figures as a simulation (``tracklab.evaluate``).

A flight test gives measurements and a reference track (GPS/INS, a theodolite, a
trajectory file); ``run_filter`` runs each filter over the measurements, and
``evaluate`` turns its results and the truth into the per-step RMSE, mean error, NEES,
NIS and one-step prediction error of ``tracklab.metrics``, computed by the same code as a
simulation's sums (``worlds.tracking.recorded_sums``). Several recordings (N, T, …) are
N runs; one (T, …) is one run. A truth file in the trajectory format gives the truth at
the steps: ``Trajectory(path, dt, steps, dim).simulate(None)[1:]``.
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab.checks import check_finite, check_positive, refuse, wrong_type
from tracklab.filtering import FilterResult
from tracklab.filters.core import Out
from tracklab.models import cv_index, interleaved
from tracklab.montecarlo.samples import RunSamples
from tracklab.montecarlo.statistics import REPORT_WINDOW
from tracklab.output import atomic_folder, check_results_folder
from tracklab.worlds.tracking.errors import (
    MAXIMA,
    SUMS,
    accumulated_count,
    accumulated_lengths,
    lane_sums,
    named,
    run_errors,
    run_samples,
    sample_names,
    window_sums,
)
from tracklab.worlds.tracking.experiment import stats_document, write_results
from tracklab.worlds.tracking.outcome import MonteCarloResult
from tracklab.worlds.tracking.scan import window_mask, with_report_window


def recorded_sums(out, truth, layout, windows: dict | None = None) -> dict:
    """One filter's per-step sums over recorded runs, as a chunk's scan makes them (named as
    ``unpack`` names them): ``out`` an ``Out`` of arrays (N, T, …) (``run_filter``'s), ``truth``
    (N, T, 2·dim) in CV layout at the same steps, ``layout`` where position and velocity sit in
    the filter's state. A run with a NaN/inf estimate or a covariance that is not positive
    definite at any step is diverged and left out of every sum, as in a simulation."""
    pv = tuple(int(i) for i in cv_index(layout))
    truth = jnp.asarray(truth)
    windows = with_report_window(windows or {}, truth.shape[1])
    lengths = accumulated_lengths(len(pv) // 2, windows)
    out = jax.tree_util.tree_map(jnp.asarray, out)
    res = _recorded_sums(out, truth, jnp.asarray(window_mask(windows)), jnp.asarray(lengths, truth.dtype), pv,
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
        sums, maxima, runmax = lane_sums(r, ~diverged, runmax, w_k, dtype)
        acc = acc + run_samples(r, w_k.astype(dtype))
        return (runmax, acc), (sums, maxima)

    carry0 = (jnp.zeros((len(names), d + 1, N), dtype), jnp.zeros((accumulated_count(d, names), N), dtype))
    (runmax, acc), (sums, maxima) = jax.lax.scan(step, carry0, xs)
    res = named(sums, SUMS, d) | named(maxima, MAXIMA, d)
    for j, name in enumerate(names):
        res[f"runmax_pred@{name}"] = jnp.sum(jnp.where(~diverged, runmax[j], 0.0), axis=-1)
    res["diverged"] = jnp.sum(diverged.astype(dtype))
    res["example_x"] = out.x[0][:, pv]
    res["example_var"] = jnp.diagonal(out.P[0][:, pv[:, None], pv[None, :]], axis1=-2, axis2=-1)
    values = jnp.concatenate([window_sums(acc, d, names) / lengths[:, None], runmax.reshape(-1, N)])
    res["per_run"] = {"values": values, "ok": ~diverged, "kept": jnp.sqrt(values[:1])}
    return res


@dataclass
class Recorded:
    """What ``evaluate`` judged: filters' results on recorded data, and the truth."""

    name: str
    dt: float
    steps: int
    window: tuple[int, int]
    pred_windows: dict
    raw: dict
    parameters: dict = field(default_factory=dict)  # label -> {name: value}, as given
    path: Path | None = None
    level: float = 0.95  # of every interval
    baseline: str | None = None  # the paired differences are to the first filter
    sensor = None  # no simulated sensor (the figures draw no measurements)

    def ran_with(self) -> dict:
        return self.parameters

_RESULTS = ("must be a tracklab.FilterResult (run_filter's) or a dict {label: FilterResult} of one or more, "
            "all over the same measurements")


def _batched(a, what, ndim):
    a = np.asarray(a, float)
    if a.ndim == ndim:
        a = a[None]
    if a.ndim != ndim + 1:
        raise ValueError(f"tracklab.evaluate: {what} has shape {np.shape(a)}: expected {ndim} or {ndim + 1} axes")
    return a

def evaluate(results, truth, *, dt: float, name: str = "recorded", window: tuple[int, int] | None = None,
             windows: dict | None = None, params: dict | None = None, out=None, figures: bool = True) -> dict:
    """The statistics document (what stats.json holds) of filters' results on recorded
    measurements against the truth; with ``out``, also the results folder (stats.json,
    table.md, table.csv, figures), written as ``tracklab run`` writes one. The arguments
    are those of ``judge``, refused as it refuses them, before anything compiles; ``out`` is
    refused first, in one line naming it, when it is not a path or is a folder tracklab may not
    write (one of the user's files in it, the working folder)."""
    where = "tracklab.evaluate"
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise wrong_type(where, "out", out, "must be None (no files) or the path of the results folder to write")
    folder = None if out is None else check_results_folder(out, None, "out", where)
    recorded, res = judge(results, truth, dt=dt, name=name, window=window, windows=windows, params=params)
    doc = stats_document(recorded, res)
    if folder is None:
        return doc
    with atomic_folder(folder, None, "out", where) as tmp:
        return write_results(doc, tmp, figures=figures)

def judge(results, truth, *, dt: float, name: str = "recorded", window: tuple[int, int] | None = None,
          windows: dict | None = None, params: dict | None = None):
    """Filters' results on recorded measurements against the truth, as a simulation's result.

    ``results``: a ``FilterResult`` (``run_filter``'s) or {label: FilterResult}, all over the
    same measurements; ``truth``: (T, 2·dim) or (N, T, 2·dim), the true state at each
    measurement step in CV layout [x, ẋ, y, ẏ(, z, ż)]. ``window`` (first, last step) is the
    report window, ``windows`` named step masks of the one-step prediction error, ``params``
    what to record of each filter's parameters. Returns (Recorded, MonteCarloResult), what
    ``worlds.tracking.experiment.stats_document`` takes.

    Refused in one line naming the argument: a result that is not a ``FilterResult``, or no
    result (``TypeError``/``ValueError``); ``truth`` not finite or of the wrong shape; ``dt``
    not a finite number > 0; a window outside the steps, or a ``windows`` mask not of the
    T steps (``ValueError``)."""
    where = "tracklab.evaluate"
    if not isinstance(results, dict):
        results = {"filter": results}
        if not isinstance(results["filter"], FilterResult):
            raise wrong_type(where, "results", results["filter"], _RESULTS)
    if not results:
        raise refuse(where, "results", {}, _RESULTS)
    for label, r in results.items():
        if not isinstance(r, FilterResult):
            raise wrong_type(where, f"results[{label!r}]", r, _RESULTS)
    dt = check_positive(where, "dt", dt)
    truth = _batched(check_finite(where, "truth", truth), "truth", 2)
    runs = {np.shape(r.x)[0] if np.ndim(r.x) == 3 else 1 for r in results.values()}
    if len(runs) != 1:
        raise ValueError(f"tracklab.evaluate: the results hold different numbers of recordings: {sorted(runs)}")
    if truth.shape[0] == 1 and runs != {1}:  # one truth for every recording (a deterministic path)
        truth = np.broadcast_to(truth, (runs.pop(),) + truth.shape[1:])
    N, T, n2 = truth.shape
    if n2 not in (2, 4, 6):
        raise ValueError(f"tracklab.evaluate: truth has {n2} columns: expected 2·dim, [x, ẋ, y, ẏ(, z, ż)]")
    dim = n2 // 2
    w = tuple(window) if window is not None else (1, T)
    if not 1 <= w[0] <= w[1] <= T:
        raise ValueError(f"tracklab.evaluate: window {window}: expected 1 <= first <= last <= {T}")
    for wname, m in (windows or {}).items():
        if np.shape(m) != (T,):
            raise refuse(where, f"windows[{wname!r}]", np.asarray(m), f"must be a mask of the {T} steps, shape ({T},)")
    k = np.arange(1, T + 1)
    masks = {REPORT_WINDOW: (k >= w[0]) & (k <= w[1])} | {n: np.asarray(m, bool) for n, m in (windows or {}).items()}
    t0 = time.perf_counter()
    sums, example_x, example_var, per_run = {}, {}, {}, []
    with jax.enable_x64(True):
        for label, r in results.items():
            x = _batched(r.x, f"{label}: x", 2)
            if x.shape[:2] != (N, T):
                raise ValueError(f"tracklab.evaluate: {label}: x has shape {np.shape(r.x)}, the truth {np.shape(truth)}: "
                                 f"give the truth at each of the T steps, (T, 2·dim) or (N, T, 2·dim)")
            layout = r.layout or interleaved(dim)
            why = layout.check(dim) if hasattr(layout, "check") else None
            if why or layout.n != x.shape[-1]:
                raise ValueError(f"tracklab.evaluate: {label}: its state has {x.shape[-1]} components, the truth is {dim}-D: "
                                 f"{why or 'set the filter layout (tracklab.Layout) of its position and velocity'}")
            lead = lambda a, nd: None if a is None else _batched(a, label, nd)
            out = Out(x=x, P=lead(r.P, 3), x_pred=lead(r.x_pred, 2), nu=lead(r.nu, 2), S=lead(r.S, 3),
                      valid=None if r.valid is None else np.asarray(r.valid).reshape(N, T),
                      dof=None if r.dof is None else np.asarray(r.dof).reshape(N, T))
            s = recorded_sums(out, truth, layout, masks)
            example_x[label] = s.pop("example_x")
            example_var[label] = s.pop("example_var")
            per_run.append(s.pop("per_run"))
            sums[label] = s
    samples = RunSamples()  # the recordings are the runs, the same for every filter: paired
    samples.add(*(np.stack([p[k] for p in per_run]) for k in ("values", "ok", "kept")))
    kinds = {label: "recorded" for label in results}
    res = MonteCarloResult(
        runs=N, steps=T, dt=float(dt), dim=dim, sums=sums, pcrlb=None, wall_s=time.perf_counter() - t0, compile_s=0.0,
        labels=list(results), kinds=kinds,
        example={"truth": np.concatenate([np.full((1, n2), np.nan), truth[0]]), "x": example_x, "var": example_var},
        windows=list(masks), samples=samples, sample_names=sample_names(dim, with_report_window(masks, T)),
        report_window=w)
    raw = {"experiment": {"name": name, "runs": N, "steps": T, "dt": float(dt), "built": "recorded"},
           "filter": [{"label": label} for label in results], "report": {"window": list(w)}}
    parameters = {label: {n: np.asarray(v, float) for n, v in (params or {}).get(label, {}).items()} for label in results}
    return Recorded(name, float(dt), T, w, masks, raw, parameters), res
