"""An airborne-radar experiment (paper 001), validated: its structure and numbers for the
airborne world, its Monte-Carlo run (through the runner), its statistics, tables and figures.

``tracklab.config.airborne`` reads one from a file with an ``[airborne]`` section.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from tracklab.intervals import precision_reached
from tracklab.memory import check
from tracklab.montecarlo import runner
from tracklab.montecarlo.statistics import (
    average_chi2_interval,
    lane_intervals,
    rms_half_width,
)
from tracklab.report.airborne import write_airborne_results
from tracklab.worlds import protocol
from tracklab.worlds.airborne import world as airborne_world
from tracklab.worlds.airborne.closed_loop import MRAD, SAMPLE_QUANTITIES, singer_tick
from tracklab.worlds.airborne.engagement import nominal_range
from tracklab.worlds.airborne.registry import TRACKERS
from tracklab.worlds.airborne.tracker import Setting, Timing

MAX_TICKS = 10**7  # radar samples per run (sample_dt against duration)


@dataclass(frozen=True)
class TrackerConfig:
    """One [[tracker]] table, read as its kind declares (``registry.TRACKERS``)."""

    label: str
    kind: str
    numbers: dict = field(default_factory=dict)  # name -> value: the numbers its kind declares
    choices: dict = field(default_factory=dict)  # field -> value: its structural choices


@dataclass
class AirborneExperiment(protocol.Experiment):
    path: Path
    name: str
    runs: int
    seed: int
    duration: float
    sample_dt: float
    average: int
    antenna_lag: float
    limits: tuple  # rad, m, m/s
    engagement: object
    singer: bool
    noise: tuple  # rad, rad, m, m/s
    gains: tuple
    acquisition: tuple  # rad, rad/s, m, m/s
    disturbance: tuple | None  # (time s, rad)
    trackers: list
    windows: dict  # name -> (t0, t1)
    raw: dict
    precision: str = "float64"
    also_runs: tuple = ()
    studies: list = field(default_factory=list)
    chunk: int | None = None  # runs per chunk; None: default_chunk()
    level: float = 0.95  # of every confidence interval
    baseline: str | None = None  # the tracker the paired differences are to (None: the first)
    target_precision: float | None = None  # runs = "auto": stop when every tracker's pointing RMS is this tight

    @property
    def period(self) -> float:
        return self.sample_dt * self.average

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.period))

    @property
    def window(self):
        return (1, self.steps)

    units = ("mrad", "mrad/s")
    sweep_metrics = (("rmse_pos", "true pointing error RMS (mrad)"), ("rmse_vel", "LOS-rate error RMS (mrad/s)"),
                     ("nees", "average NEES (9 states)"))
    nees_dof = 9

    def timing(self) -> Timing:
        return Timing(self.sample_dt, self.average, self.antenna_lag)

    def setting(self) -> Setting:
        """What the trackers' numbers are turned into their params with."""
        return Setting(self.engagement, self.noise, self.gains, self.acquisition, self.timing())

    def default_chunk(self, runs=None) -> int:
        """Runs per chunk when the file does not say: from the memory budget (``runner.budget_chunk``)
        of a run's per-period outputs (12 values a period and tracker), no more than ``runs`` need."""
        return runner.budget_chunk(self.run_bytes, runs)

    @property
    def run_bytes(self) -> float:
        """A run's per-period outputs in a chunk: error, NEES, pointing, range (12 values a period
        and tracker, 8 bytes each)."""
        return self.steps * 12 * len(self.trackers) * 8.0

    @property
    def statistics_bytes(self) -> float:
        return len(self.trackers) * self.steps * 16 * 8.0

    @property
    def samples_per_run(self) -> int:
        return self.ticks

    # ------------------------------------------------------------------ what is compiled

    def structure(self, chunk=None, runs=None):
        """What the compiled program depends on: timing, periods, jolt tick, Singer on/off, the
        trackers' kinds and choices, and the chunk size (by default from the memory budget and ``runs``)."""
        jolt_tick = int(round(self.disturbance[0] / self.sample_dt)) if self.disturbance is not None else -1
        trackers = tuple(airborne_world.TrackerSpec(tc.label, tc.kind, tuple(sorted(tc.choices.items())))
                         for tc in self.trackers)
        return airborne_world.AirborneStructure(trackers, self.timing(), self.steps, jolt_tick, self.singer,
                                                int(chunk or self.chunk or self.default_chunk(runs)))

    def params(self):
        """Every number of the experiment, as the compiled program's argument."""
        phi, L = singer_tick(self.engagement, self.sample_dt, self.singer)
        made = [TRACKERS[tc.kind].numbers(self.setting(), tc.numbers) for tc in self.trackers]
        return airborne_world.AirborneParams(
            self.engagement, np.asarray(self.gains, float), np.asarray(self.noise, float), np.asarray(self.limits, float),
            np.asarray(self.acquisition, float), float(self.disturbance[1]) if self.disturbance is not None else 0.0,
            phi, L, [p for p, _ in made], [sd0 for _, sd0 in made], self.window_weights())

    def world(self, structure):
        return airborne_world.world(structure)

    def window_weights(self):
        """(W + 1, periods): each report window's averaging weights over the filter periods, then
        the whole run's (a window holding no period: NaN, its statistics missing)."""
        _, masks = self.window_masks()
        rows = [m.astype(float) for m in masks.values()] + [np.ones(self.steps)]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([r / r.sum() for r in rows])

    def nominal_range(self):
        t = self.period * np.arange(1, self.steps + 1)
        return nominal_range(self.engagement, t)

    @property
    def ticks(self) -> int:
        """Radar samples per run."""
        return self.steps * self.average

    # ------------------------------------------------------------------ declared numbers

    def tables(self):
        return "tracker", [tc.label for tc in self.trackers]

    def declared(self):
        return {tc.label: dict(TRACKERS[tc.kind].params) for tc in self.trackers}

    def values(self, params):
        """The trackers' numbers as the file gives them (the params hold what they make)."""
        return {tc.label: dict(tc.numbers) for tc in self.trackers}

    def with_values(self, params, values):
        """``params`` with the trackers' params made from their numbers and ``values``."""
        trackers, setting = list(params.trackers), self.setting()
        for i, tc in enumerate(self.trackers):
            if values.get(tc.label):
                trackers[i] = TRACKERS[tc.kind].numbers(setting, {**tc.numbers, **values[tc.label]})[0]
        return params._replace(trackers=trackers)

    def scalable(self):
        """Scale factors q (the trackers' Q: their q_scale) and r (R: r_scale), where a tracker filters."""
        return ["q", "r"] if any(TRACKERS[tc.kind].params for tc in self.trackers) else []

    def scaled(self, params, factors: dict):
        """``params`` with the filtering trackers' q_scale and r_scale multiplied by the factors q and r."""
        names = {"q": "q_scale", "r": "r_scale"}
        return self.with_values(params, {tc.label: {names[f]: tc.numbers[names[f]] * v for f, v in factors.items()
                                                    if names.get(f) in tc.numbers}
                                         for tc in self.trackers})

    # ------------------------------------------------------------------ tuning

    @property
    def tune_losses(self):
        return {
            # mean over the filter periods of the mean-square true pointing error (rad²) of the runs in lock
            "pointing": lambda sums, lane: jnp.mean(sums[lane]["sum_point2"] / jnp.maximum(sums[lane]["n"], 1.0)),
            # the same of the LOS-rate estimate's error ((rad/s)², both axes)
            "los_rate": lambda sums, lane: jnp.mean((sums[lane]["sum_e2"][:, 1] + sums[lane]["sum_e2"][:, 4])
                                                    / jnp.maximum(sums[lane]["n"], 1.0)),
        }

    def tune_memory_bytes(self, runs_per_step, tuned, forward) -> float:
        """Forward mode: the batch's per-period outputs; reverse mode keeps every run's loop state
        (tracker, antenna, truth: ~200 values) per tick."""
        if forward:
            return runs_per_step * self.run_bytes
        return runs_per_step * self.ticks * len(self.trackers) * 200 * 8.0

    def headline(self):
        """The statistic ``runs = "auto"`` makes tight: each tracker's true pointing error RMS over
        the whole run (the root of its samples' last window's first quantity)."""
        return ("root", [len(self.windows) * len(SAMPLE_QUANTITIES)])

    # ------------------------------------------------------------------ running

    def monte_carlo(self, runs=None, seed=None, progress=None, precision=None, chunk=None, target_precision=None):
        """The runner's outcome: per-period sums over runs for every tracker ({label: sums}) and the
        runs' samples. With a target precision (``target_precision``, or the file's runs = "auto")
        chunks run until every tracker's pointing-error interval is that tight, ``runs`` at most."""
        target = target_precision or self.target_precision
        enough = None if target is None else (
            lambda sums, samples, done: precision_reached(samples, target, self.level, self.headline()))
        runs = runs or self.runs
        return runner.run(self.world(self.structure(chunk, runs)), self.params(), runs,
                          self.seed if seed is None else seed, precision=precision or self.precision, progress=progress,
                          enough=enough)

    def simulate(self, runs=None, seed=None, progress=None, precision=None, target_precision=None) -> dict:
        target = target_precision or self.target_precision
        out = self.monte_carlo(runs or self.runs, seed, progress, precision, target_precision=target)
        doc = self.document(out.sums, out.runs, out.wall_s, out.compile_s, precision or self.precision, out.samples)
        if target is not None:
            doc["auto"] = {"target": target, "max_runs": runs or self.runs, "statistic": "pointing-error RMS",
                           "reached": precision_reached(out.samples, target, self.level, self.headline())}
        return doc

    def summarise(self, structure, params, sums, out, point=None) -> dict:
        samples = out.samples if point is None or out.samples is None else out.samples.point(point)
        return self.document(sums, out.runs, out.wall_s, out.compile_s, self.precision, samples)

    def write(self, doc, folder, figures=True):
        return write_airborne_results(doc, folder, figures)

    def memory_bytes(self, runs=None, chunk=None) -> float:
        """A lower bound: a chunk's per-period outputs (error, NEES, pointing, range: 12 values a
        run and period) and the per-period statistics on the host."""
        chunk = self.structure(chunk, runs or self.runs).chunk
        return chunk * self.run_bytes + self.statistics_bytes

    def check_memory(self, runs=None, limit=None):
        check(self.path, self.memory_bytes(runs), limit, f"{self.steps} filter periods a run",
              "raise airborne.sample_dt or airborne.average, or shorten airborne.duration")

    def window_masks(self):
        t = self.period * np.arange(1, self.steps + 1)
        masks = {}
        for name, (t0, t1) in self.windows.items():
            masks[name] = (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
        return t, masks

    def document(self, sums, runs, wall, compile_s, precision, samples=None):
        """The statistics document of the per-period ``sums`` over ``runs`` runs; with the runs'
        ``samples`` every summary number has its ``level`` interval, and each tracker its paired
        differences to the baseline and its runs' pointing-error percentiles (``intervals``)."""
        t, masks = self.window_masks()
        steady = masks.get("steady")
        trackers = {}
        for tc in self.trackers:
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
                    series[f"{key}_hw"] = rms_half_width(mean_sq[key], s["sum4"][:, j], s["n"], self.level)
            series["nees_lo"], series["nees_hi"] = average_chi2_interval(9, s["n_nees"], self.level)
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
                events = [("acquisition", 0.0)] + ([("disturbance", self.disturbance[0])] if self.disturbance else [])
                for name, t_e in events:
                    summary[f"settle[{name}]"] = settling_time(t, series["los_rate"], t_e, 1.5 * level)
            trackers[tc.label] = {"kind": tc.kind, "label": tc.label, "summary": summary, "series": series}
        if samples is not None:
            self._with_intervals(trackers, samples, runs)
        return {
            "name": self.name, "runs": runs, "steps": self.steps, "dt": self.period, "window": [1, self.steps],
            "series_stride": 1, "units": ["mrad", "mrad/s"], "axes": ["e", "d"], "windows": list(self.windows),
            "level": self.level, "wall_s": wall, "compile_s": compile_s, "precision": precision,
            "experiment": self.raw, "t": t, "nominal_range": self.nominal_range(), "filters": trackers,
        }

    def _with_intervals(self, trackers, samples, runs):
        """Each tracker's window summaries from its runs' samples (``closed_loop.run_samples``) with
        their intervals, the Wilson interval of its lost-lock fraction, the percentiles and
        distribution of its runs' RMS true pointing error per window, its paired differences."""
        whole = {"pointing": "rmse_pos", "los_rate": "rmse_vel", "nees": "nees"}  # the whole run's keys
        names = list(self.windows)
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
        lanes = lane_intervals(samples, list(trackers), stats, self.level, self.baseline, paired, diverged, kept)
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
