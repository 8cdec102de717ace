"""What a filter kind declares beside its code, once, for everything else to read.

A kind's module ends with its declaration::

    KIND = FilterKind(
        name="ekf", doc="extended Kalman filter, Jacobians by autodiff",
        accepts=("polar", "spherical", "angles", "cartesian", "mount", "suite"),
        params=NOISE,               # name -> Param: its parameter pytree, with constraints, units, defaults
        read=read_q_r,              # its [[filter]] table -> (motion model, params, options)
        build=lambda model, sensor, params, options: model_ekf(model, sensor, params))

and ``tracklab.filters.registry`` collects the declarations: the experiment files
(``tracklab.config``), tuning (a parameter's constraint gives the unconstrained
coordinates it is optimised in, its ``write`` how a tuned value goes back into the
file), sweeps (which parameters a scale factor may multiply) and ``tracklab list``
read them there.

Numbers are inputs: every number of a [[filter]] table ends up in ``params``, the
pytree the compiled program takes as an argument. ``options`` holds only structural
choices (strings, booleans, integer sizes, tuples of them), all hashable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, NamedTuple

import jax.numpy as jnp
import numpy as np

from tracklab.errors import ConfigError
from tracklab.models import MODELS
from tracklab.parameters import Param, positive
from tracklab.toml_fields import sigma_list

# ------------------------------------------------------------------ writing tuned values back


class WriteBack(NamedTuple):
    """What decides where a filter's tuned values go in its [[filter]] table."""

    model: str  # its motion model, "cv" or "ca"
    sensor: str  # the kind of what it sees ("suite": several sensors)
    sigma_fields: tuple[str, ...]  # that sensor's noise fields (sigma_r, …); empty for several sensors


def write_q(table, name, value, where: WriteBack):
    """As q if the file gives q, otherwise as the noise std of the motion model (accel_sigma, cv;
    accel_increment_sigma, ca)."""
    if "q" in table:
        table["q"] = float(value)
    else:
        table["accel_sigma" if where.model == "cv" else "accel_increment_sigma"] = math.sqrt(float(value))


def write_r(table, name, value, where: WriteBack):
    """As r if the file gives r, otherwise as the seen sensor's noise stds."""
    if "r" in table:
        table["r"] = [float(v) for v in np.atleast_1d(value)]
        return
    sig = [math.sqrt(v) for v in np.atleast_1d(value)]
    if where.sensor == "cartesian":
        table["sigma"] = sig
    elif where.sigma_fields:
        table.update(zip(where.sigma_fields, sig))
    else:
        raise ValueError("it sees several sensors: its r cannot be written back as sensor sigmas "
                         "(give the filter r = [...] in the file to tune it)")


@dataclass(frozen=True)
class FilterKind:
    """A kind of filter an experiment file may name: what it is, what it sees, its parameters,
    how its [[filter]] table is read and how the filter is built."""

    name: str
    doc: str  # one line
    accepts: tuple[str, ...]  # measurement models it works with ("suite": several sensors)
    params: Mapping[str, Param]  # its parameter pytree: every one it may have
    read: Callable[["Entry"], tuple[str, dict, dict]]  # -> (motion model, params, options)
    build: Callable[[Any, Any, dict, dict], Any]  # (motion model, measurement model, params, options) -> Filter
    guided: bool = False  # also sees a guide sensor, which the field ``guide`` names
    scans: bool = False  # associates the returns of a scan (filters.association): z is (capacity, m)

    def with_defaults(self, params: dict) -> dict:
        """``params`` and every parameter it leaves out that has a fixed default."""
        fixed = {n: jnp.asarray(p.default, dtype=float) for n, p in self.params.items()
                 if p.default is not None and n not in params}
        return {**params, **fixed}


# ------------------------------------------------------------------------- reading the file


