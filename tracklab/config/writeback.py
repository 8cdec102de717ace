"""A tuned experiment file: the user's own file with the tuned numbers written in.

The file is read again with tomlkit, which keeps what a person wrote — comments, the order
of tables and keys, number formats, inline tables, nested tables and arrays of tables — and
only these change:

* each tuned number, where its declaration says it goes (``Param.write``: ``q`` as ``q`` or
  as the model's noise standard deviation, ``r`` as ``r`` or as the sensor's sigmas, …; any
  other under its own name);
* the experiment's name (``<name>_tuned``: its results go to their own folder) and each
  tuned filter's (tracker's) label (``<label>, tuned``; a servo's estimators keep theirs,
  which its cases name);
* the ``[[study]]`` tables are left out: the studies stay with the original file;
* relative paths are rewritten to name the same files from the tuned copy's folder: a
  trajectory's ``scenario.path``, and, when a kind names a module of one's own
  (``"module:factory"``), the original file's folder and its own ``pythonpath`` become the
  copy's ``[experiment] pythonpath``.

The text starts with ``TUNED_HEADER``, by which ``tracklab tune`` knows a file it may
replace.
"""

from __future__ import annotations

import os
from pathlib import Path

import tomlkit

from tracklab.config.factories import is_factory
from tracklab.output import TUNED_HEADER
from tracklab.parameters import write_value


def write_values(exp, doc, values: dict):
    """Write ``values`` ({label: {name: value}}) into the units' tables of ``doc`` (the parsed file:
    plain dictionaries or tomlkit's), each where its declaration says (``Param.write``; a leaf of a
    filter of one's own under its name); ValueError (one line) for a value no field can hold."""
    section, labels = exp.tables()
    declared = exp.declared()
    for label, table in zip(labels, doc.get(section, [])):
        for name, v in values.get(label, {}).items():
            p = declared.get(label, {}).get(name)
            if p is not None and p.write is None:
                raise ValueError(f"{label!r}: tuned {name} ({p.doc}) cannot be written into an experiment file")
            try:
                (p.write if p is not None else write_value)(table, name, v, exp.write_where(label))
            except ValueError as e:
                raise ValueError(f"{label!r}: {e}") from None


def _relabel(doc, exp, values: dict):
    """Each tuned unit labelled ``<label>, tuned`` (where the experiment's units are its lanes), and
    ``[report] baseline`` with it."""
    if not exp.relabel_tuned:
        return
    section, labels = exp.tables()
    renamed = {}
    for label, table in zip(labels, doc.get(section, [])):
        if values.get(label) and not label.endswith(", tuned"):  # a tuned file tuned again keeps its label
            renamed[label] = table["label"] = f"{label}, tuned"
    report = doc.get("report")
    if isinstance(report, dict) and report.get("baseline") in renamed:
        report["baseline"] = renamed[report["baseline"]]


def _relative(target: Path, folder: Path) -> str:
    return Path(os.path.relpath(target, folder)).as_posix()


def _uses_modules(doc) -> bool:
    """Whether a file names a kind of one's own anywhere (a filter, the scenario, a sensor)."""
    tables = []
    for section in ("filter", "scenario", "sensor"):
        t = doc.get(section)
        tables += list(t) if isinstance(t, list) else [t] if t is not None else []
    return any(isinstance(t, dict) and is_factory(t.get("kind")) for t in tables)


def _repoint(doc, source: Path, out_dir: Path):
    """Relative paths of a file read from ``source`` made to name the same files from ``out_dir``."""
    here = source.resolve().parent
    if here == out_dir:
        return
    sc = doc.get("scenario")
    if isinstance(sc, dict) and isinstance(sc.get("path"), str) and not Path(sc["path"]).is_absolute():
        sc["path"] = _relative(here / sc["path"], out_dir)
    experiment = doc["experiment"]
    own = [p for p in experiment.get("pythonpath", []) if isinstance(p, str)]
    if _uses_modules(doc):
        folders = [_relative(here, out_dir)] + [p if Path(p).is_absolute() else _relative(here / p, out_dir) for p in own]
        experiment["pythonpath"] = list(dict.fromkeys(folders))


def tuned_text(exp, values: dict, out_path) -> str:
    """The text of ``exp``'s file with the tuned ``values`` ({label: {name: value}}) written in, to
    be saved at ``out_path`` (see the module's doc). ValueError (one line) for a value no field
    of the file can hold."""
    source = Path(exp.path)
    text = source.read_text()
    if text.startswith(TUNED_HEADER):  # a tuned file tuned again: one header
        text = text.split("\n", 1)[1] if "\n" in text else ""
    doc = tomlkit.parse(text)
    if "study" in doc:
        del doc["study"]
    doc["experiment"]["name"] = f"{exp.name}_tuned"
    write_values(exp, doc, values)
    _relabel(doc, exp, values)
    _repoint(doc, source, Path(out_path).resolve().parent)
    return TUNED_HEADER + "\n" + tomlkit.dumps(doc)
