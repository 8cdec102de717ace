"""Results folders: stats.json, table.md, table.csv and figures.

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

from tracklab.metrics import AXES, PAIRED, REPORT_WINDOW, statistics

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
    ("diverged", "diverged", "{:d}"),
    ("runs", "runs", "{:d}"),
]
PAIRED_COLUMN = "rmse_pos"  # the paired difference table.md shows (stats.json and table.csv hold them all)
WINDOW_COLUMNS = [  # per named prediction-error window
    ("pred_err_rms[{w}]", "pred err RMS {w} ({p})", "{:.{d}f}"),
    ("pred_err_max[{w}]", "pred err max {w} ({p})", "{:.{d}f}"),
]


def _fmt(v, spec):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    s = spec.format(v)
    return s.rstrip("%") if spec.endswith("%}") else s


def _missing(v) -> bool:
    return v is None or (isinstance(v, (float, np.floating)) and not math.isfinite(v))


def with_half_width(v, hw, spec="{:.2f}", sign=False) -> str:
    """``34.45 ± 0.05``: the half-width to two significant digits, the value to the same decimal;
    the column's own format when there is no half-width."""
    if _missing(v):
        return "—"
    if _missing(hw):
        return _fmt(v, spec)
    if hw == 0:
        return f"{v:{'+' if sign else ''}.{_decimals(spec)}f} ± 0"
    d = max(0, 1 - math.floor(math.log10(abs(hw))))
    return f"{v:{'+' if sign else ''}.{d}f} ± {hw:.{d}f}"


def _decimals(spec) -> int:
    try:
        return int(spec.split(".")[1].split("f")[0]) if "f}" in spec else 2
    except ValueError:
        return 2


def _diverged_cell(f) -> str:
    """``k (lo–hi %)``: the diverged runs and the Wilson interval of their fraction."""
    k = f["summary"].get("diverged")
    lo_hi = f.get("intervals", {}).get("diverged_fraction")
    if k is None or not lo_hi or _missing(lo_hi[1]):
        return _fmt(k, "{:d}")
    lo, hi = (100.0 * v for v in lo_hi)
    return f"{k} ({lo:.2g}–{hi:.2g} %)"


def _paired_cell(f, key=PAIRED_COLUMN) -> str:
    pd = f.get("paired", {})
    c = pd.get(key)
    if c is None:
        return "—"
    if pd.get("baseline") == f.get("label"):
        return "baseline"
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


def table_rows(stats):
    """The one-row-per-filter table: a number with an interval as ``value ± half-width``, the
    diverged runs with the interval of their fraction, and the paired difference to the baseline."""
    cols = _columns(stats)
    base = _baseline(stats)
    p = stats.get("units", ("m", "m/s"))[0]
    header = ["filter", "kind"] + [t for _, t, _ in cols]
    if base is not None:
        header.insert(2 + next((i + 1 for i, c in enumerate(cols) if c[0] == PAIRED_COLUMN), 0),
                      f"Δ RMSE pos vs {base} ({p})")
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
            if k == PAIRED_COLUMN and base is not None:
                cells.append(_paired_cell(f))
        rows.append([label, f["kind"]] + cells)
    return header, rows


def table_caption(stats) -> str:
    """What the table's ± and Δ mean (empty when it has no intervals)."""
    if not any("half_width" in f for f in stats["filters"].values()):
        return ""
    level = stats.get("level", 0.95)
    runs = stats.get("runs")
    text = (f"± : half-width of the {level:.0%} confidence interval over the {runs} runs (Student t over the runs' "
            "time-averaged values; delta method for an RMSE and the NIS). diverged: runs, with the Wilson interval of "
            "their fraction. run err pNN: percentiles of the runs' RMS position errors.")
    base = _baseline(stats)
    if base is not None:
        text += (f" Δ: difference to {base} on the same runs with its paired interval; "
                 f"(n.s.): not significant at {level:.0%}.")
    if stats.get("auto"):
        a = stats["auto"]
        text += (f" Runs chosen automatically: {runs} runs brought every filter's position-RMSE interval within "
                 f"± {100 * a['target']:g} % (at most {a['max_runs']})" + ("." if a["reached"] else "; the target was not reached."))
    return text


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
    paired = [k for k in PAIRED if any(k in f.get("paired", {}) for f in stats["filters"].values())]
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
    temporary folder swapped in whole; returns what ``write`` returns (the statistics)."""
    from tracklab.output import atomic_folder, check_results_folder

    file = exp.path if exp.path is not None else "tracklab.experiment"  # what a refusal names
    out = check_results_folder(results_path(exp, out), file)
    exp.check_memory(runs, max_memory)
    result = simulate()
    with atomic_folder(out, file) as tmp:
        return write(result, tmp)


def _example(exp, res):
    """Run 0 in CV layout: truth, each filter's estimates and (Cartesian sensors) the measurements."""
    ex = res.example
    if not ex:
        return {}
    doc = {"truth": ex["truth"][1:], "estimates": ex["x"]}
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


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_results(exp, res, folder: Path, figures=True):
    """Write the statistics document, tables and figures into ``folder``; return the document."""
    doc = stats_document(exp, res)
    write_tables(folder, doc)
    if figures:
        plot_figures(doc, folder)
    return doc


