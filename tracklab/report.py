"""Results folders: stats.json, table.md, table.csv (and the figures of ``tracklab.figures``).

They are written into a temporary folder that replaces the destination in one
step when complete (``tracklab.output.atomic_folder``).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from tracklab.intervals import format_value, missing, with_half_width
from tracklab.metrics import AXES, REPORT_WINDOW, statistics

# (summary key, title, format); {p}/{v} are the position/velocity units, {a} an axis name
COLUMNS = [
    ("rmse_pos", "RMSE pos ({p})", "{:.{d}f}"),
    ("rmse_vel", "RMSE vel ({v})", "{:.{d}f}"),
    ("rmse_pos_over_pcrlb", "RMSE/PCRLB", "{:.3f}"),
    ("max_err_pos", "max err pos ({p})", "{:.{d1}f}"),
    ("mean_err_{a}", "mean err {a} ({p})", "{:.{d}f}"),
    ("pred_err_rms", "pred err RMS ({p})", "{:.{d}f}"),
    ("pred_err_max", "pred err max ({p})", "{:.{d}f}"),
    ("max_track_err", "max tracking error (′)", "{:.3f}"),
    ("max_track_err_worst", "worst run (′)", "{:.3f}"),
    ("random_err", "random error (″)", "{:.2f}"),
    ("max_rate_err", "max rate-estimate error (°/s)", "{:.4f}"),
    ("nees", "NEES", "{:.2f}"),
    ("nees_in_bounds", "NEES in 95% (%)", "{:.0%}"),
    ("nis", "NIS", "{:.2f}"),
    ("err_pos_p50", "run err p50 ({p})", "{:.{d}f}"),
    ("err_pos_p90", "run err p90 ({p})", "{:.{d}f}"),
    ("err_pos_p99", "run err p99 ({p})", "{:.{d}f}"),
    ("max_track_err_p50", "run max error p50 (′)", "{:.3f}"),
    ("max_track_err_p90", "run max error p90 (′)", "{:.3f}"),
    ("max_track_err_p99", "run max error p99 (′)", "{:.3f}"),
    ("diverged", "diverged", "{:d}"),
    ("runs", "runs", "{:d}"),
]
PAIRED_COLUMNS = ("rmse_pos", "max_track_err")  # the paired difference table.md shows, the first there is
# (stats.json and table.csv hold them all)
WINDOW_COLUMNS = [  # per named prediction-error window
    ("pred_err_rms[{w}]", "pred err RMS {w} ({p})", "{:.{d}f}"),
    ("pred_err_max[{w}]", "pred err max {w} ({p})", "{:.{d}f}"),
]


def _fmt(v, spec):
    return format_value(v, spec)


def _diverged_cell(f, key="diverged") -> str:
    """``k (lo–hi %)``: the diverged runs (summary ``key``) and the Wilson interval of their fraction."""
    k = f["summary"].get(key)
    lo_hi = f.get("intervals", {}).get("diverged_fraction")
    if k is None or not lo_hi or missing(lo_hi[1]):
        return _fmt(k, "{:d}")
    lo, hi = (100.0 * v for v in lo_hi)
    return f"{k} ({lo:.2g}–{hi:.2g} %)"


def _paired_cell(f, key) -> str:
    pd = f.get("paired", {})
    c = pd.get(key)
    if c is None:
        return "—"
    if pd.get("baseline") == f.get("label"):
        return "baseline"
    if c["difference"] == 0 and c["half_width"] == 0:
        return "0 (identical)"
    cell = with_half_width(c["difference"], c["half_width"], sign=True)
    return cell if c["significant"] or cell == "—" else cell + " (n.s.)"


def _columns(stats):
    p, v = stats.get("units", ("m", "m/s"))
    d, d1 = (2, 1) if p == "m" else (5, 4)  # decimals: metres, or degrees
    axes = stats.get("axes", AXES)
    cols = []

    def add(key, title, spec, **kw):
        key, title = key.format(**kw), title.format(p=p, v=v, **kw)
        if any(key in f["summary"] for f in stats["filters"].values()):
            cols.append((key, title, spec.replace("{d}", str(d)).replace("{d1}", str(d1))))

    for key, title, spec in COLUMNS:
        for a in axes if "{a}" in key else [None]:
            add(key, title, spec, a=a)
        if key == "pred_err_max":
            for w in stats.get("windows", []):
                for k2, t2, s2 in WINDOW_COLUMNS:
                    add(k2, t2, s2, w=w)
    return cols


def _baseline(stats):
    return next((f["paired"]["baseline"] for f in stats["filters"].values() if "paired" in f), None)


def _paired_column(stats, cols):
    """The key of the paired difference the table shows, and its column's title (None: none)."""
    have = {k for f in stats["filters"].values() for k in f.get("paired", {})}
    return next(((k, t) for k, t, _ in cols if k in PAIRED_COLUMNS and k in have), (None, None))


