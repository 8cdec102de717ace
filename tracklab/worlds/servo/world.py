"""The servo world (paper 003), as the Monte-Carlo runner drives it.

A chunk of runs is every case's closed loop (``loops.track``: the estimator's
prediction steers the mount) over the same runs — run i's miss-distance noise
comes from the runner's ``fold_in(key, i)`` whatever the case — reduced to sums
over the runs: per case the number of healthy runs, the sums and the largest
of each run's statistics after ``settle`` (maximum tracking error, random error,
the estimator's largest rate error), and run 0's error series for the figures;
and each run's statistics themselves as the runner's ``per_run`` samples (in the
tables' units: ′, ″, °/s), behind the intervals and paired comparisons.

A run is diverged (counted, not averaged) when a statistic is not finite or its
tracking error passes ``LOST`` (half a turn: the target is lost).

Numbers are the params' leaves: the target's, the noise, the acceleration
feed-forward gain, each estimator's parameters (the DEKF's trained weights
included), the prior, and the after-``settle`` masks with the harmonic fit's
basis and pseudo-inverse (computed on the host from ``settle`` and the target's
frequency). The structure is the timing (frames, ticks a frame, the frame
period, which the correctors are discretised with, the delay), the target's
kind, the cases' modes and estimator kinds (a DEKF's network shape and input
scaling), and the chunk size.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from tracklab.filters.core import Prior
from tracklab.montecarlo import runner
from tracklab.worlds.servo.loops import AzimuthAxis, sine_target, track
from tracklab.worlds.servo.registry import ESTIMATORS

LOST = 180.0  # deg: a run whose tracking error passes half a turn has lost the target (diverged)


def cone_target(half_angle, axis_elevation, period):
    """Azimuth of a point circling a cone (the dynamic-target rig): θ, θ̇, θ̈ in degrees."""
    b, e = jnp.radians(half_angle), jnp.radians(axis_elevation)
    a = jnp.stack([0.0 * e, jnp.cos(e), jnp.sin(e)])  # axis towards north at elevation e
    e1 = jnp.array([1.0, 0.0, 0.0])
    e2 = jnp.cross(a, e1)
    w = 2 * math.pi / period

    def az(t):
        d = jnp.cos(b) * a + jnp.sin(b) * (jnp.cos(w * t) * e1 + jnp.sin(w * t) * e2)
        return jnp.degrees(jnp.arctan2(d[0], d[1]))

    d1 = jax.grad(az)
    d2 = jax.grad(d1)

    def target(t):
        t = jnp.asarray(t, jnp.result_type(float))
        return jnp.stack([az(t), d1(t), d2(t)])

    return target


def target_function(kind: str, numbers: dict):
    """θ(t), θ̇(t), θ̈(t) of a [target] table's numbers."""
    if kind == "sine":
        return sine_target(numbers["amplitude"], numbers["omega"])
    return cone_target(numbers["half_angle"], numbers["axis_elevation"], numbers["period"])


@dataclass(frozen=True)
class CaseSpec:
    """One [[case]] as structure: its mode and what estimates the target for it; its label names it in
    the tables only."""

    label: str = field(compare=False, repr=False)
    mode: str  # double_loop | velocity_lag | on_axis
    estimator: str | None  # an estimator kind (registry.ESTIMATORS), "perfect" or None
    network: Any = None  # what its code is compiled for beyond its kind (a DEKF's Network)


@dataclass(frozen=True)
class ServoStructure:
    cases: tuple[CaseSpec, ...]
    frames: int
    frame_ticks: int
    frame_dt: float
    delay: int  # frames between exposure and delivery
    target: str  # "sine" | "cone"
    chunk: int

    @property
    def labels(self):
        return [c.label for c in self.cases]

    @property
    def ticks(self) -> int:
        return self.frames * self.frame_ticks


class ServoParams(NamedTuple):
    """Every number of a servo experiment: the program's argument."""

    target: dict  # the [target] table's numbers
    noise: Any  # deg, the miss distance's noise
    accel_ff: Any  # s, on_axis acceleration feed-forward gain
    prior_var: Any  # (3,) the estimators' prior variances of θ, θ̇, θ̈
    estimators: list  # per case: its estimator's parameters (None without one)
    late: Any  # (ticks,) 1 after settle
    frame_late: Any  # (frames,) 1 after settle
    basis: Any  # (ticks, 7) constant and the target's first three harmonics, zero before settle
    pinv: Any  # (7, ticks) its pseudo-inverse


SAMPLES = ("max_track_err", "random_err", "max_rate_err")  # per run: ′, ″, °/s


def healthy(max_err, random_err, rate_err=None):
    """The runs that count: every statistic finite, the tracking error within ``LOST``."""
    ok = jnp.isfinite(max_err) & jnp.isfinite(random_err) & (max_err <= LOST)
    return ok & jnp.isfinite(rate_err) if rate_err is not None else ok


