"""Tables of a statistics document: Markdown (every number ``value ± half-width``, the paired
difference to the baseline, a caption saying what they are) and CSV (the same as numbers)."""

from __future__ import annotations

import csv
import io
import math

import numpy as np

from tracklab.intervals import format_value, missing, percent, with_half_width
from tracklab.montecarlo.statistics import AXES

# (summary key, title, format); {p}/{v} are the position/velocity units, {a} an axis name
COLUMNS = [
    ("lost", "lost tracks", "{:d}"),
    ("time_to_loss", "time to loss (s)", "{:.1f}"),
    ("validated_per_scan", "validated/scan", "{:.2f}"),
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
    ("on_track", "runs on track", "{:d}"),
    ("runs", "runs", "{:d}"),
]

PAIRED_COLUMNS = ("rmse_pos", "max_track_err")  # the paired difference table.md shows, the first there is

# (stats.json and table.csv hold them all)
WINDOW_COLUMNS = [  # per named prediction-error window
    ("pred_err_rms[{w}]", "pred err RMS {w} ({p})", "{:.{d}f}"),
    ("pred_err_max[{w}]", "pred err max {w} ({p})", "{:.{d}f}"),
]

def fmt(v, spec):
    return format_value(v, spec)

def diverged_cell(f, key="diverged", fraction="diverged_fraction") -> str:
    """``k (lo–hi %)``: the diverged runs (summary ``key``) and the Wilson interval of their fraction
    (``8 (68–100 %)``, ``0 (0–0.12 %)``); the lost tracks with ``fraction = "p_lost"``."""
    k = f["summary"].get(key)
    lo_hi = f.get("intervals", {}).get(fraction)
    if k is None or not lo_hi or missing(lo_hi[0]) or missing(lo_hi[1]):
        return fmt(k, "{:d}")
    return f"{k} ({percent(lo_hi[0], sign=False)}–{percent(lo_hi[1])})"

def paired_cell(f, key) -> str:
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

def lost_paired_cell(f) -> str:
    """The difference in the fraction of lost tracks to the baseline, in percentage points."""
    c = f.get("paired", {}).get("p_lost")
    if c is None:
        return "—"
    if f.get("paired", {}).get("baseline") == f.get("label"):
        return "baseline"
    if missing(c["difference"]):
        return "—"
    cell = f"{100 * c['difference']:+.1f} ± {100 * c['half_width']:.1f} pp"
    return cell if c["significant"] else cell + " (n.s.)"

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
    lost_paired = base is not None and any("p_lost" in f.get("paired", {}) for f in stats["filters"].values())
    if lost_paired:  # the difference in the fraction of lost tracks, after their column
        header.insert(3 + next(i for i, c in enumerate(cols) if c[0] == "lost"), f"Δ lost vs {base}")
    rows = []
    for label, f in stats["filters"].items():
        f = dict(f, label=label)
        hw = f.get("half_width", {})
        cells = []
        for k, _, spec in cols:
            if k == "diverged":
                cells.append(diverged_cell(f))
            elif k == "lost":
                cells.append(diverged_cell(f, "lost", "p_lost"))
                if lost_paired:
                    cells.append(lost_paired_cell(f))
            elif k in hw:
                cells.append(with_half_width(f["summary"].get(k), hw[k], spec))
            else:
                cells.append(fmt(f["summary"].get(k), spec))
            if k == paired_key and base is not None:
                cells.append(paired_cell(f, k))
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
    text = (f"± : half-width of the {percent(level)} confidence interval over the {runs} runs (Student t over the runs' "
            + ("values)." if servo else f"time-averaged values; delta method for an RMSE{' and the NIS' if nis else ''}).")
            + " diverged: runs, with the Wilson interval of their fraction.")
    loss = stats.get("track_loss")
    if loss:
        text += (f" lost tracks: runs whose position error stayed beyond {loss['distance']:g} {stats.get('units', ['m'])[0]} "
                 f"for {loss['steps']} consecutive steps"
                 + (f" or whose existence probability (IPDA) stayed below {loss['existence']:g}" if "existence" in loss else "")
                 + " (lost for good), with the Wilson interval of their fraction; "
                 "time to loss: the mean time of the first of those steps, over the lost runs; validated/scan: returns "
                 "inside the gate per scan. Every other statistic is over the runs on track (never lost).")
        over = stats.get("overflow") or {}
        if over.get("scans"):
            text += (f" {over['scans']} scans in {over['runs']} runs held more returns than their capacity of "
                     f"{over['capacity']} (max_returns): their first {over['capacity']} were kept.")
        if _baseline(stats) is not None:
            text += f" Δ lost: difference in the fraction of lost tracks to {_baseline(stats)} on the same runs (pp: percentage points)."
    if any("max_track_err_p50" in s for s in summaries):
        text += " run max error pNN: percentiles of the runs' maximum tracking errors."
    elif any("err_pos_p50" in s for s in summaries):
        text += " run err pNN: percentiles of the runs' RMS position errors."
    base = _baseline(stats)
    if base is not None:
        text += (f" Δ: difference to {base} on the same runs with its paired interval; "
                 f"(n.s.): not significant at {percent(level)}.")
    return text + auto_note(stats)