class Entry:
    """One [[filter]] table as its kind reads it.

    ``fields`` is the configuration's typed reader of the table (``number``, ``integer``,
    ``string``, ``get``, ``has``): it records what was read, and a field nobody read is
    refused afterwards. ``meas`` is the measurement model the filter sees, ``guide`` the
    guide sensor of a guided kind (None: its own previous observation).
    """

    def __init__(self, fields, kind: FilterKind, meas, *, dim, dt, accel_sigma, sigma_fields, guide=None):
        self.fields, self.kind, self.meas = fields, kind, meas
        self.file, self.where = fields.file, fields.name
        self.dim, self.dt = dim, dt
        self.accel_sigma = accel_sigma  # the scenario's: the default of the filter's own
        self.sigma_fields = sigma_fields  # the seen sensor's noise fields (empty for several sensors)
        self.guide = guide

    def number(self, key, default=None, **checks):
        return self.fields.number(key, default, **checks)

    def integer(self, key, default=None, **checks):
        return self.fields.integer(key, default, **checks)

    def string(self, key, default=None, **checks):
        return self.fields.string(key, default, **checks)

    def get(self, key, default=None):
        return self.fields.get(key, default)

    def has(self, key):
        return self.fields.has(key)

    def error(self, key, value, allowed) -> ConfigError:
        return ConfigError(self.file, f"{self.where}.{key}", value, allowed)

    def default(self, name):
        """The declared default of the kind's parameter ``name``."""
        return self.kind.params[name].default

    def sigmas(self, key, n, default=None, required=True):
        """A number or a list of ``n`` numbers in (0, MAX_MAGNITUDE] -> a tuple (None if absent and not required)."""
        return sigma_list(self.file, f"{self.where}.{key}", self.get(key, default), n, required)

    def motion_model(self, default="cv") -> str:
        return self.string("model", default, choices=tuple(MODELS))

    def process_noise(self, model) -> float:
        """q: given, or the square of the model's noise std (accel_sigma, by default the scenario's, for
        cv; accel_increment_sigma for ca)."""
        sigma_key = "accel_sigma" if model == "cv" else "accel_increment_sigma"
        if self.has("q"):  # the process-noise variance itself (a paper's q)
            if self.has(sigma_key):
                raise self.error("q", self.get("q"), f"give either q or {sigma_key}, not both")
            return self.number("q", positive=True)
        if model == "cv":
            return self.number("accel_sigma", self.accel_sigma if self.accel_sigma > 0 else 1.0, positive=True) ** 2
        return self.number("accel_increment_sigma", 1.0, positive=True) ** 2

    def measurement_noise(self) -> tuple[float, ...]:
        """r: given (one variance, or one per component), or the squares of the noise stds, by default
        the sensors' own."""
        meas = self.meas
        if self.has("r"):
            if any(self.has(k) for k in self.sigma_fields):
                raise self.error("r", self.get("r"), f"give either r or {'/'.join(self.sigma_fields)}, not both")
            return self.sigmas("r", meas.m)  # variances, checked like sigmas
        if meas.kind in ("suite", "custom"):  # a custom sensor: the diagonal of its R
            return tuple(v**2 for v in meas.sigma)
        if meas.kind == "cartesian":
            return tuple(v**2 for v in (self.sigmas("sigma", self.dim, required=False) or meas.sigma))
        return tuple(self.number(k, sv, positive=True) ** 2 for k, sv in zip(self.sigma_fields, meas.sigma))


# ------------------------------------------------------------------ what most kinds share

ANY_SENSOR = ("polar", "spherical", "angles", "cartesian", "mount", "custom", "suite")  # "suite": several sensors

PROCESS_NOISE = Param("process-noise variance: σ² of accel_sigma (cv) or accel_increment_sigma (ca); "
                      "default the scenario's", positive, "(m/s²)²", tune=True, sweep=True, write=write_q)
MEASUREMENT_NOISE = Param("measurement-noise variances, one per component; default the sensors'", positive,
                          "sensor units²", tune=True, sweep=True, write=write_r)
NOISE = {"q": PROCESS_NOISE, "r": MEASUREMENT_NOISE}


def noise(e: Entry, model) -> dict:
    """{"q": process-noise variance of ``model``, "r": measurement-noise variances}."""
    return {"q": e.process_noise(model), "r": e.measurement_noise()}


def read_noise(e: Entry) -> tuple[str, dict, dict]:
    """The [[filter]] table of a kind whose only parameters are q and r (on a cv or ca model)."""
    model = e.motion_model()
    return model, noise(e, model), {}
