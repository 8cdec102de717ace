"""A tuned experiment file: the user's own file with the tuned numbers written in.

The file is read again with tomlkit, which keeps what a person wrote — comments, the order
of tables and keys, number formats, inline tables, nested tables and arrays of tables — and
only these change:

* each tuned number, where its kind declares it goes (``Param.write``: ``q`` as ``q`` or as
  the model's noise standard deviation, ``r`` as ``r`` or as the sensor's sigmas, …), or an
  airborne tracker's / servo estimator's field of that name;
* the experiment's name (``<name>_tuned``: its results go to their own folder) and each
  tuned filter's (tracker's) label (``<label>, tuned``);
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
from tracklab.filters.kind import WriteBack
from tracklab.filters.registry import KINDS
from tracklab.parameters import write_value
from tracklab.output import TUNED_HEADER
from tracklab.sensors import SENSOR_SIGMAS
from tracklab.worlds.tracking.lanes import FilterSpec


def write_back(exp, fc) -> WriteBack:
    """Where a built-in filter's tuned values go in its [[filter]] table (its model, what it sees)."""
    _, meas = exp.view(fc)
    return WriteBack(fc.model, meas.kind, SENSOR_SIGMAS.get(meas.kind, ()))


def write_filters(exp, doc, values: dict):
    """Write ``values`` ({label: {name: value}}) into the [[filter]] tables of ``doc`` (a parsed
    open-loop file: plain dictionaries or tomlkit's), each as its kind declares; ValueError (one
    line) for a value no field of the file can hold."""
    for fc, table in zip(exp.filters, doc["filter"]):
        tuned = values.get(fc.label)
        if not tuned:
            continue
        if isinstance(fc, FilterSpec):  # a factory's filter: under the keyword of that name (as declared)
            for n, v in tuned.items():
                (fc.declared[n].write if n in fc.declared else write_value)(table, n, v)
            continue
        for name, p in KINDS[fc.kind].params.items():  # in the order the kind declares them
            if name not in tuned:
                continue
            if p.write is None:
                raise ValueError(f"filter {fc.label!r}: tuned {name} ({p.doc}) cannot be written into an experiment file")
            try:
                p.write(table, name, tuned[name], write_back(exp, fc))
            except ValueError as e:
                raise ValueError(f"filter {fc.label!r}: {e}") from None


def _relabel(doc, exp, values: dict):
    """Each tuned filter (airborne tracker) labelled ``<label>, tuned``, and ``[report] baseline``
    with it. (A servo file's tuned estimators keep their labels, which its cases name.)"""
    section, lanes = ("filter", exp.filters) if "filter" in doc else ("tracker", getattr(exp, "trackers", []))
    renamed = {}
    for lane, table in zip(lanes, doc.get(section, [])):
        if values.get(lane.label):
            renamed[lane.label] = table["label"] = f"{lane.label}, tuned"
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
    if hasattr(exp, "write_tuned"):  # airborne trackers, servo estimators
        exp.write_tuned(doc, values)
    else:
        write_filters(exp, doc, values)
    _relabel(doc, exp, values)
    _repoint(doc, source, Path(out_path).resolve().parent)
    return TUNED_HEADER + "\n" + tomlkit.dumps(doc)
