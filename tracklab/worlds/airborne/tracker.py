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
"""

from __future__ import annotations

from typing import Callable, NamedTuple


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
