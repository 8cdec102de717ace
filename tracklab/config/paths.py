"""PATHs to the numbers of an experiment file, and the grids a sweep runs over them.

``NAME=LO:HI:N`` scales a filter parameter (log-spaced factors); ``PATH=LO:HI:N[:log]``
gives values to any number of the file: ``section.field`` (``sensor.sigma_r``,
``scenario.speed``) or ``section[LABEL].field`` (``filter[EKF].accel_sigma``), an entry of
an array of tables picked by its label, name or 1-based index.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from tracklab.filters.registry import SCALABLE

GRID_RE = re.compile(r"^(?P<key>[^=]+)=(?P<lo>[^:]+):(?P<hi>[^:]+):(?P<n>[^:]+)(?::(?P<spacing>[a-z]+))?$")
PATH_RE = re.compile(r"^(?P<section>[A-Za-z_][A-Za-z0-9_]*)(?:\[(?P<label>[^\]]+)\])?\.(?P<field>[A-Za-z_][A-Za-z0-9_]*)$")
MAX_POINTS_PER_AXIS = 1000
# units of the numbers a figure's axis may name (by field)
UNITS = {"sigma_r": "m", "sigma": "m", "sigma_angle": "rad", "sigma_az": "rad", "sigma_el": "rad", "speed": "m/s",
         "offset": "m", "start_x": "m", "altitude": "m", "accel_sigma": "m/s²", "accel_increment_sigma": "m/s²",
         "pos_sigma": "m", "vel_sigma": "m/s", "acc_sigma": "m/s²", "period": "s", "dt": "s", "max_elevation": "deg",
         "t_closest": "s", "heading": "deg", "amplitude": "deg", "omega": "rad/s", "phase": "rad", "lam": "1/s",
         "noise": "arcsec", "settle": "s", "accel_ff": "s", "turn_g": "g", "own_speed": "m/s", "target_speed": "m/s",
         "target_range": "m", "singer_sigma": "m/s²", "singer_tau": "s", "angle": "mrad", "range": "m",
         "velocity": "m/s", "pointing": "mrad", "los_rate": "mrad/s", "range_rate": "m/s", "half_angle": "deg",
         "axis_elevation": "deg", "tracking_index": "", "p_detect": "", "snr": "dB",
         "clutter_density": "per unit measurement volume"}


@dataclass(frozen=True)
class Axis:
    name: str  # NAME (scale factors) or PATH (values), as given
    values: np.ndarray
    path: tuple | None = None  # (section, label or None, field) of a PATH axis; None: scale factors
    log: bool = True  # spaced evenly in log (figures: log axis)

    @property
    def title(self) -> str:
        """The axis in a figure: the swept field and its unit."""
        if self.path is None:
            return f"{self.name} scale factor"
        unit = UNITS.get(self.path[2], "")
        return f"{self.name} ({unit})" if unit else self.name


def parse_grid(spec: str) -> Axis:
    """``NAME=LO:HI:N`` (scale factors, log-spaced) or ``PATH=LO:HI:N[:log]`` (values) -> Axis.

    Raises ValueError (the reason, in words) for a malformed spec; whether PATH names a
    number of a file is checked against the file (``resolve``)."""
    m = GRID_RE.match(spec.strip())
    if not m:
        raise ValueError("must look like NAME=LO:HI:N (q=0.01:100:9) or PATH=LO:HI:N[:log] (sensor.sigma_r=50:200:7)")
    key, spacing = m.group("key").strip(), m.group("spacing")
    try:
        lo, hi = float(m.group("lo")), float(m.group("hi"))
    except ValueError:
        raise ValueError("LO and HI must be numbers") from None
    try:
        n = int(m.group("n"))
    except ValueError:
        raise ValueError(f"N must be a whole number of grid values, not {m.group('n')!r}") from None
    if not 1 <= n <= MAX_POINTS_PER_AXIS:
        raise ValueError(f"N must be in [1, {MAX_POINTS_PER_AXIS}]")
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError("LO and HI must be finite numbers")
    if spacing not in (None, "log"):
        raise ValueError(f"the spacing after N can only be 'log', not {spacing!r}")
    if "." not in key:
        if not key.isidentifier():
            raise ValueError(f"NAME must be a filter parameter a scale factor may multiply ({', '.join(SCALABLE)}, or "
                             "one a filter of one's own declares), or a PATH to a number of the file (section.field, "
                             "section[LABEL].field)")
        if not 0 < lo <= hi:
            raise ValueError("scale factors need 0 < LO <= HI")
        return Axis(key, _tidy(np.geomspace(lo, hi, n)))
    p = PATH_RE.match(key)
    if not p:
        raise ValueError("PATH must be section.field or section[LABEL].field, e.g. sensor.sigma_r or "
                         "filter[EKF].accel_sigma")
    path = (p.group("section"), p.group("label"), p.group("field"))
    if spacing == "log":
        if not 0 < lo <= hi:
            raise ValueError("a log grid needs 0 < LO <= HI")
        return Axis(key, _tidy(np.geomspace(lo, hi, n)), path, True)
    if lo > hi:
        raise ValueError("needs LO <= HI")
    return Axis(key, _tidy(np.linspace(lo, hi, n)), path, False)


def _tidy(values) -> np.ndarray:
    """Grid values to 12 significant digits: 0.8, not linspace's 0.7999999999999999."""
    return np.array([float(f"{v:.12g}") for v in values])


def entry_label(section, table):
    return table.get("label", table.get("name", table.get("kind")))


def table_of(raw: dict, path, create=False):
    """The TOML table a PATH's field lives in (a new one when ``create`` and the section is
    absent); raises ValueError with the reason."""
    section, label, _ = path
    t = raw.get(section)
    if label is None:
        if isinstance(t, list):
            names = [str(entry_label(section, e)) for e in t if isinstance(e, dict)]
            raise ValueError(f"[[{section}]] holds several tables: pick one, {section}[LABEL].field "
                             f"(labels: {', '.join(names)})")
        if t is None and create:
            t = raw[section] = {}
        if not isinstance(t, dict):
            raise ValueError(f"the file has no [{section}] table")
        return t
    if not isinstance(t, list):
        if isinstance(t, dict) and str(entry_label(section, t)) == label:
            return t  # a single table picked by its label
        raise ValueError(f"the file has no [[{section}]] tables to pick {label!r} from")
    entries = [e for e in t if isinstance(e, dict)]
    found = [e for e in entries if str(entry_label(section, e)) == label]
    if not found and label.isdigit() and 1 <= int(label) <= len(entries):
        found = [entries[int(label) - 1]]
    if not found:
        names = [str(entry_label(section, e)) for e in entries]
        raise ValueError(f"no [[{section}]] entry is labelled {label!r} (labels: {', '.join(names)})")
    return found[0]


def set_value(raw: dict, path, value):
    table = table_of(raw, path, create=True)
    old = table.get(path[2])
    whole = not isinstance(old, float) and float(value).is_integer()
    table[path[2]] = int(value) if whole else float(value)  # a whole value is an integer, unless the file's is a float