def auto_note(stats) -> str:
    """How many runs ``runs = "auto"`` took and whether it met its target ("" for a fixed count)."""
    a = stats.get("auto")
    if not a:
        return ""
    return (f" Runs chosen automatically: {stats.get('runs')} runs brought every filter's "
            f"{a.get('statistic', 'position-RMSE')} interval within ± {100 * a['target']:g} % (at most {a['max_runs']})"
            + ("." if a["reached"] else "; the target was not reached."))

def stored(v):
    """A number as stats.json and table.csv keep it: 10 significant digits; NaN and infinities as None."""
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return float(f"{v:.10g}") if math.isfinite(v) else None  # 10 significant digits
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def md_cell(text) -> str:
    """A Markdown table cell: a '|' in a label is escaped, so it cannot start a new column."""
    return str(text).replace("\\", "\\\\").replace("|", "\\|")

def markdown_table(stats) -> str:
    header, rows = table_rows(stats)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    lines += ["| " + " | ".join(md_cell(c) for c in r) + " |" for r in rows]
    caption = table_caption(stats)
    return "\n".join(lines) + "\n" + (f"\n{caption}\n" if caption else "")

TERMINAL_KEYS = ("lost tracks", "Δ lost", "RMSE pos", "Δ RMSE pos", "RMSE/PCRLB", "NEES", "max tracking error",
                 "Δ max tracking error", "diverged")  # the columns the terminal shows, in this order of precedence


def terminal_table(stats, width: int = 120) -> str:
    """The table as the terminal shows it: the key columns (``TERMINAL_KEYS``, as many as fit in
    ``width`` characters, in the table's order), aligned, labels cut to 24 characters; the whole
    table is ``table.md`` and ``table.csv``."""
    header, rows = table_rows(stats)
    rank = {i: next((r for r, k in enumerate(TERMINAL_KEYS) if h.startswith(k)), None) for i, h in enumerate(header)}
    keys = sorted((i for i, r in rank.items() if r is not None), key=lambda i: rank[i])
    cut = lambda text, n: text if len(text) <= n else text[:n - 1] + "…"  # noqa: E731
    labels = [cut(str(r[0]), 24) for r in rows]
    wide = {j: max(len(header[j]), *(len(str(r[j])) for r in rows)) for j in keys}  # each column's width
    first = max(len("filter"), *map(len, labels))
    chosen = []
    for i in keys:
        if first + sum(wide[j] + 2 for j in chosen + [i]) <= width:
            chosen = sorted(chosen + [i])
    widths = [first] + [wide[j] for j in chosen]
    line = lambda cells: "  ".join(c.ljust(w) if k == 0 else c.rjust(w)  # noqa: E731
                                   for k, (c, w) in enumerate(zip(cells, widths))).rstrip()
    out = [line(["filter"] + [header[j] for j in chosen])]
    out += [line([labels[n]] + [str(r[j]) for j in chosen]) for n, r in enumerate(rows)]
    return "\n".join(out) + "\n"


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
        row = [label, f["kind"]] + [stored(f["summary"].get(k)) for k in keys]
        row += [stored(f.get("half_width", {}).get(k)) for k in hw_keys]
        if intervals:
            row += [stored(v) for v in f.get("intervals", {}).get("diverged_fraction", [None, None])]
        pd = f.get("paired", {})
        row += [stored(pd.get(k, {}).get(c)) for k in paired for c in ("difference", "half_width")]
        row += [pd.get("baseline")] if paired else []
        w.writerow(row)
    return buf.getvalue()
