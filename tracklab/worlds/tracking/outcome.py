"""The open-loop world's outcome: ``MonteCarloResult``, the per-step sums of every filter over
the runs with run 0's example, the runs' samples and the PCRLB; ``run`` (through the runner)
and ``monte_carlo`` (filters of one's own from Python).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from tracklab.checks import (
    check_count,
    check_covariance,
    check_filter,
    check_key,
    check_positive,
    check_precision,
    numeric,
    refuse,
    wrong_type,
)
from tracklab.filters.core import Filter
from tracklab.intervals import LEVEL, precision_reached
from tracklab.montecarlo import runner
from tracklab.montecarlo.pcrlb import pcrlb64
from tracklab.montecarlo.statistics import REPORT_WINDOW
from tracklab.scenarios import Scenario
from tracklab.sensors import SensorSuite
from tracklab.sensors.clutter import cluttered_of, scan_information_scale
from tracklab.worlds.tracking.errors import TrackLoss, sample_names, unpack
from tracklab.worlds.tracking.lanes import FilterSpec
from tracklab.worlds.tracking.scan import (
    TrackingParams,
    TrackingStructure,
    default_chunk,
    windows_of,
    with_report_window,
    world,
)


@dataclass
class MonteCarloResult:
    runs: int
    steps: int
    dt: float
    dim: int
    sums: dict[str, dict[str, np.ndarray]]  # label -> name -> (T, ...)
    pcrlb: np.ndarray | None  # (T, 2·dim, 2·dim) bound on the CV-layout state, or None
    wall_s: float
    compile_s: float
    labels: list[str]
    kinds: dict[str, str]
    example: dict = field(default_factory=dict)  # run 0: truth, z, and each filter's estimates
    axes: tuple[str, ...] = ("x", "y", "z")  # names of the reporting frame's position axes
    units: tuple[str, str] = ("m", "m/s")  # of position and velocity
    windows: list[str] = field(default_factory=list)  # named windows of the prediction-error maxima
    samples: Any = None  # the per-run samples' moments (montecarlo.samples.RunSamples), lanes in ``labels`` order
    sample_names: list = field(default_factory=list)  # (name, width) of each lane's samples (``sample_names``)
    report_window: tuple[int, int] | None = None  # 1-based steps the samples average over
    auto: dict | None = None  # runs chosen by a target precision: {target, max_runs, reached}
    loss: Any = None  # the track-loss test (errors.TrackLoss) or None
    lost_pairs: Any = None  # (filters, filters): runs lost by one filter and not by the other
    overflow: dict | None = None  # a cluttered sensor's scans over their capacity: {scans, runs, capacity}

def run(structure: TrackingStructure, params: TrackingParams, runs: int, key, *, progress=None,
        precision: str = "float64", points: int | None = None, target: float | None = None, level: float = LEVEL):
    """Per-step error statistics of the structure's filters over ``runs`` Monte-Carlo runs: a
    ``MonteCarloResult``, or with ``points`` (params stacked along a leading axis, as a sweep's
    grid) a list of them, one per parameter set, all on the same runs. With ``target``, chunks
    run until ``precision_reached`` (``runs`` at most): the result's ``auto`` says how it went."""
    enough = None
    if target is not None and points is None:
        enough = lambda sums, samples, done: precision_reached(samples, target, level)
    out = runner.run(world(structure), params, runs, key, precision=precision, points=points, progress=progress,
                     enough=enough)
    if points is None:
        res = result(structure, params, out.sums, out)
        if target is not None:
            res.auto = {"target": target, "max_runs": runs, "reached": precision_reached(out.samples, target, level)}
        return res
    return [result(structure, runner.pick(params, j), runner.pick(out.sums, j), out, j) for j in range(points)]

