"""Reading airborne-radar experiment files (paper 001): an experiment file with an ``[airborne]`` section.

```toml
[experiment]
name = "airborne_radar"
runs = 1000              # or "auto" with target_precision = 0.01 (and max_runs): until every
seed = 0                 # tracker's pointing-error RMS is within ±1 %

[airborne]
duration = 39.0          # s
sample_dt = 0.01         # s, the radar's error-signal samples
average = 5              # samples pre-averaged per filter period (50 ms)
antenna_lag = 0.02       # s, the stabilised antenna's rate loop
beam = 30.0              # mrad, half-width of the angle discriminators' linear range
range_gate = 150.0       # m, half-width of the range gate
velocity_gate = 15.0     # m/s, half-width of the velocity gate

[engagement]             # tracklab.airborne.engagement.Engagement's fields (these are the defaults)
own_speed = 250.0
target_range = 20000.0
target_offset = 3000.0
target_height = -500.0
target_speed = 300.0
target_heading = 180.0
turn_g = 4.0
turn_start = 20.0
turn_end = 30.0
turn_direction = 1.0
singer_sigma = 30.0      # m/s²; singer = false for the nominal path alone
singer_tau = 10.0

[noise]                  # per 10 ms sample, before the detector gains
angle = 1.0              # mrad (glint included)
range = 10.0             # m
velocity = 1.0           # m/s
gains = [1.0, 1.0, 1.0, 1.0]   # k_e, k_d, k_r, k_ṙ

[acquisition]            # designation errors (std)
pointing = 3.0           # mrad
los_rate = 2.0           # mrad/s
range = 30.0             # m
range_rate = 3.0         # m/s

[disturbance]            # optional: the antenna is jolted about its d axis
time = 15.0              # s
pointing = 10.0          # mrad

[[tracker]]
label = "joint EKF"
kind = "cd_ekf"          # cd_ekf | decoupled | classical | moose
lam = 5.0                # 1/s, eq. 1's gain on ε̂ (cd_ekf, decoupled)
q_scale = 1.0            # the filter's Q and R against the truth's (mismatch)
r_scale = 1.0
# decoupled: range_velocity = "coupled" | "separate"; model: sigma_m, tau, sigma_r, tau_r
# moose: levels = [-40.0, -20.0, 0.0, 20.0, 40.0] (m/s²), p_stay = 0.99 (per filter period: a 5 s mean sojourn)

[report]                 # optional
level = 0.95             # of every confidence interval
baseline = "joint EKF"   # the tracker the paired differences are to (default the first)

[report.windows]         # name = [t0, t1] s; defaults below when absent
steady = [5.0, 20.0]
```

Every tracker sees the same runs (the same target path, designation errors
and noise), so differences between trackers are paired.
"""

from __future__ import annotations

import math
from dataclasses import fields
from pathlib import Path

import numpy as np

from tracklab.config.fields import (
    MAX_RUN_STEPS,
    WINDOW_NAME_RE,
    Section,
    auto_runs,
    check_sections,
    check_unique,
    declared_numbers,
    experiment_header,
    level_and_baseline,
)
from tracklab.errors import ConfigError
from tracklab.worlds.airborne.closed_loop import MRAD
from tracklab.worlds.airborne.engagement import Engagement, nominal_range
from tracklab.worlds.airborne.experiment import MAX_TICKS, AirborneExperiment
from tracklab.worlds.airborne.registry import TRACKERS
from tracklab.worlds.protocol import UnitConfig
from tracklab.worlds.airborne.tracker import Setting, Timing


