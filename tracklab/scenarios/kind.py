"""What a scenario kind declares beside its code, once, for the experiment files to read.

A kind's module ends with its declaration (a ``ScenarioKind``): what it is, the numbers of its
``[scenario]`` table (``params``: name -> ``Param``, each read, defaulted and checked as
declared) and how the scenario is made from them (``build(context, numbers, fields)``; ``fields``
reads a table's other fields — a list, a path — with one-line refusals). ``registry.SCENARIOS``
lists the kinds; the file's reader and ``tracklab list`` read them there.

``Scenario`` holds what a truth has unless it says otherwise: metres and m/s on x, y, z, no
acceleration noise, nothing to refuse.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np

from tracklab.parameters import Param
from tracklab.toml_fields import MAX_MAGNITUDE


class Scenario:
    """What every scenario has unless it says otherwise (the built-in ones and ``Generated``)."""

    units = ("m", "m/s")  # of position and velocity
    accel_sigma = 0.0  # the truth's acceleration noise (m/s²): the default of a filter's q = σ²
    advance = None  # a one-step advance (a truth drawn step by step inside the chunk's scan), or None

    @property
    def axes(self) -> tuple[str, ...]:
        """The names of its position axes."""
        return ("x", "y", "z")[: self.dim]

    def problem(self) -> str | None:
        """Why it cannot be simulated (None if it can)."""
        return None


class ScenarioContext(NamedTuple):
    """What a scenario kind is made with besides its table: the experiment's step and step count,
    the dimension its sensors observe (None when none fixes it) and the file's folder."""

    dt: float
    steps: int
    dim: int | None
    folder: Path


@dataclass(frozen=True)
class ScenarioKind:
    """A kind of truth a [scenario] table may name."""

    name: str
    doc: str
    params: Mapping[str, Param]
    build: Callable[[ScenarioContext, dict, Any], Any]  # (context, its numbers, the table's fields) -> scenario


def numbers(v, counts):
    """A list of ``counts`` (allowed lengths) finite numbers as a tuple of floats; None if it is not one."""
    if (not isinstance(v, list) or len(v) not in counts
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x) or abs(x) > MAX_MAGNITUDE
                   for x in v)):
        return None
    return tuple(float(x) for x in v)
