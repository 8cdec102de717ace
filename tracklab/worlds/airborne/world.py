"""The airborne closed-loop world (paper 001), as the Monte-Carlo runner drives it.

A chunk of runs is every tracker's closed loop (``closed_loop.engage``: the
estimate steers the antenna) over the same runs, reduced to per-period sums
over the runs still in lock (``closed_loop.sums``), and each run's averages over
the report windows (``closed_loop.run_samples``), handed to the runner as
``per_run`` for the intervals and paired comparisons. Run i draws from the
runner's ``fold_in(key, i)`` whatever the tracker, so the trackers are compared
on the same target paths, designation errors and noise.

Numbers are the params' leaves: the engagement, the error signals' noise and
gains, the gates, the designation errors, the jolt, the Singer perturbation's
one-tick transition and noise factor (computed in float64 on the host), each
tracker's parameters and prior, the report windows' averaging weights. The structure is the timing (radar sample
period, samples per filter period, the antenna's lag, which the classical
tracker's compensator is discretised with), the number of filter periods, the
jolt's tick, whether the Singer perturbation is on, the trackers' kinds and
the chunk size.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from tracklab.montecarlo import runner
from tracklab.worlds.airborne.closed_loop import LoopConfig, engage, run_samples, sums
from tracklab.worlds.airborne.registry import TRACKERS
from tracklab.worlds.airborne.tracker import Timing


@dataclass(frozen=True)
class TrackerSpec:
    """One [[tracker]] as structure: its kind and structural choices ((field, value) pairs); its label
    names it in the tables only."""

    label: str = field(compare=False, repr=False)
    kind: str  # a key of registry.TRACKERS
    choices: tuple = ()

    def build(self, timing: Timing):
        return TRACKERS[self.kind].build(timing, dict(self.choices))


@dataclass(frozen=True)
class AirborneStructure:
    trackers: tuple[TrackerSpec, ...]
    timing: Timing
    periods: int  # filter periods a run
    jolt_tick: int  # the tick of the antenna's jolt (-1: none)
    singer: bool  # the Singer perturbation on the nominal path
    chunk: int  # runs per chunk

    @property
    def labels(self):
        return [t.label for t in self.trackers]


class AirborneParams(NamedTuple):
    """Every number of an airborne experiment: the program's argument."""

    engagement: Any  # airborne.engagement.Engagement (a pytree)
    k: Any  # (4,) detector gains
    sigma: Any  # (4,) per-sample noise of the error signals
    limits: Any  # (3,) beam (rad), range gate (m), velocity gate (m/s)
    acquisition: Any  # (4,) designation errors (std)
    jolt: Any  # rad, about the d axis
    singer_phi: Any  # (3, 3)
    singer_L: Any  # (3, 3)
    trackers: list  # each tracker's parameters (pytree)
    sd0: list  # each tracker's prior standard deviations (9,)
    windows: Any  # (W, periods) each report window's averaging weights (the last: the whole run)


def _chunk(structure: AirborneStructure):
    def local(params: AirborneParams, keys, live, exclude):
        # built while the program is traced, in its precision (their constants are float64 in a float64 run)
        trackers = [t.build(structure.timing) for t in structure.trackers]
        cfg = LoopConfig(structure.timing, structure.periods, params.k, params.sigma, tuple(params.limits),
                         params.acquisition, structure.jolt_tick, params.jolt, structure.singer, params.singer_phi,
                         params.singer_L)
        runs = jax.vmap(lambda key: engage(params.engagement, trackers, params.trackers, cfg, params.sd0, key))(keys)
        out, samples = {}, []
        for i, (spec, res) in enumerate(zip(structure.trackers, runs)):
            out[runner.lane_key(i)] = sums(res, live & ~exclude[i])
            samples.append(run_samples(res, live & ~exclude[i], params.windows))
        values, ok, kept = (jnp.stack(a) for a in zip(*samples))
        return runner.Sums(add=out, per_run={"values": values, "ok": ok, "kept": kept})

    return local


@functools.lru_cache(maxsize=16)
def world(structure: AirborneStructure) -> runner.World:
    """The airborne world of a structure (one per structure: its compiled programs are shared)."""
    return runner.World(structure, _chunk(structure), len(structure.trackers), structure.chunk,
                        compiler_options(structure))


def compiler_options(structure: AirborneStructure) -> tuple:
    """XLA's CPU fusion emitters (``tracklab.configure()`` turns them off) on when two trackers
    share their code (kind and structural choices): each such tracker then costs about half
    the compiling it costs with them off, while one whose code no other shares costs more. Compiling a
    16-run chunk, on against off: airborne_radar_lambda (five joint EKFs) 18.7 against 27.3 s,
    airborne_radar_mismatch (five) 19.5 against 30.9 s, airborne_radar_moose (three and two
    Moose) 21.2 against 29.3 s; airborne_radar (three kinds) 14.1 against 10.8 s,
    airborne_radar_range (three codes) 16.0 against 13.1 s; one joint EKF alone 7.2 against
    5.5 s (``benchmarks/compile.md``)."""
    codes = {(t.kind, t.choices) for t in structure.trackers}
    return (("xla_cpu_use_fusion_emitters", True),) if len(codes) < len(structure.trackers) else ()
