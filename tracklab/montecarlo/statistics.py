"""Error statistics from the engine's per-step sums.

Per step (over healthy runs): RMSE per axis, of position and of velocity;
mean error (bias) per axis; maximum error; average NEES and NIS with their
two-sided 95 % χ² intervals; the PCRLB on position. Over the report window
(1-based measurement steps, both ends included): time-averaged RMSE (root of
the mean of the per-step mean-square errors), maximum error, mean bias, mean
NEES/NIS and the fraction of steps whose average lies inside its interval.

One-step prediction error (every filter's prediction of the next position,
made before that measurement, against the true position): per step its RMS
and mean per axis; per named window (steps given as a mask) its RMS
(``pred_err_rms``) and the Monte-Carlo mean of each run's largest error in
the window (``pred_err_max``, what a single recorded pass such as paper 004's
Fig. 3 shows), for the norm and per axis. The report window's values have
plain keys; another window's carry its name: ``pred_err_max[60-90 s]``.
"""

from __future__ import annotations

from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammainc

from tracklab.intervals import LEVEL, half_width, paired_half_width, t_quantile, value_and_gradient, wilson

AXES = ("x", "y", "z")


def chi2_quantile(p, dof):
    """Quantile of the χ² distribution (bisection on the regularised gamma).

    The bisection runs once per distinct (p, dof) pair, compiled: a series of
    thousands of steps usually has a handful of distinct degrees of freedom.
    """
    p, dof = np.broadcast_arrays(np.asarray(p, float), np.asarray(dof, float))
    pairs, inverse = np.unique(np.stack([p.ravel(), dof.ravel()], axis=1), axis=0, return_inverse=True)
    n = max(1, 1 << (len(pairs) - 1).bit_length())  # padded to a power of two: few distinct compiles
    padded = np.concatenate([pairs, np.repeat(pairs[-1:], n - len(pairs), axis=0)])
    with jax.enable_x64(True):
        q = np.asarray(_chi2_bisection(padded[:, 0], padded[:, 1]))
    return q[: len(pairs)][inverse.ravel()].reshape(p.shape)


@jax.jit
def _chi2_bisection(p, dof):
    lo = jnp.zeros_like(dof)
    hi = jnp.maximum(dof + 20.0 * jnp.sqrt(2.0 * jnp.maximum(dof, 1.0)) + 50.0, 1.0)

    def halve(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        below = gammainc(dof / 2.0, mid / 2.0) < p
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, 200, halve, (lo, hi))
    return 0.5 * (lo + hi)


def average_chi2_interval(dof, n, level=0.95, total_dof=None):
    """Interval for the average of n independent χ² values with ``dof`` each.

    The sum is χ² with n·dof degrees of freedom (or ``total_dof`` when the
    terms have different dof, e.g. NIS of partial measurements).
    """
    n = np.maximum(np.asarray(n, float), 1.0)
    D = n * dof if total_dof is None else np.maximum(np.asarray(total_dof, float), 1.0)
    a = (1.0 - level) / 2.0
    return chi2_quantile(a, D) / n, chi2_quantile(1.0 - a, D) / n


def _div(a, b):
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(b > 0, a / np.where(b > 0, b, 1.0), np.nan)


def _inside(v, lo, hi):
    """1 where the average lies inside its interval, 0 outside, NaN where undefined."""
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(v), ((v >= lo) & (v <= hi)).astype(float), np.nan)


REPORT_WINDOW = "window"  # the name under which the report window's prediction error is kept


def window_key(key, name):
    return key if name == REPORT_WINDOW else f"{key}[{name}]"


def _step_half_width(mean, sum_sq, c, level):
    """Per-step t half-width of a mean over c runs, from the sums of the values and of their squares."""
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.maximum(_div(sum_sq, c) - mean**2, 0.0) * _div(c, c - 1)
        t = np.array([t_quantile(level, n - 1) if n >= 2 else np.nan for n in np.unique(c)])
        tq = t[np.searchsorted(np.unique(c), c)]
        return tq * np.sqrt(_div(var, c))


