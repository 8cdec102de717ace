"""One experiment protocol for every world: what ``cli``, ``tune``, ``sweep``, the studies and
``reproduce`` use, whatever the file describes.

An experiment is what one file describes in its world (open-loop tracking, the airborne closed
loop, the servo): a hashable ``structure`` the program is compiled for, every number as the
``params`` pytree the program takes, and the ``world`` that runs them (``runner.World``). Its
*units* are what the file names and a study tunes — the filters, the trackers, the estimators,
each a table of the file's array of tables (``tables``) — and each unit declares its numbers
(``declared``: name -> ``tracklab.parameters.Param``). One tuning path and one sweep path
follow from the declarations: a number's constraint gives the coordinates Adam moves in,
``values``/``with_values`` read the numbers out of the params and put others in (traced,
so the gradient flows), ``Param.write`` puts a tuned value back into the file, a ``sweep`` flag
lets a scale factor multiply it.

``run`` is the same for every world: the output folder and the memory need checked before
anything compiles, ``simulate`` (the statistics document), ``write`` (the results folder).
``run``, ``simulate`` and ``monte_carlo`` (every world's) refuse a bad ``runs``, ``seed``,
``precision``, ``chunk``, ``target_precision``, ``progress``, ``out`` or ``max_memory`` in one
line naming the method and the argument, before anything compiles (``check_arguments``).
"""

from __future__ import annotations

import abc
import functools
import inspect
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from tracklab.checks import MAX_RUN_STEPS, MAX_RUNS, check_count, check_precision, is_real, refuse, wrong_type
from tracklab.montecarlo import runner
from tracklab.parameters import Param
from tracklab.report.document import run_into_folder
from tracklab.report.figures import FORMATS, formats_of


CHECKED_METHODS = ("run", "simulate", "monte_carlo")  # every world's: their arguments checked first


@dataclass(frozen=True)
class UnitConfig:
    """One unit's table of a closed-loop file (a [[tracker]], an [[estimator]]), read as its kind
    declares: its numbers (name -> value, program inputs) and its options (field -> value, what
    its code is compiled for)."""

    label: str
    kind: str
    numbers: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)


def checking_arguments(method):
    """``method`` (``run``, ``simulate``, ``monte_carlo``) with its arguments checked first
    (``Experiment.check_arguments``), a refusal naming ``<class>.<method>``."""
    signature = inspect.signature(method)

    @functools.wraps(method)
    def checked(self, *args, **kwargs):
        given = signature.bind(self, *args, **kwargs).arguments
        self.check_arguments(f"{type(self).__name__}.{method.__name__}", given)
        return method(self, *args, **kwargs)

    checked.checks_arguments = True
    return checked


