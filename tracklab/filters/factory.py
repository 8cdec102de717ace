"""A filter factory of one's own with its numbers declared: ``@tracklab.declare``.

A ``[[filter]]`` table with ``kind = "module:factory"`` calls ``factory(context, **its other
keys)``, which returns a ``Filter``. Declaring the factory's numbers puts them on the footing
of a built-in kind's::

    @tracklab.declare(
        tau=Param(doc="manoeuvre time constant", unit="s", default=20.0, constraint="positive"),
        sigma_m=Param(doc="RMS manoeuvre acceleration", unit="m/s²", default=5.0, constraint="positive"))
    def singer(context, order=2):
        def step(params, state, meas):
            tau, sigma_m = params["tau"], params["sigma_m"]
            ...
        return tracklab.Filter(init, step, params={})

A declared number is not passed to the factory: it arrives in the filter's ``params`` under
its name (the table's value, else the default; a default may be a function of the context,
e.g. ``lambda c: np.diag(c.R)``), so it is an input of the compiled program — editing it in
the file, sweeping it (``filter[LABEL].tau=…``) and tuning it (``tracklab tune --params
tau``, in the coordinates of its constraint) reuse the program, and a tuned value goes back
into the file under its name. Every other key of the table is structure: the factory sees
it, and a change compiles anew. Called from Python, ``singer(context, tau=30.0)`` gives the
same filter the file would.
"""

from __future__ import annotations

import functools
from typing import Callable, Mapping

import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Filter
from tracklab.parameters import Param
from tracklab.toml_fields import MAX_MAGNITUDE


class Declared:
    """A filter factory and the numbers it declares (name -> ``Param``); called like the factory."""

    def __init__(self, factory: Callable, params: Mapping[str, Param]):
        functools.update_wrapper(self, factory)
        self.factory = factory
        self.params = dict(params)

    def value(self, name: str, given, context):
        """A declared number as the filter's params hold it (a float array of its default's shape):
        ``given``, or its default when None; ValueError in one line for one that does not fit its
        declaration (``problem``)."""
        default = self.params[name].value(context)
        v = default if given is None else given
        why = self.problem(name, v, default)
        if why:
            raise ValueError(f"{name} = {v!r}: {why}")
        a = np.asarray(v, float)
        return a if default is None else np.broadcast_to(a, np.shape(default)).copy()

    def problem(self, name: str, value, default=None) -> str | None:
        """Why ``value`` cannot be the declared number ``name`` (None if it can): not a number or a
        list of numbers, not finite, not of its default's shape (a single number for a list is
        every entry), or outside its constraint."""
        if value is None:
            return "is required (it has no default)"
        if isinstance(value, bool) or (isinstance(value, (list, tuple)) and any(isinstance(x, bool) for x in value)):
            return "must be a number or a list of numbers"
        try:
            a = np.asarray(value, float)
        except (TypeError, ValueError):
            return "must be a number or a list of numbers"
        if a.ndim > 1 or not np.all(np.isfinite(a)) or np.any(np.abs(a) > MAX_MAGNITUDE):
            return f"must be a finite number (or a list of them) of magnitude <= {MAX_MAGNITUDE:g}"
        shape = None if default is None else np.shape(default)
        if shape is not None and a.shape != shape and a.ndim != 0:
            return ("must be a number" if shape == () else f"must be a number or a list of {shape[0]} numbers") + \
                   f" (as its default: {np.asarray(default).tolist()})"
        if not self.params[name].constraint.contains({name: a}):
            return f"must be {self.params[name].constraint.requirement}"
        return None

    def __call__(self, context, *args, **options) -> Filter:
        values = {n: jnp.asarray(self.value(n, options.pop(n, None), context)) for n in self.params}
        flt = self.factory(context, *args, **options)
        if not isinstance(flt, Filter):
            return flt  # the caller says what is wrong with it
        own = {} if flt.params is None else flt.params
        if not isinstance(own, dict):
            raise TypeError(f"a factory with declared parameters returns Filter(params=a dict or None), not "
                            f"{type(own).__name__}: the declared ones are added to it")
        clash = sorted(set(own) & set(values))
        if clash:
            raise TypeError(f"{clash[0]} is declared and also set in the returned Filter's params: leave it to "
                            "the declaration")
        return flt._replace(params={**own, **values}, declared=dict(self.params))


def declare(**params: Param) -> Callable[[Callable], Declared]:
    """Declare a filter factory's numbers (see the module's doc): ``@declare(name=Param(...), …)``.
    Each may be tuned when its constraint has unconstrained coordinates, and scaled by a sweep's
    scale factor when the constraint keeps a scaled value, unless the Param says otherwise."""
    for name, p in params.items():
        if not isinstance(p, Param):
            raise TypeError(f"declare: {name} must be a tracklab.Param, not {type(p).__name__}")
        if not name.isidentifier() or name in ("kind", "label", "sensors"):
            raise ValueError(f"declare: {name!r} cannot name a parameter (a table's kind, label and sensors are "
                             "tracklab's)")
    declared = {n: Param(p.doc, p.constraint, p.unit, p.default, tune=p.tune or p.constraint.tunable,
                         sweep=p.sweep or p.constraint.scalable, write=p.write) for n, p in params.items()}
    return lambda factory: Declared(factory, declared)


def declared(factory) -> dict[str, Param]:
    """The numbers a factory declares (none for a plain function)."""
    return dict(factory.params) if isinstance(factory, Declared) else {}


__all__ = ["Declared", "declare", "declared"]