def result(structure, params, sums, out: runner.Outcome, point: int | None = None) -> MonteCarloResult:
    """The ``MonteCarloResult`` of one parameter set's sums (the runner's, for ``out.runs`` runs;
    ``point``: which grid point's samples, when the run had several)."""
    scenario = params.scenario
    sums = unpack(runner.labelled(sums, structure.labels), scenario.dim)
    info = sums.pop("_info")
    overflow, lost_pairs = sums.pop("_overflow", None), sums.pop("_lost_pairs", None)
    cluttered = cluttered_of(params.sensor)
    if cluttered is not None:  # a scan's information, reduced by clutter and missed detections
        info = info * scan_information_scale(cluttered)
        overflow = {"scans": int(round(float(np.sum(overflow["scans"])))), "runs": int(round(float(overflow["runs"]))),
                    "capacity": cluttered.max_returns}
    ex = sums.pop("_example")
    example = {"truth": np.asarray(ex["truth"]), "z": np.asarray(ex["z"])}
    example["x"] = {label: np.asarray(sums[label].pop("example_x")) for label in structure.labels}
    example["var"] = {label: np.asarray(sums[label].pop("example_var")) for label in structure.labels}
    windows = with_report_window(structure.window_masks(), scenario.steps)
    report = np.flatnonzero(windows[REPORT_WINDOW])
    samples = out.samples if (point is None or out.samples is None) else out.samples.point(point)
    return MonteCarloResult(
        runs=out.runs, steps=scenario.steps, dt=float(scenario.dt), dim=scenario.dim,
        sums={label: sums[label] for label in structure.labels},
        pcrlb=pcrlb64(scenario, np.asarray(params.P0, np.float64), info / out.runs) if scenario.gaussian else None,
        wall_s=out.wall_s, compile_s=out.compile_s, labels=structure.labels,
        kinds={f.label: f.kind for f in structure.filters}, example=example,
        axes=tuple(scenario.axes), units=tuple(scenario.units), windows=[n for n, _ in structure.windows],
        samples=samples, sample_names=sample_names(scenario.dim, windows),
        report_window=(int(report[0]) + 1, int(report[-1]) + 1), loss=structure.loss,
        lost_pairs=None if lost_pairs is None else np.asarray(lost_pairs, float), overflow=overflow)

