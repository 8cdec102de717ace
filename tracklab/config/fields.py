"""What every experiment file shares: typed access to its TOML tables, the [experiment]
header, the file's sections, and the limits on its sizes.

Every check raises ``ConfigError`` whose message is one line: file, field, value, what is
allowed.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np

from tracklab.checks import MAX_RUN_STEPS, MAX_RUNS  # noqa: F401 (the file's limits too)
from tracklab.errors import ConfigError
from tracklab.toml_fields import MAX_MAGNITUDE

MAX_STEPS = 1_000_000
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")
WINDOW_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9 _.+-]{0,39}")


class Section:
    """Typed access to one TOML table that remembers which keys were read."""

    def __init__(self, file, name, table):
        self.file, self.name, self.table = file, name, table
        if not isinstance(table, dict):
            raise ConfigError(file, name, table, "must be a TOML table")
        self.used: set[str] = set()

    def _err(self, key, value, allowed):
        return ConfigError(self.file, f"{self.name}.{key}", value, allowed)

    def get(self, key, default=None):
        self.used.add(key)
        return self.table.get(key, default)

    def has(self, key):
        return key in self.table

    def number(self, key, default=None, *, positive=False, nonneg=False, lo=None, hi=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required or default is None:
                if required:
                    raise self._err(key, None, "is required (a number)")
                return None
            return float(default)
        v = self.table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self._err(key, v, "must be a number")
        v = float(v)
        if not math.isfinite(v) or abs(v) > MAX_MAGNITUDE:
            raise self._err(key, v, f"must be a finite number of magnitude <= {MAX_MAGNITUDE:g}")
        if positive and v <= 0:
            raise self._err(key, v, "must be a number > 0")
        if nonneg and v < 0:
            raise self._err(key, v, "must be a number >= 0")
        if lo is not None and v < lo or hi is not None and v > hi:
            raise self._err(key, v, f"must be in [{lo}, {hi}]")
        return v

    def integer(self, key, default=None, *, lo=None, hi=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required:
                raise self._err(key, None, "is required (an integer)")
            return default
        v = self.table[key]
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._err(key, v, "must be an integer")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self._err(key, v, f"must be an integer in [{lo}, {hi}]")
        return v

    def string(self, key, default=None, *, choices=None, required=False):
        self.used.add(key)
        if key not in self.table:
            if required:
                allowed = f"one of {', '.join(choices)}" if choices else "a string"
                raise self._err(key, None, f"is required ({allowed})")
            return default
        v = self.table[key]
        if not isinstance(v, str):
            raise self._err(key, v, "must be a string")
        if choices is not None and v not in choices:
            raise self._err(key, v, f"must be one of {', '.join(choices)}")
        return v

    def label(self, key, default):
        """A label tables show: non-blank, one line, at most 100 characters."""
        v = self.string(key, default)
        if not v.strip() or len(v) > 100 or any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise self._err(key, v, "must not be empty or only spaces (1-100 characters on one line)")
        return v

    def check_unknown(self, extra=()):
        unknown = sorted(set(self.table) - self.used - set(extra))
        if unknown:
            k = unknown[0]
            allowed = ", ".join(sorted(self.used | set(extra)))
            raise self._err(k, self.table[k], f"unknown field (allowed here: {allowed})")


def declared_numbers(sec: Section, params, context=None) -> dict:
    """The numbers a kind declares (name -> ``Param``) as a table gives them — a number, or a list
    where the default is one — else their defaults (of ``context`` where a default is a function
    of it), each checked against its constraint: name -> float or tuple of floats."""
    out = {}
    for name, p in params.items():
        default = p.value(context)
        v = sec.get(name, default)
        if v is None:
            raise sec._err(name, None, "is required (a number)")
        listed = isinstance(default, (tuple, list))
        if listed:
            ok = isinstance(v, (list, tuple)) and all(not isinstance(x, bool) and isinstance(x, (int, float)) for x in v)
        else:
            ok = not isinstance(v, bool) and isinstance(v, (int, float))
        if not ok:
            raise sec._err(name, v, "must be a list of numbers" if listed else "must be a number")
        a = np.asarray(v, float)
        if not np.all(np.isfinite(a)) or np.any(np.abs(a) > MAX_MAGNITUDE):
            raise sec._err(name, v, f"must be a finite number of magnitude <= {MAX_MAGNITUDE:g}")
        if not p.constraint.contains({name: a}):
            raise sec._err(name, v, f"must be {p.constraint.requirement}" + (f" ({p.unit})" if p.unit else ""))
        out[name] = tuple(float(x) for x in a) if listed else float(a)
    return out


def declared_options(sec: Section, options) -> dict:
    """The structural fields a kind declares (name -> ``Option``) as a table gives them, else their
    defaults: an integer in its range, or one of its strings."""
    out = {}
    for name, o in options.items():
        if o.choices:
            out[name] = sec.string(name, o.default, choices=o.choices)
        else:
            out[name] = sec.integer(name, o.default, lo=o.lo, hi=o.hi)
    return out


def check_unique(f, field: str, label: str, seen: set, what: str):
    """Refuse ``label`` if it equals one of ``seen`` once surrounding spaces are trimmed ("EKF" and
    "EKF " read as one label in a table), else add it to ``seen``; ``what``: "filters", …"""
    if label.strip() in seen:
        raise ConfigError(f, field, label, f"must be unique among the {what} (labels differing only in surrounding "
                          "spaces count as the same)")
    seen.add(label.strip())


def read_toml(path: Path):
    if not path.is_file():
        raise ConfigError(path, "file", str(path), "experiment file does not exist")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "file", "", f"is not valid TOML ({e})") from None
    except RecursionError:
        raise ConfigError(path, "file", "", "is nested too deeply (arrays or tables within each other)") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(path, "file", "", f"cannot be read ({e.__class__.__name__})") from None


def check_sections(f, raw, required, allowed, kind=None):
    """The file's top-level tables: each required one present, none outside ``allowed``.

    ``kind`` ("a servo experiment", …) names the kind of file in the messages.
    """
    where = f" in {kind}" if kind else ""
    for sec in required:
        if sec not in raw:
            raise ConfigError(f, f"[{sec}]", None, f"section is required{where}")
    unknown = sorted(set(raw) - set(allowed))
    if unknown:
        raise ConfigError(f, f"[{unknown[0]}]", "...", f"unknown section{where} (allowed: {', '.join(allowed)})")


AUTO_MAX_RUNS = 100_000  # the most runs = "auto" takes unless max_runs says


def auto_runs(ex: Section):
    """``runs = "auto"``: (the most runs it may take, the target relative half-width of every
    filter's headline interval: its position RMSE, an airborne tracker's pointing error, a servo
    case's maximum tracking error); (None, None) when the runs are a number."""
    if ex.get("runs") != "auto":
        for key in ("target_precision", "max_runs"):
            if ex.has(key):
                raise ConfigError(ex.file, f"experiment.{key}", ex.get(key), 'is only for runs = "auto"')
        return None, None
    target = ex.number("target_precision", required=True)
    if not 0 < target < 1:
        raise ConfigError(ex.file, "experiment.target_precision", target,
                          "must be a relative half-width in (0, 1), e.g. 0.005 for ±0.5 %")
    return ex.integer("max_runs", AUTO_MAX_RUNS, lo=2, hi=MAX_RUNS), target


def experiment_header(f, raw):
    """[experiment]'s name, runs, seed, precision (and description) -> (name, runs, seed, precision, section);
    runs is None for ``runs = "auto"`` (``auto_runs`` reads its target)."""
    ex = Section(f, "experiment", raw["experiment"])
    name = ex.string("name", required=True)
    if not NAME_RE.fullmatch(name):
        raise ConfigError(f, "experiment.name", name, "must be 1-100 characters of letters, digits, '_', '.', '-'")
    if ex.get("runs") == "auto":
        runs = None
    else:
        runs = ex.integer("runs", required=True, lo=1, hi=MAX_RUNS)
    seed = ex.integer("seed", 0, lo=0, hi=2**32 - 1)
    precision = ex.string("precision", "float64", choices=("float64", "float32"))
    ex.string("description")
    return name, runs, seed, precision, ex


def level_and_baseline(rp: Section, labels, what="filters"):
    """[report] level (of every confidence interval, default 0.95) and baseline (the label the
    paired differences are to; None: the first of ``labels``)."""
    level = rp.number("level", 0.95)
    if not 0.5 <= level < 1:
        raise ConfigError(rp.file, "report.level", level, "must be a confidence level in [0.5, 1), e.g. 0.95")
    baseline = rp.string("baseline")
    if baseline is not None and baseline not in labels:
        raise ConfigError(rp.file, "report.baseline", baseline,
                          f"must be one of the {what}' labels: {', '.join(sorted(labels))}")
    return level, baseline
