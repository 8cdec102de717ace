"""Code of one's own named in an experiment file: ``kind = "package.module:factory"``.

A ``[[filter]]``, ``[scenario]`` or ``[sensor]`` table whose kind has a colon names a
callable: the module is imported from the experiment file's folder, the folders its
``[experiment] pythonpath`` lists (relative to the file), or the Python path, and the
callable is called with a context (what the experiment fixes) and the table's other keys
as keyword arguments. Whatever goes wrong — the module cannot be imported (its import
raises, or calls ``sys.exit``), it has no such callable, the call raises or calls
``sys.exit``, or what it returns is not what the table needs — is one ``ConfigError``
line (file, field, value, what went wrong), before anything compiles; a KeyboardInterrupt
stays one.
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
import tomllib
from pathlib import Path
from typing import NamedTuple

from tracklab.errors import ConfigError, exit_call, first_line
from tracklab.filters.factory import Declared, declared

FACTORY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


class Context(NamedTuple):
    """What a scenario or sensor factory receives (a filter factory gets a
    ``tracklab.filters.context.FilterContext``)."""

    dt: float  # s, the experiment's step
    steps: int  # measurement steps of a run
    dim: int | None  # spatial dimension of the truth (None for a scenario when no sensor fixes it)


def is_factory(kind) -> bool:
    return isinstance(kind, str) and ":" in kind


def load_factory(file, field: str, spec: str, folders=()):
    """The callable ``spec`` ("package.module:name") names, imported with the experiment file's
    folder, then ``folders`` (absolute: the file's ``pythonpath``), first on the Python path."""
    if not FACTORY_RE.fullmatch(spec):
        raise ConfigError(file, field, spec, 'must be "package.module:factory" (a module path, a colon, a name)')
    module_name, _, attr = spec.partition(":")
    own = str(Path(file).resolve().parent) if file is not None and Path(str(file)).exists() else None
    searched = [d for d in dict.fromkeys(([own] if own else []) + [str(d) for d in folders])]
    added = [d for d in searched if d not in sys.path]
    sys.path[:0] = added
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name and (module_name == e.name or module_name.startswith(e.name + ".")):
            where = ("the experiment file's folder" + (", its pythonpath" if folders else "") + " or the Python path"
                     if own else "the Python path")
            raise ConfigError(file, field, spec, f"module {module_name!r} is not found in {where}") from None
        raise ConfigError(file, field, spec, f"importing {module_name!r} failed: {first_line(e)}") from None
    except BaseException as e:  # noqa: BLE001 - the user's module: any error, a sys.exit too
        if isinstance(e, KeyboardInterrupt):
            raise
        call = exit_call(e)
        what = f"its import called {call}" if call else first_line(e)
        raise ConfigError(file, field, spec, f"importing {module_name!r} failed: {what}") from None
    finally:
        for d in added:
            sys.path.remove(d)
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(file, field, spec, f"module {module_name!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ConfigError(file, field, spec, f"{attr!r} in {module_name!r} is a {type(obj).__name__}, not a callable")
    return obj


def call_factory(file, field: str, spec: str, factory, context, options: dict):
    """``factory(context, **options)``; any exception it raises (a ``sys.exit`` too, not a
    KeyboardInterrupt) as one ConfigError line."""
    try:
        return factory(context, **options)
    except BaseException as e:  # noqa: BLE001 - the user's code: any error, a sys.exit too
        if isinstance(e, KeyboardInterrupt):
            raise
        call = exit_call(e)
        what = f"called {call}" if call else f"raised {first_line(e)}"
        raise ConfigError(file, field, spec, f"the factory {what}") from None


def build(file, field: str, spec: str, context, options: dict, folders=()):
    """Import the factory ``spec`` names (from the file's folder, then ``folders``) and call it with
    ``context`` and ``options``."""
    return call_factory(file, field, spec, load_factory(file, field, spec, folders), context, options)


def python_path(file, value) -> tuple[Path, ...]:
    """``[experiment] pythonpath``: folders (relative to the experiment file, or absolute) that plug-in
    modules are imported from after the file's own folder; ConfigError for anything else."""
    if value is None:
        return ()
    allowed = "must be a list of folders (relative to the experiment file) to import plug-in modules from"
    if not isinstance(value, list) or any(not isinstance(v, str) or not v.strip() for v in value):
        raise ConfigError(file, "experiment.pythonpath", value, allowed)
    base = Path(file).resolve().parent
    out = []
    for v in value:
        folder = (base / v).resolve()
        if not folder.is_dir():
            raise ConfigError(file, "experiment.pythonpath", v, f"is not a folder: {folder} (relative to the "
                              "experiment file's folder)")
        out.append(folder)
    return tuple(out)


def kinds_of_ones_own(path) -> list[tuple[str, str, object]]:
    """The kinds of one's own an experiment file names: (field, "module:factory", the factory, or the
    ConfigError that loading it gives), for ``tracklab list``."""
    try:
        raw = tomllib.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return []
    try:
        folders = python_path(path, raw.get("experiment", {}).get("pythonpath")) if isinstance(raw.get("experiment"), dict) else ()
    except ConfigError as e:
        folders, error = (), e
    else:
        error = None
    out = []
    for section in ("scenario", "sensor", "filter"):
        tables = raw.get(section, [])
        tables = tables if isinstance(tables, list) else [tables]
        for i, t in enumerate(tables, start=1):
            kind = t.get("kind") if isinstance(t, dict) else None
            if not is_factory(kind):
                continue
            field = f"{section}[{i}].kind" if section != "scenario" and len(tables) > 1 or section == "filter" else f"{section}.kind"
            try:
                out.append((field, kind, error or load_factory(path, field, kind, folders)))
            except ConfigError as e:
                out.append((field, kind, e))
    return out


def structural_keywords(factory) -> list[str]:
    """The keywords a factory takes besides its context and its declared numbers, ``name = default``
    (a table's value for one is structure: another value compiles anew)."""
    fn = factory.factory if isinstance(factory, Declared) else factory
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return []
    out = []
    for p in list(signature.parameters.values())[1:]:
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in declared(factory):
            out.append(p.name if p.default is p.empty else f"{p.name} = {p.default!r}")
    return out
