"""Experiment files (TOML) -> validated experiments.

Everything is checked before anything is compiled; a bad field raises
``ConfigError`` whose message is one line: file, field, value, what is allowed.
Relative paths are resolved against the experiment file's folder.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tracklab.errors import ConfigError
from tracklab.filters import FILTER_KINDS, build, noise_params
from tracklab.models import MODELS, cv
from tracklab.scenarios import Crossing, Trajectory, TrajectoryError, read_csv
from tracklab.sensors import SENSOR_KINDS, Sensor

MAX_RUNS = 100_000_000
MAX_STEPS = 1_000_000
MAX_RUN_STEPS = 10**12
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")
MAX_MAGNITUDE = 1e15  # largest accepted magnitude: squares stay finite in float64

SENSOR_SIGMAS = {
    "polar": ("sigma_r", "sigma_angle"),
    "spherical": ("sigma_r", "sigma_az", "sigma_el"),
    "cartesian": ("sigma",),
}


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
    q: float  # process-noise variance of the filter's model
    r: tuple[float, ...]  # measurement-noise variances the filter assumes
    options: dict = field(default_factory=dict)


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
    sensor: Sensor
    filters: list[FilterConfig]
    prior: dict[str, float]
    window: tuple[int, int]
    raw: dict

    @property
    def dim(self) -> int:
        return self.scenario.dim

    def prior_covariance(self) -> np.ndarray:
        d = self.dim
        return np.diag([self.prior["pos_sigma"] ** 2, self.prior["vel_sigma"] ** 2] * d)

    def filter_specs(self):
        from tracklab.engine import FilterSpec

        specs = []
        for fc in self.filters:
            model = MODELS[fc.model](self.dim, self.dt)
            params = noise_params(fc.q, np.array(fc.r))
            flt = build(fc.kind, model, self.sensor, params, fc.options)
            report_model = cv(self.dim, self.dt) if fc.kind == "polar_kf" else model
            specs.append(FilterSpec(fc.label, fc.kind, flt, report_model, self.prior["acc_sigma"] ** 2))
        return specs

    def monte_carlo(self, runs=None, seed=None, progress=None, chunk=None):
        import jax

        from tracklab.engine import monte_carlo

        return monte_carlo(
            self.scenario,
            self.sensor,
            self.filter_specs(),
            runs or self.runs,
            jax.random.key(self.seed if seed is None else seed),
            self.prior_covariance(),
            chunk=chunk or self.chunk,
            progress=progress,
        )

    def run(self, runs=None, seed=None, out=None, progress=None, figures=True):
        """Run and write the results folder; returns the statistics dictionary."""
        from tracklab.report import results_folder, write_results

        out = results_folder(self, out)
        res = self.monte_carlo(runs=runs, seed=seed, progress=progress)
        return write_results(self, res, out, figures=figures)


def _read_toml(path: Path):
    if not path.is_file():
        raise ConfigError(path, "file", str(path), "experiment file does not exist")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "file", "", f"is not valid TOML ({e})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(path, "file", "", f"cannot be read ({e.__class__.__name__})") from None


def load_experiment(path) -> Experiment:
    path = Path(path)
    raw = _read_toml(path)
    f = path
    for sec in ("experiment", "scenario", "sensor"):
        if sec not in raw:
            raise ConfigError(f, f"[{sec}]", None, "section is required")
    unknown = sorted(set(raw) - {"experiment", "scenario", "sensor", "filter", "prior", "report"})
    if unknown:
        raise ConfigError(f, f"[{unknown[0]}]", "...", "unknown section (allowed: experiment, scenario, sensor, filter, prior, report)")

    ex = _Section(f, "experiment", raw["experiment"])
    name = ex.string("name", required=True)
    if not NAME_RE.fullmatch(name):
        raise ConfigError(f, "experiment.name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
    runs = ex.integer("runs", required=True, lo=1, hi=MAX_RUNS)
    seed = ex.integer("seed", 0, lo=0, hi=2**32 - 1)
    dt = ex.number("dt", required=True, positive=True)
    if not 1e-6 <= dt <= 1e6:
        raise ConfigError(f, "experiment.dt", dt, "must be a period in [1e-06, 1e+06] s")
    steps = ex.integer("steps", required=True, lo=1, hi=MAX_STEPS)
    if runs * steps > MAX_RUN_STEPS:
        raise ConfigError(f, "experiment.runs", runs, f"runs x steps must be <= {MAX_RUN_STEPS:.0e}")
    chunk = ex.integer("chunk", None, lo=1, hi=1_000_000)
    ex.get("description")
    ex.check_unknown()

    sn = _Section(f, "sensor", raw["sensor"])
    skind = sn.string("kind", required=True, choices=tuple(SENSOR_KINDS))
    p_detect = sn.number("p_detect", 1.0)
    if not 0.0 < p_detect <= 1.0:
        raise ConfigError(f, "sensor.p_detect", p_detect, "must be a probability in (0, 1]")

    sc = _Section(f, "scenario", raw["scenario"])
    kind = sc.string("kind", required=True, choices=("crossing", "trajectory"))
    sensor_dim = {"polar": 2, "spherical": 3}.get(skind)
    if kind == "crossing":
        altitude = sc.number("altitude", None)
        scenario = Crossing(
            dt=dt,
            steps=steps,
            speed=sc.number("speed", 400.0),
            offset=sc.number("offset", 20000.0),
            start_x=sc.number("start_x", -20000.0),
            accel_sigma=sc.number("accel_sigma", 1.0, nonneg=True),
            altitude=altitude,
        )
        if sensor_dim is not None and sensor_dim != scenario.dim:
            hint = "set scenario.altitude for a 3-D crossing" if sensor_dim == 3 else "remove scenario.altitude"
            raise ConfigError(f, "sensor.kind", skind, f"observes {sensor_dim}-D positions but the scenario is {scenario.dim}-D ({hint})")
    else:
        p = sc.string("path", required=True)
        tpath = (path.parent / p).resolve()
        try:
            read_csv(tpath)
        except TrajectoryError as e:
            raise ConfigError(f, "scenario.path", p, f"trajectory file {e}") from None
        dims = sc.integer("dims", sensor_dim or 3, lo=2, hi=3)
        if sensor_dim is not None and dims != sensor_dim:
            raise ConfigError(f, "scenario.dims", dims, f"must be {sensor_dim} for a '{skind}' sensor")
        start = sc.number("start", 0.0, nonneg=True)
        scenario = Trajectory(path=str(tpath), dt=dt, steps=steps, dim=dims, start=start)
        avail = scenario.max_steps()
        if steps > avail:
            raise ConfigError(f, "experiment.steps", steps, f"the trajectory from start = {start} s holds at most {avail} steps of {dt} s")
    sc.check_unknown()
    dim = scenario.dim

    # sensor noise
    if skind == "cartesian":
        s = sn.get("sigma")
        vals = s if isinstance(s, list) else [s] * dim
        if s is None:
            raise ConfigError(f, "sensor.sigma", None, "is required (a number or a list of one per axis)")
        if len(vals) != dim:
            raise ConfigError(f, "sensor.sigma", s, f"must have {dim} values (one per axis) or be a single number")
        sig = []
        for v in vals:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE:
                raise ConfigError(f, "sensor.sigma", s, f"each value must be a number in (0, {MAX_MAGNITUDE:g}]")
            sig.append(float(v))
        sigma = tuple(sig)
    else:
        sigma = tuple(sn.number(k, required=True, positive=True) for k in SENSOR_SIGMAS[skind])
    sn.check_unknown()
    sensor = Sensor(kind=skind, dim=dim, sigma=sigma, p_detect=p_detect)

    # prior
    pr = _Section(f, "prior", raw.get("prior", {}))
    prior = {
        "pos_sigma": pr.number("pos_sigma", 100.0, positive=True),
        "vel_sigma": pr.number("vel_sigma", 10.0, positive=True),
        "acc_sigma": pr.number("acc_sigma", 1.0, positive=True),
    }
    pr.check_unknown()

    # filters
    flist = raw.get("filter")
    if not isinstance(flist, list) or not flist:
        raise ConfigError(f, "[[filter]]", flist, "at least one [[filter]] table is required")
    filters, labels = [], set()
    default_q = getattr(scenario, "accel_sigma", 1.0)
    for i, table in enumerate(flist, start=1):
        fs = _Section(f, f"filter[{i}]", table)
        fkind = fs.string("kind", required=True, choices=tuple(FILTER_KINDS))
        label = fs.string("label", fkind)
        if not label.strip():
            raise ConfigError(f, f"filter[{i}].label", label, "must not be empty")
        if label in labels:
            raise ConfigError(f, f"filter[{i}].label", label, "must be unique among the filters")
        labels.add(label)
        ok_sensors = FILTER_KINDS[fkind][1]
        if skind not in ok_sensors:
            raise ConfigError(f, f"filter[{i}].kind", fkind, f"needs a sensor of kind {' or '.join(ok_sensors)}, not '{skind}'")
        model = fs.string("model", "cv", choices=tuple(MODELS))
        if fkind == "polar_kf" and model != "cv":
            raise ConfigError(f, f"filter[{i}].model", model, "polar_kf has its own polar CV state: use model = \"cv\"")
        if model == "cv":
            q = fs.number("accel_sigma", default_q if default_q > 0 else 1.0, positive=True) ** 2
        else:
            q = fs.number("accel_increment_sigma", 1.0, positive=True) ** 2
        options = {}
        if fkind == "cmkf":
            debias = fs.string("debias", "plain", choices=("plain", "additive", "unbiased"))
            if debias == "additive" and skind != "polar":
                raise ConfigError(f, f"filter[{i}].debias", debias, "the additive (Lerro) conversion is 2-D: use plain or unbiased with a spherical sensor")
            options["debias"] = debias
        if skind == "cartesian":
            s = fs.get("sigma")
            if s is None:
                r = tuple(v**2 for v in sigma)
            else:
                vals = s if isinstance(s, list) else [s] * dim
                if len(vals) != dim or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_MAGNITUDE for v in vals):
                    raise ConfigError(f, f"filter[{i}].sigma", s, f"must be a number in (0, {MAX_MAGNITUDE:g}] or {dim} of them")
                r = tuple(float(v) ** 2 for v in vals)
        else:
            r = tuple(
                fs.number(k, sv, positive=True) ** 2 for k, sv in zip(SENSOR_SIGMAS[skind], sigma)
            )
        fs.check_unknown()
        filters.append(FilterConfig(label, fkind, model, q, r, options))

    rp = _Section(f, "report", raw.get("report", {}))
    w = rp.get("window", [1, steps])
    if (
        not isinstance(w, list)
        or len(w) != 2
        or any(isinstance(v, bool) or not isinstance(v, int) for v in w)
        or not (1 <= w[0] <= w[1] <= steps)
    ):
        raise ConfigError(f, "report.window", w, f"must be [first, last] steps with 1 <= first <= last <= {steps}")
    rp.check_unknown()

    return Experiment(
        path=path,
        name=name,
        runs=runs,
        seed=seed,
        dt=dt,
        steps=steps,
        chunk=chunk,
        scenario=scenario,
        sensor=sensor,
        filters=filters,
        prior=prior,
        window=(w[0], w[1]),
        raw=raw,
    )
