"""Results folders: stats.json (compact JSON, tracklab's header first), table.md and table.csv,
written into a temporary folder that replaces the destination in one step when complete
(``tracklab.output.atomic_folder``); the series a document keeps (``series_stride``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tracklab import __version__
from tracklab.output import HEADER_KEY, atomic_folder, check_results_folder
from tracklab.report.tables import csv_table, markdown_table, stored
from tracklab.processes import writes


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    return stored(obj)

MAX_SERIES_POINTS = 2000  # longer runs are stored (and drawn) every `stride` steps

def series_stride(steps):
    return max(1, -(-steps // MAX_SERIES_POINTS))

def decimate(tree, stride):
    if stride == 1:
        return tree
    if isinstance(tree, dict):
        return {k: decimate(v, stride) for k, v in tree.items()}
    return np.asarray(tree)[stride - 1::stride]

def results_path(exp, out=None) -> Path:
    """Where an experiment's results go: ``out``, or results/<name>/."""
    return Path(out) if out is not None else Path("results") / exp.name

def run_into_folder(exp, out, runs, max_memory, simulate, write, where=None):
    """What ``run`` is for every kind of experiment: the output folder and the memory need checked
    before anything compiles, then ``simulate()``, then ``write(its result, folder)`` into a
    temporary folder swapped in whole; returns what ``write`` returns (the statistics). In a run of
    several processes every one checks and simulates, and process 0 alone writes (the others
    return None). A refusal of the folder names ``where`` and its argument ``out`` (the Python
    method: ``Experiment.run``), or without ``where`` the experiment file and ``--out``."""
    field = "--out" if where is None else "out"
    if where is None and exp.path is None:
        where = "tracklab.experiment"
    out = check_results_folder(results_path(exp, out), exp.path, field, where)
    exp.check_memory(runs, max_memory)
    result = simulate()
    if not writes():
        return None
    with atomic_folder(out, exp.path, field, where) as tmp:
        return write(result, tmp)

def write_json(path: Path, doc):
    """Compact JSON, NaN and infinities as null, floats to 10 significant digits; tracklab's
    header (its version) first, which marks the folder as tracklab's (``tracklab.output``)."""
    doc = {HEADER_KEY: __version__} | dict(doc)
    path.write_text(json.dumps(_jsonable(doc), separators=(",", ":"), allow_nan=False) + "\n")

def write_tables(folder: Path, doc, table_md=None):
    """stats.json, table.md (``table_md``, default the one-row-per-filter table) and table.csv."""
    write_json(folder / "stats.json", doc)
    (folder / "table.md").write_text(markdown_table(doc) if table_md is None else table_md)
    (folder / "table.csv").write_text(csv_table(doc))
