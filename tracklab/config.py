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
from tracklab.filters import FILTER_KINDS, build
from tracklab.filters.fusion import LaserIrFusion, Select
from tracklab.models import MODELS, cv
from tracklab.metrics import REPORT_WINDOW
from tracklab.scenarios import (ConstantVelocity, Crossing, MountFrame, Overflight, Sine, Trajectory, TrajectoryError,
                                 read_csv)
from tracklab.sensors import SENSOR_KINDS, Sensor, SensorSuite
from tracklab.studies import parse_studies

MAX_RUNS = 100_000_000
MAX_STEPS = 1_000_000
MAX_RUN_STEPS = 10**12
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")
MAX_MAGNITUDE = 1e15  # largest accepted magnitude: squares stay finite in float64

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

    def view(self, fc: FilterConfig):
        """(view function or None, measurement model) of what a filter sees."""
        names = fc.sensors
        if fc.options.get("guide", "previous") != "previous":  # error_space: [main, guide]
            names = tuple(names) + (fc.options["guide"],)
        return _view(self.sensor, names, fc.fusion)

    def filter_specs(self):
        import jax.numpy as jnp

        from tracklab.engine import FilterSpec

        specs = []
        for fc in self.filters:
            model = MODELS[fc.model](self.dim, self.dt)
            view, meas_model = self.view(fc)
            params = {k: jnp.asarray(v, dtype=float) for k, v in fc.params.items()}
            flt = build(fc.kind, model, meas_model, params, fc.options)
            report_model = cv(self.dim, self.dt) if fc.kind == "polar_kf" else model
            specs.append(FilterSpec(fc.label, fc.kind, flt, report_model, self.prior["acc_sigma"] ** 2, view))
        return specs

    def monte_carlo(self, runs=None, seed=None, progress=None, chunk=None, precision=None):
        import jax

        from tracklab.engine import monte_carlo

        precision = precision or self.precision
        with jax.enable_x64(precision == "float64"):  # the filters' constants in the same precision
            return monte_carlo(
                self.scenario,
                self.sensor,
                self.filter_specs(),
                runs or self.runs,
                jax.random.key(self.seed if seed is None else seed),
                self.prior_covariance(),
                chunk=chunk or self.chunk,
                progress=progress,
                precision=precision,
                windows=self.pred_windows,
            )

    def memory_bytes(self, runs=None, chunk=None) -> float:
        """A lower bound on the bytes a run needs: one chunk's random draws (float32) for every
        step, and each filter's per-step statistics on the host."""
        from tracklab.engine import default_chunk

        runs = runs or self.runs
        chunk = min(chunk or self.chunk or default_chunk(self.scenario, self.sensor), runs)
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


def _view(suite: SensorSuite, names, fusion):
    names = tuple(names) or tuple(s.name for s in suite.sensors)
    if fusion is not None:
        sub = suite.subset(names)
        laser = next(s.name for s in sub.sensors if s.kind == "spherical")
        ir = next(s.name for s in sub.sensors if s.kind == "angles")
        v = LaserIrFusion(suite, laser, ir, fusion)
        return v, v.model
    if names == tuple(s.name for s in suite.sensors):
        return None, suite.sensors[0] if len(suite.sensors) == 1 else suite
    v = Select(suite, names)
    return v, v.model


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


def _sigma_list(f, field_name, s, dim, required=True):
    if s is None:
        if required:
            raise ConfigError(f, field_name, None, "is required (a number or a list of one per axis)")
        return None
    vals = s if isinstance(s, list) else [s] * dim
    if len(vals) != dim:
        raise ConfigError(f, field_name, s, f"must have {dim} values (one per axis) or be a single number")
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE:
            raise ConfigError(f, field_name, s, f"each value must be a number in (0, {MAX_MAGNITUDE:g}]")
    return tuple(float(v) for v in vals)


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
    path = Path(path)
    raw = _read_toml(path)
    f = path
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


