"""An open-loop tracking experiment, validated: its filters, scenario, sensors and prior as
the tracking world's structure and numbers, its Monte-Carlo run (through the runner), its
statistics and its results folder.

``tracklab.config.tracking`` reads one from a file with ``[scenario]``, ``[sensor]`` and
``[[filter]]`` tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from tracklab import __version__
from tracklab.filters.association import HARD_RULES
from tracklab.filters.kind import WriteBack
from tracklab.filters.registry import KINDS
from tracklab.memory import check
from tracklab.montecarlo.statistics import REPORT_WINDOW, statistics
from tracklab.pytree import named_leaves, with_leaves
from tracklab.report.document import decimate, series_stride, write_tables
from tracklab.report.figures import chosen_kinds, formats_of, plot_figures
from tracklab.sensors import SENSOR_SIGMAS, SensorSuite
from tracklab.sensors.clutter import cluttered_of
from tracklab.worlds import protocol
from tracklab.worlds.tracking import outcome, scan
from tracklab.worlds.tracking.errors import LOSSES, unpack
from tracklab.worlds.tracking.lanes import DeclaredFilter, FilterSpec, hashable


@dataclass(frozen=True)
class FilterConfig:
    label: str
    kind: str
    model: str
    params: dict  # name -> float or tuple (the filter's parameter pytree, as numbers)
    options: dict = field(default_factory=dict)
    sensors: tuple[str, ...] = ()  # which sensors the filter sees (all when empty)
    fusion: str | None = None  # "interpolate" | "none": laser + infrared fusion view


def declared_of(fc) -> dict:
    """The numbers a filter declares and has (name -> Param): those of its kind's that its table
    gives (a built-in kind; an association's and its base's), or those its factory declares
    (``tracklab.declare``). The nearest and strongest neighbours' are not tuned: their choice of a
    return is a hard one, with no gradient (tune their PDAF relaxation, kind = "pdaf", same base)."""
    if not isinstance(fc, FilterConfig):
        return dict(fc.declared)
    kinds = [KINDS[fc.kind]] + ([KINDS[fc.options["base"]]] if "base" in fc.options else [])
    declared = {n: p for k in reversed(kinds) for n, p in k.params.items() if n in fc.params}
    if fc.kind in HARD_RULES:  # the base's numbers too: the association's choice has no gradient
        declared = {n: replace(p, tune=False) for n, p in declared.items()}
    return declared


@dataclass
class Experiment(protocol.Experiment):
    """An open-loop experiment, validated: everything ``tracklab run`` needs."""

    path: Path | None  # the experiment file; None: built in Python (tracklab.experiment)
    name: str
    runs: int
    seed: int
    dt: float
    steps: int
    chunk: int | None
    scenario: Any
    sensor: SensorSuite
    filters: list  # FilterConfig (a built-in kind) or FilterSpec (a filter of one's own)
    prior: dict[str, float]
    window: tuple[int, int]
    raw: dict
    also_runs: tuple[int, ...] = ()
    precision: str = "float64"
    pred_windows: dict = field(default_factory=dict)  # name -> (steps,) bool mask, report window included
    studies: list = field(default_factory=list)  # [[study]]: tuning and sweeps `tracklab reproduce` rebuilds
    level: float = 0.95  # of the confidence intervals
    baseline: str | None = None  # the filter the paired comparisons are to (None: the first)
    target_precision: float | None = None  # runs = "auto": stop when every position RMSE is this tight (relative)
    track_loss: Any = None  # [track_loss]: the test a run's track is lost by (errors.TrackLoss), None: none

    @property
    def sweep_metrics(self) -> tuple:
        """What a sweep plots: (summary key, title); with a track-loss test its probability first
        (over a clutter density and a detection probability: a tracker operating characteristic)."""
        loss = (("p_lost", "probability of track loss"),) if self.track_loss is not None else ()
        return loss + (("rmse_pos", "time-averaged position RMSE ({pos})" + (" of the runs on track" if loss else "")),
                       ("nees", "average NEES"), ("pred_err_rms", "RMS one-step prediction error ({pos})"))

    @property
    def dim(self) -> int:
        return self.scenario.dim

    @property
    def units(self):
        return tuple(self.scenario.units)

    @property
    def nees_dof(self) -> int:
        """The NEES's degrees of freedom (position and velocity): its consistent value."""
        return 2 * self.dim

    def prior_covariance(self) -> np.ndarray:
        d = self.dim
        return np.diag([self.prior["pos_sigma"] ** 2, self.prior["vel_sigma"] ** 2] * d)

    def lane(self, fc):
        """A filter as the tracking world's structure holds it: a built-in [[filter]] as its
        declaration, a user's own ``FilterSpec`` as it is."""
        if not isinstance(fc, FilterConfig):
            return fc
        return DeclaredFilter(fc.label, fc.kind, fc.model, hashable(fc.options), tuple(fc.sensors), fc.fusion)

    def view(self, fc: FilterConfig):
        """(view function or None, measurement model) of what a filter sees."""
        return self.lane(fc).sees(self.sensor)

    # ------------------------------------------------------------------ what is compiled

    def structure(self, chunk=None, runs=None):
        """What the compiled program depends on: the filters' kinds, models, options and views,
        the report windows and the chunk size (from ``runs`` when the file sets none); never the
        run count itself, nor any number."""
        lanes = tuple(self.lane(fc) for fc in self.filters)
        chunk = int(chunk or self.chunk or scan.default_chunk(self.scenario, self.sensor, runs=runs))
        return scan.TrackingStructure(lanes, scan.windows_of(self.pred_windows), chunk, self.track_loss,
                                      cluttered_of(self.sensor) is not None)

    def params(self):
        """Every number of the experiment, as the compiled program's argument."""
        filters = [{k: np.asarray(v, float) for k, v in fc.params.items()} if isinstance(fc, FilterConfig)
                   else fc.filter.params for fc in self.filters]
        return scan.TrackingParams(self.scenario, self.sensor, self.prior_covariance(), self.prior["acc_sigma"] ** 2,
                                   filters)

    def world(self, structure):
        return scan.world(structure)

    def ran_with(self) -> dict:
        """Each filter's parameters as it runs: label -> {leaf name: value} (``pytree.named_leaves``)."""
        return {fc.label: {n: np.asarray(v, float) for n, v in named_leaves(p).items()}
                for fc, p in zip(self.filters, self.params().filters)}

    def filter_specs(self):
        """The experiment's filters built with its numbers, as ``FilterSpec``s: to run one on
        measurements of one's own (``run_filter``) or in ``tracklab.monte_carlo``."""
        structure, params = self.structure(), self.params()
        specs = []
        for f, p in zip(structure.filters, params.filters):
            if isinstance(f, FilterSpec):
                specs.append(f)
                continue
            p = {k: jnp.asarray(v) for k, v in p.items()}
            r = f.realise(params.scenario, params.sensor, p, params.prior_extra_var)
            specs.append(FilterSpec(f.label, r.filter, f.kind, f.sensors, r.model, r.view, r.prior_extra_var))
        return specs

    # ------------------------------------------------------------------ declared numbers

    def tables(self):
        return "filter", [fc.label for fc in self.filters]

    def declared(self):
        return {fc.label: declared_of(fc) for fc in self.filters}

    def values(self, params):
        return {fc.label: named_leaves(p) for fc, p in zip(self.filters, params.filters)}

    def with_values(self, params, values):
        return params._replace(filters=[with_leaves(p, values[fc.label]) if values.get(fc.label) else p
                                        for fc, p in zip(self.filters, params.filters)])

    def write_where(self, label):
        fc = next(f for f in self.filters if f.label == label)
        if isinstance(fc, FilterSpec):
            return None
        _, meas = self.view(fc)
        return WriteBack(fc.model, meas.kind, SENSOR_SIGMAS.get(meas.kind, ()))

    # ------------------------------------------------------------------ tuning

    @property
    def tune_losses(self):
        """Time-averaged over the report window, per filter: position MSE, one-step prediction MSE,
        innovation negative log-likelihood (needs no truth)."""
        d, w = self.dim, self.window
        return {name: (lambda sums, lane, f=f: f(unpack(sums, d)[lane], w)) for name, f in LOSSES.items()}

    def tune_memory_bytes(self, runs_per_step, tuned, forward, eval_runs=None) -> float:
        """Reverse mode: the filter states it keeps for every run and step of a batch; forward mode,
        which keeps no step's states: the batch's random draws for every step and the current step's
        filter states with one tangent per tuned number. Plus the held-out evaluation's draws."""
        n = [fc.report_layout(self.dim).n if isinstance(fc, FilterSpec) else (3 if fc.model == "ca" else 2) * self.dim
             for fc in self.filters]  # each filter's state dimension
        state = sum(k * (1 + k) for k in n)  # its mean and covariance
        width = 2 * self.dim + self.sensor.m
        held_out = min(eval_runs or min(self.runs, 2000), 1000) * self.steps * width * 4.0
        if forward:
            return runs_per_step * (self.steps * width + state * (1 + tuned)) * 8.0 + held_out
        return runs_per_step * self.steps * state * 8.0 + held_out

    # ------------------------------------------------------------------ running

    def monte_carlo(self, runs=None, seed=None, progress=None, chunk=None, precision=None, target_precision=None):
        """The Monte-Carlo result of ``runs`` runs (default the file's); with a target precision
        (``target_precision``, or the file's runs = "auto"), chunks run until every filter's
        position-RMSE interval is that tight relative to it, ``runs`` at most."""
        target = target_precision or self.target_precision
        runs = runs or self.runs
        return outcome.run(self.structure(chunk, runs), self.params(), runs, self.seed if seed is None else seed,
                           progress=progress, precision=precision or self.precision, target=target, level=self.level)

    def simulate(self, runs=None, seed=None, progress=None, precision=None, target_precision=None) -> dict:
        return stats_document(self, self.monte_carlo(runs=runs, seed=seed, progress=progress, precision=precision,
                                                     target_precision=target_precision))

    def summarise(self, structure, params, sums, out, point=None) -> dict:
        """The statistics document of one parameter set's sums (the runner's ``out``; ``point``:
        which of its grid points)."""
        return statistics(outcome.result(structure, params, sums, out, point), self.window, self.pred_windows, self.level,
                          self.baseline)

    def write(self, doc, folder, figures=True):
        return write_results(doc, folder, figures)

    @property
    def run_bytes(self) -> float:
        """A run's random draws (float32) for every step."""
        return self.steps * (2 * self.dim + self.sensor.m) * 4.0

    @property
    def statistics_bytes(self) -> float:
        return self.steps * (len(self.filters) * 64 + self.dim**2) * 8.0

    def memory_bytes(self, runs=None, chunk=None) -> float:
        """A lower bound on the bytes a run needs: one chunk's random draws (float32) for every
        step, and each filter's per-step statistics on the host."""
        chunk = self.structure(chunk, runs or self.runs).chunk
        return chunk * self.run_bytes + len(self.filters) * self.steps * 64 * 8.0

    def check_memory(self, runs=None, limit=None):
        check(self.path or "tracklab.experiment", self.memory_bytes(runs), limit, f"a chunk of runs x {self.steps} steps",
              "set a smaller experiment.chunk, or fewer experiment.steps")


