"""Experiment files (TOML) -> validated experiments.

Everything is checked before anything is compiled; a bad field raises
``ConfigError`` whose message is one line: file, field, value, what is allowed.
Relative paths are resolved against the experiment file's folder.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tracklab.errors import ConfigError
from tracklab.filters.fusion import view_of as _view
from tracklab.filters.kind import Entry
from tracklab.filters.registry import KINDS, scales
from tracklab.metrics import REPORT_WINDOW
from tracklab.scenarios import (ConstantVelocity, Crossing, MountFrame, Overflight, Sine, Trajectory, TrajectoryError,
                                 read_csv)
from tracklab.sensors import SENSOR_KINDS, Sensor, SensorSuite
from tracklab.studies import parse_studies
from tracklab.toml_fields import MAX_MAGNITUDE, sigma_list as _sigma_list

MAX_RUNS = 100_000_000
MAX_STEPS = 1_000_000
MAX_RUN_STEPS = 10**12
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")

SENSOR_SIGMAS = {
    "polar": ("sigma_r", "sigma_angle"),
    "spherical": ("sigma_r", "sigma_az", "sigma_el"),
    "angles": ("sigma_az", "sigma_el"),
    "cartesian": ("sigma",),
    "mount": ("sigma_az", "sigma_el"),
}
SENSOR_DIM = {"polar": 2, "spherical": 3, "angles": 3, "mount": 3}  # dimension of the truth they observe
WINDOW_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9 _.+-]{0,39}")


class _Section:
    """Typed access to one TOML table that remembers which keys were read."""

    def __init__(self, file, name, table):
        self.file, self.name, self.table = file, name, table
        if not isinstance(table, dict):
            raise ConfigError(file, name, table, "must be a TOML table")
        self.used: set[str] = set()

    def _err(self, key, value, allowed):
        return ConfigError(self.file, f"{self.name}.{key}", value, allowed)

    def get(self, key, default=None):
        self.used.add(key)
        return self.table.get(key, default)

    def has(self, key):
        return key in self.table

    def number(self, key, default=None, *, positive=False, nonneg=False, lo=None, hi=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required or default is None:
                if required:
                    raise self._err(key, None, "is required (a number)")
                return None
            return float(default)
        v = self.table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self._err(key, v, "must be a number")
        v = float(v)
        if not math.isfinite(v) or abs(v) > MAX_MAGNITUDE:
            raise self._err(key, v, f"must be a finite number of magnitude <= {MAX_MAGNITUDE:g}")
        if positive and v <= 0:
            raise self._err(key, v, "must be a number > 0")
        if nonneg and v < 0:
            raise self._err(key, v, "must be a number >= 0")
        if lo is not None and v < lo or hi is not None and v > hi:
            raise self._err(key, v, f"must be in [{lo}, {hi}]")
        return v

    def integer(self, key, default=None, *, lo=None, hi=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required:
                raise self._err(key, None, "is required (an integer)")
            return default
        v = self.table[key]
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._err(key, v, "must be an integer")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self._err(key, v, f"must be an integer in [{lo}, {hi}]")
        return v

    def string(self, key, default=None, *, choices=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required:
                allowed = f"one of {', '.join(choices)}" if choices else "a string"
                raise self._err(key, None, f"is required ({allowed})")
            return default
        v = self.table[key]
        if not isinstance(v, str):
            raise self._err(key, v, "must be a string")
        if choices is not None and v not in choices:
            raise self._err(key, v, f"must be one of {', '.join(choices)}")
        return v

    def label(self, key, default):
        """A label tables show: non-blank, one line, at most 100 characters."""
        v = self.string(key, default)
        if not v.strip() or len(v) > 100 or any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise self._err(key, v, "must not be empty or only spaces (1-100 characters on one line)")
        return v

    def check_unknown(self, extra=()):
        unknown = sorted(set(self.table) - self.used - set(extra))
        if unknown:
            k = unknown[0]
            allowed = ", ".join(sorted(self.used | set(extra)))
            raise self._err(k, self.table[k], f"unknown field (allowed here: {allowed})")


@dataclass(frozen=True)
class FilterConfig:
    label: str
    kind: str
    model: str
    params: dict  # name -> float or tuple (the filter's parameter pytree, as numbers)
    options: dict = field(default_factory=dict)
    sensors: tuple[str, ...] = ()  # which sensors the filter sees (all when empty)
    fusion: str | None = None  # "interpolate" | "none": laser + infrared fusion view


@dataclass
class Experiment:
    """A validated experiment: everything ``tracklab run`` needs."""

    path: Path
    name: str
    runs: int
    seed: int
    dt: float
    steps: int
    chunk: int | None
    scenario: Any
    sensor: SensorSuite
    filters: list[FilterConfig]
    prior: dict[str, float]
    window: tuple[int, int]
    raw: dict
    also_runs: tuple[int, ...] = ()
    precision: str = "float64"
    pred_windows: dict = field(default_factory=dict)  # name -> (steps,) bool mask, report window included
    studies: list = field(default_factory=list)  # [[study]]: tuning and sweeps `tracklab reproduce` rebuilds

    @property
    def dim(self) -> int:
        return self.scenario.dim

    def prior_covariance(self) -> np.ndarray:
        d = self.dim
        return np.diag([self.prior["pos_sigma"] ** 2, self.prior["vel_sigma"] ** 2] * d)

    def declared(self, fc: FilterConfig):
        """A [[filter]] as the tracking world's structure holds it."""
        from tracklab.worlds.tracking import DeclaredFilter, hashable

        return DeclaredFilter(fc.label, fc.kind, fc.model, hashable(fc.options), tuple(fc.sensors), fc.fusion)

    def view(self, fc: FilterConfig):
        """(view function or None, measurement model) of what a filter sees."""
        return self.declared(fc).sees(self.sensor)

    def structure(self, chunk=None, elementwise=True):
        """What the compiled program depends on: the filters' kinds, models, options and views,
        the report windows and the chunk size (never the run count, nor any number)."""
        from tracklab.worlds.tracking import TrackingStructure, default_chunk, windows_of

        lanes = tuple(self.declared(fc) for fc in self.filters)
        chunk = int(chunk or self.chunk or default_chunk(self.scenario, self.sensor))
        return TrackingStructure(lanes, windows_of(self.pred_windows), chunk, elementwise)

    def params(self):
        """Every number of the experiment, as the compiled program's argument."""
        from tracklab.worlds.tracking import TrackingParams

        filters = [{k: np.asarray(v, float) for k, v in fc.params.items()} for fc in self.filters]
        return TrackingParams(self.scenario, self.sensor, self.prior_covariance(), self.prior["acc_sigma"] ** 2, filters)

    def filter_specs(self):
        """The experiment's filters built with its numbers, as ``FilterSpec``s: to run one on
        measurements of one's own (``run_filter``) or in ``tracklab.monte_carlo``."""
        import jax.numpy as jnp

        from tracklab.worlds.tracking import FilterSpec

        structure, params = self.structure(), self.params()
        specs = []
        for f, p in zip(structure.filters, params.filters):
            p = {k: jnp.asarray(v) for k, v in p.items()}
            r = f.realise(params.scenario, params.sensor, p, params.prior_extra_var)
            specs.append(FilterSpec(f.label, f.kind, r.filter, r.model, r.prior_extra_var, r.view))
        return specs

    # what a sweep plots: (summary key, title)
    sweep_metrics = (("rmse_pos", "time-averaged position RMSE ({pos})"), ("nees", "average NEES"),
                     ("pred_err_rms", "RMS one-step prediction error ({pos})"))

    def world(self, structure):
        from tracklab.worlds import tracking

        return tracking.world(structure)

    def scaled(self, params, factors: dict):
        """``params`` with every filter's parameters named in ``factors`` multiplied by them."""
        return params._replace(filters=[{k: (v * factors[k] if k in factors and scales(fc.kind, p, k) else v)
                                         for k, v in p.items()} for fc, p in zip(self.filters, params.filters)])

    def summarise(self, structure, params, sums, out) -> dict:
        """The statistics document of one parameter set's sums (the runner's ``out``)."""
        from tracklab.metrics import statistics
        from tracklab.worlds import tracking

        return statistics(tracking.result(structure, params, sums, out), self.window, self.pred_windows)

    @property
    def units(self):
        return tuple(getattr(self.scenario, "units", ("m", "m/s")))

    def monte_carlo(self, runs=None, seed=None, progress=None, chunk=None, precision=None):
        from tracklab.worlds import tracking

        return tracking.run(self.structure(chunk), self.params(), runs or self.runs, self.seed if seed is None else seed,
                            progress=progress, precision=precision or self.precision)

    def memory_bytes(self, runs=None, chunk=None) -> float:
        """A lower bound on the bytes a run needs: one chunk's random draws (float32) for every
        step, and each filter's per-step statistics on the host."""
        chunk = self.structure(chunk).chunk
        width = 2 * self.dim + self.sensor.m
        return chunk * self.steps * width * 4.0 + len(self.filters) * self.steps * 64 * 8.0

    def check_memory(self, runs=None, limit=None):
        from tracklab.memory import check

        check(self.path, self.memory_bytes(runs), limit, f"a chunk of runs x {self.steps} steps",
              "set a smaller experiment.chunk, or fewer experiment.steps")

    def run(self, runs=None, seed=None, out=None, progress=None, figures=True, precision=None, max_memory=None):
        """Run and write the results folder; returns the statistics dictionary.

        The output folder and the memory need are checked before anything compiles."""
        from tracklab.output import atomic_folder, check_results_folder
        from tracklab.report import results_path, write_results

        out = check_results_folder(results_path(self, out), self.path)
        self.check_memory(runs, max_memory)
        res = self.monte_carlo(runs=runs, seed=seed, progress=progress, precision=precision)
        with atomic_folder(out, self.path) as tmp:
            return write_results(self, res, tmp, figures=figures)


