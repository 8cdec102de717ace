"""A servo experiment (paper 003), validated: its structure and numbers for the servo world,
its Monte-Carlo run (through the runner), its case statistics, tables and figures.

``tracklab.config.servo`` reads one from a file with a ``[servo]`` section.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Prior
from tracklab.intervals import precision_reached
from tracklab.memory import check
from tracklab.montecarlo import runner
from tracklab.report.servo import write_servo_results
from tracklab.worlds import protocol
from tracklab.worlds.servo import statistics
from tracklab.worlds.servo import world as servo_world
from tracklab.worlds.servo.estimators import Estimator, Setting
from tracklab.worlds.servo.registry import ESTIMATORS
from tracklab.worlds.servo.training import train_dekf
from tracklab.worlds.servo.world import (
    CaseSpec,
    ServoParams,
    ServoStructure,
    target_function,
)

TARGET_KINDS = {  # [target] kind -> its fields (paper 003: the sine test and the dynamic-target rig)
    "sine": "amplitude (deg), omega (rad/s)",
    "cone": "half_angle, axis_elevation (deg), period (s): a point circling a cone",
}

MAX_TICKS = 10**7  # servo ticks per run (frames × frame_ticks)

# the correctors are the paper's continuous designs (poles up to 400 rad/s), discretised at
# the tick: the tick is kept near the paper's 1 ms
TICK_RANGE = (1e-4, 2e-3)  # s

CAMERA_LOOPS = ("double_loop", "velocity_lag")  # modes whose position loop is closed through the camera

@dataclass(frozen=True)
class Case:
    label: str
    mode: str
    estimator: str | None  # a label, "perfect" or None


@functools.lru_cache(maxsize=256)
def _target_scale(kind: str, numbers: tuple, duration: float) -> tuple:
    """The largest |θ|, |θ̇|, |θ̈| of a target over a run (sampled at 2001 instants)."""
    f = target_function(kind, dict(numbers))
    with jax.ensure_compile_time_eval():  # numbers of the file, also when asked inside a traced tuning step
        t = jnp.linspace(0.0, duration, 2001)
        vals = np.abs(np.asarray(jax.vmap(f)(t)))
    return tuple(float(max(v, 1e-6)) for v in vals.max(axis=0))


@dataclass
class ServoExperiment(protocol.Experiment):
    path: Path
    name: str
    runs: int
    seed: int
    frames: int
    frame_dt: float
    frame_ticks: int
    delay: int
    noise: float  # arcsec
    settle: float
    accel_ff: float
    target: dict
    estimators: list[protocol.UnitConfig]
    cases: list[Case]
    raw: dict
    also_runs: tuple[int, ...] = ()
    studies: list = field(default_factory=list)
    precision: str = "float64"
    chunk: int | None = None  # runs per chunk; None: default_chunk()
    level: float = 0.95  # of every confidence interval
    baseline: str | None = None  # the case the paired differences are to (None: the first)
    target_precision: float | None = None  # runs = "auto": stop when every case's max tracking error is this tight

    units = ("deg", "deg/s")
    sweep_metrics = (("max_track_err", "maximum tracking error (′)"), ("random_err", "random error (″)"))
    relabel_tuned = False  # its cases name the estimators by label

    @property
    def steps(self) -> int:
        return self.frames

    @property
    def window(self):
        return (1, self.frames)

    @property
    def samples_per_run(self) -> int:
        return self.ticks

    @property
    def ticks(self) -> int:
        """Servo ticks per run."""
        return self.frames * self.frame_ticks

    def target_fn(self):
        return target_function(self.target["kind"], {k: v for k, v in self.target.items() if k != "kind"})

    def target_omega(self) -> float:
        t = self.target
        return t["omega"] if t["kind"] == "sine" else 2 * math.pi / t["period"]

    def target_scale(self):
        """Typical |θ|, |θ̇|, |θ̈| of the target (the network's input scaling)."""
        numbers = tuple(sorted((k, float(v)) for k, v in self.target.items() if k != "kind"))
        return _target_scale(self.target["kind"], numbers, self.frames * self.frame_dt)

    def setting(self) -> Setting:
        """What the estimators' kinds make their code and numbers with."""
        return Setting(self.frame_dt, max(self.noise, 1e-3) / 3600.0, self.target_scale())

    def estimator_structure(self, cfg: protocol.UnitConfig):
        return ESTIMATORS[cfg.kind].structure(self.setting(), cfg.options)

    def estimator_params(self, cfg: protocol.UnitConfig, numbers=None):
        """An estimator's parameters from its numbers (``numbers``: in place of its table's)."""
        kind = ESTIMATORS[cfg.kind]
        return kind.numbers(self.setting(), self.estimator_structure(cfg), {**cfg.numbers, **(numbers or {})}, cfg.options)

    def build_estimator(self, cfg: protocol.UnitConfig):
        """An estimator with its parameters (what a training starts from)."""
        est = ESTIMATORS[cfg.kind].build(self.frame_dt, self.estimator_structure(cfg))
        return Estimator(est.filter, est.ahead, self.estimator_params(cfg), est.filter_net)

    def prior_var(self):
        """The estimators' prior variances of θ, θ̇, θ̈ (about the target's true start)."""
        return np.array([(self.noise / 3600.0) ** 2 * 4, 1.0, 1.0])

    def prior(self):
        x0 = jnp.asarray(np.asarray(self.target_fn()(0.0)))
        return Prior(x0, jnp.diag(jnp.asarray(self.prior_var())))

    def default_chunk(self, runs=None) -> int:
        """Runs per chunk when the file does not say: from the memory budget (``runner.budget_chunk``)
        of a run's per-tick values (4 a tick), no more than ``runs`` need."""
        return runner.budget_chunk(self.run_bytes, runs)

    @property
    def run_bytes(self) -> float:
        """A run's per-tick values in a chunk (4 a tick, 8 bytes each)."""
        return self.ticks * 4 * 8.0

    @property
    def statistics_bytes(self) -> float:
        return self.ticks * 16 * 8.0

    def memory_bytes(self, runs=None, chunk=None) -> float:
        """The arrays a run holds: a chunk's per-tick values (the tracking error, its part after
        ``settle``, the harmonic fit and its residual), the fit's basis and pseudo-inverse and
        the masks (16 values a tick), and run 0's series."""
        chunk = chunk or self.chunk or self.default_chunk(runs or self.runs)
        return chunk * self.run_bytes + self.statistics_bytes

    def check_memory(self, runs=None, limit=None):
        check(self.path, self.memory_bytes(runs), limit, f"{self.ticks} servo ticks a run",
              "fewer servo.frames or servo.frame_ticks")

    # ------------------------------------------------------------------ what is compiled

    def structure(self, chunk=None, runs=None):
        """What the compiled program depends on: the timing, the target's kind, the cases' modes and
        estimator kinds (what their code is compiled for: a DEKF's network), and the chunk size (by
        default from the memory budget and ``runs``)."""
        by = {e.label: e for e in self.estimators}
        cases = []
        for c in self.cases:
            e = by.get(c.estimator)
            kind = e.kind if e is not None else c.estimator  # "perfect" or None
            cases.append(CaseSpec(c.label, c.mode, kind, self.estimator_structure(e) if e is not None else None))
        return ServoStructure(tuple(cases), self.frames, self.frame_ticks, self.frame_dt, self.delay,
                              self.target["kind"], int(chunk or self.chunk or self.default_chunk(runs)))

    def params(self, estimators: dict | None = None):
        """Every number of the experiment, as the compiled program's argument (``estimators``:
        label -> parameters replacing an estimator's own, e.g. trained ones)."""
        estimators = estimators or {}
        own = {e.label: estimators.get(e.label) or self.estimator_params(e) for e in self.estimators}
        t = (1.0 / self.frame_ticks) * self.frame_dt * np.arange(self.ticks)
        late = (t >= self.settle).astype(float)
        w = self.target_omega()
        basis = np.stack([np.ones_like(t)] + [f(k * w * t) for k in (1, 2, 3) for f in (np.sin, np.cos)], -1)
        basis = basis * late[:, None]  # the fit over the ticks after settle
        frame_late = ((self.frame_dt * np.arange(self.frames)) >= self.settle).astype(float)
        return ServoParams({k: v for k, v in self.target.items() if k != "kind"}, self.noise / 3600.0, self.accel_ff,
                           self.prior_var(), [own.get(c.estimator) for c in self.cases], late, frame_late, basis,
                           np.linalg.pinv(basis))

    def world(self, structure):
        return servo_world.world(structure)

    # ------------------------------------------------------------------ declared numbers

    def tables(self):
        return "estimator", [e.label for e in self.estimators]

    def declared(self):
        """The numbers of the estimators that feed a case and are not trained first (a training
        sets its own)."""
        used = {c.estimator for c in self.cases}
        return {e.label: dict(ESTIMATORS[e.kind].params) for e in self.estimators
                if e.label in used and not self.trains(e)}

    def values(self, params):
        return {e.label: dict(e.numbers) for e in self.estimators}

    def with_values(self, params, values):
        """``params`` with the estimators' parameters made from their numbers and ``values``, in every
        case they feed (a DEKF's weights drawn again from its seed)."""
        made = {e.label: self.estimator_params(e, values[e.label]) for e in self.estimators if values.get(e.label)}
        return params._replace(estimators=[made.get(c.estimator, p) for c, p in zip(self.cases, params.estimators)])

    def scalable(self):
        """Scale factors q and r: every estimator's q and measurement-noise variance r."""
        return ["q", "r"] if self.estimators else []

    def scaled(self, params, factors: dict):
        """``params`` with the estimators' q (and measurement-noise variance r) scaled."""
        def scale(p):
            if p is None:
                return p
            return {k: (v * factors[k] if k in factors else v) for k, v in p.items()}

        return params._replace(estimators=[scale(p) for p in params.estimators])

    # ------------------------------------------------------------------ tuning

    @property
    def tune_losses(self):
        return {
            # the healthy runs' mean-square tracking error after settle (deg²)
            "track_mse": lambda sums, lane: sums[lane]["sum_track_ms"] / jnp.maximum(sums[lane]["healthy"], 1.0),
            # the same of the estimator's rate error ((deg/s)²): what it feeds forward
            "rate_mse": lambda sums, lane: sums[lane]["sum_rate_ms"] / jnp.maximum(sums[lane]["healthy"], 1.0),
        }

    def tune_lanes(self, chosen) -> list[str]:
        """The cases whose statistics a tuning of ``chosen`` estimators minimises."""
        return [c.label for c in self.cases if c.estimator in chosen]

    def tune_memory_bytes(self, runs_per_step, tuned, forward) -> float:
        """Forward mode: the batch's per-tick values; reverse mode keeps every run's loop state (servo
        blocks, estimator: ~40 values) per tick."""
        if forward:
            return runs_per_step * self.run_bytes
        return runs_per_step * self.ticks * len(self.cases) * 40 * 8.0

    def trains(self, e: protocol.UnitConfig) -> bool:
        """Whether an estimator is trained before the Monte-Carlo runs (a DEKF with ``train_steps``)."""
        return e.options.get("train_steps", 0) > 0

    def trained_first(self) -> list[protocol.UnitConfig]:
        """The estimators a run trains before its Monte-Carlo runs."""
        return [e for e in self.estimators if self.trains(e)]

    def before_runs(self) -> list[str]:
        """What a run does before its Monte-Carlo runs, a line each."""
        return [f"{e.label}: training w0 and λ first ({e.options['train_steps']} Adam steps of "
                f"{e.options['train_runs']} runs each)" for e in self.trained_first()]

    def train(self, cfg: protocol.UnitConfig, est, progress=None):
        """Train a DEKF estimator's initial weights and λ on the rate it feeds forward; held-out
        evaluation. A ``progress`` callback with a ``train(label, step, steps, loss)`` attribute (the
        command's phases) is told every Adam step."""
        t0 = time.perf_counter()
        told = getattr(progress, "train", None)
        net = est.filter_net
        frames = min(self.frames, int(round((self.settle + 10.0) / self.frame_dt)))
        trained, history, before, after = train_dekf(
            net, est.params, self.target_fn(), self.prior(), frames=frames, frame_dt=self.frame_dt, delay=self.delay,
            sigma=max(self.noise, 1e-3) / 3600.0, settle=min(self.settle, 0.5 * frames * self.frame_dt),
            steps=cfg.options["train_steps"], lr=cfg.numbers["train_lr"], runs_per_step=cfg.options["train_runs"],
            seed=cfg.options["seed"] + 1,
            on_step=None if told is None else lambda k, n, loss: told(cfg.label, k, n, loss))
        info = {"steps": len(history), "loss_history": [v for _, v in history], "heldout_before": before,
                "heldout_after": after, "forget": float(trained["forget"]), "frames": frames,
                "wall_s": time.perf_counter() - t0}
        return Estimator(est.filter, est.ahead, trained, net), info

    # ------------------------------------------------------------------ running

    def simulate(self, runs=None, seed=None, progress=None, precision=None, target_precision=None) -> dict:
        """Train what is to be trained, run the cases' Monte-Carlo runs (with a target precision,
        ``target_precision`` or the file's runs = "auto", until every case's maximum-tracking-error
        interval is that tight, ``runs`` at most) and return the statistics document (traced and
        run in ``precision``: single precision in float32)."""
        precision = precision or self.precision
        runs = runs or self.runs
        seed = self.seed if seed is None else seed
        with jax.enable_x64(precision == "float64"):
            training, trained = {}, {}
            for e in self.trained_first():
                est, training[e.label] = self.train(e, self.build_estimator(e), progress)
                trained[e.label] = est.params
            structure = self.structure(None, runs)
            max_runs = runs
            target = target_precision or self.target_precision
            headline = ("mean", 0)  # each run's maximum tracking error
            enough = None if target is None else (
                lambda sums, samples, done: precision_reached(samples, target, self.level, headline))
            out = runner.run(self.world(structure), self.params(trained), runs, seed, precision=precision,
                             progress=progress, enough=enough)
        runs = out.runs
        cases = self.summarise(structure, None, out.sums, out)["filters"]
        out.sums = runner.labelled(out.sums, structure.labels)
        examples = {c.label: {"error": np.asarray(out.sums[c.label]["example_error"]),
                              "rate_error": np.asarray(out.sums[c.label]["example_rate_error"])} for c in structure.cases}
        n_ticks = self.ticks
        t = (self.frame_dt / self.frame_ticks) * np.arange(n_ticks)
        stride = max(1, n_ticks // 3000)
        return {
            "name": self.name, "runs": runs, "steps": self.frames, "dt": self.frame_dt, "series_stride": 1,
            "window": [1, self.frames], "level": self.level, "wall_s": out.wall_s, "compile_s": out.compile_s,
            "experiment": self.raw, "units": ["deg", "deg/s"], "axes": ["az"], "precision": precision,
            "training": training,
            "filters": cases,
            "example_run": {"t": t[::stride], "error": {k: v["error"][::stride] for k, v in examples.items()},
                            "t_frames": self.frame_dt * np.arange(self.frames), "settle": self.settle,
                            "rate_error": {k: v["rate_error"] for k, v in examples.items()
                                           if self._case(k).estimator not in (None, "perfect")}},
        } | ({"auto": {"target": target, "max_runs": max_runs, "statistic": "maximum-tracking-error",
                       "reached": precision_reached(out.samples, target, self.level, headline)}}
             if target is not None else {})

    def summarise(self, structure, params, sums, out, point=None) -> dict:
        """The cases' statistics from their sums over the runs (``statistics.summarise``)."""
        return statistics.summarise(self, structure, sums, out, point)

    def write(self, doc, folder, figures=True):
        return write_servo_results(doc, folder, figures)

    def _case(self, label):
        return next(c for c in self.cases if c.label == label)
