"""An open-loop experiment built in Python: ``tracklab.experiment(scenario, sensors, filters)``.

The same experiment an experiment file gives, from objects: a scenario (any of
``tracklab.scenarios``, or ``Generated`` around a truth function of one's own), sensors
(``Sensor``, ``CustomSensor``, a ``SensorSuite`` or a list of them) and filters, each a
built-in kind as the dictionary a ``[[filter]]`` table holds (``{"kind": "ekf",
"accel_sigma": 2.0}``), a ``FilterConfig`` of a loaded experiment, or a ``FilterSpec``
around a ``Filter`` of one's own. Everything is checked as a file is, before anything
compiles; a bad input raises ``ConfigError`` (a ``ValueError``) in one line.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from tracklab.checks import is_real, kind_of
from tracklab.config.fields import MAX_RUN_STEPS, MAX_RUNS, NAME_RE, check_unique
from tracklab.config.tracking import parse_filter, pred_windows_of
from tracklab.errors import ConfigError
from tracklab.filters.core import Filter
from tracklab.pytree import Code
from tracklab.scenarios import Generated, Scenario
from tracklab.sensors import (
    SENSOR_SIGMAS,
    SENSORS,
    Cluttered,
    CustomSensor,
    Sensor,
    SensorSuite,
)
from tracklab.sensors.clutter import cluttered_of
from tracklab.worlds.tracking.errors import TrackLoss
from tracklab.worlds.tracking.experiment import Experiment, FilterConfig
from tracklab.worlds.tracking.lanes import FilterSpec

WHERE = "tracklab.experiment"  # what the one-line errors name in place of a file


def _suite(sensors, scenario) -> SensorSuite:
    if isinstance(sensors, SensorSuite):
        items = list(sensors.sensors)
    elif isinstance(sensors, (Sensor, CustomSensor, Cluttered)):
        items = [sensors]
    elif isinstance(sensors, (list, tuple)):
        items = list(sensors)
    else:
        raise ConfigError(WHERE, "sensors", kind_of(sensors), "must be a tracklab.sensors.Sensor or CustomSensor, "
                          "a list of them, or a SensorSuite")
    if not items:
        raise ConfigError(WHERE, "sensors", sensors, "must name at least one sensor")
    out, names = [], set()
    for i, s in enumerate(items):
        field = f"sensors[{i}]"
        clutter = None
        if isinstance(s, Cluttered):  # checked as its sensor, then its false alarms
            if len(items) > 1:
                raise ConfigError(WHERE, field, "Cluttered", "clutter needs the experiment's only sensor")
            clutter, s = s, s.sensor
            field = f"{field}.sensor"
        if not isinstance(s, (Sensor, CustomSensor)):
            raise ConfigError(WHERE, field, type(s).__name__, "must be a tracklab.sensors.Sensor or CustomSensor")
        if isinstance(s, Sensor):
            if s.kind not in SENSOR_SIGMAS:
                raise ConfigError(WHERE, f"{field}.kind", s.kind, f"must be one of {', '.join(SENSORS)} "
                                  "(a sensor of one's own: tracklab.sensors.CustomSensor(h, R))")
            want = s.dim if s.kind == "cartesian" else len(SENSOR_SIGMAS[s.kind])
            if len(s.sigma) != want or not all(np.isfinite(v) and v > 0 for v in s.sigma):
                raise ConfigError(WHERE, f"{field}.sigma", tuple(s.sigma), f"a {s.kind} sensor needs {want} noise "
                                  f"standard deviations > 0 ({', '.join(SENSOR_SIGMAS[s.kind])})")
        frame_dim = scenario.dim
        if s.dim != frame_dim:
            raise ConfigError(WHERE, f"{field}.dim", s.dim, f"the scenario's truth is {frame_dim}-D")
        if s.name in names:
            raise ConfigError(WHERE, f"{field}.name", s.name, "must be unique among the sensors")
        names.add(s.name)
        if s.period > 0 and s.dt != scenario.dt:  # the report epochs are on the scenario's grid
            s = dataclasses.replace(s, dt=scenario.dt, misses=s.misses)
        why = s.problem() if isinstance(s, CustomSensor) else None
        if why:
            raise ConfigError(WHERE, field, s.name, why)
        if isinstance(s, CustomSensor):  # structure by what its h traces to
            s = s.keyed()
        if not s.report_mask(scenario.steps).any():
            raise ConfigError(WHERE, f"{field}.offset", s.offset, "the sensor reports at no step of the run")
        out.append(s if clutter is None else _cluttered(clutter, s, f"sensors[{i}]"))
    return SensorSuite(tuple(out))


def _cluttered(c: Cluttered, sensor, field) -> Cluttered:
    """``c`` around its checked ``sensor``, its numbers checked as a file's are."""
    m = sensor.m
    if not is_real(c.density) or not (np.isfinite(c.density) and c.density >= 0):
        raise ConfigError(WHERE, f"{field}.density", c.density, "must be a number >= 0 (false alarms per unit volume "
                          "of the measurement space)")
    half = np.asarray(c.half_width, float) if np.size(c.half_width) else np.zeros(0)
    if half.shape != (m,) or not np.all(np.isfinite(half)) or np.any(half <= 0):
        raise ConfigError(WHERE, f"{field}.half_width", c.half_width, f"must be {m} numbers > 0: the clutter "
                          f"region's half-widths ({', '.join(sensor.names)})")
    if c.center is not None and (np.shape(c.center) != (m,) or not np.all(np.isfinite(np.asarray(c.center, float)))):
        raise ConfigError(WHERE, f"{field}.center", c.center, f"must be None (about the target) or {m} finite numbers")
    if isinstance(c.max_returns, bool) or not isinstance(c.max_returns, (int, np.integer)) or not 1 <= c.max_returns <= 1024:
        raise ConfigError(WHERE, f"{field}.max_returns", c.max_returns, "must be an integer in [1, 1024]")
    if c.snr is not None and (not is_real(c.snr) or not -30.0 <= c.snr <= 60.0):
        raise ConfigError(WHERE, f"{field}.snr", c.snr, "must be None or the target's mean SNR in dB, in [-30, 60]")
    out = Cluttered(dataclasses.replace(sensor, misses=True), float(c.density), tuple(half.tolist()),
                    None if c.center is None else tuple(float(v) for v in c.center), int(c.max_returns),
                    None if c.snr is None else float(c.snr))
    why = out.problem()
    if why is not None:
        name, value, allowed = why
        raise ConfigError(WHERE, f"{field}.{name}", value, allowed)
    return out