def table_rows(stats):
    """The one-row-per-filter table: a number with an interval as ``value ± half-width``, the
    diverged runs with the interval of their fraction, and the paired difference to the baseline."""
    cols = _columns(stats)
    base = _baseline(stats)
    paired_key, paired_title = _paired_column(stats, cols)
    header = ["filter", "kind"] + [t for _, t, _ in cols]
    if base is not None and paired_key is not None:
        header.insert(2 + next(i + 1 for i, c in enumerate(cols) if c[0] == paired_key), f"Δ {paired_title} vs {base}")
    rows = []
    for label, f in stats["filters"].items():
        f = dict(f, label=label)
        hw = f.get("half_width", {})
        cells = []
        for k, _, spec in cols:
            if k == "diverged":
                cells.append(_diverged_cell(f))
            elif k in hw:
                cells.append(with_half_width(f["summary"].get(k), hw[k], spec))
            else:
                cells.append(_fmt(f["summary"].get(k), spec))
            if k == paired_key and base is not None:
                cells.append(_paired_cell(f, k))
        rows.append([label, f["kind"]] + cells)
    return header, rows


def table_caption(stats) -> str:
    """What the table's ± and Δ mean (empty when it has no intervals)."""
    if not any("half_width" in f for f in stats["filters"].values()):
        return ""
    level = stats.get("level", 0.95)
    runs = stats.get("runs")
    summaries = [f["summary"] for f in stats["filters"].values()]
    servo = any("max_track_err" in s for s in summaries)
    nis = any(not missing(f.get("half_width", {}).get("nis")) for f in stats["filters"].values())
    text = (f"± : half-width of the {level:.0%} confidence interval over the {runs} runs (Student t over the runs' "
            + ("values)." if servo else f"time-averaged values; delta method for an RMSE{' and the NIS' if nis else ''}).")
            + " diverged: runs, with the Wilson interval of their fraction.")
    if any("max_track_err_p50" in s for s in summaries):
        text += " run max error pNN: percentiles of the runs' maximum tracking errors."
    elif any("err_pos_p50" in s for s in summaries):
        text += " run err pNN: percentiles of the runs' RMS position errors."
    base = _baseline(stats)
    if base is not None:
        text += (f" Δ: difference to {base} on the same runs with its paired interval; "
                 f"(n.s.): not significant at {level:.0%}.")
    return text + auto_note(stats)


def auto_note(stats) -> str:
    """How many runs ``runs = "auto"`` took and whether it met its target ("" for a fixed count)."""
    a = stats.get("auto")
    if not a:
        return ""
    return (f" Runs chosen automatically: {stats.get('runs')} runs brought every filter's "
            f"{a.get('statistic', 'position-RMSE')} interval within ± {100 * a['target']:g} % (at most {a['max_runs']})"
            + ("." if a["reached"] else "; the target was not reached."))


def md_cell(text) -> str:
    """A Markdown table cell: a '|' in a label is escaped, so it cannot start a new column."""
    return str(text).replace("\\", "\\\\").replace("|", "\\|")


def markdown_table(stats) -> str:
    header, rows = table_rows(stats)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    lines += ["| " + " | ".join(md_cell(c) for c in r) + " |" for r in rows]
    caption = table_caption(stats)
    return "\n".join(lines) + "\n" + (f"\n{caption}\n" if caption else "")


def csv_table(stats) -> str:
    """Every column of the table as numbers: a value's half-width in ``<key>_hw``, the diverged
    fraction's interval in ``diverged_lo``/``diverged_hi``, the paired differences to the
    baseline in ``delta_<key>`` and ``delta_<key>_hw``."""
    cols = _columns(stats)
    keys = [k for k, _, _ in cols]
    hw_keys = [k for k in keys if any(k in f.get("half_width", {}) for f in stats["filters"].values())]
    paired = list(dict.fromkeys(k for f in stats["filters"].values() for k in f.get("paired", {})
                                if k not in ("baseline", "runs") and k in keys))
    intervals = any("intervals" in f for f in stats["filters"].values())
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["filter", "kind"] + keys + [f"{k}_hw" for k in hw_keys] + (["diverged_lo", "diverged_hi"] if intervals else [])
               + [c for k in paired for c in (f"delta_{k}", f"delta_{k}_hw")] + (["baseline"] if paired else []))
    for label, f in stats["filters"].items():
        row = [label, f["kind"]] + [_json_num(f["summary"].get(k)) for k in keys]
        row += [_json_num(f.get("half_width", {}).get(k)) for k in hw_keys]
        if intervals:
            row += [_json_num(v) for v in f.get("intervals", {}).get("diverged_fraction", [None, None])]
        pd = f.get("paired", {})
        row += [_json_num(pd.get(k, {}).get(c)) for k in paired for c in ("difference", "half_width")]
        row += [pd.get("baseline")] if paired else []
        w.writerow(row)
    return buf.getvalue()


