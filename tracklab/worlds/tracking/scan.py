"""The open-loop world's chunk: one scan over the steps for every filter.

A chunk of runs is one ``lax.scan`` over the steps that carries every run's truth and every
filter's state: at each step the runs' truths advance, their measurements are made, every
filter steps (``batching.runs_last``: batched over the runs, the runs last in every array) and the errors are reduced over the runs to per-step sums
(and maxima). The random draws of the whole chunk are made first, in float32
(``tracklab.random``), so nothing of size (runs × steps) is kept in the working precision. One
scan serves every compared filter, and a filter state that is the same in every run (a linear
KF's covariance when the report pattern is) is carried once, not per run, and so are the errors
that are (its variances and log det S: ``errors.MAY_BE_SHARED``, ``lanes.errors_dependence``).
Filters whose errors have the same shapes are a group: their errors and per-step sums are
computed together along a leading filter axis.

Every number — scenario, sensors, prior, filters — is a leaf of ``TrackingParams``, an argument
of the compiled program; ``TrackingStructure`` (the filters' kinds, models and views, the report
windows, the chunk size) and the params' pytree structure are what the program is compiled for.
The runner (``tracklab.montecarlo.runner``) drives the chunks: keys, devices, padding,
divergence, progress, timing and the host-side sums.

A run in which a filter produces NaN/inf or a covariance that is not positive definite is
*diverged* for that filter: it is counted and left out of that filter's averages (the runner
runs the chunk a second time without it); it never stops the batch.

With a track-loss test (``TrackingStructure.loss``, ``errors.TrackLoss``) a run whose track a
filter loses leaves that filter's per-step sums from the step the loss is declared, and its
per-run samples (the summaries and their intervals) altogether: no second pass is needed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab import random
from tracklab.batching import runs_last
from tracklab.linalg import pick
from tracklab.montecarlo import runner
from tracklab.montecarlo.statistics import REPORT_WINDOW
from tracklab.sensors import SensorSuite
from tracklab.sensors.clutter import cluttered_of
from tracklab.worlds.tracking.errors import (
    RunErrors,
    accumulated_count,
    accumulated_lengths,
    errors_of,
    lane_sums,
    run_samples,
    track_loss,
    window_sums,
    with_errors,
)
from tracklab.worlds.tracking.lanes import errors_dependence, lane, run_dependence, view_pattern


@dataclass(frozen=True)
class TrackingStructure:
    """What an open-loop program is compiled for, besides the params' pytree structure."""

    filters: tuple  # DeclaredFilter or FilterSpec, one per compared filter
    windows: tuple = ()  # (name, (steps,) bools): where each run's largest prediction error is taken
    chunk: int = 1000  # runs per chunk
    loss: Any = None  # the track-loss test (errors.TrackLoss), None: none
    scans: bool = False  # the sensor's scans hold clutter (sensors.Cluttered)

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

def window_mask(windows: dict) -> np.ndarray:
    """(steps, windows) bools: whether each step is in each of ``windows`` (``with_report_window``'s), in order."""
    return np.stack([np.asarray(m, bool) for m in windows.values()], axis=1)

def windows_of(masks: dict | None) -> tuple:
    """Named step masks as a hashable structure field."""
    return tuple((name, tuple(bool(b) for b in np.asarray(m))) for name, m in (masks or {}).items())

def split_keys(keys):
    """A run's key -> its truth, measurement and prior keys."""
    split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
    return split[:, 0], split[:, 1], split[:, 2]

def simulate_runs(scenario, sensor, P0_cv, key, idx):
    """Runs ``idx`` as the tracking world simulates them: (truth (B, T+1, 2d), z (B, T, M), prior (B, 2d)).

    Run i's truth, measurements and prior mean come from ``fold_in(key, i)`` (the runner's keys);
    ``P0_cv`` is the prior covariance (CV layout). The world draws the same values step by step
    inside its scan; this gives them whole.
    """
    k_truth, k_meas, k_prior = split_keys(runner.run_keys(key, idx))
    truth = jax.vmap(scenario.simulate)(k_truth)  # (B, T+1, 2d)
    z = jax.vmap(sensor.measure)(k_meas, truth[:, 1:, 0::2])  # (B, T, M)
    return truth, z, prior_means(truth[:, 0], k_prior, jnp.linalg.cholesky(jnp.asarray(P0_cv)))

