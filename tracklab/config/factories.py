"""Code of one's own named in an experiment file: ``kind = "package.module:factory"``.

A ``[[filter]]``, ``[scenario]`` or ``[sensor]`` table whose kind has a colon names a
callable: the module is imported from the experiment file's folder or the Python path,
and the callable is called with a context (what the experiment fixes) and the table's
other keys as keyword arguments. Whatever goes wrong — the module cannot be imported,
it has no such callable, the call raises, or what it returns is not what the table
needs — is one ``ConfigError`` line (file, field, value, what went wrong), before
anything compiles.
"""

from __future__ import annotations

import importlib
import re
import sys
from pathlib import Path
from typing import NamedTuple

from tracklab.errors import ConfigError, first_line

FACTORY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


class Context(NamedTuple):
    """What a scenario or sensor factory receives (a filter factory gets a
    ``tracklab.filters.context.FilterContext``)."""

    dt: float  # s, the experiment's step
    steps: int  # measurement steps of a run
    dim: int | None  # spatial dimension of the truth (None for a scenario when no sensor fixes it)


def is_factory(kind) -> bool:
    return isinstance(kind, str) and ":" in kind


def load_factory(file, field: str, spec: str):
    """The callable ``spec`` ("package.module:name") names, imported with the experiment file's
    folder first on the Python path."""
    if not FACTORY_RE.fullmatch(spec):
        raise ConfigError(file, field, spec, 'must be "package.module:factory" (a module path, a colon, a name)')
    module_name, _, attr = spec.partition(":")
    folder = str(Path(file).resolve().parent) if file is not None and Path(str(file)).exists() else None
    added = folder is not None and folder not in sys.path
    if added:
        sys.path.insert(0, folder)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name and (module_name == e.name or module_name.startswith(e.name + ".")):
            where = "the experiment file's folder or the Python path" if folder else "the Python path"
            raise ConfigError(file, field, spec, f"module {module_name!r} is not found in {where}") from None
        raise ConfigError(file, field, spec, f"importing {module_name!r} failed: {first_line(e)}") from None
    except Exception as e:  # noqa: BLE001 - the user's module, any error
        raise ConfigError(file, field, spec, f"importing {module_name!r} failed: {first_line(e)}") from None
    finally:
        if added:
            sys.path.remove(folder)
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(file, field, spec, f"module {module_name!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ConfigError(file, field, spec, f"{attr!r} in {module_name!r} is a {type(obj).__name__}, not a callable")
    return obj


def call_factory(file, field: str, spec: str, factory, context, options: dict):
    """``factory(context, **options)``; any exception it raises as one ConfigError line."""
    try:
        return factory(context, **options)
    except Exception as e:  # noqa: BLE001 - the user's code, any error
        raise ConfigError(file, field, spec, f"the factory raised {first_line(e)}") from None


def build(file, field: str, spec: str, context, options: dict):
    """Import the factory ``spec`` names and call it with ``context`` and ``options``."""
    return call_factory(file, field, spec, load_factory(file, field, spec), context, options)
