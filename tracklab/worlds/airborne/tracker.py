"""What a four-coordinate tracker is to the closed-loop simulation (``closed_loop.engage``).

The radar samples its four error signals every tick (10 ms); the trackers
here run their filter every ``n`` ticks (50 ms) on the pre-averaged signals.
A tracker is five pure functions of its parameters (a pytree) and its state:

* ``start(params, x0, P0)`` — the state at acquisition (antenna at rest);
* ``tick(params, state, i)`` → (antenna rate command (ω_e, ω_d) held over tick
  i of the period, gates (r, ṙ) for the sample at the tick's end);
* ``sample(params, state, i, z)`` — take that sample's error signals z (4);
* ``update(params, state, w_a)`` — the filter update at the period's end,
  ``w_a`` being the antenna rate the gyros read now; it also plans the next
  period (command, predicted gates);
* ``estimate(state)`` → (x̂ in the 9-state layout of ``boresight``, P or NaN).

A kind of tracker an ``[[tracker]]`` table names is declared once, at the end of its module
(a ``TrackerKind``: its numbers, its structural choices, its code and how its numbers make its
params), and listed in ``worlds.airborne.registry``; the file's reader, ``tracklab list``,
tuning, sweeps and the tuned file's write-back read the declaration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np

from tracklab.parameters import Constraint, Param, positive


class Timing(NamedTuple):
    dt: float  # s, the radar's sample period (one tick)
    n: int  # ticks pre-averaged per filter period
    lag: float  # s, the antenna's rate-loop time constant


class Tracker(NamedTuple):
    start: Callable
    tick: Callable
    sample: Callable
    update: Callable
    estimate: Callable


class Setting(NamedTuple):
    """What a tracker's numbers are turned into its params with: the experiment's engagement,
    the error signals' noise and detector gains, the designation errors and the timing."""

    engagement: Any  # engagement.Engagement
    noise: Any  # (4,) per-sample noise of the error signals (rad, rad, m, m/s)
    gains: Any  # (4,) detector gains
    acquisition: Any  # (4,) designation errors (std)
    timing: Timing


@dataclass(frozen=True)
class TrackerKind:
    """A kind of tracker a [[tracker]] table may name: what it is, the numbers of its table
    (``params``: name -> Param, each read, checked and tuned as declared), its structural choices
    (``choices``: field -> the strings allowed, the default first), its code
    (``build(timing, choices) -> Tracker``) and its params (``numbers(setting, numbers) -> (params
    pytree, prior standard deviations (9,))``: traceable in the numbers, which tuning varies)."""

    name: str
    doc: str
    params: Mapping[str, Param]
    build: Callable[[Timing, Mapping[str, str]], Tracker]
    numbers: Callable[[Setting, Mapping[str, Any]], tuple[Any, Any]]
    choices: Mapping[str, tuple[str, ...]] = field(default_factory=dict)


def prior_sd(setting: Setting, sigma_m, sigma_r):
    """The prior standard deviations of the 9 states at acquisition: the designation errors, and the
    model's acceleration spread for the accelerations."""
    acq = setting.acquisition
    return np.array([acq[0], acq[1], sigma_m, acq[0], acq[1], sigma_m, acq[2], acq[3], sigma_r], float)


_gain = Constraint("(0, 1000]", lambda v: (v > 0) & (v <= 1000), to_free=positive.to_free, from_free=positive.from_free,
                   scalable=True)
FILTERING = {  # the numbers of every tracker with a filter (the joint EKF's model)
    "q_scale": Param("the filter's Q against the truth's (its Singer σ² scaled)", positive, "", 1.0, tune=True, sweep=True),
    "r_scale": Param("the filter's R against the truth's", positive, "", 1.0, tune=True, sweep=True),
    "lam": Param("eq. 1's gain on ε̂", _gain, "1/s", 5.0, tune=True),
    "sigma_m": Param("the model's Singer σ of the angular accelerations, default the engagement's", positive, "m/s²",
                     lambda s: s.engagement.singer_sigma),
    "tau": Param("its Singer τ, default the engagement's", positive, "s", lambda s: s.engagement.singer_tau),
    "sigma_r": Param("its Singer σ of the range acceleration, default the engagement's", positive, "m/s²",
                     lambda s: s.engagement.singer_sigma),
    "tau_r": Param("its Singer τ of the range acceleration, default the engagement's", positive, "s",
                   lambda s: s.engagement.singer_tau),
}