def _describe(obj):
    """A scenario or sensor as numbers and names, for stats.json."""
    if dataclasses.is_dataclass(obj):
        doc = {"type": type(obj).__name__}
        for fld in dataclasses.fields(obj):
            v = getattr(obj, fld.name)
            v = v.fn if isinstance(v, Code) else v
            if dataclasses.is_dataclass(v):  # a cluttered sensor's sensor
                v = _describe(v)
            elif callable(v):
                v = f"{getattr(v, '__module__', '?')}:{getattr(v, '__qualname__', type(v).__name__)}"
            elif v is not None and not isinstance(v, (str, bool, int, float, tuple, list)):
                v = np.asarray(v).tolist()
            doc[fld.name] = v
        return doc
    return {"type": type(obj).__name__}


def _filter_table(fc) -> dict:
    if isinstance(fc, FilterConfig):
        return {"label": fc.label, "kind": fc.kind, "model": fc.model,
                **{k: np.asarray(v).tolist() for k, v in fc.params.items()}, **fc.options}
    layout = fc.layout or fc.filter.layout
    doc = {"label": fc.label, "kind": fc.kind}
    if layout is not None:
        doc["layout"] = {"n": int(layout.n), "pos_idx": list(layout.pos_idx), "vel_idx": list(layout.vel_idx)}
    if fc.sensors:
        doc["sensors"] = list(fc.sensors)
    return doc