def stats_document(exp, res):
    """The statistics document (stats.json) of an open-loop experiment (or recorded data judged
    like one: ``recorded.Recorded``) and its Monte-Carlo result."""
    level = exp.level
    st = statistics(res, exp.window, exp.pred_windows, level, exp.baseline)
    ran = exp.ran_with()
    stride = series_stride(res.steps)
    st = {
        "bounds": decimate(st["bounds"], stride),
        "filters": {k: dict(f, series=decimate(f["series"], stride)) for k, f in st["filters"].items()},
    }
    return {
        "name": exp.name,
        "tracklab_version": __version__,
        "runs": res.runs,
        "steps": res.steps,
        "dt": res.dt,
        "window": list(exp.window),
        "series_stride": stride,  # series hold steps stride, 2·stride, … (summaries use every step)
        "axes": list(res.axes),  # names of the reporting frame's position axes
        "units": list(res.units),  # of position and velocity
        "windows": [w for w in exp.pred_windows if w != REPORT_WINDOW],  # named prediction-error windows
        "level": level,  # of every interval: value ± half_width
        "wall_s": res.wall_s,
        "compile_s": res.compile_s,
        "experiment": exp.raw,
        "bounds": st["bounds"],
        "example_run": decimate(example_of(exp, res), stride),
        "filters": {
            label: {"kind": f["kind"], "label": label, "params": ran.get(label, {}), "summary": f["summary"]}
            | {k: f[k] for k in ("half_width", "intervals", "paired", "cdf") if k in f} | {"series": f["series"]}
            for label, f in st["filters"].items()
        },
    } | ({"auto": res.auto} if res.auto else {}) | clutter_of(exp, res)