def monte_carlo(
    scenario,
    sensor,
    specs: Sequence[FilterSpec],
    runs: int,
    key,
    P0_cv,
    *,
    chunk: int | None = None,
    params: Sequence[Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    precision: str = "float64",
    windows: dict[str, np.ndarray] | None = None,
    track_loss: tuple[float, int] | None = None,
) -> MonteCarloResult:
    """Per-step error statistics of several filters over ``runs`` Monte-Carlo runs.

    ``P0_cv`` is the prior covariance in CV layout: run i's prior mean is the
    truth one period before the first measurement plus a N(0, P0) draw, shared
    by all filters in that run. ``precision = "float32"`` traces and runs the
    simulation and the filters in single precision (JAX's 64-bit mode off for
    them); sums are accumulated on the host in float64 either way, and the
    random draws are the same (made in float32 in both). ``key``: an integer seed, a JAX key
    (``jax.random.key``) or a raw uint32[2] one (``jax.random.PRNGKey``); run i draws from
    ``fold_in(key, i)``. ``windows`` (name -> (steps,) bool mask) are where each run's largest
    one-step prediction error is taken. ``track_loss``: (distance, steps), the track-loss test
    (``errors.TrackLoss``; needed for the statistics of tracking in clutter).

    Refused before anything compiles, in one line naming the argument: ``scenario`` not a
    tracklab scenario, or its ``dt`` not a finite number > 0; ``specs`` empty, or holding
    anything but ``FilterSpec``s around a ``tracklab.Filter``; ``runs`` or ``chunk`` not an
    integer >= 1; ``key`` none of the forms above (an integer seed in [0, 2⁶⁴ − 1]); ``P0_cv``
    not (2·dim, 2·dim), not finite, not symmetric or not positive definite; ``params`` not one
    per filter; ``precision`` neither "float64" nor "float32"; ``windows`` not a dict, or a mask
    in it not of the scenario's steps; ``progress`` not callable.
    """
    key = _check(scenario, specs, runs, key, P0_cv, chunk, params, precision, windows, progress)
    if not isinstance(sensor, SensorSuite):
        sensor = SensorSuite((sensor,))
    chunk = int(chunk or default_chunk(scenario, sensor, runs=runs))
    loss = None
    if track_loss is not None:
        where = "tracklab.monte_carlo"
        if not isinstance(track_loss, (list, tuple)) or len(track_loss) != 2:
            raise refuse(where, "track_loss", track_loss, "must be (distance > 0, steps >= 1)")
        loss = TrackLoss(check_positive(where, "track_loss[0]", track_loss[0]),
                         check_count(where, "track_loss[1]", track_loss[1]))
    structure = TrackingStructure(tuple(specs), windows_of(windows), chunk, loss, cluttered_of(sensor) is not None)
    filter_params = list(params) if params is not None else [s.filter.params for s in specs]
    p = TrackingParams(scenario, sensor, np.asarray(P0_cv, float), 0.0, filter_params)
    return run(structure, p, runs, key, progress=progress, precision=precision)


def _check(scenario, specs, runs, key, P0_cv, chunk, params, precision, windows, progress):
    """``monte_carlo``'s refusals (see its doc); the key as the simulation's typed key."""
    where = "tracklab.monte_carlo"
    if not isinstance(scenario, Scenario):
        raise wrong_type(where, "scenario", scenario, "must be a tracklab scenario (tracklab.scenarios; "
                         "Generated(truth, dt=…, steps=…, dim=…) for a truth function of one's own)")
    check_positive(where, "scenario.dt", scenario.dt)
    steps = check_count(where, "scenario.steps", scenario.steps)
    check_precision(where, precision)
    check_count(where, "runs", runs)
    check_count(where, "chunk", chunk, optional=True)
    key = check_key(where, "key", key)
    if isinstance(specs, (str, FilterSpec, Filter)) or not isinstance(specs, Sequence):
        raise wrong_type(where, "specs", specs, "must be a list of tracklab.FilterSpec(label, filter)")
    if not specs:
        raise refuse(where, "specs", specs, "must hold at least one tracklab.FilterSpec(label, filter)")
    for i, spec in enumerate(specs):
        if isinstance(spec, Filter):
            raise wrong_type(where, f"specs[{i}]", spec, "give it a label: tracklab.FilterSpec(label, filter)")
        if not isinstance(spec, FilterSpec):
            raise wrong_type(where, f"specs[{i}]", spec, "must be a tracklab.FilterSpec(label, filter)")
        check_filter(where, f"specs[{i}].filter", spec.filter)
    if params is not None and (isinstance(params, (str, dict)) or not isinstance(params, Sequence)
                               or len(params) != len(specs)):
        raise refuse(where, "params", params, f"must be None or a list of {len(specs)} parameter pytrees, one per filter")
    n = 2 * int(scenario.dim)
    if np.shape(P0_cv) != (n, n):
        raise refuse(where, "P0_cv", numeric(where, "P0_cv", P0_cv), f"must be ({n}, {n}): the prior covariance of "
                     f"[x, ẋ, y, ẏ{', z, ż' if n == 6 else ''}] (CV layout)")
    check_covariance(where, "P0_cv", P0_cv)
    if windows is not None and not isinstance(windows, dict):
        raise wrong_type(where, "windows", windows, "must be None or a dict {name: (steps,) bool mask}")
    if progress is not None and not callable(progress):
        raise wrong_type(where, "progress", progress, "must be None or a function progress(done, runs)")
    for name, m in (windows or {}).items():
        if np.shape(m) != (steps,):
            raise refuse(where, f"windows[{name!r}]", np.asarray(m), f"must be a mask of the {steps} steps, "
                         f"shape ({steps},)")
    return key
