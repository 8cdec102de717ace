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
from tracklab.report.airborne import write_airborne_results
from tracklab.worlds import protocol
from tracklab.worlds.airborne import statistics
from tracklab.worlds.airborne import world as airborne_world
from tracklab.worlds.airborne.closed_loop import SAMPLE_QUANTITIES, singer_tick
from tracklab.worlds.airborne.engagement import nominal_range
from tracklab.worlds.airborne.registry import TRACKERS
from tracklab.worlds.airborne.tracker import Setting, Timing

MAX_TICKS = 10**7  # radar samples per run (sample_dt against duration)


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
    trackers: list[protocol.UnitConfig]
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
        trackers = tuple(airborne_world.TrackerSpec(tc.label, tc.kind, tuple(sorted(tc.options.items())))
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
        out = runner.run(self.world(self.structure(chunk, runs)), self.params(), runs,
                         self.seed if seed is None else seed, precision=precision or self.precision, progress=progress,
                         enough=enough)
        out.sums = runner.labelled(out.sums, self.tables()[1])
        return out

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
        """The statistics document of the per-period ``sums`` over ``runs`` runs (``statistics.document``)."""
        return statistics.document(self, runner.labelled(sums, self.tables()[1]), runs, wall, compile_s, precision,
                                   samples)
