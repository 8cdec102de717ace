"""An airborne-radar experiment (paper 001), validated: its structure and numbers for the
airborne world, its Monte-Carlo run (through the runner), its statistics, tables and figures.

``tracklab.config.airborne`` reads one from a file with an ``[airborne]`` section.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import jax.numpy as jnp
import numpy as np
from tracklab.worlds.airborne.closed_loop import MRAD, SAMPLE_QUANTITIES
from tracklab.report.airborne import write_airborne_results
from tracklab.worlds.airborne.engagement import nominal_range


TRACKERS = {
    "cd_ekf": "joint continuous-discrete EKF on the 9-state boresight model, antenna command eq. 1",
    "decoupled": "Pearson/Shibata: e, d and range channels filtered separately (range_velocity coupled | separate)",
    "classical": "eq. 17 angle loop, alpha-beta-gamma range loop, alpha-beta velocity loop",
    "moose": "joint EKF with Markov-switching mean accelerations (Moose-type adaptive filter)",
}

TRACKER_KINDS = tuple(TRACKERS)

MAX_TICKS = 10**7  # radar samples per run (sample_dt against duration)

@dataclass(frozen=True)
class TrackerConfig:
    label: str
    kind: str
    lam: float = 5.0
    q_scale: float = 1.0
    r_scale: float = 1.0
    range_velocity: str = "coupled"
    model: tuple = ()  # (sigma_m, tau, sigma_r, tau_r)
    levels: tuple = ()  # moose: mean-acceleration levels (m/s²)
    p_stay: float = 0.99

@dataclass
class AirborneExperiment:
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

    def timing(self):
        from tracklab.worlds.airborne.tracker import Timing

        return Timing(self.sample_dt, self.average, self.antenna_lag)

    def default_chunk(self, runs=None) -> int:
        """Runs per chunk when the file does not say: from the memory budget (``runner.budget_chunk``)
        of a run's per-period outputs (12 values a period and tracker), no more than ``runs`` need."""
        from tracklab.montecarlo import runner

        return runner.budget_chunk(self.run_bytes, runs)

    @property
    def run_bytes(self) -> float:
        """A run's per-period outputs in a chunk: error, NEES, pointing, range (12 values a period
        and tracker, 8 bytes each)."""
        return self.steps * 12 * len(self.trackers) * 8.0

    def structure(self, chunk=None, runs=None):
        """What the compiled program depends on: timing, periods, jolt tick, Singer on/off, the
        trackers' kinds and the chunk size (by default from the memory budget and ``runs``)."""
        from tracklab.worlds.airborne.world import AirborneStructure, TrackerSpec

        jolt_tick = int(round(self.disturbance[0] / self.sample_dt)) if self.disturbance is not None else -1
        trackers = tuple(TrackerSpec(tc.label, tc.kind, tc.range_velocity) for tc in self.trackers)
        return AirborneStructure(trackers, self.timing(), self.steps, jolt_tick, self.singer,
                                 int(chunk or self.chunk or self.default_chunk(runs)))

    def params(self):
        """Every number of the experiment, as the compiled program's argument."""
        from tracklab.worlds.airborne.closed_loop import singer_tick
        from tracklab.worlds.airborne.world import AirborneParams

        phi, L = singer_tick(self.engagement, self.sample_dt, self.singer)
        trackers, sd0 = [], []
        for tc in self.trackers:
            p, s = self.tracker_params(tc)
            trackers.append(p)
            sd0.append(s)
        return AirborneParams(self.engagement, np.asarray(self.gains, float), np.asarray(self.noise, float),
                              np.asarray(self.limits, float), np.asarray(self.acquisition, float),
                              float(self.disturbance[1]) if self.disturbance is not None else 0.0, phi, L, trackers, sd0,
                              self.window_weights())

    def window_weights(self):
        """(W + 1, periods): each report window's averaging weights over the filter periods, then
        the whole run's (a window holding no period: NaN, its statistics missing)."""
        _, masks = self.window_masks()
        rows = [m.astype(float) for m in masks.values()] + [np.ones(self.steps)]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([r / r.sum() for r in rows])

    def tracker_params(self, tc: TrackerConfig, q_scale=None, r_scale=None, lam=None):
        """(parameters, prior standard deviations) of one [[tracker]] table (``q_scale``, ``r_scale``,
        ``lam``: values in place of the table's, possibly traced: what tuning varies)."""
        from tracklab.worlds.airborne.boresight import ModelParams
        from tracklab.worlds.airborne.cd_ekf import CDParams
        from tracklab.worlds.airborne.classical import ClassicalParams, loop_gains
        from tracklab.worlds.airborne.moose import MooseParams

        timing = self.timing()
        acq = self.acquisition
        sm_r = (tc.model[0], tc.model[2]) if tc.model else (self.engagement.singer_sigma,) * 2
        sd0 = np.array([acq[0], acq[1], sm_r[0], acq[0], acq[1], sm_r[0], acq[2], acq[3], sm_r[1]], float)
        k = np.asarray(self.gains, float)
        if tc.kind == "classical":
            g_r, g_v = loop_gains(self.engagement.singer_sigma, self.engagement.singer_tau, self.noise[2], self.noise[3], timing)
            return ClassicalParams(k, np.asarray(g_r, float), np.asarray(g_v, float)), sd0
        sm, tau, sr, tr = tc.model or (self.engagement.singer_sigma, self.engagement.singer_tau,
                                       self.engagement.singer_sigma, self.engagement.singer_tau)
        q_scale = tc.q_scale if q_scale is None else q_scale
        r_scale = tc.r_scale if r_scale is None else r_scale
        lam = tc.lam if lam is None else lam
        q = q_scale ** 0.5  # Q ∝ σ²
        mp = ModelParams(q * np.asarray(sm, float), np.asarray(tau, float), q * np.asarray(sr, float),
                         np.asarray(tr, float))
        r = r_scale * (k * np.asarray(self.noise, float)) ** 2
        params = CDParams(mp, r, k, lam * np.ones((), float))
        if tc.kind == "moose":
            return MooseParams(params, np.asarray(tc.levels, float), np.asarray(tc.p_stay, float)), sd0
        return params, sd0

    def nominal_range(self):
        t = self.period * np.arange(1, self.steps + 1)
        return nominal_range(self.engagement, t)

    sweep_metrics = (("rmse_pos", "true pointing error RMS (mrad)"), ("rmse_vel", "LOS-rate error RMS (mrad/s)"),
                      ("nees", "average NEES (9 states)"))
    units = ("mrad", "mrad/s")

    def world(self, structure):
        from tracklab.worlds.airborne.world import world

        return world(structure)

    def scaled(self, params, factors: dict):
        """``params`` with the trackers' Q (q: the Singer σ's squared) and R (r) scaled (the classical
        loops have neither)."""
        from tracklab.worlds.airborne.classical import ClassicalParams
        from tracklab.worlds.airborne.moose import MooseParams

        q, r = factors.get("q", 1.0), factors.get("r", 1.0)

        def scale(p):
            if isinstance(p, ClassicalParams):
                return p
            if isinstance(p, MooseParams):
                return p._replace(base=scale(p.base))
            m = p.model
            s = np.sqrt(q)
            return p._replace(model=m._replace(sigma_m=m.sigma_m * s, sigma_r=m.sigma_r * s), r=p.r * r)

        return params._replace(trackers=[scale(p) for p in params.trackers])

    def summarise(self, structure, params, sums, out, point=None) -> dict:
        samples = out.samples if point is None or out.samples is None else out.samples.point(point)
        return self.document(sums, out.runs, out.wall_s, out.compile_s, self.precision, samples)

    # tuning (tracklab.tune): the [[tracker]] fields q_scale, r_scale and lam of the filtering trackers
    tune_names = ("q_scale", "r_scale", "lam")
    tune_losses = {
        # mean over the filter periods of the mean-square true pointing error (rad²) of the runs in lock
        "pointing": lambda s: jnp.mean(s["sum_point2"] / jnp.maximum(s["n"], 1.0)),
        # the same of the LOS-rate estimate's error ((rad/s)², both axes)
        "los_rate": lambda s: jnp.mean((s["sum_e2"][:, 1] + s["sum_e2"][:, 4]) / jnp.maximum(s["n"], 1.0)),
    }

    def tune_selection(self, names, labels=None) -> dict:
        return {tc.label: tuple(names) for tc in self.trackers
                if tc.kind != "classical" and (not labels or tc.label in labels)}

    def tune_start(self, chosen) -> dict:
        by = {tc.label: tc for tc in self.trackers}
        return {l: {n: float(getattr(by[l], n)) for n in names} for l, names in chosen.items()}

    def with_tuned(self, params, values: dict):
        """``params`` with the trackers' q_scale, r_scale, lam from ``values`` ({label: {name: value}})."""
        trackers = list(params.trackers)
        for i, tc in enumerate(self.trackers):
            if tc.label in values:
                trackers[i] = self.tracker_params(tc, **values[tc.label])[0]
        return params._replace(trackers=trackers)

    def write_tuned(self, doc, values: dict):
        for table, tc in zip(doc["tracker"], self.trackers):
            if tc.label in values:
                table.update({n: float(v) for n, v in values[tc.label].items()})

    def tune_memory_bytes(self, runs_per_step) -> float:
        """Reverse mode keeps every run's loop state (tracker, antenna, truth: ~200 values) per tick."""
        return runs_per_step * self.ticks * len(self.trackers) * 200 * 8.0

    def headline(self):
        """The statistic ``runs = "auto"`` makes tight: each tracker's true pointing error RMS over
        the whole run (the root of its samples' last window's first quantity)."""
        return ("root", [len(self.windows) * len(SAMPLE_QUANTITIES)])

    def monte_carlo(self, runs=None, seed=None, progress=None, precision=None, chunk=None, target_precision=None):
        """The runner's outcome: per-period sums over runs for every tracker ({label: sums}) and the
        runs' samples. With a target precision (``target_precision``, or the file's runs = "auto")
        chunks run until every tracker's pointing-error interval is that tight, ``runs`` at most."""
        from tracklab.worlds.airborne.world import world
        from tracklab.intervals import precision_reached
        from tracklab.montecarlo import runner

        target = target_precision or self.target_precision
        enough = None if target is None else (
            lambda sums, samples, done: precision_reached(samples, target, self.level, self.headline()))
        runs = runs or self.runs
        return runner.run(world(self.structure(chunk, runs)), self.params(), runs,
                          self.seed if seed is None else seed, precision=precision or self.precision, progress=progress,
                          enough=enough)

    @property
    def ticks(self) -> int:
        """Radar samples per run."""
        return self.steps * self.average

    def memory_bytes(self, runs=None) -> float:
        """A lower bound: a chunk's per-period outputs (error, NEES, pointing, range: 12 values a
        run and period) and the per-period statistics on the host."""
        chunk = self.structure(runs=runs or self.runs).chunk
        return chunk * self.run_bytes + len(self.trackers) * self.steps * 16 * 8.0

    def check_memory(self, runs=None, limit=None):
        from tracklab.memory import check

        check(self.path, self.memory_bytes(runs), limit, f"{self.steps} filter periods a run",
              "raise airborne.sample_dt or airborne.average, or shorten airborne.duration")

    def run(self, runs=None, seed=None, out=None, progress=None, figures=True, precision=None, max_memory=None,
            target_precision=None):
        from tracklab.intervals import precision_reached
        from tracklab.report.document import run_into_folder

        def simulate():
            target = target_precision or self.target_precision
            out = self.monte_carlo(runs or self.runs, seed, progress, precision, target_precision=target)
            doc = self.document(out.sums, out.runs, out.wall_s, out.compile_s, precision or self.precision, out.samples)
            if target is not None:
                doc["auto"] = {"target": target, "max_runs": runs or self.runs, "statistic": "pointing-error RMS",
                               "reached": precision_reached(out.samples, target, self.level, self.headline())}
            return doc

        return run_into_folder(self, out, runs, max_memory, simulate,
                               lambda doc, tmp: write_airborne_results(doc, tmp, figures))

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
        from tracklab.montecarlo.statistics import average_chi2_interval, rms_half_width

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
        from tracklab.montecarlo.statistics import lane_intervals

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
