"""Results folders: stats.json (compact JSON, tracklab's header first: the summaries, intervals
and metadata a reader or ``tracklab table`` needs), series.npz (every per-step series, run 0's
example and other long arrays of the document, compressed binary), table.md and table.csv,
written into a temporary folder that replaces the destination in one step when complete
(``tracklab.output.atomic_folder``); the series a document keeps (``series_stride``).
``read_results(folder)`` gives back the whole document, as ``run`` returned it (the series in
single precision)."""

from __future__ import annotations

import json
import zipfile
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

MAX_SERIES_POINTS = 500  # longer runs are stored (and drawn) every `stride` steps (a panel is ~1000 px wide)

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

SERIES_FILE = "series.npz"
SERIES_MARK = "$series"  # in stats.json, where an array of series.npz belongs (its key there: its path, as JSON)
LONGEST_INLINE = 32  # a list of numbers longer than this goes to series.npz


def _as_numbers(obj):
    """A (nested) list of numbers and None as a float array (None: NaN); None if it is not one."""
    def clean(v):
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        if v is None:
            return np.nan
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise TypeError
        return v

    try:
        a = np.asarray(clean(list(obj)) if not isinstance(obj, np.ndarray) else obj, dtype=float)
    except (TypeError, ValueError):
        return None
    return a


def split_series(doc) -> tuple[dict, dict]:
    """(the document with every long array replaced by a mark, {key: array}): what stats.json and
    series.npz hold. A key is the array's path in the document, as JSON."""
    arrays = {}

    def walk(obj, path):
        if isinstance(obj, dict):
            return {k: walk(v, path + [k]) for k, v in obj.items()}
        if isinstance(obj, np.ndarray) and obj.ndim == 0:
            return obj.item()
        if isinstance(obj, (list, tuple, np.ndarray)):
            a = _as_numbers(obj) if len(obj) > LONGEST_INLINE or np.ndim(obj) > 1 else None
            if a is not None and a.size > LONGEST_INLINE:
                key = json.dumps(path, ensure_ascii=False)
                arrays[key] = a
                return SERIES_MARK
            return [walk(v, path + [i]) for i, v in enumerate(obj)]
        return obj

    return walk(doc, []), arrays


def read_results(folder) -> dict:
    """The statistics document of a results folder, whole: stats.json with the arrays of
    series.npz back in their places (float32 NumPy arrays, NaN where a value is missing)."""
    folder = Path(folder)
    doc = json.loads((folder / "stats.json").read_text())
    path = folder / SERIES_FILE
    if not path.is_file():
        return doc
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}

    def walk(obj, path):
        if isinstance(obj, dict):
            return {k: walk(v, path + [k]) for k, v in obj.items()}
        if isinstance(obj, list):
            return [walk(v, path + [i]) for i, v in enumerate(obj)]
        if obj == SERIES_MARK:  # a string of the file's own ("$series" as a label) has no array
            return arrays.get(json.dumps(path, ensure_ascii=False), obj)
        return obj

    return walk(doc, [])


def world_of(doc) -> str:
    """Which world wrote a statistics document: "airborne", "servo" or "tracking"."""
    if "nominal_range" in doc:
        return "airborne"
    if "t_frames" in (doc.get("example_run") or {}):
        return "servo"
    return "tracking"


def write_series(path: Path, arrays: dict):
    """An .npz that ``numpy.load`` reads: each array in single precision (seven digits, more than
    any figure or table shows; half the bytes), compressed with LZMA (a tenth smaller than
    ``numpy.savez_compressed``'s deflate on these noisy series)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_LZMA) as archive:
        for key, a in arrays.items():
            with archive.open(f"{key}.npy", "w") as fh:
                np.lib.format.write_array(fh, np.asarray(a, np.float32), allow_pickle=False)


def write_tables(folder: Path, doc, table_md=None):
    """stats.json with series.npz beside it (``split_series``), table.md (``table_md``, default the
    one-row-per-filter table) and table.csv."""
    lean, arrays = split_series(doc)
    write_json(folder / "stats.json", lean)
    if arrays:
        write_series(folder / SERIES_FILE, arrays)
    (folder / "table.md").write_text(markdown_table(doc) if table_md is None else table_md)
    (folder / "table.csv").write_text(csv_table(doc))