def run_samples(max_err, random_err, rate_err=None):
    """Each run's statistics in the tables' units (``SAMPLES``; the rate error 0 without an estimator)."""
    rate = rate_err if rate_err is not None else jnp.zeros_like(max_err)
    return 60.0 * max_err, 3600.0 * random_err, rate


def case_sums(max_err, random_err, rate_err, live, track_ms=None, rate_ms=None):
    """One case's sums over runs from each run's statistics (deg, deg, deg/s; ``rate_err`` None
    without an estimator): (what adds up, what is the largest) — healthy runs counted and summed
    (their largest maximum kept), the others counted as diverged: a non-finite statistic, or an
    error past ``LOST``."""
    ok = healthy(max_err, random_err, rate_err)
    use = live & ok
    dtype = jnp.result_type(max_err)
    added = {
        "healthy": jnp.sum(use.astype(dtype)),
        "diverged": jnp.sum((live & ~ok).astype(dtype)),
        "sum_max_err": jnp.sum(jnp.where(use, max_err, 0.0)),
        "sum_random_err": jnp.sum(jnp.where(use, random_err, 0.0)),
        "sum_rate_err": jnp.sum(jnp.where(use, rate_err, 0.0)) if rate_err is not None else jnp.zeros((), dtype),
    } | {name: jnp.sum(jnp.where(use, v, 0.0)) for name, v in (("sum_track_ms", track_ms), ("sum_rate_ms", rate_ms))
         if v is not None}
    return added, {"max_max_err": jnp.max(jnp.where(use, max_err, -jnp.inf))}


def _estimator(case: CaseSpec, frame_dt):
    """A case's estimator, its numbers arriving with the params (none for "perfect" or none)."""
    return ESTIMATORS[case.estimator].build(frame_dt, case.network) if case.estimator in ESTIMATORS else None


def _chunk(structure: ServoStructure):
    axis = AzimuthAxis(dt=structure.frame_dt / structure.frame_ticks)

    def one(params, case, est, est_params, key):
        target = target_function(structure.target, params.target)
        prior = Prior(target(0.0), jnp.diag(params.prior_var))
        r = track(axis, case.mode, target, structure.frames, key, estimator=est, prior=prior,
                  frame_ticks=structure.frame_ticks, delay=structure.delay, noise=params.noise,
                  accel_ff=params.accel_ff, perfect=case.estimator == "perfect", estimator_params=est_params)
        late = params.late > 0
        e = jnp.where(late, r["error"], 0.0)  # the error after settle
        resid = jnp.where(late, e - params.basis @ (params.pinv @ e), 0.0)
        random_err = jnp.sqrt(jnp.sum(resid**2) / jnp.sum(params.late))
        max_err = jnp.max(jnp.abs(e))
        frame_late = params.frame_late > 0
        rate = jnp.max(jnp.where(frame_late, jnp.abs(r["rate_error"]), 0.0))
        # mean squares after settle: what tuning minimises
        track_ms = jnp.sum(e**2) / jnp.sum(params.late)
        rate_ms = jnp.sum(jnp.where(frame_late, r["rate_error"] ** 2, 0.0)) / jnp.sum(params.frame_late)
        return max_err, random_err, rate, track_ms, rate_ms, r["error"], r["rate_error"]

    def local(params: ServoParams, keys, live, exclude):
        # built while the program is traced, in its precision (their constants are float64 in a float64 run)
        estimators = [_estimator(c, structure.frame_dt) for c in structure.cases]
        added, largest, first, values, oks = {}, {}, {}, [], []
        for i, (case, est) in enumerate(zip(structure.cases, estimators)):
            mx, rnd, rate, track_ms, rate_ms, err, rate_err = jax.vmap(
                lambda k: one(params, case, est, params.estimators[i], k))(keys)
            rate = rate if est is not None else None
            key = runner.lane_key(i)
            added[key], largest[key] = case_sums(mx, rnd, rate, live & ~exclude[i], track_ms, rate_ms)
            first[key] = {"example_error": err[0], "example_rate_error": rate_err[0]}
            values.append(jnp.stack(run_samples(mx, rnd, rate)))
            oks.append(healthy(mx, rnd, rate) & live & ~exclude[i])
        values = jnp.stack(values)
        return runner.Sums(added, largest, first, {"values": values, "ok": jnp.stack(oks), "kept": values[:, :1]})

    return local


@functools.lru_cache(maxsize=16)
def world(structure: ServoStructure) -> runner.World:
    """The servo world of a structure (one per structure: its compiled programs are shared)."""
    return runner.World(structure, _chunk(structure), len(structure.cases), structure.chunk)