def rms_half_width(ms, sum_sq2, c, level=LEVEL):
    """Per-step half-width of an RMS over c runs, sqrt(ms), by the delta method: from the mean
    square ``ms`` and the sum over the runs of each run's squared value squared (``sum_sq2``)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return _step_half_width(ms, sum_sq2, c, level) / (2.0 * np.sqrt(ms))


def per_step(sums, dim, axes=AXES, level=LEVEL):
    """Per-step series for one filter from its sums; ``*_hw`` are the half-widths of the per-step
    RMSE and mean error at ``level`` (over the runs; an RMSE's by the delta method)."""
    c = sums["count"]
    s = {}
    msepred = _div(sums["sumsq_pred"], c[:, None])
    for a in range(dim):
        s[f"pred_rmse_{axes[a]}"] = np.sqrt(msepred[:, a])
        s[f"pred_mean_err_{axes[a]}"] = _div(sums["sum_pred"][:, a], c)
    s["pred_mse"] = msepred.sum(-1)
    s["pred_rmse"] = np.sqrt(s["pred_mse"])
    msep = _div(sums["sumsq_pos"], c[:, None])
    msev = _div(sums["sumsq_vel"], c[:, None])
    bias = _div(sums["sum_pos"], c[:, None])
    bias_v = _div(sums["sum_vel"], c[:, None])
    for a in range(dim):
        ax = axes[a]
        s[f"rmse_{ax}"] = np.sqrt(msep[:, a])
        s[f"mean_err_{ax}"] = bias[:, a]
        s[f"rmse_v{ax}"] = np.sqrt(msev[:, a])
        s[f"mean_err_v{ax}"] = bias_v[:, a]
    s["mse_pos"] = msep.sum(-1)
    s["mse_vel"] = msev.sum(-1)
    s["rmse_pos"] = np.sqrt(s["mse_pos"])
    s["rmse_vel"] = np.sqrt(s["mse_vel"])
    s["max_err_pos"] = np.where(c > 0, sums["max_err_pos"], np.nan)
    s["max_err_vel"] = np.where(c > 0, sums["max_err_vel"], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        for a in range(dim):
            ax = axes[a]
            for tag, sq, four, sm in (("", msep, "sum4_pos", "sum_pos"), ("v", msev, "sum4_vel", "sum_vel")):
                if four not in sums:
                    continue
                s[f"rmse_{tag}{ax}_hw"] = rms_half_width(sq[:, a], sums[four][:, a], c, level)
                s[f"mean_err_{tag}{ax}_hw"] = _step_half_width(_div(sums[sm][:, a], c), sums[f"sumsq_{sm[4:]}"][:, a],
                                                               c, level)
        for q in ("pos", "vel"):
            if f"sumsq2_{q}" in sums:
                s[f"rmse_{q}_hw"] = rms_half_width(s[f"mse_{q}"], sums[f"sumsq2_{q}"], c, level)
    s["nees"] = _div(sums["sum_nees"], c)
    s["nees_lo"], s["nees_hi"] = average_chi2_interval(2 * dim, c)
    s["nees_in_bounds"] = _inside(s["nees"], s["nees_lo"], s["nees_hi"])
    s["nis"] = _div(sums["sum_nis"], sums["count_nis"])
    s["nis_lo"], s["nis_hi"] = average_chi2_interval(None, sums["count_nis"], total_dof=sums["dof_nis"])
    s["nis_in_bounds"] = _inside(s["nis"], s["nis_lo"], s["nis_hi"])
    s["healthy_runs"] = c
    return s


def summarise(series, window, pcrlb_pos=None, diverged=0.0, runs=0, axes=AXES, pred_windows=None, runmax=None):
    """Time-averaged summary of per-step series over a 1-based inclusive window.

    ``pred_windows``: name -> (steps,) mask; ``runmax``: name -> sums over runs of
    each run's largest prediction error in that window (per axis, then the norm),
    with ``series["healthy_runs"]`` as the number of runs.
    """
    a, b = window
    w = slice(a - 1, b)

    def fraction(flags):
        flags = flags[w]
        ok = np.isfinite(flags)
        return float(np.mean(flags[ok])) if ok.any() else float("nan")

    out = {
        "rmse_pos": float(np.sqrt(np.mean(series["mse_pos"][w]))),
        "rmse_vel": float(np.sqrt(np.mean(series["mse_vel"][w]))),
    }
    for ax in axes:
        if f"rmse_{ax}" in series:
            out[f"rmse_{ax}"] = float(np.sqrt(np.mean(np.square(series[f"rmse_{ax}"][w]))))
            out[f"mean_err_{ax}"] = float(np.mean(series[f"mean_err_{ax}"][w]))
            out[f"mean_err_v{ax}"] = float(np.mean(series[f"mean_err_v{ax}"][w]))
    out["max_err_pos"] = float(np.max(series["max_err_pos"][w]))
    out["max_err_vel"] = float(np.max(series["max_err_vel"][w]))
    out["nees"] = float(np.mean(series["nees"][w]))
    out["nees_in_bounds"] = fraction(series["nees_in_bounds"])
    out["nis"] = float(np.nanmean(series["nis"][w])) if np.isfinite(series["nis"][w]).any() else float("nan")
    out["nis_in_bounds"] = fraction(series["nis_in_bounds"])
    if pcrlb_pos is not None:
        out["pcrlb_pos"] = float(np.sqrt(np.mean(np.square(pcrlb_pos[w]))))
        out["rmse_pos_over_pcrlb"] = out["rmse_pos"] / out["pcrlb_pos"]
    dim = sum(1 for ax in axes if f"pred_rmse_{ax}" in series)
    k = np.arange(len(series["pred_mse"]))
    windows = {REPORT_WINDOW: (k >= a - 1) & (k < b)} | dict(pred_windows or {})
    n = float(series["healthy_runs"][0]) if len(series["healthy_runs"]) else 0.0
    for name, mask in windows.items():
        mask = np.asarray(mask, bool)
        out[window_key("pred_err_rms", name)] = float(np.sqrt(np.mean(series["pred_mse"][mask])))
        for i, ax in enumerate(axes[:dim]):
            out[window_key(f"pred_err_rms_{ax}", name)] = float(np.sqrt(np.mean(np.square(series[f"pred_rmse_{ax}"][mask]))))
        if runmax is not None and name in runmax and n > 0:
            mx = np.asarray(runmax[name], float) / n
            out[window_key("pred_err_max", name)] = float(mx[-1])
            for i, ax in enumerate(axes[:dim]):
                out[window_key(f"pred_err_max_{ax}", name)] = float(mx[i])
    out["diverged"] = int(diverged)
    out["runs"] = int(runs)
    return out


def pcrlb_series(pcrlb, dim, axes=AXES):
    """Position bounds per axis and in total from J⁻¹ (CV layout)."""
    if pcrlb is None:
        return {}
    out = {}
    tot = np.zeros(len(pcrlb))
    for a in range(dim):
        v = pcrlb[:, 2 * a, 2 * a]
        out[f"pcrlb_{axes[a]}"] = np.sqrt(v)
        tot += v
    out["pcrlb_pos"] = np.sqrt(tot)
    vel = sum(pcrlb[:, 2 * a + 1, 2 * a + 1] for a in range(dim))
    out["pcrlb_vel"] = np.sqrt(vel)
    return out


PERCENTILES = (50, 90, 99)  # of each run's RMS position error
PAIRED = ("rmse_pos", "rmse_vel", "nees", "pred_err_rms")  # compared with the baseline filter
CDF_POINTS = 201  # quantiles of the per-run error kept for the error-CDF figure


def sample_statistics(names, axes, windows):
    """Summary key -> statistic of the per-run samples' means (``intervals.value_and_gradient``),
    for samples laid out as ``names`` ((name, width), ``worlds.tracking.sample_names``)."""
    off, i = {}, 0
    for n, w in names:
        off[n], i = list(range(i, i + w)), i + w
    d = len(off["err_pos"])
    stats = {"rmse_pos": ("root", off["sq_pos"]), "rmse_vel": ("root", off["sq_vel"]),
             "nees": ("mean", off["nees"][0]), "nis": ("ratio", off["nis"][0], off["updates"][0])}
    for a, ax in enumerate(axes[:d]):
        stats[f"rmse_{ax}"] = ("root", [off["sq_pos_axes"][a]])
        stats[f"mean_err_{ax}"] = ("mean", off["err_pos"][a])
        stats[f"mean_err_v{ax}"] = ("mean", off["err_vel"][a])
    for w in windows:
        stats[window_key("pred_err_rms", w)] = ("root", off[f"sq_pred@{w}"])
        stats[window_key("pred_err_max", w)] = ("mean", off[f"max_pred@{w}"][-1])
        for a, ax in enumerate(axes[:d]):
            stats[window_key(f"pred_err_rms_{ax}", w)] = ("root", [off[f"sq_pred_axes@{w}"][a]])
            stats[window_key(f"pred_err_max_{ax}", w)] = ("mean", off[f"max_pred@{w}"][a])
    return stats


def lane_intervals(samples, labels, stats, level=LEVEL, baseline=None, paired=(), diverged=None, kept=()):
    """Per lane (filter, tracker or case): its summary numbers from its runs' samples and what a
    reviewer needs beside them.

    ``stats``: summary key -> statistic of the samples' means (``intervals.value_and_gradient``);
    ``paired``: the keys compared with the ``baseline`` lane (default the first) on the runs healthy
    in both; ``diverged``: label -> (diverged runs, runs), given its Wilson interval; ``kept``:
    (index of a kept per-run value, summary key with ``{p}`` for its percentiles, its cdf key).
    Returns label -> {"summary", "half_width", "intervals", "paired", "cdf"}.
    """
    base = labels.index(baseline) if baseline in labels else 0
    out = {}
    for li, label in enumerate(labels):
        summary, hw = {}, {}
        own = samples.pair(li, li)
        for key, stat in stats.items():
            v, g = value_and_gradient(stat, own.mean_f)
            summary[key] = float(v) if own.n > 0 else float("nan")
            hw[key] = half_width(g, own.cov_ff, own.n, level) if np.isfinite(v) else float("nan")
        lane = {"summary": summary, "half_width": hw}
        if diverged is not None:
            k, runs = diverged[label]
            summary["diverged_fraction"] = k / runs if runs else float("nan")
            lane["intervals"] = {"diverged_fraction": list(wilson(k, runs, level))}
        q = np.linspace(0.0, 1.0, CDF_POINTS)
        for j, pct_key, cdf_key in kept:
            values = samples.kept(li, j)
            for p, v in zip(PERCENTILES, np.percentile(values, PERCENTILES) if values.size else [np.nan] * 3):
                summary[pct_key.format(p=p)] = float(v)
            if values.size:
                lane.setdefault("cdf", {"probability": q})[cdf_key] = np.quantile(values, q)
        pair = samples.pair(li, base)
        pd = {"baseline": labels[base], "runs": pair.n}
        for key in paired:
            vf, gf = value_and_gradient(stats[key], pair.mean_f)
            vb, gb = value_and_gradient(stats[key], pair.mean_g)
            h = paired_half_width(gf, gb, pair.cov_dd, pair.cov_dg, pair.cov_gg, pair.n, level)
            diff = float(vf - vb) if pair.n > 0 else float("nan")
            rounding = 1e-9 * max(abs(float(vf)), abs(float(vb)))  # same numbers but for the last digits
            if abs(diff) <= rounding and h <= rounding:
                diff, h = 0.0, 0.0
            pd[key] = {"difference": diff, "half_width": h,
                       "significant": bool(np.isfinite(h) and abs(diff) > h) if li != base else False}
        lane["paired"] = pd
        out[label] = lane
    return out


def with_intervals(result, filters, level=LEVEL, baseline=None):
    """Each filter's summary from its runs' samples with the half-widths of their ``level``
    intervals (``half_width``), the Wilson interval of its diverged fraction, the percentiles of
    its runs' RMS position error with their distribution (``cdf``), and (``paired``) its
    differences to the ``baseline`` filter (default the first) on their common runs."""
    labels = list(result.labels)
    windows = [n.split("@", 1)[1] for n, _ in result.sample_names if n.startswith("max_pred@")]
    stats = sample_statistics(result.sample_names, tuple(result.axes), windows)
    diverged = {l: (filters[l]["summary"]["diverged"], filters[l]["summary"].get("runs", 0)) for l in labels}
    lanes = lane_intervals(result.samples, labels, stats, level, baseline, [k for k in PAIRED if k in stats],
                           diverged, kept=[(0, "err_pos_p{p}", "err_pos")])
    for label, lane in lanes.items():
        f = filters[label]
        summary = f["summary"]
        summary.update(lane.pop("summary"))
        f.update(lane)
        if "pcrlb_pos" in summary:
            summary["rmse_pos_over_pcrlb"] = summary["rmse_pos"] / summary["pcrlb_pos"]
            f["half_width"]["rmse_pos_over_pcrlb"] = f["half_width"]["rmse_pos"] / summary["pcrlb_pos"]
    return filters


def wilson_series(k, n, level=LEVEL):
    """Per-step Wilson intervals (lo, hi) of the fractions k/n."""
    lo_hi = np.array([wilson(a, n, level) for a in np.asarray(k, float)]).reshape(-1, 2)
    return lo_hi[:, 0], lo_hi[:, 1]


def track_loss_statistics(sums, runs, dt, loss_steps, window, level=LEVEL):
    """A filter's tracking in clutter from its sums: (per-step series, summary, intervals).

    Per step: the fraction of runs whose track is lost by then (``p_lost``) with its Wilson
    interval, and the mean number of returns validated per scan (over the runs on track).
    Summary: the runs lost by the end (``lost``) and their fraction with its Wilson interval,
    the mean time to loss (the first of the test's consecutive steps beyond its distance, over
    the lost runs; missing when none is), the runs on track, and the validated returns per scan
    over the report window (missing for a filter that sees no scans)."""
    lost = np.asarray(sums["lost"], float)
    series = {"p_lost": lost / runs if runs else np.full(len(lost), np.nan)}
    series["p_lost_lo"], series["p_lost_hi"] = wilson_series(lost, runs, level)
    series["validated"] = _div(sums["sum_validated"], sums["count_scans"])
    k_lost = float(lost[-1]) if len(lost) else 0.0
    new = np.diff(np.concatenate([[0.0], lost]))  # runs declared lost at each step
    onset = dt * (np.arange(1, len(lost) + 1) - (loss_steps - 1))
    a, b = window
    w = slice(a - 1, b)
    scans = float(np.sum(sums["count_scans"][w]))
    summary = {
        "lost": int(round(k_lost)),
        "p_lost": k_lost / runs if runs else float("nan"),
        "time_to_loss": float(np.sum(new * onset) / k_lost) if k_lost > 0 else float("nan"),
        "on_track": int(runs - round(k_lost)),
        "validated_per_scan": float(np.sum(sums["sum_validated"][w]) / scans) if scans > 0 else float("nan"),
    }
    return series, summary, {"p_lost": list(wilson(k_lost, runs, level))}


def paired_loss(pairs, labels, base, runs, level=LEVEL):
    """Each filter's difference in the fraction of lost tracks to the ``base`` filter's on the same
    runs, with its half-width (paired proportions: n₁₀ runs lost by it only, n₀₁ by the base only,
    Var = (n₁₀ + n₀₁ − (n₁₀ − n₀₁)²/n)/n²)."""
    z = NormalDist().inv_cdf(1.0 - (1.0 - level) / 2.0)
    b = labels.index(base)
    out = {}
    for i, label in enumerate(labels):
        n10, n01 = float(pairs[i, b]), float(pairs[b, i])
        diff = (n10 - n01) / runs if runs else float("nan")
        var = max(n10 + n01 - (n10 - n01) ** 2 / runs, 0.0) / runs**2 if runs else float("nan")
        h = z * float(np.sqrt(var))
        out[label] = {"difference": diff, "half_width": h, "significant": bool(i != b and abs(diff) > h)}
    return out


def statistics(result, window, pred_windows=None, level=LEVEL, baseline=None):
    """All statistics of a MonteCarloResult: {'bounds': {...}, 'filters': {label: {...}}, 'level': …}.

    ``pred_windows``: name -> (steps,) mask of the prediction-error windows
    (the report window is always one, as ``REPORT_WINDOW``). With the runs' samples (and
    ``window`` the window they average over) every summary number has its ``level`` interval
    and each filter its paired differences to ``baseline`` (``with_intervals``).
    """
    axes = tuple(result.axes)
    bounds = pcrlb_series(result.pcrlb, result.dim, axes)
    filters = {}
    for label in result.labels:
        sums = result.sums[label]
        series = per_step(sums, result.dim, axes, level)
        runmax = {k.split("@", 1)[1]: v for k, v in sums.items() if k.startswith("runmax_pred@")}
        summary = summarise(
            series,
            window,
            bounds.get("pcrlb_pos"),
            diverged=float(np.asarray(sums["diverged"]).sum()),
            runs=result.runs,
            axes=axes,
            pred_windows=pred_windows,
            runmax=runmax,
        )
        filters[label] = {"kind": result.kinds[label], "summary": summary, "series": series}
        if result.loss is not None:
            more, loss_summary, loss_intervals = track_loss_statistics(sums, result.runs, result.dt, result.loss.steps,
                                                                       window, level)
            series.update(more)
            summary.update(loss_summary)
            filters[label]["loss_intervals"] = loss_intervals
    if result.samples is not None and tuple(result.report_window or ()) == tuple(window):
        with_intervals(result, filters, level, baseline)
    if result.loss is not None:
        labels = list(result.labels)
        paired = paired_loss(result.lost_pairs, labels, baseline if baseline in labels else labels[0], result.runs,
                             level)
        for label, f in filters.items():
            f.setdefault("intervals", {}).update(f.pop("loss_intervals"))
            f.setdefault("paired", {"baseline": baseline if baseline in labels else labels[0]})["p_lost"] = paired[label]
    return {"bounds": bounds, "filters": filters, "level": level}