def _read_windows(f, rp: Section, duration, disturbance):
    defaults = {"acquisition": (0.0, 2.0), "steady": (5.0, 20.0), "turn": (20.0, 30.0),
                "close": (max(duration - 4.0, 0.0), duration)}
    if disturbance is not None:
        defaults["disturbance"] = (disturbance[0], min(disturbance[0] + 2.0, duration))
    if not rp.has("windows"):
        return {k: v for k, v in defaults.items() if v[0] < duration}
    table = rp.get("windows")
    if not isinstance(table, dict) or not table:
        raise ConfigError(f, "report.windows", table, "must be a table: name = [t0, t1] (seconds)")
    out = {}
    for name, v in table.items():
        if not WINDOW_NAME_RE.fullmatch(name):
            raise ConfigError(f, f"report.windows.{name}", name, "window names are 1-40 letters, digits, spaces, '_.+-'")
        if (not isinstance(v, list) or len(v) != 2
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)
                or not 0 <= v[0] < v[1] <= duration):
            raise ConfigError(f, f"report.windows.{name}", v, f"must be [t0, t1] in seconds with 0 <= t0 < t1 <= {duration:g}")
        out[name] = (float(v[0]), float(v[1]))
    return out


def parse_airborne(f: Path, raw: dict) -> AirborneExperiment:
    """Validate an airborne experiment file's contents ``raw`` read from ``f``."""
    check_sections(f, raw, ("experiment", "tracker"), ("experiment", "airborne", "engagement", "noise", "acquisition",
                                                      "disturbance", "tracker", "report"), "an airborne experiment")
    name, runs, seed, precision, ex = experiment_header(f, raw)
    max_runs, target_precision = auto_runs(ex)
    chunk = ex.integer("chunk", None, lo=1, hi=100_000)
    ex.check_unknown()
    ab = Section(f, "airborne", raw["airborne"])
    duration = ab.number("duration", 39.0, positive=True, hi=3600.0)
    sample_dt = ab.number("sample_dt", 0.01, positive=True, hi=1.0)
    average = ab.integer("average", 5, lo=1, hi=1000)
    if duration < 2 * sample_dt * average:
        raise ConfigError(f, "airborne.duration", duration, f"must hold at least two filter periods ({2 * sample_dt * average:g} s)")
    if runs is None:  # runs = "auto": at most max_runs (unless given, what the run limit allows)
        runs = max_runs if ex.has("max_runs") else max(2, min(max_runs, int(MAX_RUN_STEPS * sample_dt / duration)))
    if runs * duration / sample_dt > MAX_RUN_STEPS:
        raise ConfigError(f, "experiment.runs", runs, f"runs x radar samples must be <= {MAX_RUN_STEPS:.0e}")
    if duration / sample_dt > MAX_TICKS:
        raise ConfigError(f, "airborne.sample_dt", sample_dt,
                          f"gives {duration / sample_dt:.3g} radar samples a run; at most {MAX_TICKS:.0e}: "
                          f"sample_dt >= {duration / MAX_TICKS:.3g} s for duration = {duration:g} s")
    lag = ab.number("antenna_lag", 0.02, positive=True, hi=10.0)
    limits = (ab.number("beam", 30.0, positive=True, hi=1000.0) * MRAD, ab.number("range_gate", 150.0, positive=True),
              ab.number("velocity_gate", 15.0, positive=True))
    ab.check_unknown()
    eg = Section(f, "engagement", raw.get("engagement", {}))
    kw = {}
    for fld in fields(Engagement):
        if fld.name == "turn_direction":
            if eg.has(fld.name):
                v = eg.number(fld.name)
                if v not in (1.0, -1.0):
                    raise ConfigError(f, "engagement.turn_direction", v, "must be 1 (left) or -1 (right)")
                kw[fld.name] = v
        elif fld.name in ("target_offset", "target_height", "target_heading"):
            kw[fld.name] = eg.number(fld.name, fld.default)
        elif fld.name == "turn_g":
            kw[fld.name] = eg.number(fld.name, fld.default, nonneg=True, hi=20.0)
        else:
            kw[fld.name] = eg.number(fld.name, fld.default, positive=True)
    singer = eg.get("singer", True)
    if not isinstance(singer, bool):
        raise ConfigError(f, "engagement.singer", singer, "must be true or false")
    eg.check_unknown()
    eng = Engagement(**kw)
    if eng.turn_end < eng.turn_start:
        raise ConfigError(f, "engagement.turn_end", eng.turn_end, f"must be >= turn_start ({eng.turn_start:g})")
    t = np.linspace(0.0, duration, int(min(duration / sample_dt, 100_000)) + 1)
    r_min = float(np.min(nominal_range(eng, t)))
    if r_min < 100.0:
        raise ConfigError(f, "[engagement]", f"{r_min:.0f} m", "the nominal range must stay above 100 m for the whole run")
    nz = Section(f, "noise", raw.get("noise", {}))
    noise = (nz.number("angle", 1.0, positive=True) * MRAD,) * 2 + (nz.number("range", 10.0, positive=True),
                                                                   nz.number("velocity", 1.0, positive=True))
    gains = nz.get("gains", [1.0, 1.0, 1.0, 1.0])
    if (not isinstance(gains, list) or len(gains) != 4
            or any(isinstance(g, bool) or not isinstance(g, (int, float)) or not math.isfinite(g) or g <= 0 for g in gains)):
        raise ConfigError(f, "noise.gains", gains, "must be 4 positive numbers: k_e, k_d, k_r, k_rdot")
    nz.check_unknown()
    aq = Section(f, "acquisition", raw.get("acquisition", {}))
    acquisition = (aq.number("pointing", 3.0, nonneg=True) * MRAD, aq.number("los_rate", 2.0, nonneg=True) * MRAD,
                   aq.number("range", 30.0, nonneg=True), aq.number("range_rate", 3.0, nonneg=True))
    aq.check_unknown()
    if acquisition[0] >= limits[0]:
        raise ConfigError(f, "acquisition.pointing", acquisition[0] / MRAD, f"must be below the beam half-width ({limits[0] / MRAD:g} mrad)")
    disturbance = None
    if "disturbance" in raw:
        ds = Section(f, "disturbance", raw["disturbance"])
        dt_ = ds.number("time", required=True, positive=True)
        if dt_ >= duration:
            raise ConfigError(f, "disturbance.time", dt_, f"must be within the run (< {duration:g} s)")
        disturbance = (dt_, ds.number("pointing", required=True, hi=1000.0, lo=-1000.0) * MRAD)
        ds.check_unknown()
    tables = raw["tracker"]
    if not isinstance(tables, list) or not tables:
        raise ConfigError(f, "[[tracker]]", tables, "at least one [[tracker]] table is required")
    trackers, labels, trimmed = [], set(), set()
    setting = Setting(eng, noise, tuple(float(g) for g in gains), acquisition, Timing(sample_dt, average, lag))
    for i, table in enumerate(tables, start=1):
        ts = Section(f, f"tracker[{i}]", table)
        kind = TRACKERS[ts.string("kind", required=True, choices=tuple(TRACKERS))]
        label = ts.label("label", kind.name)
        check_unique(f, f"tracker[{i}].label", label, trimmed, "trackers")
        labels.add(label)
        options = {k: ts.string(k, allowed[0], choices=allowed) for k, allowed in kind.choices.items()}
        numbers = declared_numbers(ts, kind.params, setting)
        ts.check_unknown()
        trackers.append(UnitConfig(label, kind.name, numbers, options))
    rp = Section(f, "report", raw.get("report", {}))
    windows = _read_windows(f, rp, duration, disturbance)
    level, baseline = level_and_baseline(rp, [t.label for t in trackers], "trackers")
    rp.check_unknown()
    return AirborneExperiment(f, name, runs, seed, duration, sample_dt, average, lag, limits, eng, singer, noise,
                              tuple(float(g) for g in gains), acquisition, disturbance, trackers, windows, raw, precision,
                              chunk=chunk, level=level, baseline=baseline, target_precision=target_precision)