def clutter_of(exp, res) -> dict:
    """What a statistics document says of tracking in clutter: the track-loss test, the clutter
    (its density, region volume, expected false alarms per scan, capacity) and the scans that
    passed their capacity (empty when the experiment has none of these)."""
    doc = {}
    if res.loss is not None:
        doc["track_loss"] = {"distance": float(res.loss.distance), "steps": int(res.loss.steps)} | (
            {"existence": float(res.loss.existence)} if res.loss.existence is not None else {})
    cluttered = cluttered_of(exp.sensor)
    if cluttered is not None:
        doc["clutter"] = {"density": float(np.asarray(cluttered.density)), "volume": float(cluttered.volume()),
                          "false_alarms_per_scan": float(cluttered.mean_false_alarms()),
                          "max_returns": cluttered.max_returns, "p_detect": float(np.asarray(cluttered.p_detect)),
                          "region": "about the target" if cluttered.about_target else "fixed coverage"}
    if res.overflow is not None:
        doc["overflow"] = res.overflow
    return doc

def example_of(exp, res):
    """Run 0 in CV layout: truth, each filter's estimates and (Cartesian sensors) the measurements."""
    ex = res.example
    if not ex:
        return {}
    doc = {"truth": ex["truth"][1:], "estimates": ex["x"]}
    if ex.get("var"):  # each filter's own standard deviations of its errors, for the ±3σ envelope
        doc["sd"] = {k: np.sqrt(np.maximum(np.asarray(v, float), 0.0)) for k, v in ex["var"].items()}
    kinds = [s.kind for s in exp.sensor.sensors] if exp.sensor is not None else []
    if len(kinds) == 1 and kinds[0] in ("cartesian", "mount"):
        doc["measurements"] = ex["z"]
    return doc

DERIVED_SERIES = ("mse_pos", "mse_vel", "pred_mse", "nees_in_bounds", "nis_in_bounds")


def kept_on_disk(doc) -> dict:
    """What a results folder keeps of a statistics document: all of it but the per-step series
    another one gives (``mse_pos`` is ``rmse_pos`` squared) or that the summaries have already
    counted (``nees_in_bounds``: its fraction is in the summary), and run 0's estimates only when
    the experiment file draws ``run0`` or ``run0_error`` (the truth stays, for ``track.png``)."""
    out = dict(doc)
    out["filters"] = {label: f | {"series": {k: v for k, v in f["series"].items() if k not in DERIVED_SERIES}}
                      if "series" in f else f for label, f in doc["filters"].items()}
    example = doc.get("example_run")
    if example and not chosen_kinds(doc) & {"run0", "run0_error"}:
        out["example_run"] = {"truth": example["truth"]}
    return out


def write_results(doc, folder: Path, figures=True):
    """A statistics document's tables and (``figures``) figures in ``folder``; returns the document."""
    write_tables(folder, kept_on_disk(doc))
    if formats_of(figures):
        plot_figures(doc, folder, formats_of(figures))
    return doc