def experiment(scenario, sensors, filters, *, name: str = "experiment", runs: int = 1000, seed: int = 0,
               prior: dict | None = None, window: tuple[int, int] | None = None, windows: dict | None = None,
               chunk: int | None = None, precision: str = "float64", level: float = 0.95,
               baseline: str | None = None, target_precision: float | None = None,
               track_loss: tuple | None = None) -> Experiment:
    """An open-loop experiment from Python objects (see the module's doc).

    ``prior``: ``pos_sigma`` (m), ``vel_sigma`` (m/s), ``acc_sigma`` (the prior std of states
    beyond position and velocity), by default 100, 10, 1. ``window``: the report window
    (first, last step, both included; default all). ``windows``: named windows of the
    one-step prediction error, as ``[report.windows]`` in a file. ``level``: of the confidence
    intervals; ``baseline``: the filter the paired differences are to (default the first);
    ``target_precision``: run until every filter's position-RMSE interval is within ± that
    fraction of it, ``runs`` at most (as ``runs = "auto"`` in a file). ``chunk``: runs per
    chunk (None: the default). ``track_loss``: (distance, steps, existence), the track-loss test of a
    file's ``[track_loss]`` (required with a ``Cluttered`` sensor; steps may be left out: 5; the
    existence threshold of an IPDA's test too).

    Refused (``ConfigError``, one line): besides what a file's reader refuses, a scenario whose
    ``dt`` is not a finite number > 0 or whose ``steps`` is not an integer >= 1, ``filters`` not
    a list, a ``FilterSpec`` whose filter is not a ``tracklab.Filter``, ``chunk`` not an integer
    >= 1, ``precision`` neither "float64" nor "float32".
    """
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        raise ConfigError(WHERE, "name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
    for field, v, lo, hi in (("runs", runs, 1, MAX_RUNS), ("seed", seed, 0, 2**32 - 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
            raise ConfigError(WHERE, field, v, f"must be an integer in [{lo}, {hi}]")
    if not (isinstance(level, (int, float)) and 0.5 <= level < 1):
        raise ConfigError(WHERE, "level", level, "must be a confidence level in [0.5, 1), e.g. 0.95")
    if target_precision is not None and not (isinstance(target_precision, (int, float)) and 0 < target_precision < 1):
        raise ConfigError(WHERE, "target_precision", target_precision, "must be a relative half-width in (0, 1)")
    if chunk is not None and (isinstance(chunk, (bool, np.bool_)) or not isinstance(chunk, (int, np.integer))
                              or chunk < 1):
        raise ConfigError(WHERE, "chunk", chunk, "must be None (the default) or an integer >= 1")
    if not isinstance(precision, str) or precision not in ("float64", "float32"):
        raise ConfigError(WHERE, "precision", precision, "must be float64 or float32")
    if not isinstance(scenario, Scenario):
        raise ConfigError(WHERE, "scenario", type(scenario).__name__, "must be a tracklab scenario (tracklab.scenarios; "
                          "Generated(truth, dt=…, steps=…, dim=…) for a truth function of one's own)")
    if not is_real(scenario.dt) or not (np.isfinite(scenario.dt) and scenario.dt > 0):
        raise ConfigError(WHERE, "scenario.dt", scenario.dt, "must be a finite number > 0")
    steps = scenario.steps
    if isinstance(steps, (bool, np.bool_)) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ConfigError(WHERE, "scenario.steps", steps, "must be an integer >= 1")
    why = scenario.problem()
    if why:
        raise ConfigError(WHERE, "scenario", type(scenario).__name__, why)
    if isinstance(scenario, Generated):  # structure by what its truth traces to
        scenario = scenario.keyed()
    dt, steps, dim = float(scenario.dt), int(scenario.steps), int(scenario.dim)
    if runs * steps > MAX_RUN_STEPS:
        raise ConfigError(WHERE, "runs", runs, f"runs x steps must be <= {MAX_RUN_STEPS:.0e}")
    suite = _suite(sensors, scenario)
    if prior is not None and not isinstance(prior, Mapping):
        raise ConfigError(WHERE, "prior", kind_of(prior), "must be None or a dict of pos_sigma, vel_sigma, acc_sigma "
                          "(numbers > 0)")
    prior = {"pos_sigma": 100.0, "vel_sigma": 10.0, "acc_sigma": 1.0} | dict(prior or {})
    for k, v in prior.items():
        if (k not in ("pos_sigma", "vel_sigma", "acc_sigma") or not is_real(v)
                or not np.isfinite(v) or v <= 0):
            raise ConfigError(WHERE, f"prior.{k}", v, "pos_sigma, vel_sigma, acc_sigma: numbers > 0")

    if filters is not None and not isinstance(filters, (list, tuple)):
        raise ConfigError(WHERE, "filters", type(filters).__name__, "must be a list of filters (FilterSpec, a "
                          "[[filter]] table as a dict, or a FilterConfig of a loaded experiment)")
    default_q = float(np.asarray(scenario.accel_sigma))
    entries, labels, trimmed = [], set(), set()
    for i, fc in enumerate(filters or [], start=1):
        where = f"filters[{i - 1}]"
        if isinstance(fc, dict):
            fc = parse_filter(WHERE, i, dict(fc), suite, dim, dt, default_q, scenario)
        elif isinstance(fc, Filter):
            raise ConfigError(WHERE, where, "Filter", "give it a label: tracklab.FilterSpec(label, filter)")
        elif isinstance(fc, FilterSpec):
            if fc.sensors and any(n not in {s.name for s in suite.sensors} for n in fc.sensors):
                raise ConfigError(WHERE, f"{where}.sensors", list(fc.sensors),
                                  f"must name sensors from: {', '.join(s.name for s in suite.sensors)}")
            why = fc.problem(scenario, suite)
            if why:
                raise ConfigError(WHERE, where, fc.label, f"the filter {why}")
            if fc.view is None and fc.code is None:  # structure by what it compiles to
                fc = fc.with_code(scenario, suite)
        elif not isinstance(fc, FilterConfig):
            raise ConfigError(WHERE, where, type(fc).__name__, "must be a FilterSpec, a [[filter]] table as a dict, "
                              "or a FilterConfig of a loaded experiment")
        check_unique(WHERE, f"{where}.label", fc.label, trimmed, "filters")
        labels.add(fc.label)
        entries.append(fc)
    if not entries:
        raise ConfigError(WHERE, "filters", filters, "must hold at least one filter")
    if baseline is not None and baseline not in labels:
        raise ConfigError(WHERE, "baseline", baseline, f"must be one of the filters' labels: {', '.join(sorted(labels))}")

    w = tuple(window) if isinstance(window, (list, tuple, np.ndarray)) else (1, steps) if window is None else ()
    if len(w) != 2 or not all(isinstance(v, (int, np.integer)) for v in w) or not 1 <= w[0] <= w[1] <= steps:
        raise ConfigError(WHERE, "window", window, f"must be (first, last) steps with 1 <= first <= last <= {steps}")
    if windows is not None and not isinstance(windows, Mapping):
        raise ConfigError(WHERE, "windows", kind_of(windows), 'must be None or a dict {name: [t0, t1] (seconds) or '
                          '"rest"}, as [report.windows] in a file')
    pred_windows = pred_windows_of(WHERE, dict(windows or {}), w, steps, dt)
    loss = _loss(track_loss, suite)
    raw = {
        "experiment": {"name": name, "runs": int(runs), "seed": int(seed), "dt": dt, "steps": steps,
                       "precision": precision, "built": "python"},
        "scenario": _describe(scenario),
        "sensor": [_describe(s) for s in suite.sensors],
        "prior": prior,
        "filter": [_filter_table(fc) for fc in entries],
        "report": {"window": list(w), **({"windows": {k: v for k, v in (windows or {}).items()}} if windows else {}),
                   "level": level, **({"baseline": baseline} if baseline else {})},
    }
    return Experiment(path=None, name=name, runs=int(runs), seed=int(seed), dt=dt, steps=steps, chunk=chunk,
                      scenario=scenario, sensor=suite, filters=entries, prior=prior, window=(int(w[0]), int(w[1])),
                      raw=raw, precision=precision, pred_windows=pred_windows, level=float(level), baseline=baseline,
                      target_precision=target_precision, track_loss=loss)


def _loss(track_loss, suite):
    """``track_loss`` as the experiment's test (``TrackLoss``), checked as a file's [track_loss]."""
    cluttered = cluttered_of(suite) is not None
    if track_loss is None:
        if cluttered:
            raise ConfigError(WHERE, "track_loss", None, "is required with a cluttered sensor: (distance, steps), a "
                              "track lost after `steps` consecutive steps with its position error beyond `distance`")
        return None
    allowed = "must be (distance > 0[, steps >= 1 (default 5)[, existence in (0, 1) (an IPDA's test)]])"
    t = tuple(track_loss) if isinstance(track_loss, (list, tuple)) else (track_loss,)
    distance, steps, existence = t + (None, 5, None)[len(t):] if len(t) in (1, 2, 3) else (None, None, None)
    if not is_real(distance) or not (np.isfinite(distance) and distance > 0):
        raise ConfigError(WHERE, "track_loss", track_loss, allowed)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ConfigError(WHERE, "track_loss", track_loss, allowed)
    if existence is not None and not (is_real(existence) and 0.0 < float(existence) < 1.0):
        raise ConfigError(WHERE, "track_loss", track_loss, allowed)
    return TrackLoss(float(distance), int(steps), None if existence is None else float(existence))


__all__ = ["experiment"]
