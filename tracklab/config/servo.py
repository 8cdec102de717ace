"""Reading servo experiment files (paper 003): an experiment file with a ``[servo]`` section.

```toml
[experiment]
name = "dekf_on_axis"
runs = 100                     # Monte-Carlo runs: miss-distance noise differs; or "auto" with
                               # target_precision (and max_runs): every case's max error that tight
seed = 0

[servo]
frames = 3000                  # camera frames (100 Hz: 30 s)
frame_dt = 0.01                # s; the servo ticks at frame_dt / frame_ticks
frame_ticks = 10
delay = 2                      # frames between exposure and delivery (paper: two)
noise = 10.0                   # arcsec, miss-distance noise (ours: the paper gives none)
settle = 15.0                  # s left out of the statistics
accel_ff = 0.0                 # on_axis: acceleration feed-forward gain (s)

[target]
kind = "sine"                  # amplitude (deg), omega (rad/s); or "cone": half_angle,
amplitude = 83.33              # axis_elevation (deg), period (s)
omega = 0.6

[[estimator]]                  # what velocity_lag / on_axis get their target angle and rate from
label = "KF"
kind = "kf"                    # kf (CA model) | dekf (dual EKF, paper 003)
q = 1.0                        # acceleration-increment variance per frame, (deg/s²)²

# a "dekf" estimator: hidden, reading (residual | literal), q, lam, r_e, pw0, seed, and
# train_steps > 0 (train_lr, train_runs) to train its initial weights and λ first

[[case]]
mode = "on_axis"               # double_loop | velocity_lag | on_axis
estimator = "KF"               # none for double_loop; "perfect" = the true target

[report]                       # optional
level = 0.95                   # of every confidence interval
baseline = "on_axis, KF"       # the case the paired differences are to (default the first)
```

Statistics per case over the runs, after ``settle``: the maximum tracking
error (′; the mean over runs of each run's largest |target − boresight|, and
the worst run), the random error (″; the RMS of the error left after a
least-squares fit of the target's first three harmonics and a constant, per
run, averaged over runs) and the estimator's largest rate error (°/s), each
with its confidence interval over the runs; percentiles of the runs' maximum
tracking errors; each case's paired differences to the baseline case.
"""

from __future__ import annotations

from pathlib import Path

from tracklab.config.fields import (
    MAX_RUN_STEPS,
    Section,
    auto_runs,
    check_sections,
    check_unique,
    declared_numbers,
    declared_options,
    experiment_header,
    level_and_baseline,
)
from tracklab.errors import ConfigError
from tracklab.worlds.servo.experiment import (
    CAMERA_LOOPS,
    MAX_TICKS,
    TARGET_KINDS,
    TICK_RANGE,
    Case,
    ServoExperiment,
)
from tracklab.worlds.protocol import UnitConfig
from tracklab.worlds.servo.loops import MODES, AzimuthAxis
from tracklab.worlds.servo.registry import ESTIMATORS


def _check_latency(f, delay, frame_dt, mode):
    """A position loop closed through the camera is stable only while the camera's latency (the
    delay plus half a held frame) stays inside the loop's delay margin."""
    margin, pm, wc = AzimuthAxis().delay_margin()
    latency = (delay + 0.5) * frame_dt
    if latency >= margin:
        raise ConfigError(f, "servo.delay", delay,
                          f"with frame_dt = {frame_dt:g} s the camera's latency ({latency:.3g} s: delay + half a frame) "
                          f"passes the position loop's delay margin ({margin:.3g} s: {pm:.1f}° phase margin at "
                          f"{wc:.1f} rad/s), so {mode} would be unstable; use fewer frames of delay, a shorter "
                          f"frame_dt, or on_axis cases only")