def plot_figures(doc, folder: Path):
    plt = pyplot()

    dt, stride = doc["dt"], doc.get("series_stride", 1)
    t = dt * np.arange(stride, doc["steps"] + 1, stride)
    filters = doc["filters"]
    bounds = doc["bounds"]
    axes_names = doc.get("axes", AXES)
    pu, vu = doc.get("units", ("m", "m/s"))
    dim = sum(1 for a in axes_names if f"rmse_{a}" in next(iter(filters.values()))["series"])
    AX = axes_names
    title = f"{doc['name']} — {doc['runs']} runs"

    def arr(v):
        return np.array([np.nan if x is None else x for x in v], float) if isinstance(v, list) else np.asarray(v, float)

    # per-step RMSE per axis with the PCRLB (the paper's Fig. 2, panels A and C)
    fig, axes = plt.subplots(dim, 1, figsize=(8, 2.8 * dim), sharex=True)
    for a, ax in enumerate(np.atleast_1d(axes)):
        for label, f in filters.items():
            ax.plot(t, arr(f["series"][f"rmse_{AX[a]}"]), lw=1.2, label=label)
        if f"pcrlb_{AX[a]}" in bounds:
            ax.plot(t, arr(bounds[f"pcrlb_{AX[a]}"]), "k--", lw=1, label="PCRLB")
        ax.set_yscale("log")
        ax.set_ylabel(f"RMSE {AX[a]} ({pu})")
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=7, ncol=2)
    np.atleast_1d(axes)[0].set_title(title)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(folder / "rmse.png", dpi=110)
    plt.close(fig)

    # mean error (bias) per axis (panels B and D)
    fig, axes = plt.subplots(dim, 1, figsize=(8, 2.8 * dim), sharex=True)
    for a, ax in enumerate(np.atleast_1d(axes)):
        for label, f in filters.items():
            ax.plot(t, arr(f["series"][f"mean_err_{AX[a]}"]), lw=1.2, label=label)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_yscale("symlog", linthresh=1.0 if pu == "m" else 1e-4)  # small biases stay visible beside large ones
        ax.set_ylabel(f"mean error {AX[a]} ({pu})")
        ax.grid(True, alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=7, ncol=2)
    np.atleast_1d(axes)[0].set_title(title)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(folder / "mean_error.png", dpi=110)
    plt.close(fig)

    # one-step prediction error per axis (paper 004's Fig. 3), named windows shaded
    fig, axes = plt.subplots(dim, 1, figsize=(8, 2.8 * dim), sharex=True)
    for a, ax in enumerate(np.atleast_1d(axes)):
        for label, f in filters.items():
            ax.plot(t, arr(f["series"][f"pred_rmse_{AX[a]}"]), lw=1.2, label=label)
        for w, (t0, t1) in _window_spans(doc).items():
            ax.axvspan(t0, t1, color="0.9", zorder=0)
            ax.text(0.5 * (t0 + t1), 1.0, w, transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel(f"one-step pred. RMS err {AX[a]} ({pu})")
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=7, ncol=2)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(folder / "pred_error.png", dpi=110)
    plt.close(fig)

    example = doc.get("example_run") or {}
    if example:
        plot_example(doc, example, t, dim, folder)
        if dim >= 2 and pu == "m":
            plot_track(doc, example, folder)

    # average NEES with its 95 % interval
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for label, f in filters.items():
        (line,) = ax.plot(t, arr(f["series"]["nees"]), lw=1.2, label=label)
    f0 = next(iter(filters.values()))["series"]
    ax.fill_between(t, arr(f0["nees_lo"]), arr(f0["nees_hi"]), color="0.8", label="95 % interval")
    ax.axhline(2 * dim, color="k", lw=0.6)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"average NEES (dof {2 * dim})")
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(folder / "nees.png", dpi=110)
    plt.close(fig)