class Experiment(abc.ABC):
    """A validated experiment of any world (each world's is a dataclass with these fields).

    Each world's ``run``, ``simulate`` and ``monte_carlo`` check their arguments first
    (``check_arguments``): a subclass's own are wrapped as it is defined."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for name in CHECKED_METHODS:
            method = cls.__dict__.get(name)
            if callable(method) and not getattr(method, "checks_arguments", False):
                setattr(cls, name, checking_arguments(method))

    path: Path | None  # the experiment file (None: built in Python)
    name: str
    runs: int
    seed: int
    precision: str  # "float64" | "float32"
    chunk: int | None  # runs per chunk (None: the world's default)
    level: float  # of every confidence interval
    baseline: str | None  # the lane the paired differences are to (None: the first)
    target_precision: float | None  # runs = "auto": the relative half-width every headline interval must reach
    also_runs: tuple  # extra run counts ``reproduce`` writes
    studies: list  # [[study]] tables
    raw: dict  # the file as read

    units: tuple[str, str]  # of the headline statistics (position, velocity)
    sweep_metrics: tuple  # (summary key, title) a sweep draws
    nees_dof: int | None = None  # the NEES's consistent value, where there is one
    relabel_tuned: bool = True  # a tuned file labels its tuned units "<label>, tuned"

    # ------------------------------------------------------------------ what is compiled

    @abc.abstractmethod
    def structure(self, chunk: int | None = None, runs: int | None = None):
        """What the program is compiled for (hashable), besides the params' pytree structure:
        kinds, dimensions, steps, report timing, the chunk (by default from ``runs``)."""

    @abc.abstractmethod
    def params(self):
        """Every number of the experiment, the compiled program's argument (a pytree)."""

    @abc.abstractmethod
    def world(self, structure) -> runner.World:
        """The world that runs a structure's chunks."""

    steps: int  # the steps a run reports (measurement steps, filter periods, camera frames)
    window: tuple[int, int]  # the first and last step (1-based) the summaries average over

    @property
    def samples_per_run(self) -> int:
        """What the run limits count (runs × samples ≤ 10¹²): steps, radar samples, servo ticks."""
        return self.steps

    # ------------------------------------------------------------------ declared numbers

    @abc.abstractmethod
    def tables(self) -> tuple[str, list[str]]:
        """The file's array of tables holding the units ("filter", "tracker", "estimator") and
        their labels, in the file's order."""

    @abc.abstractmethod
    def declared(self) -> dict[str, dict[str, Param]]:
        """Each unit's declared numbers (label -> name -> Param): what ``tune --params`` and a
        scale-factor sweep name."""

    @abc.abstractmethod
    def values(self, params) -> dict[str, dict[str, Any]]:
        """The numbers of each unit in ``params`` (label -> name -> value): its declared ones, and
        for a filter of one's own every leaf of its params by name (``pytree.named_leaves``)."""

    @abc.abstractmethod
    def with_values(self, params, values: Mapping[str, Mapping[str, Any]]):
        """``params`` with the units' numbers in ``values`` (label -> name -> value) put in; traceable."""

    def write_where(self, label: str):
        """What a unit's ``Param.write`` needs to know of it (its model and sensor: a built-in
        filter's ``WriteBack``); None for the closed loops."""
        return None

    def scalable(self) -> list[str]:
        """The names a scale-factor sweep axis may name here."""
        return list(dict.fromkeys(n for d in self.declared().values() for n, p in d.items() if p.sweep))

    def scaled(self, params, factors: Mapping[str, float]):
        """``params`` with every unit's numbers named in ``factors`` (and declared scalable) multiplied."""
        declared, values = self.declared(), self.values(params)
        return self.with_values(params, {l: {n: v * factors[n] for n, v in values[l].items()
                                              if n in factors and n in d and d[n].sweep}
                                         for l, d in declared.items()})

    # ------------------------------------------------------------------ tuning

    @property
    @abc.abstractmethod
    def tune_losses(self) -> Mapping[str, Callable]:
        """The losses ``tune`` may minimise: name -> f(sums, lane label) -> scalar, ``sums`` the
        runner's (``runner.merged``) for one batch of runs; the first is the default."""

    def tune_lanes(self, chosen: Mapping[str, Any]) -> list[str]:
        """The lanes whose losses a tuning of the units ``chosen`` minimises (each unit its own)."""
        return list(chosen)

    @abc.abstractmethod
    def tune_memory_bytes(self, runs_per_step: int, tuned: int, forward: bool) -> float:
        """A lower bound on one tuning step's memory (``tuned`` numbers; ``forward``: forward mode)."""

    def trained_first(self) -> list:
        """What a run trains before its Monte-Carlo runs (a servo's DEKF): nothing here."""
        return []

    def before_runs(self) -> list[str]:
        """What a run does before its Monte-Carlo runs, a line each (minutes without a word otherwise)."""
        return []

    # ------------------------------------------------------------------ running

    @abc.abstractmethod
    def simulate(self, runs=None, seed=None, progress=None, precision=None, target_precision=None) -> dict:
        """The statistics document of ``runs`` runs (default the file's; with a target precision,
        chunks until every headline interval is that tight, ``runs`` at most)."""

    @abc.abstractmethod
    def summarise(self, structure, params, sums, out, point=None) -> dict:
        """The statistics document of one parameter set's sums (``point``: which of the runner's
        grid points): what a sweep keeps of each point."""

    @abc.abstractmethod
    def write(self, doc: dict, folder: Path, figures=True) -> dict:
        """The results folder's files of a statistics document (tables, stats.json, figures: True for
        PNG, False for none, or formats from ``report.figures.FORMATS``)."""

    @property
    @abc.abstractmethod
    def run_bytes(self) -> float:
        """The bytes a run of a chunk holds (its per-step arrays)."""

    @property
    @abc.abstractmethod
    def statistics_bytes(self) -> float:
        """The bytes of one parameter set's per-step statistics on the host."""

    @abc.abstractmethod
    def memory_bytes(self, runs=None, chunk=None) -> float:
        """A lower bound on what a run needs."""

    @abc.abstractmethod
    def check_memory(self, runs=None, limit=None):
        """ConfigError in one line (with what to shrink) when a run would pass the machine's memory or ``limit``."""

    def check_arguments(self, where: str, given: Mapping[str, Any]):
        """Refuse, in one line naming ``where`` (``Experiment.monte_carlo``) and the argument, what
        ``given`` (argument name -> value, as called) holds of: ``runs`` (None: the experiment's;
        else an integer in [1, 10⁸] with runs × steps <= 10¹²), ``seed`` (None or an integer in
        [0, 2³² − 1]), ``precision`` (None, "float64" or "float32"), ``chunk`` (None or an integer
        >= 1), ``target_precision`` (None or a relative half-width in (0, 1)), ``progress`` (None or
        a function), ``out`` (None or a path), ``max_memory`` (None or a number of bytes >= 1)."""
        if "runs" in given:
            runs = check_count(where, "runs", given["runs"], 1, MAX_RUNS, optional=True)
            if runs is not None and runs * self.samples_per_run > MAX_RUN_STEPS:
                raise refuse(where, "runs", runs, f"runs x steps must be <= {MAX_RUN_STEPS:.0e} "
                             f"({self.samples_per_run} steps a run)")
        if "seed" in given:
            check_count(where, "seed", given["seed"], 0, 2**32 - 1, optional=True)
        if "precision" in given:
            check_precision(where, given["precision"], optional=True)
        if "chunk" in given:
            check_count(where, "chunk", given["chunk"], optional=True)
        target = given.get("target_precision")
        if target is not None and not (is_real(target) and 0 < float(target) < 1):
            allowed = "must be None or a relative half-width in (0, 1), e.g. 0.005"
            raise (refuse if is_real(target) else wrong_type)(where, "target_precision", target, allowed)
        progress = given.get("progress")
        if progress is not None and not callable(progress):
            raise wrong_type(where, "progress", progress, "must be None or a function progress(done, runs)")
        out = given.get("out")
        if out is not None and not isinstance(out, (str, os.PathLike)):
            raise wrong_type(where, "out", out, "must be None (results/<name>/) or the path of the results folder")
        if "max_memory" in given:
            check_count(where, "max_memory", given["max_memory"], optional=True)
        if "figures" in given:
            try:
                formats_of(given["figures"])
            except ValueError:
                raise wrong_type(where, "figures", given["figures"], "must be True, False, or a format or list of "
                                 f"formats from {', '.join(FORMATS)}") from None

    @checking_arguments
    def run(self, runs=None, seed=None, out=None, progress=None, figures=True, precision=None, max_memory=None,
            target_precision=None):
        """``tracklab run``: the results folder (default results/<name>/) and the memory need checked
        before anything compiles, then the runs, then the folder written whole; returns the
        statistics document (None in a process other than 0 of a run of several)."""
        return run_into_folder(self, out, runs, max_memory,
                               lambda: self.simulate(runs, seed, progress, precision, target_precision),
                               lambda doc, tmp: self.write(doc, tmp, figures), where=f"{type(self).__name__}.run")