def _dekf_fields(f, i, fs, options, q, r):
    """[[filter]] fields of kind dekf -> its parameters (and static network shape in ``options``)."""
    import jax

    from tracklab.filters.dual_ekf import Network, dekf_params

    options["hidden"] = fs.integer("hidden", 4, lo=1, hi=256)
    options["reading"] = fs.string("reading", "residual", choices=("residual", "literal"))
    options["scale"] = _sigma_list(f, f"filter[{i}].scale", fs.get("scale", [100.0, 50.0, 30.0]), 3)
    forget = fs.number("forget", 0.999)
    if not 0.0 < forget <= 1.0:
        raise ConfigError(f, f"filter[{i}].forget", forget, "the forgetting factor must be in (0, 1]")
    seed = fs.integer("weights_seed", 0, lo=0, hi=2**32 - 1)
    net = Network(options["hidden"], options["scale"], 1.0, options["reading"] == "residual")
    p = dekf_params(net, q=q, r=r[0], lam=forget, r_e=fs.number("r_e", 0.5, positive=True),
                    pw0=fs.number("pw0", 1e-4, positive=True), key=jax.random.key(seed))
    return {k: np.asarray(v).tolist() for k, v in p.items() if k not in ("q", "r")}


def _imm_fields(f, i, fs, dim, default_q, r):
    """[[filter]] fields of kind imm -> its parameters (and its models, turn-rate prior)."""
    from tracklab.filters import IMM_MODELS, imm_params

    models = fs.get("models", list(IMM_MODELS) if dim >= 2 else ["cv", "ca"])
    if not isinstance(models, list) or not models or any(m not in IMM_MODELS for m in models) or len(set(models)) != len(models):
        raise ConfigError(f, f"filter[{i}].models", models, f"must be a list of distinct models from: {', '.join(IMM_MODELS)}")
    if "ct" in models and dim < 2:
        raise ConfigError(f, f"filter[{i}].models", models, "the coordinated turn (ct) needs a 2-D or 3-D scenario")
    cv_q = default_q**2 if default_q > 0 else 1.0
    q = fs.get("q", [cv_q if m != "ca" else 0.1 * cv_q for m in models])
    if (not isinstance(q, list) or len(q) != len(models)
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE for v in q)):
        raise ConfigError(f, f"filter[{i}].q", q, f"must be {len(models)} process-noise variances > 0, one per model")
    q_turn = fs.number("q_turn", 1e-4, positive=True)
    turn_sigma = fs.number("turn_rate_sigma", 0.1, positive=True)
    k = len(models)
    if fs.has("transition"):
        if fs.has("p_stay"):
            raise ConfigError(f, f"filter[{i}].p_stay", fs.get("p_stay"), "give either p_stay or transition, not both")
        tm = fs.get("transition")
        ok = isinstance(tm, list) and len(tm) == k and all(
            isinstance(row, list) and len(row) == k
            and all(not isinstance(v, bool) and isinstance(v, (int, float)) and 0 <= v <= 1 for v in row)
            and abs(sum(row) - 1.0) < 1e-9 for row in tm)
        if not ok:
            raise ConfigError(f, f"filter[{i}].transition", tm, f"must be a {k}x{k} matrix of probabilities whose rows sum to 1")
        matrix = np.array(tm, float)
    else:
        p_stay = fs.number("p_stay", 0.95)
        if not 0.0 < p_stay <= 1.0 or (k > 1 and p_stay == 1.0):
            raise ConfigError(f, f"filter[{i}].p_stay", p_stay, "must be a probability in (0, 1) (1 with one model)")
        matrix = None
    out = imm_params(models, q, q_turn, r, p_stay=p_stay if matrix is None else 0.95, transition_matrix=matrix)
    out = {k: np.asarray(v).tolist() for k, v in out.items()}  # plain numbers, like every filter's parameters
    return dict(out, models=models, turn_rate_sigma=turn_sigma)


def _gain_value(fs, key, required=True):
    v = fs.get(key)
    if v is None:
        if required:
            raise fs._err(key, None, "is required for explicit gains")
        return None
    vals = v if isinstance(v, list) else [v]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 < x < 4 for x in vals):
        raise fs._err(key, v, "must be a number (or one per axis) in (0, 4)")
    return tuple(float(x) for x in vals) if isinstance(v, list) else float(v)