def plot_track(doc, example, folder: Path):
    """The true path seen from above, coloured by each filter's per-step position RMSE (errors along the path)."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    truth = np.asarray(example["truth"], float)
    xy = truth[:, [0, 2]] / 1000.0
    filters = doc["filters"]
    vals = {label: np.array([np.nan if v is None else v for v in f["series"]["rmse_pos"]], float)
            for label, f in filters.items()}
    finite = np.concatenate([v[np.isfinite(v)] for v in vals.values()])
    lo, hi = (np.percentile(finite, 2), np.percentile(finite, 98)) if finite.size else (1.0, 10.0)
    norm = plt.Normalize(max(lo, 0.0), max(hi, lo + 1e-9))
    k = len(filters)
    cols = min(k, 3)
    rows = -(-k // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.8 * rows), squeeze=False, constrained_layout=True)
    seg = np.stack([xy[:-1], xy[1:]], axis=1)
    for ax, (label, v) in zip(axes.flat, vals.items()):
        lc = LineCollection(seg, cmap="viridis", norm=norm, linewidths=2.5)
        lc.set_array(v[1:])
        ax.add_collection(lc)
        ax.plot([0], [0], "k^", ms=7)  # the sensor
        ax.autoscale()
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{label}: RMSE {filters[label]['summary']['rmse_pos']:.1f} m", fontsize=8)
        ax.set_xlabel("east (km)", fontsize=8)
        ax.set_ylabel("north (km)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[k:]:
        ax.axis("off")
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=axes, shrink=0.8, label="position RMSE (m)")
    fig.suptitle(f"{doc['name']} — {doc['runs']} runs: error along the path", fontsize=10)
    fig.savefig(folder / "track.png", dpi=110)
    plt.close(fig)


def _window_spans(doc):
    """Named windows given as [t0, t1] in the experiment file (not "rest")."""
    table = doc.get("experiment", {}).get("report", {}).get("windows", {})
    return {w: v for w, v in table.items() if isinstance(v, list) and w in doc.get("windows", [])}


def plot_example(doc, example, t, dim, folder: Path):
    """Run 0: true and estimated position and velocity, and their errors (paper 002 Figs. 4–7)."""
    import matplotlib.pyplot as plt

    truth = np.asarray(example["truth"], float)
    est = {k: np.asarray(v, float) for k, v in example["estimates"].items()}
    z = np.asarray(example["measurements"], float) if "measurements" in example else None
    pu, vu = doc.get("units", ("m", "m/s"))
    AX = doc.get("axes", AXES)
    names = [("position", pu, 0), ("velocity", vu, 1)]
    for kind in ("state", "error"):
        fig, axes = plt.subplots(2, dim, figsize=(5 * dim, 6), sharex=True, squeeze=False)
        for a in range(dim):
            for row, (q, unit, j) in enumerate(names):
                ax = axes[row, a]
                col = 2 * a + j
                if kind == "state":
                    if z is not None and j == 0:
                        ax.plot(t, z[:, a], ".", color="0.7", ms=2, label="measured")
                    ax.plot(t, truth[:, col], "k-", lw=1.5, label="true")
                    for label, x in est.items():
                        ax.plot(t, x[:, col], lw=1, label=label)
                else:
                    for label, x in est.items():
                        ax.plot(t, x[:, col] - truth[:, col], lw=1, label=label)
                    ax.axhline(0, color="k", lw=0.6)
                ax.set_ylabel(f"{q} {AX[a]} ({unit})" if kind == "state" else f"{q} error {AX[a]} ({unit})")
                ax.grid(True, alpha=0.3)
        axes[0, 0].legend(fontsize=7)
        axes[0, 0].set_title(f"{doc['name']} — run 0")
        for ax in axes[-1]:
            ax.set_xlabel("time (s)")
        fig.tight_layout()
        fig.savefig(folder / ("run0.png" if kind == "state" else "run0_error.png"), dpi=110)
        plt.close(fig)
