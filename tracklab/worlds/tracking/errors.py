"""The open-loop world's errors and sums: a filter's output at a step against the truth.

Per run and step (``error_inputs`` picked inside the filter's step, ``errors_of`` for all the
filters of the same shapes at once): the estimation error in the CV layout, NEES, NIS and
log det S, the one-step prediction error, the filter's own variances, and whether the run
turned bad (NaN/inf, a covariance not positive definite). Per step, over the runs of a chunk:
the sums and maxima of ``SUMS`` and ``MAXIMA`` (``lane_sums``: one variadic reduction per row
height, ``sum_over_runs``), cut into named quantities after the chunk (``named``, ``unpack``).
Per run, over the report windows: the samples of ``sample_names`` behind the intervals
(``run_samples``; a total is summed from its axes after the scan, ``window_sums``). The losses
``tracklab tune`` minimises (``LOSSES``) read the sums.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab.linalg import mahalanobis2, mahalanobis2_logdet, norm, pick, sum_elements
from tracklab.montecarlo.statistics import REPORT_WINDOW


class RunErrors(NamedTuple):
    """One filter's errors at one step, per run (batched with the runs last: (…, runs)); a field of
    ``MAY_BE_SHARED`` that is the same in every run may have a runs axis of 1 instead."""

    e: Any  # (2d,) estimate minus truth, CV layout
    nees: Any
    nis: Any  # 0 where no update
    valid: Any  # bool: an update happened
    dof: Any  # innovation components used
    bad: Any  # bool: NaN/inf estimate, NEES or NIS
    logdet_s: Any  # log det S, 0 where no update
    e_pred: Any  # (d,) one-step position prediction error
    var: Any  # (2d,) the filter's own variances of e (the diagonal of its covariance), CV layout
    validated: Any  # returns it validated in a scan (a filter of scans); NaN: no scan, or not such a filter
    existence: Any  # the target's existence probability it reports (IPDA); NaN: none

    @classmethod
    def zeros(cls, d, B, dtype):
        """In the place of the errors before the first step (the scan's first carry)."""
        z = lambda *shape: jnp.zeros(shape + (B,), dtype)
        no = jnp.zeros((B,), bool)
        nan = jnp.full((B,), jnp.nan, dtype)
        return cls(z(2 * d), z(), z(), no, z(), no, z(), z(d), z(2 * d), nan, nan)

# the fields that the sums and samples read only against a per-run value (a run's ``ok``, its NIS)
# or at run 0: the chunk carries them once, with a runs axis of 1, where they are the same in every
# run (a linear KF's variances and log det S, a filter's constant dof, validated and existence)
MAY_BE_SHARED = ("valid", "dof", "logdet_s", "var", "validated", "existence")

class ErrorInputs(NamedTuple):
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
    validated: Any  # returns validated in a scan (NaN: none made, or not a filter of scans)
    existence: Any  # the target's existence probability the filter reports (NaN: none)

def error_inputs(out, truth_k, pv, dtype) -> ErrorInputs:
    """One run's ``ErrorInputs`` at one step from a filter's output ``out`` (an ``Out``), the
    true state ``truth_k`` (2d,) in CV layout and ``pv``, the indices of [x, ẋ, y, ẏ, …] in its state."""
    e = pick(out.x, pv) - truth_k
    Pe = pick(pick(out.P, pv), pv, axis=1)
    nu = S = None
    valid, dof = jnp.asarray(False), jnp.asarray(0.0, dtype)
    if out.nu is not None and out.S is not None:
        nu, S = out.nu, out.S
        valid = jnp.asarray(True if out.valid is None else out.valid, bool)
        dof = jnp.asarray(out.nu.shape[-1] if out.dof is None else out.dof, dtype)
    if out.x_pred is not None:
        e_pred = pick(out.x_pred, pv[0::2]) - truth_k[0::2]
    else:  # no prediction reported: its statistics are NaN, shown as missing
        e_pred = jnp.full((len(pv) // 2,), jnp.nan, dtype)
    validated = jnp.asarray(jnp.nan if out.validated is None else out.validated, dtype)
    aux = out.aux if isinstance(out.aux, dict) else {}
    existence = jnp.asarray(aux.get("existence", jnp.nan), dtype)
    return ErrorInputs(e, Pe, sum_elements(out.x), nu, S, valid, dof, e_pred, validated, existence)

def errors_of(a: ErrorInputs, dtype) -> RunErrors:
    """One run's errors from its ``ErrorInputs``."""
    nees = mahalanobis2(a.Pe, a.e)  # NaN when P is not positive definite
    bad = ~jnp.isfinite(nees + a.x_sum)
    if a.nu is not None:
        nis, logdet_s = mahalanobis2_logdet(a.S, a.nu)
        nis = jnp.where(a.valid, nis, 0.0)
        logdet_s = jnp.where(a.valid, logdet_s, 0.0)
        bad = bad | (a.valid & ~jnp.isfinite(nis))
    else:  # no innovation reported: no NIS (its columns are empty)
        nis, logdet_s = 0.0, 0.0
    # fixed dtypes, so that the scan's carry is known without tracing the step (RunErrors.zeros)
    f = lambda v: jnp.asarray(v, dtype)
    return RunErrors(f(a.e), f(nees), f(nis), jnp.asarray(a.valid, bool), f(a.dof), bad, f(logdet_s), f(a.e_pred),
                      f(jnp.diagonal(a.Pe)), f(a.validated), f(a.existence))

def run_errors(out, truth_k, pv, dtype) -> RunErrors:
    """One run's errors at one step from a filter's output ``out`` (see ``error_inputs``)."""
    return errors_of(error_inputs(out, truth_k, pv, dtype), dtype)

def with_errors(body, dtype):
    """A filter's one-run step returning its errors (``errors_of``) instead of their inputs."""

    def step(state, inp):
        state, inputs = body(state, inp)
        return state, errors_of(inputs, dtype)

    return step

# a step's sums over the runs and maxima over the runs, each one vector per filter inside the
# scan (one reduction each, one output each), cut into the named quantities after it
SUMS = ("count", "sum_pos", "sum_vel", "sumsq_pos", "sumsq_vel", "sum_nees", "sum_nis", "count_nis", "dof_nis",
         "sum_logdet_s", "sum_pred", "sumsq_pred", "sum4_pos", "sum4_vel", "sumsq2_pos", "sumsq2_vel",
         "sum_validated", "count_scans", "lost")

MAXIMA = ("max_err_pos", "max_err_vel")

PER_RUN_SCALARS = {"count", "sum_nees", "sum_nis", "count_nis", "dof_nis", "sum_logdet_s", "max_err_pos", "max_err_vel",
                    "sumsq2_pos", "sumsq2_vel", "sum_validated", "count_scans", "lost"}

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

def _averaged(d: int, windows) -> list[tuple[str, int]]:
    """The samples of ``sample_names`` that are window means (all but the maxima)."""
    return [(n, w) for n, w in sample_names(d, windows) if not n.startswith("max_pred@")]

def _axes_of(name: str) -> str | None:
    """The per-axis samples whose sum is the total ``name`` (``sq_pos``, ``sq_pred@…``); None for a
    sample summed in the scan."""
    if name == "sq_pos":
        return "sq_pos_axes"
    return name.replace("sq_pred@", "sq_pred_axes@") if name.startswith("sq_pred@") else None

def _accumulated(d: int, windows) -> list[tuple[str, int]]:
    """The per-run samples summed step by step in the scan: the window means but the totals,
    which are the sums of their per-axis rows (``window_sums``)."""
    return [(n, w) for n, w in _averaged(d, windows) if _axes_of(n) is None]

def accumulated_count(d: int, windows) -> int:
    """The rows of ``run_samples``."""
    return sum(w for _, w in _accumulated(d, windows))

def accumulated_lengths(d: int, windows: dict) -> np.ndarray:
    """Per window mean of ``sample_names``, the steps of its window: what a run's window sum
    (``window_sums``) is divided by."""
    return np.concatenate([np.full(w, windows[n.split("@")[1] if "@" in n else REPORT_WINDOW].sum())
                           for n, w in _averaged(d, windows)])

def run_samples(r: RunErrors, w_k):
    """One step's contributions (Q, B) to each run's sums of the accumulated samples
    (``_accumulated``): ``w_k`` (windows,) whether the step is in each named window, the report
    window first (``with_report_window``)."""
    w_report = w_k[0]
    ep, ev = r.e[0::2], r.e[1::2]
    upd = jnp.broadcast_to(r.valid, r.nees.shape).astype(ep.dtype)
    report = jnp.concatenate([sum_elements(ev**2)[None], ep**2, ep, ev, r.nees[None], (r.nis * upd)[None], upd[None]])
    rows = [w_report * report]
    for j in range(w_k.shape[0]):
        rows.append(w_k[j] * r.e_pred**2)
    return jnp.concatenate(rows)

def window_sums(acc, d: int, windows):
    """Each run's accumulated sums ``acc`` (Q, runs) (``run_samples``) laid out as
    ``sample_names`` without the maxima: a total is the sum of its axes' sums. ``windows``: the
    windows' names, in order."""
    at, i = {}, 0
    for name, width in _accumulated(d, windows):
        at[name], i = acc[i:i + width], i + width
    return jnp.concatenate([at[name] if name in at else sum_elements(at[_axes_of(name)])[None]
                            for name, _ in _averaged(d, windows)])

def lane_sums(r: RunErrors, ok, runmax, w_k, dtype, lost=None):
    """One step's sums over the runs ``ok`` (B,) of one filter's per-run errors (runs last): the
    vectors of ``SUMS`` and of ``MAXIMA`` (see ``named``), and the updated per-run maxima.
    ``lost`` (B,): the live runs whose track is lost by this step (``track_loss``), counted
    whether or not they are among ``ok`` (None: none)."""
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
        "sumsq2_pos": sum_elements(ep**2)[None] ** 2,
        "sumsq2_vel": sum_elements(ev**2)[None] ** 2,
        "sum_validated": jnp.where(ok & jnp.isfinite(r.validated), r.validated, 0.0)[None],
        "count_scans": (ok & jnp.isfinite(r.validated)).astype(dtype)[None],
        "lost": (jnp.zeros_like(ok) if lost is None else lost).astype(dtype)[None],
    }
    top = {
        "max_err_pos": norm(ep)[None],
        "max_err_vel": norm(ev)[None],
    }
    sums = sum_over_runs([add[n] for n in SUMS])
    maxima = jnp.max(jnp.where(ok, jnp.concatenate([top[n] for n in MAXIMA]), -jnp.inf), axis=-1)
    return sums, maxima, runmax

class TrackLoss(NamedTuple):
    """The track-loss test: a run's track is lost at the first of ``steps`` consecutive steps whose
    position error is beyond ``distance`` (or not finite) or, with ``existence``, whose
    existence probability (a filter that reports one: IPDA) is below it; lost stays lost."""

    distance: float
    steps: int
    existence: float | None = None


def track_loss(test: TrackLoss | None, e, existence, beyond_steps, lost):
    """One step of the test on position errors ``e`` ((2d, B), CV layout) and reported existence
    probabilities (B,) (NaN: none): the runs' updated count of consecutive steps failing it and
    whether each is lost."""
    if test is None:
        return beyond_steps, lost
    beyond = ~(norm(e[0::2]) <= test.distance)  # NaN: beyond
    if test.existence is not None:
        beyond = beyond | (existence < test.existence)
    beyond_steps = jnp.where(beyond, beyond_steps + 1, 0)
    return beyond_steps, lost | (beyond_steps >= test.steps)


@jax.custom_jvp
def sum_over_runs(rows):
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

@sum_over_runs.defjvp
def _sum_over_runs_jvp(primals, tangents):
    (rows,), (d_rows,) = primals, tangents
    return sum_over_runs(rows), jnp.concatenate([jnp.sum(t, axis=-1) for t in d_rows])

def named(v, names, d):
    """Vectors (..., width) of ``lane_sums`` cut into the named quantities along the last axis
    (a per-run scalar's sum one column, the others d columns)."""
    out, i = {}, 0
    for name in names:
        if name in PER_RUN_SCALARS:
            out[name], i = v[..., i], i + 1
        else:
            out[name], i = v[..., i:i + d], i + d
    return out

def unpack(out, d):
    """Each filter's per-step sums and maxima as named arrays, from the two vectors per step that
    the scan writes (``lane_sums``); the leading axes (steps, grid points) are kept. Cut after
    the compiled chunk, each part is not an output buffer and a kernel of its own."""
    res = dict(out)
    for label, v in out.items():
        if isinstance(v, dict) and "sums" in v:
            v = dict(v)
            res[label] = named(v.pop("sums"), SUMS, d) | named(v.pop("maxima"), MAXIMA, d) | v
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