def _parse_filter(f, i, table, suite: SensorSuite, dim, dt, default_q) -> FilterConfig:
    fs = _Section(f, f"filter[{i}]", table)
    fkind = fs.string("kind", required=True, choices=tuple(FILTER_KINDS))
    label = fs.label("label", fkind)

    # what the filter sees
    all_names = tuple(s.name for s in suite.sensors)
    guide = fs.string("guide", "previous") if fkind == "error_space" else "previous"
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
    if fkind == "error_space":
        if len(names) != 1 or guide in names:
            raise ConfigError(f, f"filter[{i}].sensors", list(names), "error_space observes one sensor (its guide is set by 'guide')")
        if guide != "previous":
            g = suite.subset((guide,)).sensors[0]
            if g.kind != mkind or g.m != meas.m:
                raise ConfigError(f, f"filter[{i}].guide", guide, f"the guide sensor must be of the observed sensor's kind ({mkind})")
    if fkind == "kf" and not meas.linear:
        raise ConfigError(f, f"filter[{i}].kind", fkind, "needs linear sensors only (cartesian or mount): use ekf, ukf or stf")
    ok = FILTER_KINDS[fkind][1]
    if mkind not in ok:
        seen = "several sensors" if mkind == "suite" else f"a '{mkind}' sensor"
        raise ConfigError(f, f"filter[{i}].kind", fkind, f"needs a sensor of kind {' or '.join(ok)}, but sees {seen}")

    if fkind == "dekf" and (dim != 1 or meas.m != 1):
        raise ConfigError(f, f"filter[{i}].kind", fkind, "dekf tracks one angle channel: a 1-D scenario and a 1-D cartesian sensor")
    if fkind == "dekf" and fs.get("model", "ca") != "ca":
        raise ConfigError(f, f"filter[{i}].model", fs.get("model"), "dekf works on the ca state [theta, rate, acceleration]")
    if fkind == "imm" and fs.has("model"):
        raise ConfigError(f, f"filter[{i}].model", fs.get("model"), "imm has its own models: use models = [\"cv\", \"ca\", \"ct\"]")
    model = "ca" if fkind in ("imm", "dekf") else fs.string("model", "ca" if fkind == "alpha_beta_gamma" else "cv", choices=tuple(MODELS))
    if fkind == "polar_kf" and model != "cv":
        raise ConfigError(f, f"filter[{i}].model", model, "polar_kf has its own polar CV state: use model = \"cv\"")
    if fkind == "alpha_beta" and model != "cv" or fkind == "alpha_beta_gamma" and model != "ca":
        need = "cv" if fkind == "alpha_beta" else "ca"
        raise ConfigError(f, f"filter[{i}].model", model, f"{fkind} works on the {need} model")
    sigma_key = "accel_sigma" if model == "cv" else "accel_increment_sigma"
    if fkind == "imm":
        q = None  # one per model, below
    elif fs.has("q"):  # the process-noise variance itself (a paper's q)
        if fs.has(sigma_key):
            raise ConfigError(f, f"filter[{i}].q", fs.get("q"), f"give either q or {sigma_key}, not both")
        q = fs.number("q", positive=True)
    elif model == "cv":
        q = fs.number("accel_sigma", default_q if default_q > 0 else 1.0, positive=True) ** 2
    else:
        q = fs.number("accel_increment_sigma", 1.0, positive=True) ** 2
    sigma_v = math.sqrt(q) if q is not None else None

    options = {}
    if fkind == "cmkf":
        debias = fs.string("debias", "plain", choices=("plain", "additive", "unbiased"))
        if debias == "additive" and mkind != "polar":
            raise ConfigError(f, f"filter[{i}].debias", debias, "the additive (Lerro) conversion is 2-D: use plain or unbiased with a spherical sensor")
        options["debias"] = debias

    if fkind == "ukf":
        options["ut_alpha"] = fs.number("ut_alpha", 1.0, lo=1e-4, hi=1.0)
        options["ut_beta"] = fs.number("ut_beta", 2.0, nonneg=True)
        options["ut_kappa"] = fs.number("ut_kappa", 0.0, nonneg=True)

    # the noise the filter assumes: defaults to the sensors' own
    if fs.has("r"):  # the measurement-noise variances themselves, one or one per component
        sig_keys = SENSOR_SIGMAS.get(mkind, ())
        if any(fs.has(k) for k in sig_keys):
            raise ConfigError(f, f"filter[{i}].r", fs.get("r"), f"give either r or {'/'.join(sig_keys)}, not both")
        r = _sigma_list(f, f"filter[{i}].r", fs.get("r"), meas.m)  # variances, checked like sigmas
    elif mkind == "suite":
        r = tuple(v**2 for v in meas.sigma)
    elif mkind == "cartesian":
        r = tuple(v**2 for v in (_sigma_list(f, f"filter[{i}].sigma", fs.get("sigma"), dim, required=False) or meas.sigma))
    else:
        r = tuple(fs.number(k, sv, positive=True) ** 2 for k, sv in zip(SENSOR_SIGMAS[mkind], meas.sigma))
    params = {"q": q, "r": r}

    if fkind == "imm":
        params.update(_imm_fields(f, i, fs, dim, default_q, r))
        options["models"] = tuple(params.pop("models"))
        options["turn_rate_sigma"] = params.pop("turn_rate_sigma")
    if fkind == "dekf":
        params.update(_dekf_fields(f, i, fs, options, q, r))
    if fkind == "stf":
        params["rho"] = fs.number("rho", 0.95)
        if not 0.0 < params["rho"] <= 1.0:
            raise ConfigError(f, f"filter[{i}].rho", params["rho"], "the forgetting factor must be in (0, 1]")
        params["b"] = fs.number("b", 1.0, positive=True)
    if fkind == "error_space":
        params["q_e"] = fs.number("q_e", q, positive=True)
        r_e = fs.get("r_e")
        params["r_e"] = r if r_e is None else _sigma_list(f, f"filter[{i}].r_e", r_e, meas.m)
        options["guide"] = guide
        if guide != "previous":
            r_g = fs.get("r_guide")
            g = suite.subset((guide,)).sensors[0]
            params["r_guide"] = tuple(v**2 for v in g.sigma) if r_g is None else _sigma_list(f, f"filter[{i}].r_guide", r_g, meas.m)
            options["guide_delay"] = fs.integer("guide_delay", 0, lo=0, hi=10_000)
        elif fs.has("guide_delay"):
            raise ConfigError(f, f"filter[{i}].guide_delay", fs.get("guide_delay"), "applies to an external guide sensor only")

    if fkind in ("alpha_beta", "alpha_beta_gamma"):
        order = 2 if fkind == "alpha_beta" else 3
        gnames = ("alpha", "beta", "gamma")[:order]
        explicit = any(fs.has(g) for g in gnames)
        gains = fs.string("gains", "explicit" if explicit else "kalata", choices=("kalata", "growing_memory", "explicit"))
        if mkind != "cartesian":
            options["conversion"] = fs.string("conversion", "plain", choices=("plain", "unbiased"))
        if gains == "explicit":
            for g in gnames:
                params[g] = _gain_value(fs, g)
        elif explicit:
            raise ConfigError(f, f"filter[{i}].gains", gains, "explicit alpha/beta/gamma need gains = \"explicit\" (or no gains field)")
        floor = fs.get("floor") if gains == "growing_memory" else None
        if gains == "growing_memory" and floor is not None:
            if floor == "kalata":
                options["floor"] = "kalata"
            elif isinstance(floor, list) and len(floor) == order and all(
                not isinstance(v, bool) and isinstance(v, (int, float)) and 0 <= v < 4 for v in floor
            ):
                options["floor"] = "explicit"
                params["floor"] = tuple(float(v) for v in floor)
            else:
                raise ConfigError(f, f"filter[{i}].floor", floor, f"must be \"kalata\" or {order} gains [{', '.join(gnames)}] in [0, 4)")
        options["gains"] = gains
        if gains == "kalata" or options.get("floor") == "kalata":
            lam = _sigma_list(f, f"filter[{i}].tracking_index", fs.get("tracking_index"), dim, required=False)
            if lam is None:
                sw = fs.get("sigma_w")
                if sw is None and mkind != "cartesian":
                    raise ConfigError(f, f"filter[{i}].sigma_w", None, "is required (position-noise std per axis, m) for Kalata gains behind a non-Cartesian sensor, unless tracking_index is given")
                sigma_w = _sigma_list(f, f"filter[{i}].sigma_w", sw, dim) if sw is not None else tuple(np.sqrt(r))
                T = getattr(meas, "period", 0.0) or dt  # the update interval
                lam = tuple(sigma_v * T**2 / w for w in sigma_w)
            elif fs.has("sigma_w"):
                raise ConfigError(f, f"filter[{i}].sigma_w", fs.get("sigma_w"), "give either tracking_index or sigma_w, not both")
            params["lam"] = lam
    fs.check_unknown()
    return FilterConfig(label, fkind, model, params, options, names if names != all_names else (), fusion)
