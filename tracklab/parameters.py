"""The vocabulary every component declares its numbers in: ``Param`` and its constraints.

A number of a filter kind, or of a filter of one's own (``tracklab.declare``), is declared
once with what it is (``doc``), its ``unit``, its ``default`` and its ``constraint``: where
its values lie. Everything else reads the declaration — parsing and validation of the
experiment files, ``tracklab list``, ``tune`` (the constraint's unconstrained coordinates,
in which Adam moves), ``sweep`` (which numbers a scale factor may multiply) and the tuned
file's write-back (``Param.write``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.toml_fields import MAX_MAGNITUDE

# ----------------------------------------------------------------------------- constraints


@dataclass(frozen=True)
class Constraint:
    """Where a parameter's values lie.

    ``inside`` tests each value against ``bounds``, the interval an experiment file may
    hold; ``to_free``/``from_free`` map the values onto the real line and back (tune
    optimises there; None: not tunable); ``scalable``: a sweep may multiply the values
    by a positive factor.
    """

    bounds: str
    inside: Callable[[np.ndarray], np.ndarray]
    to_free: Callable | None = None
    from_free: Callable | None = None
    scalable: bool = False
    members: tuple[str, ...] = ()  # parameters transformed together; empty: each on its own
    says: str = ""  # what a file's value must be, in words (default: in ``bounds``)

    @property
    def requirement(self) -> str:
        """What a value must be, as a one-line refusal says it."""
        return self.says or f"in {self.bounds}"

    @property
    def tunable(self) -> bool:
        return self.to_free is not None

    def encode(self, values: dict) -> dict:
        """Unconstrained coordinates of ``values`` (name -> value)."""
        return {n: self.to_free(jnp.asarray(v, float)) for n, v in values.items()}

    def decode(self, theta: dict) -> dict:
        """The values at unconstrained coordinates ``theta`` (name -> coordinates)."""
        return {n: self.from_free(u) for n, u in theta.items()}

    def contains(self, values: dict) -> bool:
        return all(bool(np.all(self.inside(np.asarray(v, float)))) for v in values.values())


@dataclass(frozen=True)
class StabilityRegion(Constraint):
    """α-β(-γ) gains, jointly inside the stability region (Jury): 0 < α < 2, 0 < β < 4 − 2α,
    0 < γ < 4αβ/(2 − α); tuned as α = 2σ(u), β = (4 − 2α)σ(v), γ = 4αβ/(2 − α)·σ(w), σ the
    logistic. A file holds each gain in (0, 4)."""

    bounds: str = "(0, 4)"
    inside: Callable = lambda v: (v > 0) & (v < 4)
    scalable: bool = True
    members: tuple[str, ...] = ("alpha", "beta", "gamma")

    @property
    def tunable(self) -> bool:
        return True

    def encode(self, values):
        logit = jax.scipy.special.logit
        a, b = jnp.asarray(values["alpha"], float), jnp.asarray(values["beta"], float)
        theta = {"alpha": logit(a / 2), "beta": logit(b / (4 - 2 * a))}
        if "gamma" in values:
            theta["gamma"] = logit(jnp.asarray(values["gamma"], float) * (2 - a) / (4 * a * b))
        return theta

    def decode(self, theta):
        a = 2 * jax.nn.sigmoid(theta["alpha"])
        b = (4 - 2 * a) * jax.nn.sigmoid(theta["beta"])
        out = {"alpha": a, "beta": b}
        if "gamma" in theta:
            out["gamma"] = 4 * a * b / (2 - a) * jax.nn.sigmoid(theta["gamma"])
        return out

    def contains(self, values):
        a, b = np.asarray(values["alpha"], float), np.asarray(values["beta"], float)
        ok = (a > 0) & (a < 2) & (b > 0) & (b < 4 - 2 * a)
        if "gamma" in values:
            g = np.asarray(values["gamma"], float)
            ok = ok & (g > 0) & (g < 4 * a * b / (2 - a))
        return bool(np.all(ok))


# variances, the tracking index, the STF's weakening factor: logarithms
positive = Constraint(f"(0, {MAX_MAGNITUDE:g}]", lambda v: (v >= 1e-300) & (v <= MAX_MAGNITUDE),
                      to_free=jnp.log, from_free=jnp.exp, scalable=True, says="a number > 0")
# forgetting factors: logit
unit_interval = Constraint("(0, 1]", lambda v: (v > 0) & (v <= 1),
                           to_free=lambda v: jax.scipy.special.logit(jnp.minimum(v, 1.0 - 1e-6)),
                           from_free=jax.nn.sigmoid, scalable=True)
# network weights: as they are
free = Constraint("(-inf, inf)", np.isfinite, to_free=lambda v: v, from_free=lambda v: v, says="a finite number")
stable_gains = StabilityRegion()
# fixed by the file, never tuned
nonnegative = Constraint(f"[0, {MAX_MAGNITUDE:g}]", lambda v: (v >= 0) & (v <= MAX_MAGNITUDE), says="a number >= 0")
probabilities = Constraint("[0, 1], summing to 1", lambda v: (v >= 0) & (v <= 1))


def bounded(lo: float, hi: float) -> Constraint:
    """(lo, hi), tuned as lo + (hi − lo)·σ(u), σ the logistic."""
    lo, hi = float(lo), float(hi)
    width = hi - lo
    return Constraint(f"({lo:g}, {hi:g})", lambda v: (v > lo) & (v < hi),
                      to_free=lambda v: jax.scipy.special.logit((v - lo) / width),
                      from_free=lambda u: lo + width * jax.nn.sigmoid(u), scalable=False)


def constraint_of(spec) -> Constraint:
    """A constraint a user names for a parameter of their own filter: "positive" (logarithm),
    "unit" (in (0, 1), logit), "free" (as it is), or (lo, hi) (bounded, scaled logit).
    ``ValueError`` in one line for anything else."""
    named = {"positive": positive, "unit": bounded(0.0, 1.0), "free": free}
    if isinstance(spec, str) and spec in named:
        return named[spec]
    if isinstance(spec, Constraint) and spec.tunable and not spec.members:
        return spec
    if (isinstance(spec, (tuple, list)) and len(spec) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in spec)
            and spec[0] < spec[1]):
        return bounded(*spec)
    raise ValueError(f"constraint {spec!r}: must be \"positive\", \"unit\" (in (0, 1)), \"free\" or (lo, hi) with lo < hi")


def interval(lo, hi) -> Constraint:
    """[lo, hi], fixed by the file."""
    return Constraint(f"[{lo:g}, {hi:g}]", lambda v: (v >= lo) & (v <= hi))


# ------------------------------------------------------------------------------ declarations


def write_value(table, name, value, where=None):
    """A tuned value into its experiment-file table under its own name: a number, or a list."""
    v = np.asarray(value, float)
    table[name] = float(v) if v.ndim == 0 else v.tolist()


@dataclass(frozen=True)
class Param:
    """One declared number (or vector of numbers): what it is (``doc``), where its values lie
    (``constraint``: a ``Constraint``, or for a filter of one's own "positive", "unit",
    "free" or (lo, hi)), its ``unit`` and ``default`` (a number, a tuple, None when another
    field gives it, or a function of the factory's context: a default from the scenario or
    the sensors), whether ``tracklab tune`` may name it and a ``sweep`` scale factor multiply
    it, and how a tuned value goes back into the file (``write(table, name, value, where)``;
    None: no file holds it)."""

    doc: str = ""
    constraint: Constraint | str | tuple = "positive"
    unit: str = ""
    default: Any = None
    tune: bool = False  # `tracklab tune --params` may name it
    sweep: bool = False  # `tracklab sweep --grid NAME=…` may scale it
    write: Callable | None = write_value

    def __post_init__(self):
        if not isinstance(self.constraint, Constraint):
            object.__setattr__(self, "constraint", constraint_of(self.constraint))
        if self.tune and not self.constraint.tunable:
            raise ValueError(f"{self.doc}: a tuned parameter needs a constraint with unconstrained coordinates")
        if self.sweep and not self.constraint.scalable:
            raise ValueError(f"{self.doc}: a swept parameter needs a constraint a scale factor keeps")

    def value(self, context=None):
        """Its default: the declared value, or the declared function of ``context``."""
        return self.default(context) if callable(self.default) else self.default

    def describe(self, name, with_doc=False) -> str:
        """``name [unit] = default`` (and what it is, ``with_doc``), as `tracklab list` shows it;
        marked ``*`` when `tracklab tune` may tune it, ``×`` when a sweep may scale it."""
        unit = f" [{self.unit}]" if self.unit else ""
        marks = ("*" if self.tune else "") + ("×" if self.sweep else "")
        marks = f" {marks}" if marks else ""
        d = self.default
        if callable(d):  # a default of the context: what the doc says of it
            return f"{name}{unit} ({self.doc}){marks}"
        doc = f" ({self.doc})" if with_doc and self.doc else ""
        if d is None:
            return f"{name}{unit}{doc}{marks}"
        shown = f"[{', '.join(f'{v:g}' for v in d)}]" if isinstance(d, tuple) else f"{d:g}"
        return f"{name}{unit} = {shown}{doc}{marks}"


@dataclass(frozen=True)
class Option:
    """A structural field of a kind's table, declared once: an integer in [lo, hi], or one of
    ``choices`` (strings); what the program is compiled for, or how a run is set up (a network's
    size, a training's steps), never one of its numbers."""

    doc: str
    default: int | str
    choices: tuple[str, ...] = ()
    lo: int | None = None
    hi: int | None = None

    def describe(self, name) -> str:
        """``name = default`` with what it may be, as `tracklab list` shows it."""
        allowed = " | ".join(self.choices) if self.choices else f"{self.lo}…{self.hi}"
        return f"{name} = {self.default!r} ({allowed})"