def _read_toml(path: Path):
    if not path.is_file():
        raise ConfigError(path, "file", str(path), "experiment file does not exist")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "file", "", f"is not valid TOML ({e})") from None
    except RecursionError:
        raise ConfigError(path, "file", "", "is nested too deeply (arrays or tables within each other)") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(path, "file", "", f"cannot be read ({e.__class__.__name__})") from None


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
        sn = _Section(f, where, table)
        kind = sn.string("kind", required=True, choices=tuple(SENSOR_KINDS))
        out.append((where, sn, kind))
    return out


def _build_sensors(f, parsed, dim, dt, steps):
    sensors, names = [], set()
    for where, sn, kind in parsed:
        name = sn.string("name", kind)
        if not NAME_RE.fullmatch(name):
            raise ConfigError(f, f"{where}.name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
        if name in names:
            raise ConfigError(f, f"{where}.name", name, "must be unique among the sensors")
        names.add(name)
        if SENSOR_DIM.get(kind, dim) != dim:
            hint = " (set scenario.altitude for a 3-D crossing)" if SENSOR_DIM[kind] == 3 else " (remove scenario.altitude, or use a 3-D sensor)"
            raise ConfigError(f, f"{where}.kind", kind, f"observes {SENSOR_DIM[kind]}-D positions but the scenario is {dim}-D{hint}")
        p_detect = sn.number("p_detect", 1.0)
        if not 0.0 < p_detect <= 1.0:
            raise ConfigError(f, f"{where}.p_detect", p_detect, "must be a probability in (0, 1]")
        period = sn.number("period", dt, positive=True)
        if not _multiple_of(period, dt, zero=False):
            raise ConfigError(f, f"{where}.period", period, f"must be a whole multiple (1, 2, …) of experiment.dt = {dt}")
        offset = sn.number("offset", 0.0, nonneg=True)
        if not _multiple_of(offset, dt):
            raise ConfigError(f, f"{where}.offset", offset, f"must be a whole multiple (0, 1, …) of experiment.dt = {dt}")
        if kind == "cartesian":
            sigma = _sigma_list(f, f"{where}.sigma", sn.get("sigma"), dim)
        else:
            sigma = tuple(sn.number(k, required=True, positive=True) for k in SENSOR_SIGMAS[kind])
        sn.check_unknown()
        frame_dim = 2 if kind == "mount" else dim  # a mount observes its two angles
        sensor = Sensor(kind, frame_dim, sigma, p_detect, name=name, dt=dt, period=period, offset=offset)
        if not sensor.report_mask(steps).any():
            raise ConfigError(f, f"{where}.offset", offset, f"the sensor reports at no step: the run ends at {steps * dt:g} s")
        sensors.append(sensor)
    return SensorSuite(tuple(sensors))


def dump_toml(doc: dict) -> str:
    """A TOML text for the shapes experiment files use (tables, arrays of tables, scalars, lists)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, np.integer)):
            return str(int(v))
        if isinstance(v, (float, np.floating)):
            return repr(float(v))
        if isinstance(v, str):
            return json.dumps(v, ensure_ascii=False)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    def key(k):
        return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k, ensure_ascii=False)

    def table(name, t, out):
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict) and not _is_table_list(v)}
        out.append(f"[{name}]")
        out += [f"{key(k)} = {value(v)}" for k, v in scalars.items()]
        out.append("")
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{name}.{key(k)}", v, out)

    out = []
    for k, v in doc.items():
        if isinstance(v, dict):
            table(k, v, out)
        elif _is_table_list(v):
            for item in v:
                out.append(f"[[{k}]]")
                out += [f"{key(kk)} = {value(vv)}" for kk, vv in item.items()]
                out.append("")
        else:
            out.insert(0, f"{k} = {value(v)}")
    return "\n".join(out)


def _is_table_list(v):
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def check_sections(f, raw, required, allowed, kind=None):
    """The file's top-level tables: each required one present, none outside ``allowed``.

    ``kind`` ("a servo experiment", …) names the kind of file in the messages.
    """
    where = f" in {kind}" if kind else ""
    for sec in required:
        if sec not in raw:
            raise ConfigError(f, f"[{sec}]", None, f"section is required{where}")
    unknown = sorted(set(raw) - set(allowed))
    if unknown:
        raise ConfigError(f, f"[{unknown[0]}]", "...", f"unknown section{where} (allowed: {', '.join(allowed)})")


def experiment_header(f, raw, section=None):
    """[experiment]'s name, runs, seed, precision (and description) -> (name, runs, seed, precision, section)."""
    ex = (section or _Section)(f, "experiment", raw["experiment"])
    name = ex.string("name", required=True)
    if not NAME_RE.fullmatch(name):
        raise ConfigError(f, "experiment.name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
    runs = ex.integer("runs", required=True, lo=1, hi=MAX_RUNS)
    seed = ex.integer("seed", 0, lo=0, hi=2**32 - 1)
    precision = ex.string("precision", "float64", choices=("float64", "float32"))
    ex.string("description")
    return name, runs, seed, precision, ex


def load_experiment(path) -> Experiment:
    """Read and validate an experiment file (any kind: open loop, airborne, servo)."""
    path = Path(path)
    return parse_experiment(path, _read_toml(path))


def parse_experiment(path: Path, raw: dict):
    """Validate an experiment file's contents ``raw`` (its TOML as a dictionary) read from ``path``."""
    f = path = Path(path)
    if isinstance(raw, dict) and "servo" in raw:  # a closed-loop servo experiment (paper 003)
        from tracklab.servo.experiment import load_servo_experiment

        return load_servo_experiment(path, raw, _Section)
    if isinstance(raw, dict) and "airborne" in raw:  # a closed-loop airborne-radar experiment (paper 001)
        from tracklab.airborne.experiment import load_airborne_experiment

        return load_airborne_experiment(path, raw, _Section)
    check_sections(f, raw, ("experiment", "scenario", "sensor"),
                   ("experiment", "scenario", "sensor", "filter", "prior", "report", "study"))
    name, runs, seed, precision, ex = experiment_header(f, raw)
    dt = ex.number("dt", required=True, positive=True)
    if not 1e-6 <= dt <= 1e6:
        raise ConfigError(f, "experiment.dt", dt, "must be a period in [1e-06, 1e+06] s")
    steps = ex.integer("steps", required=True, lo=1, hi=MAX_STEPS)
    if runs * steps > MAX_RUN_STEPS:
        raise ConfigError(f, "experiment.runs", runs, f"runs x steps must be <= {MAX_RUN_STEPS:.0e}")
    chunk = ex.integer("chunk", None, lo=1, hi=1_000_000)
    also = ex.get("also_runs", [])  # extra run counts `tracklab reproduce` writes, e.g. a paper's own
    if not isinstance(also, list) or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_RUNS for v in also):
        raise ConfigError(f, "experiment.also_runs", also, f"must be a list of run counts in [1, {MAX_RUNS}]")
    ex.check_unknown()

    parsed_sensors = _parse_sensors(f, raw)
    fixed_dims = {SENSOR_DIM[k] for _, _, k in parsed_sensors if k in SENSOR_DIM}
    sensor_dim = fixed_dims.pop() if len(fixed_dims) == 1 else None
    if len(fixed_dims) > 0:
        raise ConfigError(f, "[[sensor]]", "...", "all sensors must observe positions of the same dimension")

    sc = _Section(f, "scenario", raw["scenario"])
    kind = sc.string("kind", required=True, choices=("crossing", "constant_velocity", "trajectory", "overflight", "sine"))
    if kind == "sine":
        scenario = Sine(dt=dt, steps=steps, amplitude=sc.number("amplitude", 83.33, positive=True),
                        omega=sc.number("omega", 0.6, positive=True), phase=sc.number("phase", 0.0))
    elif kind == "overflight":
        max_el = sc.number("max_elevation", 74.947)
        if not 0.0 < max_el < 90.0:
            raise ConfigError(f, "scenario.max_elevation", max_el, "must be an elevation in (0, 90) degrees")
        scenario = Overflight(
            dt=dt,
            steps=steps,
            altitude=sc.number("altitude", 8000.0, positive=True),
            speed=sc.number("speed", 250.0, positive=True),
            max_elevation=max_el,
            t_closest=sc.number("t_closest", 75.0),
            heading=sc.number("heading", 90.0),
        )
    elif kind == "crossing":
        scenario = Crossing(
            dt=dt,
            steps=steps,
            speed=sc.number("speed", 400.0),
            offset=sc.number("offset", 20000.0),
            start_x=sc.number("start_x", -20000.0),
            accel_sigma=sc.number("accel_sigma", 1.0, nonneg=True),
            altitude=sc.number("altitude", None),
        )
    elif kind == "constant_velocity":
        init = sc.get("initial")
        if (
            not isinstance(init, list)
            or len(init) not in (2, 4, 6)
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > MAX_MAGNITUDE for v in init)
        ):
            raise ConfigError(f, "scenario.initial", init, "must be 2, 4 or 6 finite numbers [x, vx(, y, vy(, z, vz))]")
        scenario = ConstantVelocity(dt=dt, steps=steps, initial=tuple(float(v) for v in init),
                                    accel_sigma=sc.number("accel_sigma", 0.0, nonneg=True))
    else:
        p = sc.string("path", required=True)
        try:
            tpath = (path.parent / p).resolve()
            read_csv(tpath)
        except (RuntimeError, OSError) as e:  # a symbolic-link loop, a name too long, …
            raise ConfigError(f, "scenario.path", p, f"trajectory file cannot be opened ({e.__class__.__name__})") from None
        except TrajectoryError as e:
            raise ConfigError(f, "scenario.path", p, f"trajectory file {e}") from None
        dims = sc.integer("dims", sensor_dim or 3, lo=2, hi=3)
        if sensor_dim is not None and dims != sensor_dim:
            raise ConfigError(f, "scenario.dims", dims, f"must be {sensor_dim} for the sensors given")
        start = sc.number("start", 0.0, nonneg=True)
        scenario = Trajectory(path=str(tpath), dt=dt, steps=steps, dim=dims, start=start)
        avail = scenario.max_steps()
        if steps > avail:
            raise ConfigError(f, "experiment.steps", steps, f"the trajectory from start = {start} s holds at most {avail} steps of {dt} s")
    sc.check_unknown()
    dim = scenario.dim
    suite = _build_sensors(f, parsed_sensors, dim, dt, steps)
    mounts = [s.kind == "mount" for s in suite.sensors]
    if any(mounts):  # angle tracking: the truth in the mount frame, filters on [az, el] (deg)
        if not all(mounts):
            raise ConfigError(f, "[[sensor]]", "mount", "a mount cannot share an experiment with sensors of other kinds")
        scenario = MountFrame(scenario)
        dim = scenario.dim

    pr = _Section(f, "prior", raw.get("prior", {}))
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
    filters, labels = [], set()
    default_q = getattr(getattr(scenario, "scenario", scenario), "accel_sigma", 1.0)
    for i, table in enumerate(flist, start=1):
        fc = _parse_filter(f, i, table, suite, dim, dt, default_q)
        if fc.label in labels:
            raise ConfigError(f, f"filter[{i}].label", fc.label, "must be unique among the filters")
        labels.add(fc.label)
        filters.append(fc)

    rp = _Section(f, "report", raw.get("report", {}))
    w = rp.get("window", [1, steps])
    if (
        not isinstance(w, list)
        or len(w) != 2
        or any(isinstance(v, bool) or not isinstance(v, int) for v in w)
        or not (1 <= w[0] <= w[1] <= steps)
    ):
        raise ConfigError(f, "report.window", w, f"must be [first, last] steps with 1 <= first <= last <= {steps}")
    pred_windows = _pred_windows(f, rp.get("windows", {}), (w[0], w[1]), steps, dt)
    rp.check_unknown()
    studies = parse_studies(f, raw.get("study"), _Section, filters)

    return Experiment(
        path=path, name=name, runs=runs, seed=seed, dt=dt, steps=steps, chunk=chunk, scenario=scenario,
        sensor=suite, filters=filters, prior=prior, window=(w[0], w[1]), raw=raw, also_runs=tuple(also), precision=precision,
        pred_windows=pred_windows, studies=studies,
    )


