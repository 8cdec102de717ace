"""Reading open-loop tracking experiment files: ``[experiment]``, ``[scenario]``, ``[sensor]``
(or ``[[sensor]]``), ``[prior]``, ``[[filter]]``, ``[report]`` and ``[[study]]``.

Relative paths are resolved against the experiment file's folder.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np

from tracklab.config import factories
from tracklab.config.factories import is_factory
from tracklab.config.fields import (
    MAX_RUN_STEPS,
    MAX_RUNS,
    MAX_STEPS,
    NAME_RE,
    WINDOW_NAME_RE,
    Section,
    auto_runs,
    check_sections,
    check_unique,
    declared_numbers,
    experiment_header,
    level_and_baseline,
)
from tracklab.config.studies import parse_studies
from tracklab.errors import ConfigError, failure
from tracklab.filters.context import filter_context
from tracklab.filters.association import ASSOCIATION_FIELDS, associated, association_numbers
from tracklab.filters.core import Filter, trace_problem
from tracklab.filters.factory import declared
from tracklab.filters.fusion import view_of
from tracklab.filters.kind import Entry
from tracklab.filters.registry import KINDS
from tracklab.montecarlo.statistics import REPORT_WINDOW
from tracklab.report.figures import FIGURE_KINDS
from tracklab.scenarios import (
    SCENARIOS,
    Generated,
    MountFrame,
    Scenario,
    ScenarioContext,
)
from tracklab.sensors import (
    SENSOR_SIGMAS,
    SENSORS,
    Cluttered,
    CustomSensor,
    Sensor,
    SensorSuite,
)
from tracklab.sensors.clutter import cluttered_of
from tracklab.toml_fields import sigma_list
from tracklab.worlds.tracking.errors import TrackLoss
from tracklab.worlds.tracking.experiment import Experiment, FilterConfig
from tracklab.worlds.tracking.lanes import FilterSpec



def _multiple_of(value, dt, zero=True):
    """Whether ``value`` is a whole multiple of ``dt`` (0 allowed when ``zero``)."""
    n = value / dt
    return abs(n - round(n)) < 1e-6 and (round(n) >= 1 or zero and value == 0)


def _sensor_tables(f, raw):
    tables = raw["sensor"]
    if isinstance(tables, dict):
        return [("sensor", tables)]
    if isinstance(tables, list) and tables and all(isinstance(t, dict) for t in tables):
        return [(f"sensor[{i}]", t) for i, t in enumerate(tables, start=1)]
    raise ConfigError(f, "sensor", tables, "must be a [sensor] table or one or more [[sensor]] tables")


def _parse_sensors(f, raw):
    """First pass: kinds and names (the scenario's dimension may depend on them)."""
    out = []
    for where, table in _sensor_tables(f, raw):
        sn = Section(f, where, table)
        kind = sn.string("kind", required=True)
        if kind not in SENSORS and not is_factory(kind):
            raise ConfigError(f, f"{where}.kind", kind,
                              f"must be one of {', '.join(SENSORS)}, or \"package.module:factory\" (a sensor of one's own)")
        out.append((where, sn, kind))
    return out


def _build_sensors(f, parsed, dim, dt, steps, folders=()):
    sensors, names = [], set()
    for where, sn, kind in parsed:
        name = sn.string("name", kind.rpartition(":")[2])  # default: the kind (a factory: its name)
        if not NAME_RE.fullmatch(name):
            raise ConfigError(f, f"{where}.name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
        if name in names:
            raise ConfigError(f, f"{where}.name", name, "must be unique among the sensors")
        names.add(name)
        if is_factory(kind):
            sensors.append(_own_sensor(f, where, sn, kind, name, dim, dt, steps, folders))
            continue
        observes = SENSORS[kind].dim
        if observes is not None and observes != dim:
            hint = " (set scenario.altitude for a 3-D crossing)" if observes == 3 else " (remove scenario.altitude, or use a 3-D sensor)"
            raise ConfigError(f, f"{where}.kind", kind, f"observes {observes}-D positions but the scenario is {dim}-D{hint}")
        p_detect, period, offset = _timing(f, where, sn, dt)
        if kind == "cartesian":
            sigma = sigma_list(f, f"{where}.sigma", sn.get("sigma"), dim)
        else:
            sigma = tuple(declared_numbers(sn, SENSORS[kind].params).values())
        frame_dim = 2 if kind == "mount" else dim  # a mount observes its two angles
        sensor = Sensor(kind, frame_dim, sigma, p_detect, name=name, dt=dt, period=period, offset=offset)
        sensor = _clutter(f, where, sn, sensor)
        sn.check_unknown()
        if not sensor.report_mask(steps).any():
            raise ConfigError(f, f"{where}.offset", offset, f"the sensor reports at no step: the run ends at {steps * dt:g} s")
        sensors.append(sensor)
    cluttered = [(where, s) for (where, _, _), s in zip(parsed, sensors) if isinstance(s, Cluttered)]
    if cluttered and len(sensors) > 1:
        where, s = cluttered[0]
        raise ConfigError(f, f"{where}.clutter_density", float(np.asarray(s.density)), "clutter needs the experiment's only sensor: "
                          "several sensors with a cluttered one are not supported")
    return SensorSuite(tuple(sensors))


CLUTTER_FIELDS = ("clutter_density", "max_returns", "clutter_window", "clutter_coverage", "snr")


def _clutter(f, where, sn, sensor):
    """``sensor`` with the false alarms its table declares (``sensors.Cluttered``), or as it is:
    ``clutter_density`` (λ ≥ 0, per unit volume of the measurement space in the sensor's units),
    ``max_returns`` (the scan's capacity, default 16) and the region, either ``clutter_window``
    (half-widths about the target's measurement, one per component) or ``clutter_coverage``
    ([[lo, hi], …] per component: a fixed box); ``snr``, the target's mean SNR in dB, puts the
    returns in order of amplitude (a strongest neighbour needs it)."""
    if not any(sn.has(k) for k in CLUTTER_FIELDS):
        return sensor
    sensor = dataclasses.replace(sensor, misses=True)  # detections drawn at any p_detect: one program for all
    m = sensor.m
    density = sn.number("clutter_density", required=True, nonneg=True)
    capacity = sn.integer("max_returns", 16, lo=1, hi=1024)
    snr = sn.number("snr", None, lo=-30.0, hi=60.0)
    if sn.has("clutter_window") == sn.has("clutter_coverage"):
        raise ConfigError(f, f"{where}.clutter_window", sn.get("clutter_window"), "give the clutter's region, one of "
                          f"clutter_window = [{m} half-widths about the target] or clutter_coverage = [[lo, hi] x {m}], "
                          "not both")
    if sn.has("clutter_window"):
        window = sn.get("clutter_window")
        if not isinstance(window, list) and len(set(sensor.angle_mask)) > 1:  # metres and radians: one each
            raise ConfigError(f, f"{where}.clutter_window", window, f"must be {m} half-widths, one per component "
                              f"({', '.join(sensor.names)}): its components have different units")
        half = sigma_list(f, f"{where}.clutter_window", window, m)
        return _checked_clutter(f, where, Cluttered(sensor, density, half, None, capacity, snr))
    box = sn.get("clutter_coverage")
    sn.used.add("clutter_coverage")
    if (not isinstance(box, list) or len(box) != m
            or any(not isinstance(b, list) or len(b) != 2 or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                                                  or not math.isfinite(v) for v in b) or not b[0] < b[1]
                   for b in box)):
        raise ConfigError(f, f"{where}.clutter_coverage", box, f"must be [[lo, hi] x {m}] with lo < hi, one per "
                          f"component ({', '.join(sensor.names)})")
    lo, hi = np.asarray(box, float).T
    return _checked_clutter(f, where, Cluttered(sensor, density, tuple((hi - lo) / 2.0), tuple((hi + lo) / 2.0),
                                                capacity, snr))


def _checked_clutter(f, where, sensor: Cluttered) -> Cluttered:
    """``sensor`` if its region and capacity can be simulated faithfully (``Cluttered.problem``);
    else the field of the file to change, in one line."""
    why = sensor.problem()
    if why is None:
        return sensor
    name, value, allowed = why
    field = {"half_width": "clutter_coverage" if sensor.center is not None else "clutter_window",
             "coverage": "clutter_coverage", "density": "clutter_density"}.get(name, name)
    half = np.asarray(sensor.half_width, float)
    box = None if sensor.center is None else np.stack([np.asarray(sensor.center) - half, np.asarray(sensor.center) + half], 1)
    shown = {"clutter_window": half.tolist(), "max_returns": sensor.max_returns,
             "clutter_coverage": None if box is None else box.tolist(),
             "clutter_density": float(np.asarray(sensor.density))}[field]
    raise ConfigError(f, f"{where}.{field}", shown, allowed)


def _timing(f, where, sn, dt):
    """A sensor's p_detect, period and offset fields."""
    p_detect = sn.number("p_detect", 1.0)
    if not 0.0 < p_detect <= 1.0:
        raise ConfigError(f, f"{where}.p_detect", p_detect, "must be a probability in (0, 1]")
    period = sn.number("period", dt, positive=True)
    if not _multiple_of(period, dt, zero=False):
        raise ConfigError(f, f"{where}.period", period, f"must be a whole multiple (1, 2, …) of experiment.dt = {dt}")
    offset = sn.number("offset", 0.0, nonneg=True)
    if not _multiple_of(offset, dt):
        raise ConfigError(f, f"{where}.offset", offset, f"must be a whole multiple (0, 1, …) of experiment.dt = {dt}")
    return p_detect, period, offset


def _own_sensor(f, where, sn, kind, name, dim, dt, steps, folders=()):
    """A [sensor] whose kind names a factory: ``factory(Context(dt, steps, dim), **other keys)``
    returns a sensor (``tracklab.sensors.CustomSensor``, or a built-in ``Sensor``); the table's
    name, p_detect, period and offset apply to it."""
    p_detect, period, offset = _timing(f, where, sn, dt)
    options = {k: sn.get(k) for k in sn.table if k not in ("kind", "name", "p_detect", "period", "offset")
               + CLUTTER_FIELDS}
    sensor = factories.build(f, f"{where}.kind", kind, factories.Context(dt, steps, dim), options, folders)
    if not isinstance(sensor, (Sensor, CustomSensor)):
        raise ConfigError(f, f"{where}.kind", kind, f"the factory returned {type(sensor).__name__}: expected a "
                          "tracklab.sensors.CustomSensor(h, R, angles=…) or Sensor")
    if sensor.dim != dim:
        raise ConfigError(f, f"{where}.kind", kind, f"the factory's sensor observes {sensor.dim}-D positions, the scenario is {dim}-D")
    sensor = dataclasses.replace(sensor, name=name, dt=dt, period=period, offset=offset, p_detect=p_detect, misses=None)
    why = sensor.problem() if isinstance(sensor, CustomSensor) else None
    if why:
        raise ConfigError(f, f"{where}.kind", kind, f"the factory's sensor: {why}")
    if isinstance(sensor, CustomSensor):
        sensor = sensor.keyed()
    sensor = _clutter(f, where, sn, sensor)
    if not sensor.report_mask(steps).any():
        raise ConfigError(f, f"{where}.offset", offset, f"the sensor reports at no step: the run ends at {steps * dt:g} s")
    return sensor


def _own_scenario(f, sc, kind, dt, steps, dim, folders=()):
    """A [scenario] whose kind names a factory: ``factory(Context(dt, steps, dim), **other keys)``
    returns a scenario, or a function of a run's key giving its truth (steps + 1, 2·dim)."""
    options = {k: sc.get(k) for k in sc.table if k != "kind"}
    made = factories.build(f, "scenario.kind", kind, factories.Context(dt, steps, dim), options, folders)
    if callable(made) and not isinstance(made, Scenario):
        made = _generated(f, kind, made, dt, steps)
    if not isinstance(made, Scenario):
        raise ConfigError(f, "scenario.kind", kind, f"the factory returned {type(made).__name__}: expected a scenario "
                          "(tracklab.scenarios) or a function of a run's key giving its truth (steps + 1, 2·dim)")
    if made.dt != dt or made.steps != steps:
        raise ConfigError(f, "scenario.kind", kind, f"the factory's scenario has dt = {made.dt}, steps = {made.steps}: "
                          f"the experiment has {dt}, {steps}")
    why = made.problem()
    if why:
        raise ConfigError(f, "scenario.kind", kind, f"the factory's scenario: {why}")
    return made.keyed() if isinstance(made, Generated) else made


def _generated(f, kind, fn, dt, steps):
    """A truth function as a ``Generated`` scenario, its dimension read from its output's shape."""
    try:
        with jax.enable_x64(True):
            shape = jax.eval_shape(fn, jax.random.key(0)).shape
    except BaseException as e:  # noqa: BLE001 - the user's function: any error, a sys.exit too
        if isinstance(e, KeyboardInterrupt):
            raise
        raise ConfigError(f, "scenario.kind", kind, f"the factory's truth(key) fails: {failure(e)}") from None
    if len(shape) != 2 or shape[1] not in (2, 4, 6):
        raise ConfigError(f, "scenario.kind", kind, f"the factory's truth(key) gives shape {shape}: expected "
                          f"({steps + 1}, 2·dim) rows of [x, ẋ, y, ẏ(, z, ż)]")
    return Generated(fn, dt=dt, steps=steps, dim=shape[1] // 2)


class _Fields:
    """A [scenario] table's fields as a scenario kind's ``build`` reads them: typed, one-line refusals
    (a key with a dot names another section's field)."""

    def __init__(self, section: Section):
        self.section = section
        self.get, self.has, self.number, self.integer, self.string = (section.get, section.has, section.number,
                                                                      section.integer, section.string)

    def error(self, key, value, allowed) -> ConfigError:
        return ConfigError(self.section.file, key if "." in key else f"scenario.{key}", value, allowed)

    def table(self, where, table) -> Section:
        return Section(self.section.file, f"scenario.{where}", table)


def parse_tracking(path: Path, raw: dict) -> Experiment:
    """Validate an open-loop experiment file's contents ``raw`` read from ``path``."""
    f = path = Path(path)
    check_sections(f, raw, ("experiment", "scenario", "sensor"),
                   ("experiment", "scenario", "sensor", "filter", "prior", "report", "study", "track_loss"))
    name, runs, seed, precision, ex = experiment_header(f, raw)
    max_runs, target = auto_runs(ex)
    runs = runs or max_runs
    dt = ex.number("dt", required=True, positive=True)
    if not 1e-6 <= dt <= 1e6:
        raise ConfigError(f, "experiment.dt", dt, "must be a period in [1e-06, 1e+06] s")
    steps = ex.integer("steps", required=True, lo=1, hi=MAX_STEPS)
    if target is not None and not ex.has("max_runs"):
        runs = max(2, min(runs, MAX_RUN_STEPS // steps))
    if runs * steps > MAX_RUN_STEPS:
        raise ConfigError(f, "experiment.runs", runs, f"runs x steps must be <= {MAX_RUN_STEPS:.0e}")
    chunk = ex.integer("chunk", None, lo=1, hi=1_000_000)
    also = ex.get("also_runs", [])  # extra run counts `tracklab reproduce` writes, e.g. a paper's own
    if not isinstance(also, list) or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_RUNS for v in also):
        raise ConfigError(f, "experiment.also_runs", also, f"must be a list of run counts in [1, {MAX_RUNS}]")
    folders = factories.python_path(f, ex.get("pythonpath"))  # where plug-in modules are imported from
    ex.check_unknown()

    parsed_sensors = _parse_sensors(f, raw)
    fixed_dims = {SENSORS[k].dim for _, _, k in parsed_sensors if k in SENSORS and SENSORS[k].dim is not None}
    sensor_dim = fixed_dims.pop() if len(fixed_dims) == 1 else None
    if len(fixed_dims) > 0:
        raise ConfigError(f, "[[sensor]]", "...", "all sensors must observe positions of the same dimension")

    sc = Section(f, "scenario", raw["scenario"])
    kind = sc.string("kind", required=True)
    if kind not in SCENARIOS and not is_factory(kind):
        raise ConfigError(f, "scenario.kind", kind,
                          f"must be one of {', '.join(SCENARIOS)}, or \"package.module:factory\" (a truth of one's own)")
    if is_factory(kind):
        scenario = _own_scenario(f, sc, kind, dt, steps, sensor_dim, folders)
    else:
        declared = SCENARIOS[kind]
        scenario = declared.build(ScenarioContext(dt, steps, sensor_dim, path.parent), declared_numbers(sc, declared.params),
                                  _Fields(sc))
    sc.check_unknown()
    dim = scenario.dim
    suite = _build_sensors(f, parsed_sensors, dim, dt, steps, folders)
    mounts = [s.kind == "mount" for s in suite.sensors]
    if any(mounts):  # angle tracking: the truth in the mount frame, filters on [az, el] (deg)
        if not all(mounts):
            raise ConfigError(f, "[[sensor]]", "mount", "a mount cannot share an experiment with sensors of other kinds")
        scenario = MountFrame(scenario)
        dim = scenario.dim

    pr = Section(f, "prior", raw.get("prior", {}))
    angular = any(mounts)  # in the mount frame the prior is in deg, deg/s, deg/s²
    prior = {
        "pos_sigma": pr.number("pos_sigma", 0.1 if angular else 100.0, positive=True),
        "vel_sigma": pr.number("vel_sigma", 1.0 if angular else 10.0, positive=True),
        "acc_sigma": pr.number("acc_sigma", 1.0, positive=True),
    }
    pr.check_unknown()

    flist = raw.get("filter")
    if not isinstance(flist, list) or not flist:
        raise ConfigError(f, "[[filter]]", flist, "at least one [[filter]] table is required")
    filters, labels, trimmed = [], set(), set()
    default_q = scenario.accel_sigma
    for i, table in enumerate(flist, start=1):
        fc = parse_filter(f, i, table, suite, dim, dt, default_q, scenario, folders)
        check_unique(f, f"filter[{i}].label", fc.label, trimmed, "filters")
        labels.add(fc.label)
        filters.append(fc)

    loss = _track_loss(f, raw, suite)
    if loss is not None and loss.existence is not None and not any(t.get("kind") == "ipda" for t in flist):
        raise ConfigError(f, "track_loss.existence", loss.existence, "tests an existence probability, which no filter "
                          "here reports: it needs a kind = \"ipda\" filter (or leave it out)")

    rp = Section(f, "report", raw.get("report", {}))
    w = rp.get("window", [1, steps])
    if (
        not isinstance(w, list)
        or len(w) != 2
        or any(isinstance(v, bool) or not isinstance(v, int) for v in w)
        or not (1 <= w[0] <= w[1] <= steps)
    ):
        raise ConfigError(f, "report.window", w, f"must be [first, last] steps with 1 <= first <= last <= {steps}")
    pred_windows = pred_windows_of(f, rp.get("windows", {}), (w[0], w[1]), steps, dt)
    level, baseline = level_and_baseline(rp, labels)
    _figure_kinds(f, rp)
    rp.check_unknown()
    studies = parse_studies(f, raw.get("study"), filters)

    return Experiment(
        path=path, name=name, runs=runs, seed=seed, dt=dt, steps=steps, chunk=chunk, scenario=scenario,
        sensor=suite, filters=filters, prior=prior, window=(w[0], w[1]), raw=raw, also_runs=tuple(also), precision=precision,
        pred_windows=pred_windows, studies=studies, level=level, baseline=baseline, target_precision=target,
        track_loss=loss,
    )


def _track_loss(f, raw, suite):
    """[track_loss]: distance (in the scenario's position unit) and steps (default 5): a run's track is
    lost at the first of ``steps`` consecutive steps whose position error is beyond ``distance``, or
    (``existence``, optional) whose reported existence probability (IPDA) is below it.
    Required with a cluttered sensor; None when the file has none."""
    cluttered = cluttered_of(suite) is not None
    if "track_loss" not in raw:
        if cluttered:
            raise ConfigError(f, "[track_loss]", None, "is required with a cluttered sensor: distance = … (a track is "
                              "lost after `steps` consecutive steps, default 5, with its position error beyond it)")
        return None
    if not isinstance(raw["track_loss"], dict):
        raise ConfigError(f, "track_loss", raw["track_loss"], "must be a table: [track_loss] distance = …, steps = …")
    tl = Section(f, "track_loss", raw["track_loss"])
    existence = tl.number("existence", None)
    if existence is not None and not 0.0 < existence < 1.0:
        raise ConfigError(f, "track_loss.existence", existence, "must be a probability in (0, 1)")
    loss = TrackLoss(tl.number("distance", required=True, positive=True), tl.integer("steps", 5, lo=1, hi=MAX_STEPS),
                     existence)
    tl.check_unknown()
    return loss


def _figure_kinds(f, rp):
    """[report] figures = ["rmse", "nees", …]: the figure kinds a run draws (default: every one)."""
    kinds = rp.get("figures")
    if kinds is None:
        return
    if (not isinstance(kinds, list) or any(not isinstance(k, str) or k not in FIGURE_KINDS for k in kinds)
            or len(set(kinds)) != len(kinds)):
        raise ConfigError(f, "report.figures", kinds, f"must be a list of distinct figure kinds: {', '.join(FIGURE_KINDS)}")


def pred_windows_of(f, table, window, steps, dt):
    """[report.windows]: name = [t0, t1] (s, inclusive) or "rest" -> (steps,) step masks.

    "rest" is the report window's steps outside every other named window. The
    report window itself is always included, under ``REPORT_WINDOW``.
    """
    k = np.arange(1, steps + 1)
    report = (k >= window[0]) & (k <= window[1])
    if not isinstance(table, dict):
        raise ConfigError(f, "report.windows", table, 'must be a table: name = [t0, t1] (seconds) or "rest"')
    out, rest = {}, []
    t = dt * k
    for name, v in table.items():
        field_name = f"report.windows.{name}"
        if not WINDOW_NAME_RE.fullmatch(name) or name == REPORT_WINDOW:
            raise ConfigError(f, field_name, name, f"window names are 1-40 letters, digits, spaces, '_.+-' (not {REPORT_WINDOW!r})")
        if v == "rest":
            rest.append(name)
            continue
        if (
            not isinstance(v, list) or len(v) != 2
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)
            or not v[0] <= v[1]
        ):
            raise ConfigError(f, field_name, v, 'must be [t0, t1] in seconds with t0 <= t1, or "rest"')
        mask = (t >= v[0] - 1e-9 * dt) & (t <= v[1] + 1e-9 * dt)
        if not mask.any():
            raise ConfigError(f, field_name, v, f"holds no step: steps are at t = k*{dt} s, k = 1..{steps}")
        out[name] = mask
    if len(rest) > 1:
        raise ConfigError(f, f"report.windows.{rest[1]}", "rest", 'only one window can be "rest"')
    if rest:
        mask = report & ~np.any([m for m in out.values()] or [np.zeros(steps, bool)], axis=0)
        if not mask.any():
            raise ConfigError(f, f"report.windows.{rest[0]}", "rest", "holds no step of the report window")
        out[rest[0]] = mask
    return {REPORT_WINDOW: report} | out


def _seen(f, where, fs, suite, default=None):
    """The sensor names a filter's ``sensors`` field gives (default: ``default``, else all)."""
    all_names = tuple(s.name for s in suite.sensors)
    names = fs.get("sensors", list(all_names if default is None else default))
    if not isinstance(names, list) or not names or any(not isinstance(n, str) or n not in all_names for n in names):
        raise ConfigError(f, f"{where}.sensors", names, f"must be a list of sensor names from: {', '.join(all_names)}")
    return tuple(dict.fromkeys(names))


def _own_filter(f, i, fs, spec, suite, scenario, folders=(), rule=None):
    """A [[filter]] whose kind names a factory: ``factory(FilterContext, **the table's other keys)``
    returns a ``Filter`` (its ``layout`` saying where position and velocity sit in its state). The
    numbers the factory declares (``tracklab.declare``) are checked against their declarations
    here and go into the filter's params; the filter is then structure by what it compiles to
    (``FilterSpec.with_code``). With ``rule`` ("nn", "pdaf", "ipda": a table ``kind = "pdaf"``,
    ``base = "module:factory"``) the factory's filter is the base of that association, whose numbers
    (gate, p_detect, …) the table holds beside the factory's."""
    field = "kind" if rule is None else "base"
    label = fs.label("label", spec.rpartition(":")[2] if rule is None else rule)
    names = _seen(f, f"filter[{i}]", fs, suite)
    own_keys = ("kind", "label", "sensors") + (ASSOCIATION_FIELDS if rule else ())
    options = {k: fs.get(k) for k in fs.table if k not in own_keys}
    context = filter_context(scenario, suite.subset(names))
    factory = factories.load_factory(f, f"filter[{i}].{field}", spec, folders)
    params = declared(factory)
    for name in params:
        try:
            default = params[name].value(context)
        except BaseException as e:  # noqa: BLE001 - the user's default: any error, a sys.exit too
            if isinstance(e, KeyboardInterrupt):
                raise
            raise ConfigError(f, f"filter[{i}].{name}", None, f"its declared default fails: {failure(e)}") from None
        why = factory.problem(name, options.get(name, default), default)
        if why and name in options:
            raise ConfigError(f, f"filter[{i}].{name}", options[name], why)
        if why:
            shown = None if default is None else np.asarray(default).tolist()
            raise ConfigError(f, f"filter[{i}].{name}", None, f"its declared default ({shown}, from the experiment) "
                              f"{why.removeprefix('is ')}: give it in the table")
    flt = factories.call_factory(f, f"filter[{i}].{field}", spec, factory, context, options)
    if not isinstance(flt, Filter):
        raise ConfigError(f, f"filter[{i}].{field}", spec, f"the factory returned {type(flt).__name__}: expected a "
                          "tracklab.filters.Filter(init, step, params)")
    sensors = names if names != tuple(s.name for s in suite.sensors) else ()
    if rule is not None:  # the base sees one return at a time; the association, the scans
        kind = KINDS[rule]
        seen = suite.subset(names)
        base = FilterSpec(label, flt, kind=spec, sensors=sensors, declared=params)
        why = trace_problem(flt, base.report_layout(scenario.dim).n, seen.m)
        if why:
            raise ConfigError(f, f"filter[{i}].base", spec, f"the factory's filter {why}")
        numbers = association_numbers(Entry(fs, kind, seen, dim=scenario.dim, dt=scenario.dt, accel_sigma=0.0,
                                            sigma_fields=()), rule)
        try:
            flt = associated(flt, rule, numbers, seen.m)
        except TypeError as e:
            raise ConfigError(f, f"filter[{i}].base", spec, f"the factory's filter: {e}") from None
        params = {**params, **{n: kind.params[n] for n in numbers}}
        spec = f"{rule} of {spec}"
    own = FilterSpec(label, flt, kind=spec, sensors=sensors, declared=params)
    why = own.problem(scenario, suite)
    if why:
        raise ConfigError(f, f"filter[{i}].{field}", spec, f"the factory's filter {why}")
    return own.with_code(scenario, suite)


def parse_filter(f, i, table, suite: SensorSuite, dim, dt, default_q, scenario=None, folders=()) -> FilterConfig:
    """One [[filter]] table: its kind, label and what it sees (the sensors, a guide, a fusion), checked
    against the sensor kinds the kind accepts; then the kind's own fields (its declaration's ``read``)."""
    fs = Section(f, f"filter[{i}]", table)
    name = fs.string("kind", required=True)
    if is_factory(name):
        return _own_filter(f, i, fs, name, suite, scenario, folders)
    if name in KINDS and KINDS[name].scans and is_factory(fs.get("base")):  # an association over one's own filter
        return _own_filter(f, i, fs, fs.string("base"), suite, scenario, folders, rule=name)
    if name not in KINDS:
        raise ConfigError(f, f"filter[{i}].kind", name,
                          f"must be one of {', '.join(KINDS)}, or \"package.module:factory\" (a filter of one's own)")
    kind = KINDS[name]
    label = fs.label("label", kind.name)

    # what the filter sees
    all_names = tuple(s.name for s in suite.sensors)
    guide = fs.string("guide", "previous") if kind.guided else "previous"
    if guide != "previous" and guide not in all_names:
        raise ConfigError(f, f"filter[{i}].guide", guide, f"must be \"previous\" or a sensor name from: {', '.join(all_names)}")
    names = _seen(f, f"filter[{i}]", fs, suite, [n for n in all_names if n != guide])
    fusion = fs.string("fusion", None, choices=("interpolate", "none"))
    if fusion is not None:
        kinds = sorted(s.kind for s in suite.subset(names).sensors)
        if kinds != ["angles", "spherical"]:
            raise ConfigError(f, f"filter[{i}].fusion", fusion, "needs exactly one 'spherical' (laser) and one 'angles' (infrared) sensor among filter.sensors")
        ir = next(s for s in suite.subset(names).sensors if s.kind == "angles")
        if ir.p_detect < 1.0:
            raise ConfigError(f, f"filter[{i}].fusion", fusion, "registration needs every infrared report: set its p_detect = 1")
    _, meas = view_of(suite, names, fusion)
    mkind = meas.kind
    guide_sensor = None
    if kind.guided:
        if len(names) != 1 or guide in names:
            raise ConfigError(f, f"filter[{i}].sensors", list(names), f"{kind.name} observes one sensor (its guide is set by 'guide')")
        if guide != "previous":
            guide_sensor = suite.subset((guide,)).sensors[0]
            if guide_sensor.kind != mkind or guide_sensor.m != meas.m:
                raise ConfigError(f, f"filter[{i}].guide", guide, f"the guide sensor must be of the observed sensor's kind ({mkind})")
    if mkind not in kind.accepts:
        seen = "several sensors" if mkind == "suite" else f"a '{mkind}' sensor"
        raise ConfigError(f, f"filter[{i}].kind", kind.name, f"needs a sensor of kind {' or '.join(kind.accepts)}, but sees {seen}")

    if cluttered_of(meas) is not None and not kind.scans:
        raise ConfigError(f, f"filter[{i}].kind", kind.name, "sees a cluttered sensor's scans: name an association, "
                          f"kind = \"pdaf\" (or \"nn\", \"snf\", \"ipda\") with base = \"{kind.name}\"")
    entry = Entry(fs, kind, meas, dim=dim, dt=dt, accel_sigma=default_q, sigma_fields=SENSOR_SIGMAS.get(mkind, ()),
                  guide=guide_sensor)
    model, params, options = kind.read(entry)
    if kind.guided:
        options = {"guide": guide, **options}
    fs.check_unknown()
    return FilterConfig(label, kind.name, model, params, options, names if names != all_names else (), fusion)