def prior_means(truth0, k_prior, L0):
    """Run i's prior mean: its truth at the prior epoch plus a N(0, L0 L0ᵀ) draw."""
    w = jax.vmap(lambda k: random.normal(k, (L0.shape[0],), L0.dtype))(k_prior)
    return truth0 + w @ L0.T

def _streams(scenario, views) -> bool:
    """Whether the chunk can draw truth and measurements step by step inside its scan: the
    truth is the same in every run or has a one-step ``advance``, and every filter sees each
    step's measurement alone (a view that registers one sensor's reports in time needs them all)."""
    truth_ok = not scenario.per_run or scenario.advance is not None
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
        lengths = accumulated_lengths(d, windows)
        n_acc = accumulated_count(d, names)
        P0_cv = params.P0
        L0 = jnp.linalg.cholesky(P0_cv)
        dtype = L0.dtype
        pattern = np.concatenate([np.repeat(s.report_mask(T)[:, None], s.m, axis=1) for s in sensor.sensors],
                                 axis=1)  # (steps, M): which components each sensor reports at each step
        report_masks = np.stack([s.report_mask(T) for s in sensor.sensors], axis=1)  # (steps, sensors)
        detect_all = not sensor.misses
        cluttered = cluttered_of(sensor)
        with_bound = scenario.gaussian  # no PCRLB, no information to gather
        stand_in = _stand_in(sensor)
        views = [f.view_for(stand_in) for f in structure.filters]
        stream = _streams(scenario, views)
        k_truth, k_meas, k_prior = split_keys(keys)
        B = keys.shape[0]
        t = dt * jnp.arange(1, T + 1, dtype=dtype)
        if stream and not scenario.per_run:  # one truth for every run: a table
            table = jnp.asarray(scenario.simulate(None), dtype)  # (T+1, 2d)
            truth0, src = table[0], None
        elif stream:  # each run's truth advanced step by step
            truth0 = jnp.broadcast_to(jnp.asarray(scenario.initial_state(), dtype), (B, 2 * d))
            src = None
        else:  # drawn whole, read step by step (time-major, the truth's runs last)
            truth_all = jax.vmap(scenario.simulate, out_axes=-1)(k_truth).astype(dtype)  # (T+1, 2d, B)
            z_all = jax.vmap(sensor.measure, in_axes=(0, -1), out_axes=1)(k_meas, truth_all[1:, 0::2])
            truth0, src = truth_all[0].T, (truth_all[1:], z_all)
        prior = prior_means(truth0, k_prior, L0.astype(dtype))
        n_live = jnp.sum(live.astype(dtype))
        reports_by_sensor = jnp.asarray(report_masks, dtype)  # (steps, sensors)
        if stream:  # every draw of the chunk made at once (float32, cheap), read step by step (time-major)
            meas_draws = jax.vmap(lambda k: sensor.draws(k, T), out_axes=1)(k_meas)
            accel = jax.vmap(scenario.draws, out_axes=1)(k_truth) if scenario.per_run else None

        lanes = []
        for f, p, view in zip(structure.filters, params.filters, views):
            real = f.realise(scenario, sensor, p, params.prior_extra_var)
            lanes.append(lane(real, p, P0_cv, view_pattern(view, pattern, dtype), detect_all, dtype))
        z_views = []
        if not stream:  # a view of the whole sequence per run, time-major
            z_views = [z_all if ln.view is None else jax.vmap(ln.view, in_axes=1, out_axes=1)(z_all)
                       for ln in lanes]
        truth_batched = scenario.per_run or not stream
        # the filters' per-run values with the runs last (batching.runs_last), but for filters of
        # scans in clutter: their association over a scan's returns runs faster with the runs first
        # (plain vmap; benchmarks/README.md)
        runs_axis = 0 if cluttered is not None else -1
        state_axes, states0, err_axes, kinds, bodies, err_shared = [], [], [], [], [], []
        for ln in lanes:
            fixed = (t, ln.present, jnp.asarray(ln.reports))
            m_f = ln.pattern.shape[1]
            scan_shape = (cluttered.max_returns,) if cluttered is not None else ()  # a scan's returns
            z_ex, truth_ex = jnp.zeros(scan_shape + (m_f,), dtype), jnp.zeros((2 * d,), dtype)
            shared, varies, inputs, body = run_dependence(ln.init, ln.body, prior[0], z_ex, truth_ex, fixed,
                                                           may_share=ln.present is not None)
            bodies.append(body)
            state_axes.append(jax.tree_util.tree_map(lambda s: None if s else runs_axis, shared))
            states0.append(jax.vmap(ln.init, out_axes=state_axes[-1])(prior))
            # the error inputs that differ between runs carry the runs last; the others (a shared
            # covariance's Pe and S) once
            in_tree = jax.tree_util.tree_structure(inputs)
            err_axes.append(jax.tree_util.tree_unflatten(in_tree, [-1 if v else None for v in varies]))
            kinds.append((in_tree, tuple((a.shape, a.dtype) for a in jax.tree_util.tree_leaves(inputs)), tuple(varies)))
            # and of its errors, those the same in every run are carried once (a runs axis of 1)
            err_shared.append(errors_dependence(inputs, varies, dtype))
        errors_axes = [RunErrors(*[None if s else -1 for s in shared]) for shared in err_shared]
        # filters whose error inputs have the same shapes form a group: their errors, per-step sums
        # and per-run samples are computed together, one set of kernels for the group. A filter
        # alone has its errors made inside its own batched step, where XLA fuses them with
        # the filter's arithmetic (its scan step as fast as before grouping; benchmarks/compile.md)
        groups: dict = {}
        for i, kind in enumerate(kinds):
            groups.setdefault(kind, []).append(i)
        groups = list(groups.values())
        steps = [None] * len(lanes)
        for g in groups:
            for i in g:
                alone = len(g) == 1
                body, out_axes = (with_errors(bodies[i], dtype), errors_axes[i]) if alone else (bodies[i], err_axes[i])
                batch = jax.vmap if runs_axis == 0 else functools.partial(runs_last, size=B)
                steps[i] = batch(body, in_axes=(state_axes[i], (runs_axis, runs_axis if truth_batched else None, None,
                                                                None, None)), out_axes=(state_axes[i], out_axes))
        carries = []
        for g in groups:
            L = len(g)
            zeros = RunErrors(*[one if s else per_run for per_run, one, s in
                                zip(RunErrors.zeros(d, B, dtype), RunErrors.zeros(d, 1, dtype), err_shared[g[0]])])
            no_errors = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (L,) + a.shape), zeros)
            nothing = (no_errors, jnp.zeros((L, 4 * d), dtype))
            carries.append((tuple(states0[i] for i in g), nothing, jnp.zeros((L, B), bool),
                            (jnp.zeros((L, len(names), d + 1, B), dtype), jnp.zeros((L, n_acc, B), dtype)),
                            (jnp.zeros((L, B), jnp.int32), jnp.zeros((L, B), bool))))

        def group_errors(g, outs):
            """The errors (lanes, …, runs) of a group's filters from their steps' outputs: their
            error inputs, or for a filter alone the errors it made in its step (a field the same in
            every run with a runs axis of 1)."""
            shared = err_shared[g[0]]
            if len(g) == 1:
                r = jax.tree_util.tree_map(lambda a: a[None], outs[0])
            else:
                stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *outs)
                per_run = runs_last(lambda a: errors_of(a, dtype), in_axes=(err_axes[g[0]],),
                                    out_axes=errors_axes[g[0]], size=B)
                r = jax.vmap(per_run)(stacked)
            return RunErrors(*[a[..., None] if s else a for a, s in zip(r, shared)])

        def group_stats(g, pending, w_k, bad_any, per_run_acc, loss):  # w_k: the step before's windows
            r, first = pending
            runmax, acc = per_run_acc
            bad_any = bad_any | r.bad
            # the track-loss test on the step before's errors (before the first step: zero errors, no
            # existence, nothing beyond): a run leaves the step's sums from the step its loss is declared
            loss = jax.vmap(lambda e, x, b, l: track_loss(structure.loss, e, x, b, l))(r.e, r.existence, *loss)
            ok = live & ~pick(exclude, g) & ~bad_any & ~loss[1]
            sums, maxima, runmax = jax.vmap(lambda r, ok, m, l: lane_sums(r, ok, m, w_k, dtype, live & l))(
                r, ok, runmax, loss[1])
            acc = acc + jax.vmap(lambda r: run_samples(r, w_k.astype(dtype)))(r)
            return (sums, maxima, first), bad_any, (runmax, acc), loss

        def scan_step(carry, inp):
            truth_prev, w_prev, group_carries, overflowed = carry
            k, t_k, src_k, zv_k, lane_in, w_k, over_k = inp
            if not stream:
                truth_k, z_k = src_k
            else:
                accel_k, meas_k = src_k
                truth_k = (runs_last(scenario.advance, in_axes=(-1, -1), size=B)(truth_prev, accel_k.T)
                           if scenario.per_run else table[k + 1])
                z_k = jax.vmap(sensor.measure_step, in_axes=(0, None, None, -1 if truth_batched else None))(
                    meas_k, k, T, truth_k[0::2])
            out = {"_example": {"truth": truth_k[:, 0] if truth_batched else truth_k, "z": z_k[0]}}
            if cluttered is not None:  # the scans that passed their capacity
                over_k = jax.vmap(cluttered.overflowed, in_axes=(0, 0, None, None, None))(*over_k, k, T, dtype)
                out["_overflowed_scans"] = jnp.sum((live & over_k).astype(dtype))
                overflowed = overflowed | over_k
            if with_bound:  # expected measurement information at the true positions, for the PCRLB
                pos_k = truth_k[0::2]
                info = 0.0
                for j, s in enumerate(sensor.sensors):
                    if truth_batched:
                        I = jnp.sum(jnp.where(live[:, None, None], jax.vmap(s.information, in_axes=-1)(pos_k), 0.0),
                                    axis=0)
                    else:
                        I = n_live * s.information(pos_k)
                    info = info + reports_by_sensor[k, j] * I
                out["_info"] = info
            new_carries = []
            for g, (states, pending, bad_any, per_run_acc, loss) in zip(groups, group_carries):
                # the sums of the step before, from its per-run errors held in the carry: a loop
                # variable is computed once, where XLA would otherwise recompute the filter's
                # arithmetic inside every reduction that reads it
                (sums, maxima, first), bad_any, per_run_acc, loss = group_stats(g, pending, w_prev, bad_any,
                                                                                per_run_acc, loss)
                for j, i in enumerate(g):
                    out[runner.lane_key(i)] = (sums[j], maxima[j], first[j])
                new_states, outs = [], []
                for i, state in zip(g, states):
                    present_k, reports_k = lane_in[i]
                    z_f = zv_k[i] if not stream else (z_k if lanes[i].view is None else lanes[i].view(z_k))
                    if runs_axis == -1:
                        z_f = jnp.moveaxis(z_f, 0, -1)
                    truth_in = jnp.moveaxis(truth_k, -1, runs_axis) if truth_batched else truth_k
                    state, out_i = steps[i](state, (z_f, truth_in, t_k, present_k, reports_k))
                    new_states.append(state)
                    outs.append(out_i)
                r = group_errors(g, outs)
                x_first = r.e[:, :, 0] + (truth_k[:, 0] if truth_batched else truth_k)  # run 0's estimate
                first = jnp.concatenate([x_first, r.var[:, :, 0]], axis=1)  # and its variances
                new_carries.append((tuple(new_states), (r, first), bad_any, per_run_acc, loss))
            return (truth_k if (stream and scenario.per_run) else None, w_k, new_carries, overflowed), out

        lanes_in = [(ln.present, jnp.asarray(ln.reports)) for ln in lanes]
        if stream:
            src = (accel, meas_draws)
        # T + 1 iterations: iteration k adds up step k - 1's errors (held in the carry), so the
        # statistics are written once, inside the loop. Iteration 0 adds up nothing; iteration T
        # reads step T - 1's inputs again, and its simulation and filter steps are not kept
        over_in = None
        if cluttered is not None:  # its detection and false-alarm count draws, time-major
            mine = meas_draws[0] if stream else jax.vmap(lambda key: sensor.draws(key, T), out_axes=1)(k_meas)[0]
            over_in = (mine[0][1], mine[1])
        # each run's truth (2d, runs), the runs last as the filters take it
        carry0 = (truth0.T if (stream and scenario.per_run) else None, jnp.zeros((len(names),), bool), carries,
                  jnp.zeros((B,), bool))
        again = lambda a: jnp.concatenate([a, a[-1:]])
        w_masks = jnp.asarray(window_mask(windows))  # (T, windows)
        xs = jax.tree_util.tree_map(again, (jnp.arange(T), t, src, z_views, lanes_in, w_masks, over_in))
        (_, _, finals, overflowed), out = jax.lax.scan(scan_step, carry0, xs)
        example = {"truth": jnp.concatenate([(truth0[0] if truth_batched else truth0)[None], out["_example"]["truth"][:T]]),
                   "z": out["_example"]["z"][:T]}
        added = {"_info": out["_info"][:T] if with_bound else jnp.zeros((T, d, d), dtype)}
        if cluttered is not None:  # scans over their capacity, per step, and the runs with any
            added["_overflow"] = {"scans": out["_overflowed_scans"][:T],
                                  "runs": jnp.sum((live & overflowed).astype(dtype))}
        largest, first = {}, {"_example": example}
        n = len(lanes)
        flags, values, oks = [None] * n, [None] * n, [None] * n
        lost_final = [None] * n
        for g, (_, _, bad_any, (runmax, acc), (_, lost)) in zip(groups, finals):
            for j, i in enumerate(g):
                ln = lanes[i]
                key = runner.lane_key(i)
                sums, maxima, run0 = (a[1:] for a in out[key])
                ok = live & ~exclude[i] & ~bad_any[j] & ~lost[j]  # the runs' samples: those never lost
                added[key] = {"sums": sums, "diverged": jnp.sum((live & bad_any[j]).astype(dtype))}  # cut by unpack
                for w, name in enumerate(names):  # sum over runs of each run's largest |error| (per axis, then norm)
                    added[key][f"runmax_pred@{name}"] = jnp.sum(jnp.where(ok, runmax[j, w], 0.0), axis=-1)
                largest[key] = {"maxima": maxima}
                first[key] = {"example_x": run0[:, :2 * d], "example_var": run0[:, 2 * d:]}
                flags[i] = live & bad_any[j]
                lost_final[i] = live & lost[j]
                values[i] = jnp.concatenate([window_sums(acc[j], d, names) / jnp.asarray(lengths, dtype)[:, None],
                                             runmax[j].reshape(-1, B)])
                oks[i] = ok
        per_run = None
        if values:  # each run's time-averaged samples, for intervals and paired comparisons
            values = jnp.stack(values)
            per_run = {"values": values, "ok": jnp.stack(oks), "kept": jnp.sqrt(values[:, :1])}
        if structure.loss is not None and n:  # runs lost by one filter and not by another, for paired differences
            lf = jnp.stack(lost_final)
            added["_lost_pairs"] = jnp.sum((lf[:, None, :] & ~lf[None, :, :]).astype(dtype), axis=-1)
        # diverged (filters, B): the runner runs the chunk again without them
        return runner.Sums(added, largest, first, per_run, jnp.stack(flags) if flags else jnp.zeros((0, B), bool))


    return local