def _pred_windows(f, table, window, steps, dt):
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


def _parse_filter(f, i, table, suite: SensorSuite, dim, dt, default_q) -> FilterConfig:
    """One [[filter]] table: its kind, label and what it sees (the sensors, a guide, a fusion), checked
    against the sensor kinds the kind accepts; then the kind's own fields (its declaration's ``read``)."""
    fs = _Section(f, f"filter[{i}]", table)
    kind = KINDS[fs.string("kind", required=True, choices=tuple(KINDS))]
    label = fs.label("label", kind.name)

    # what the filter sees
    all_names = tuple(s.name for s in suite.sensors)
    guide = fs.string("guide", "previous") if kind.guided else "previous"
    if guide != "previous" and guide not in all_names:
        raise ConfigError(f, f"filter[{i}].guide", guide, f"must be \"previous\" or a sensor name from: {', '.join(all_names)}")
    default_names = [n for n in all_names if n != guide]
    names = fs.get("sensors", default_names)
    if not isinstance(names, list) or not names or any(not isinstance(n, str) or n not in all_names for n in names):
        raise ConfigError(f, f"filter[{i}].sensors", names, f"must be a list of sensor names from: {', '.join(all_names)}")
    names = tuple(dict.fromkeys(names))
    fusion = fs.string("fusion", None, choices=("interpolate", "none"))
    if fusion is not None:
        kinds = sorted(s.kind for s in suite.subset(names).sensors)
        if kinds != ["angles", "spherical"]:
            raise ConfigError(f, f"filter[{i}].fusion", fusion, "needs exactly one 'spherical' (laser) and one 'angles' (infrared) sensor among filter.sensors")
        ir = next(s for s in suite.subset(names).sensors if s.kind == "angles")
        if ir.p_detect < 1.0:
            raise ConfigError(f, f"filter[{i}].fusion", fusion, "registration needs every infrared report: set its p_detect = 1")
    _, meas = _view(suite, names, fusion)
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

    entry = Entry(fs, kind, meas, dim=dim, dt=dt, accel_sigma=default_q, sigma_fields=SENSOR_SIGMAS.get(mkind, ()),
                  guide=guide_sensor)
    model, params, options = kind.read(entry)
    if kind.guided:
        options = {"guide": guide, **options}
    fs.check_unknown()
    return FilterConfig(label, kind.name, model, params, options, names if names != all_names else (), fusion)