def _json_num(v):
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return float(f"{v:.10g}") if math.isfinite(v) else None  # 10 significant digits
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    return _json_num(obj)


MAX_SERIES_POINTS = 2000  # longer runs are stored (and drawn) every `stride` steps


def series_stride(steps):
    return max(1, -(-steps // MAX_SERIES_POINTS))


def _decimate(tree, stride):
    if stride == 1:
        return tree
    if isinstance(tree, dict):
        return {k: _decimate(v, stride) for k, v in tree.items()}
    return np.asarray(tree)[stride - 1::stride]


def stats_document(exp, res):
    from tracklab import __version__

    level = getattr(exp, "level", 0.95)
    st = statistics(res, exp.window, exp.pred_windows, level, getattr(exp, "baseline", None))
    ran = exp.ran_with()
    stride = series_stride(res.steps)
    st = {
        "bounds": _decimate(st["bounds"], stride),
        "filters": {k: dict(f, series=_decimate(f["series"], stride)) for k, f in st["filters"].items()},
    }
    return {
        "name": exp.name,
        "tracklab_version": __version__,
        "runs": res.runs,
        "steps": res.steps,
        "dt": res.dt,
        "window": list(exp.window),
        "series_stride": stride,  # series hold steps stride, 2·stride, … (summaries use every step)
        "axes": list(res.axes),  # names of the reporting frame's position axes
        "units": list(res.units),  # of position and velocity
        "windows": [w for w in exp.pred_windows if w != REPORT_WINDOW],  # named prediction-error windows
        "level": level,  # of every interval: value ± half_width
        "wall_s": res.wall_s,
        "compile_s": res.compile_s,
        "experiment": exp.raw,
        "bounds": st["bounds"],
        "example_run": _decimate(_example(exp, res), stride),
        "filters": {
            label: {"kind": f["kind"], "label": label, "params": ran.get(label, {}), "summary": f["summary"]}
            | {k: f[k] for k in ("half_width", "intervals", "paired", "cdf") if k in f} | {"series": f["series"]}
            for label, f in st["filters"].items()
        },
    } | ({"auto": res.auto} if getattr(res, "auto", None) else {})


def results_path(exp, out=None) -> Path:
    """Where an experiment's results go: ``out``, or results/<name>/."""
    return Path(out) if out is not None else Path("results") / exp.name


def run_into_folder(exp, out, runs, max_memory, simulate, write):
    """What ``run`` is for every kind of experiment: the output folder and the memory need checked
    before anything compiles, then ``simulate()``, then ``write(its result, folder)`` into a
    temporary folder swapped in whole; returns what ``write`` returns (the statistics). In a run of
    several processes every one checks and simulates, and process 0 alone writes (the others
    return None)."""
    from tracklab.output import atomic_folder, check_results_folder
    from tracklab.runtime import writes

    file = exp.path if exp.path is not None else "tracklab.experiment"  # what a refusal names
    out = check_results_folder(results_path(exp, out), file)
    exp.check_memory(runs, max_memory)
    result = simulate()
    if not writes():
        return None
    with atomic_folder(out, file) as tmp:
        return write(result, tmp)


def _example(exp, res):
    """Run 0 in CV layout: truth, each filter's estimates and (Cartesian sensors) the measurements."""
    ex = res.example
    if not ex:
        return {}
    doc = {"truth": ex["truth"][1:], "estimates": ex["x"]}
    if ex.get("var"):  # each filter's own standard deviations of its errors, for the ±3σ envelope
        doc["sd"] = {k: np.sqrt(np.maximum(np.asarray(v, float), 0.0)) for k, v in ex["var"].items()}
    kinds = [s.kind for s in exp.sensor.sensors] if exp.sensor is not None else []
    if len(kinds) == 1 and kinds[0] in ("cartesian", "mount"):
        doc["measurements"] = ex["z"]
    return doc


def write_json(path: Path, doc):
    """Compact JSON, NaN and infinities as null, floats to 10 significant digits; tracklab's
    header (its version) first, which marks the folder as tracklab's (``tracklab.output``)."""
    from tracklab import __version__
    from tracklab.output import HEADER_KEY

    doc = {HEADER_KEY: __version__} | dict(doc)
    path.write_text(json.dumps(_jsonable(doc), separators=(",", ":"), allow_nan=False) + "\n")


def write_tables(folder: Path, doc, table_md=None):
    """stats.json, table.md (``table_md``, default the one-row-per-filter table) and table.csv."""
    write_json(folder / "stats.json", doc)
    (folder / "table.md").write_text(markdown_table(doc) if table_md is None else table_md)
    (folder / "table.csv").write_text(csv_table(doc))


def write_results(exp, res, folder: Path, figures=True):
    """Write the statistics document, tables and figures into ``folder``; return the document."""
    doc = stats_document(exp, res)
    write_tables(folder, doc)
    if figures:
        from tracklab.figures import plot_figures

        plot_figures(doc, folder)
    return doc