def parse_servo(f: Path, raw: dict) -> ServoExperiment:
    """Validate a servo experiment file's contents ``raw`` read from ``f``."""
    check_sections(f, raw, ("experiment", "target", "case"), ("experiment", "servo", "target", "estimator", "case", "report"),
                   "a servo experiment")
    name, runs, seed, precision, ex = experiment_header(f, raw)
    max_runs, target_precision = auto_runs(ex)
    chunk = ex.integer("chunk", None, lo=1, hi=100_000)
    ex.check_unknown()
    sv = Section(f, "servo", raw["servo"])
    frames = sv.integer("frames", 3000, lo=10, hi=10_000_000)
    frame_dt = sv.number("frame_dt", 0.01, positive=True)
    frame_ticks = sv.integer("frame_ticks", 10, lo=1, hi=1000)
    tick = frame_dt / frame_ticks
    if not TICK_RANGE[0] <= tick <= TICK_RANGE[1]:
        raise ConfigError(f, "servo.frame_ticks", frame_ticks,
                          f"gives a servo tick of {tick:.3g} s; the correctors need a tick in "
                          f"[{TICK_RANGE[0]:g}, {TICK_RANGE[1]:g}] s (paper: 0.001 s)")
    if frames * frame_ticks > MAX_TICKS:
        raise ConfigError(f, "servo.frames", frames,
                          f"x frame_ticks = {frames * frame_ticks:.3g} servo ticks a run; at most {MAX_TICKS:.0e}")
    if runs is None:  # runs = "auto": at most max_runs (unless given, what the run limit allows)
        runs = max_runs if ex.has("max_runs") else max(2, min(max_runs, MAX_RUN_STEPS // (frames * frame_ticks)))
    if runs * frames * frame_ticks > MAX_RUN_STEPS:
        raise ConfigError(f, "experiment.runs", runs, f"runs x servo ticks must be <= {MAX_RUN_STEPS:.0e}")
    delay = sv.integer("delay", 2, lo=1, hi=100)
    if delay >= frames:
        raise ConfigError(f, "servo.delay", delay, f"must be fewer frames than the run's {frames}")
    noise = sv.number("noise", 10.0, nonneg=True)
    settle = sv.number("settle", 15.0, nonneg=True)
    if settle >= frames * frame_dt:
        raise ConfigError(f, "servo.settle", settle, f"must be shorter than the run ({frames * frame_dt:g} s)")
    accel_ff = sv.number("accel_ff", 0.0, nonneg=True)
    sv.check_unknown()
    tg = Section(f, "target", raw["target"])
    kind = tg.string("kind", required=True, choices=tuple(TARGET_KINDS))
    if kind == "sine":
        target = {"kind": kind, "amplitude": tg.number("amplitude", 83.33, positive=True),
                  "omega": tg.number("omega", 0.6, positive=True)}
    else:
        target = {"kind": kind, "half_angle": tg.number("half_angle", 13.5, positive=True, hi=80.0),
                  "axis_elevation": tg.number("axis_elevation", 26.0, lo=0.0, hi=80.0),
                  "period": tg.number("period", 4.5, positive=True)}
    tg.check_unknown()
    estimators, labels, trimmed = [], set(), set()
    tables = raw.get("estimator", [])
    if not isinstance(tables, list):
        raise ConfigError(f, "[[estimator]]", tables, "must be [[estimator]] tables")
    for i, table in enumerate(tables, start=1):
        es = Section(f, f"estimator[{i}]", table)
        kind = ESTIMATORS[es.string("kind", required=True, choices=tuple(ESTIMATORS))]
        label = es.label("label", kind.name)
        if label.strip() == "perfect":
            raise ConfigError(f, f"estimator[{i}].label", label, "must not be 'perfect' (a case's ideal estimator)")
        check_unique(f, f"estimator[{i}].label", label, trimmed, "estimators")
        labels.add(label)
        cfg = UnitConfig(label, kind.name, declared_numbers(es, kind.params), declared_options(es, kind.options))
        es.check_unknown()
        estimators.append(cfg)
    cases, case_labels, case_trimmed = [], set(), set()
    tables = raw["case"]
    if not isinstance(tables, list) or not tables:
        raise ConfigError(f, "[[case]]", tables, "at least one [[case]] table is required")
    for i, table in enumerate(tables, start=1):
        cs = Section(f, f"case[{i}]", table)
        mode = cs.string("mode", required=True, choices=MODES)
        est = cs.string("estimator", None)
        if est is not None and est != "perfect" and est not in labels:
            raise ConfigError(f, f"case[{i}].estimator", est, f"must be 'perfect' or an estimator label from: {', '.join(labels) or '(none)'}")
        if mode != "double_loop" and est is None:
            raise ConfigError(f, f"case[{i}].estimator", None, f"mode {mode} needs an estimator (or \"perfect\")")
        label = cs.label("label", mode if est is None else f"{mode}, {est}")
        check_unique(f, f"case[{i}].label", label, case_trimmed, "cases")
        case_labels.add(label)
        cs.check_unknown()
        cases.append(Case(label, mode, est))
    camera_loops = [c.mode for c in cases if c.mode in CAMERA_LOOPS]
    if camera_loops:
        _check_latency(f, delay, frame_dt, camera_loops[0])
    rp = Section(f, "report", raw.get("report", {}))
    level, baseline = level_and_baseline(rp, case_labels, "cases")
    rp.check_unknown()
    return ServoExperiment(f, name, runs, seed, frames, frame_dt, frame_ticks, delay, noise, settle, accel_ff, target,
                           estimators, cases, raw, precision=precision, chunk=chunk, level=level, baseline=baseline,
                           target_precision=target_precision)
