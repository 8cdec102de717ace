"""The servo world's statistics: per case its maximum tracking error (′), random error (″) and the
estimator's largest rate error (°/s) over the healthy runs, with intervals from the runs' samples,
the percentiles of the runs' maximum tracking errors and paired differences to the baseline case."""

from __future__ import annotations

from tracklab.montecarlo import runner
from tracklab.montecarlo.statistics import lane_intervals
from tracklab.worlds.servo.world import SAMPLES


def summarise(exp, structure, sums, out, point=None) -> dict:
    """The cases' statistics from their sums over the runs (``point``: which grid point of the
    runner's ``out``); with the runs' samples, each with its ``level`` interval, the percentiles
    of the runs' maximum tracking errors and the paired differences to the baseline case."""
    sums = runner.labelled(sums, structure.labels)
    cases = {}
    for case in structure.cases:
        s = {k: v for k, v in sums[case.label].items() if not k.startswith("example")}
        cases[case.label] = {"kind": case.mode, "label": case.label, "estimator": exp._case(case.label).estimator,
                             "summary": case_summary(s, out.runs, case.estimator not in (None, "perfect")),
                             "series": {}}
    samples = out.samples if point is None or out.samples is None else out.samples.point(point)
    if samples is not None:
        _with_intervals(exp, structure, cases, samples, out.runs)
    return {"filters": cases, "level": exp.level}

def _with_intervals(exp, structure, cases, samples, runs):
    stats = {key: ("mean", i) for i, key in enumerate(SAMPLES)}
    diverged = {l: (c["summary"]["diverged"], runs) for l, c in cases.items()}
    lanes = lane_intervals(samples, list(cases), stats, exp.level, exp.baseline, ("max_track_err", "random_err"),
                           diverged, kept=[(0, "max_track_err_p{p}", "max_track_err")])
    for case in structure.cases:
        lane = lanes[case.label]
        if case.estimator in (None, "perfect"):  # no rate estimate: its statistic stays missing
            lane["summary"]["max_rate_err"] = lane["half_width"]["max_rate_err"] = float("nan")
        cases[case.label]["summary"].update(lane.pop("summary"))
        cases[case.label].update(lane)


def case_summary(sums: dict, runs: int, estimated: bool) -> dict:
    """One case's statistics from its sums over the runs (deg, deg, deg/s; the rate error only
    with an estimator). A diverged run (a non-finite value, or an error past half a turn: the
    target lost) is counted, not averaged; with no healthy run every statistic is NaN (missing)."""
    n = float(sums["healthy"])

    def mean(key, scale=1.0):
        return float(sums[key]) / n * scale if n > 0 else float("nan")

    return {
        "max_track_err": mean("sum_max_err", 60.0),  # arcmin
        "max_track_err_worst": float(sums["max_max_err"]) * 60.0 if n > 0 else float("nan"),
        "random_err": mean("sum_random_err", 3600.0),  # arcsec
        "max_rate_err": mean("sum_rate_err") if estimated else float("nan"),
        "diverged": int(round(float(sums["diverged"]))),
        "runs": int(runs),
    }