@functools.lru_cache(maxsize=64)
def world(structure: TrackingStructure) -> runner.World:
    """The tracking world of a structure (one per structure: its compiled programs are shared)."""
    return runner.World(structure, _chunk(structure), len(structure.filters), structure.chunk,
                        compiler_options(structure))


def compiler_options(structure: TrackingStructure) -> tuple:
    """With scans of clutter, XLA's YNNPACK fusions off: it hands the association's sums over the
    returns (K of them per run) to a library kernel per run and step, which runs them several times
    slower than XLA's own loop. A PDAF-EKF on 32 returns: 0.85 against 1.5 million runs·steps/s
    (``benchmarks/clutter.md``); clean measurements compile no such fusion of note."""
    return (("xla_cpu_experimental_ynn_fusion_type", ""),) if structure.scans else ()

def default_chunk(scenario, sensor, budget=2**28, runs=None) -> int:
    """Runs per chunk when the experiment does not say: 1 000 per device (with several filters
    in the scan, larger shares run slower on the CPU: their states no longer stay in cache),
    fewer if a chunk's per-step arrays (truth and measurements of every run and step, 8 bytes
    a value) would pass ``budget`` bytes (256 MiB), but at least 64; on an accelerator as many
    per device as its memory holds of those arrays (``runner.accelerator_runs``: an eighth of it,
    at most 2¹⁸); and no more than ``runs`` need, rounded up to a power of two per device (every
    run of a chunk is computed, live or not), so that nearby run counts, and any count from the
    largest chunk up, share one compiled program."""
    devices = jax.device_count()
    chunk = runner.sized_chunk(8 * scenario.steps * (2 * scenario.dim + sensor.m), budget, 64, 1000)
    if runs:
        per_device = -(-int(runs) // devices)
        chunk = min(chunk, devices * (1 << (per_device - 1).bit_length()))
    return chunk
