"""The airborne world's statistics document (stats.json): per tracker and filter period the RMS
true pointing, LOS-rate, range and range-rate errors over the runs in lock with their bands, the
NEES with its χ² band; per report window their summaries with intervals from the runs' samples,
paired differences to the baseline tracker, percentiles; settling times and lost lock."""

from __future__ import annotations

import numpy as np

from tracklab.montecarlo.statistics import average_chi2_interval, lane_intervals, rms_half_width
from tracklab.worlds.airborne.closed_loop import MRAD, SAMPLE_QUANTITIES


def document(exp, sums, runs, wall, compile_s, precision, samples=None):
    """The statistics document of the per-period ``sums`` over ``runs`` runs; with the runs'
    ``samples`` every summary number has its ``level`` interval, and each tracker its paired
    differences to the baseline and its runs' pointing-error percentiles (``intervals``)."""
    t, masks = exp.window_masks()
    steady = masks.get("steady")
    trackers = {}
    for tc in exp.trackers:
        s = sums[tc.label]
        # runs still in lock at each period; none: every statistic is missing (NaN), never 0
        n = np.where(s["n"] > 0, s["n"], np.nan)
        ms = s["sum_e2"] / n[:, None]
        mean_sq = {"pointing": s["sum_point2"] / n / MRAD**2, "los_rate": (ms[:, 1] + ms[:, 4]) / MRAD**2,
                   "range": ms[:, 6], "range_rate": ms[:, 7]}
        series = {
            "pointing": np.sqrt(mean_sq["pointing"]),  # mrad, the true boresight-to-LOS angle
            "pointing_estimate": np.sqrt(ms[:, 0] + ms[:, 3]) / MRAD,
            "los_rate": np.sqrt(mean_sq["los_rate"]),  # mrad/s
            "range": np.sqrt(ms[:, 6]),
            "range_rate": np.sqrt(ms[:, 7]),
            "range_bias": s["sum_e"][:, 6] / n,
            "nees": np.where(s["n_nees"] > 0, s["sum_nees"] / np.maximum(s["n_nees"], 1.0), np.nan),
        }
        if "sum4" in s:  # each period's RMS with its confidence band (delta method over the runs in lock)
            for j, key in enumerate(("pointing", "los_rate", "range", "range_rate")):
                series[f"{key}_hw"] = rms_half_width(mean_sq[key], s["sum4"][:, j], s["n"], exp.level)
        series["nees_lo"], series["nees_hi"] = average_chi2_interval(9, s["n_nees"], exp.level)
        summary = {"runs": int(runs), "diverged": int(s["lost"]), "lost_lock": int(s["lost"])}
        summary["healthy_runs"] = int(np.min(s["n"]))
        for name, m in masks.items():
            for key in ("pointing", "pointing_estimate", "los_rate", "range", "range_rate"):
                summary[f"{key}[{name}]"] = float(np.sqrt(np.mean(series[key][m] ** 2)))
            nees = series["nees"][m]
            summary[f"nees[{name}]"] = float(np.mean(nees)) if np.all(np.isfinite(nees)) else None
        summary["rmse_pos"] = float(np.sqrt(np.mean(series["pointing"] ** 2)))
        summary["rmse_vel"] = float(np.sqrt(np.mean(series["los_rate"] ** 2)))
        if np.all(np.isfinite(series["nees"])):
            lo, hi = average_chi2_interval(9, float(np.min(s["n_nees"])))
            summary["nees"] = float(np.mean(series["nees"]))
            summary["nees_in_bounds"] = float(np.mean((series["nees"] >= lo) & (series["nees"] <= hi)))
        if steady is not None and np.isfinite(series["los_rate"]).all():
            level = float(np.sqrt(np.mean(series["los_rate"][steady] ** 2)))
            events = [("acquisition", 0.0)] + ([("disturbance", exp.disturbance[0])] if exp.disturbance else [])
            for name, t_e in events:
                summary[f"settle[{name}]"] = settling_time(t, series["los_rate"], t_e, 1.5 * level)
        trackers[tc.label] = {"kind": tc.kind, "label": tc.label, "summary": summary, "series": series}
    if samples is not None:
        _with_intervals(exp, trackers, samples, runs)
    return {
        "name": exp.name, "runs": runs, "steps": exp.steps, "dt": exp.period, "window": [1, exp.steps],
        "series_stride": 1, "units": ["mrad", "mrad/s"], "axes": ["e", "d"], "windows": list(exp.windows),
        "window_spans": {w: list(span) for w, span in exp.windows.items()},
        "level": exp.level, "wall_s": wall, "compile_s": compile_s, "precision": precision,
        "experiment": exp.raw, "t": t, "nominal_range": exp.nominal_range(), "filters": trackers,
    }

def _with_intervals(exp, trackers, samples, runs):
    """Each tracker's window summaries from its runs' samples (``closed_loop.run_samples``) with
    their intervals, the Wilson interval of its lost-lock fraction, the percentiles and
    distribution of its runs' RMS true pointing error per window, its paired differences."""
    whole = {"pointing": "rmse_pos", "los_rate": "rmse_vel", "nees": "nees"}  # the whole run's keys
    names = list(exp.windows)
    stats, kept = {}, []
    for wi, w in enumerate(names + [None]):
        for qi, q in enumerate(SAMPLE_QUANTITIES):
            key = f"{q}[{w}]" if w is not None else whole.get(q)
            if key is not None:
                i = wi * len(SAMPLE_QUANTITIES) + qi
                stats[key] = ("mean", i) if q == "nees" else ("root", [i])
        kept.append((wi, f"pointing_p{{p}}[{w}]" if w is not None else "pointing_p{p}",
                     f"pointing[{w}]" if w is not None else "pointing"))
    paired = [k for k in stats if k.startswith(("pointing[", "los_rate["))] + ["rmse_pos", "rmse_vel", "nees"]
    diverged = {l: (f["summary"]["lost_lock"], runs) for l, f in trackers.items()}
    lanes = lane_intervals(samples, list(trackers), stats, exp.level, exp.baseline, paired, diverged, kept)
    for label, lane in lanes.items():
        f = trackers[label]
        f["summary"].update(lane.pop("summary"))
        f.update(lane)


def settling_time(t, series, t_event, level, hold=1.0):
    """Seconds after t_event until ``series`` stays ≤ level for ``hold`` seconds (NaN if it never does)."""
    after = t >= t_event
    ok = (series <= level) & after
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    need = max(1, int(round(hold / dt)))
    run = 0
    for i in np.nonzero(after)[0]:
        run = run + 1 if ok[i] else 0
        if run >= need:
            return float(t[i - need + 1] - t_event)
    return float("nan")
