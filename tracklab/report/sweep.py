"""A sweep's folder: sweep.json, table.md, table.csv and its figures (curves for one axis,
heatmaps for two)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from tracklab.intervals import percent, with_half_width
from tracklab.output import atomic_folder
from tracklab.report.document import write_json
from tracklab.report.figures import colour_levels, formats_of, level_label, pyplot, save, short_value, styles
from tracklab.report.tables import md_cell


def write_sweep(exp, doc, out, figures=True):
    """sweep.json, table.md, table.csv and heatmaps (1-D: curves) of RMSE and NEES per filter; a
    sweep of three axes or more has no figures (``no_figures``)."""
    with atomic_folder(Path(out), exp.path) as tmp:
        return _write_sweep(exp, doc, tmp, figures)

def no_figures(doc) -> str | None:
    """Why a sweep has no figures, in one line (None when it has them): figures draw 1 or 2 axes."""
    k = len(doc["axes"])
    if k <= 2:
        return None
    return (f"no figures: a sweep of {k} axes is written to sweep.json, table.md and table.csv only; "
            "figures draw 1 or 2 axes")

def _csv(v):
    return v if v is not None and np.isfinite(v) else ""

_NOT_METRICS = ("runs", "diverged", "lost_lock", "healthy_runs")

def _metrics(summary: dict) -> list[str]:
    """The columns of a sweep's table: the headline statistics of the world's summaries."""
    if "pred_err_rms" in summary:  # open-loop tracking (in clutter: its track loss first)
        return ((["p_lost", "lost", "validated_per_scan"] if "p_lost" in summary else [])
                + ["rmse_pos", "rmse_vel", "pred_err_rms"] + [k for k in summary if k.startswith("pred_err_max[")]
                + ["nees", "nees_in_bounds"])
    return [k for k, v in summary.items() if k not in _NOT_METRICS and (v is None or isinstance(v, (int, float)))]

def _write_sweep(exp, doc, tmp, figures):
    names = list(doc["axes"])
    labels = list(doc["points"][0]["stats"]["filters"])
    metrics = _metrics(doc["points"][0]["stats"]["filters"][labels[0]]["summary"])
    rows, hws, wilson = [], [], []
    for p in doc["points"]:
        for l in labels:
            f = p["stats"]["filters"][l]
            s, hw = f["summary"], f.get("half_width", {})
            rows.append([*(p["values"][n] for n in names), l, *(s.get(m) for m in metrics), s.get("diverged", 0)])
            hws.append([hw.get(m) for m in metrics])
            wilson.append(f.get("intervals", {}).get("p_lost") or [None, None])
    with_hw = [m for j, m in enumerate(metrics) if any(h[j] is not None for h in hws)]
    lost = "p_lost" in metrics
    heads = [n if "." in n else f"{n} x" for n in names]
    header = [*heads, "filter", *metrics, "diverged"]
    lines = ["| " + " | ".join(md_cell(h) for h in header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    for r, h, w in zip(rows, hws, wilson):
        cells = ([f"{v:.4g}" for v in r[:len(names)]] + [md_cell(r[len(names)])]
                 + [fraction_cell(v, w) if m == "p_lost" else with_half_width(v, hw, "{:.4g}")
                    for m, v, hw in zip(metrics, r[len(names) + 1:-1], h)] + [str(int(r[-1]))])
        lines.append("| " + " | ".join(cells) + " |")
    caption = "\n" + sweep_caption(doc) + "\n" if with_hw or lost else ""
    (tmp / "table.md").write_text("\n".join(lines) + "\n" + caption)
    buf = io.StringIO()
    bounds = ["p_lost_lo", "p_lost_hi"] if lost else []
    header_csv = header[:-1] + [f"{m}_hw" for m in with_hw] + bounds + header[-1:]
    csv.writer(buf).writerows([header_csv, *([*r[:len(names) + 1], *map(_csv, r[len(names) + 1:-1]),
                                              *(_csv(h[metrics.index(m)]) for m in with_hw),
                                              *(map(_csv, w) if lost else ()), r[-1]]
                                             for r, h, w in zip(rows, hws, wilson))])
    (tmp / "table.csv").write_text(buf.getvalue())
    summary_only = {
        "name": exp.name, "runs": doc["runs"], "window": list(exp.window), "axes": doc["axes"],
        "titles": doc["titles"], "wall_s": doc["wall_s"], "compile_s": doc["compile_s"],
        "level": doc["points"][0]["stats"].get("level"),
        "points": [{"values": p["values"], "filters": {l: {"kind": f["kind"], "summary": f["summary"]}
                                                        | ({"half_width": f["half_width"]} if "half_width" in f else {})
                                                        | ({"intervals": {"p_lost": f["intervals"]["p_lost"]}}
                                                           if "p_lost" in f.get("intervals", {}) else {})
                                                        for l, f in p["stats"]["filters"].items()}}
                   for p in doc["points"]],
        "experiment": exp.raw,
    }
    write_json(tmp / "sweep.json", summary_only)
    if formats_of(figures) and not no_figures(doc):
        _plot({**doc, "name": exp.name}, names, labels, tmp, formats_of(figures))
    return rows

def sweep_caption(doc) -> str:
    """What a sweep table's ± are, and which points ran on the same runs."""
    levels = sorted({p["stats"].get("level", 0.95) for p in doc["points"]})
    level = (f"the {percent(levels[0])} confidence interval" if len(levels) == 1
             else "each point's confidence interval (at its report.level)")
    structural, separate = doc.get("structural") or [], doc.get("separate") or []
    if not structural and not separate:
        same = "every point on the same runs"
    else:
        parts = []
        if structural:
            parts.append(f"{', '.join(structural)} changing what is compiled, the grid ran as {doc['programs']} programs")
        if separate:
            parts.append(f"each value of {', '.join(separate)} on runs of its own")
        same = "; ".join(parts) + "; the other points on the same runs"
    text = f"± : half-width of {level} over the {runs_text(doc['runs'])} runs at each point ({same})."
    if any("p_lost" in f.get("intervals", {}) for p in doc["points"] for f in p["stats"]["filters"].values()):
        text += (" p_lost: the fraction of lost tracks with its Wilson interval (p_lost_lo, p_lost_hi in table.csv); "
                 "the other statistics are over the runs on track.")
    return text


def fraction_cell(p, bounds) -> str:
    """A fraction with its interval, ``20 % (17–24 %)``; the fraction alone without one."""
    if p is None:
        return "—"
    lo, hi = bounds
    if lo is None or hi is None:
        return percent(p)
    return f"{percent(p)} ({percent(lo, sign=False)}–{percent(hi)})"


def runs_text(runs) -> str:
    """A sweep's runs per point: one number, or the range a runs axis spans."""
    return str(runs) if isinstance(runs, int) else f"{min(runs)}–{max(runs)}"

def _log_edges(values):
    """Cell edges for values on a log axis: geometric midpoints, the end cells as wide as their
    neighbours (a single value: a factor 2 either side)."""
    v = np.log(np.asarray(values, float))
    if len(v) == 1:
        return np.exp(v[0] + np.array([-np.log(2), np.log(2)]))
    mid = 0.5 * (v[1:] + v[:-1])
    return np.exp(np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]]))

def _edges(values, log):
    """Cell edges that put each cell's centre on its grid value (on a log axis: in log)."""
    if log:
        return _log_edges(values)
    v = np.asarray(values, float)
    if len(v) == 1:
        half = 0.5 * abs(v[0]) or 0.5
        return np.array([v[0] - half, v[0] + half])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])

def value_axis(ax, vals, positive):
    """A curve's value axis: logarithmic when its values span a decade or more; otherwise linear,
    at least ±10 % about their middle, so that a change of a fraction of a percent reads as flat
    (on a log axis auto-scaled to the data it would fill the panel)."""
    if vals.size == 0:
        return
    lo, hi = float(np.min(vals)), float(np.max(vals))
    if positive and hi >= 10 * lo:
        ax.set_yscale("log")
        return
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    half = max(half * 1.1, 0.1 * abs(mid), 1e-12)
    ax.set_ylim(mid - half, mid + half)
    ax.ticklabel_format(axis="y", style="plain", useOffset=False)

def _plot(doc, names, labels, folder, formats=("png",)):
    """Per metric one figure. A 1-D sweep: every filter's curve on one shared axis, each point
    with its confidence interval. A 2-D sweep: a heatmap per filter (at most three across) on one
    colour scale shared by all, each cell centred on its grid values and labelled with its value,
    the colour bar named in words and units. The matched point of scale-factor axes (every factor
    1) is marked; the NEES's consistent value (its degrees of freedom) is a dashed line on the
    curves and a white contour on the heatmaps."""
    from matplotlib.colors import BoundaryNorm
    from matplotlib.ticker import FuncFormatter

    plt = pyplot()
    plain = FuncFormatter(lambda v, _: f"{v:g}")  # plain numbers on a log scale (0.01, not 10⁻²)
    axes_vals = [np.asarray(doc["axes"][n]) for n in names]
    titles, log = doc["titles"], doc["log"]
    factors = set(doc.get("factors", ()))
    dof = doc.get("nees_dof")
    level = percent(doc["points"][0]["stats"].get("level", 0.95)) if doc["points"] else "95 %"
    for metric, title in doc["metrics"]:
        # None (no healthy run at a point) -> NaN -> masked: left blank
        values = {l: np.ma.masked_invalid(np.array([p["stats"]["filters"][l]["summary"].get(metric)
                                                    for p in doc["points"]], float)) for l in labels}
        half = {l: np.array([p["stats"]["filters"][l].get("half_width", {}).get(metric, np.nan)
                             for p in doc["points"]], float) for l in labels}
        if all(v.mask.all() for v in values.values()):
            continue  # nothing to draw (e.g. no NEES in this world)
        notes = []
        if any(np.ma.is_masked(v) for v in values.values()):
            notes.append("blank: no run without divergence")
        probability = metric.startswith("p_")  # on one linear 0-1 scale for every filter
        every = np.concatenate([v.compressed() for v in values.values()])
        positive = not probability and bool(np.all(every > 0))
        mark = dof if metric == "nees" and dof else None
        if len(names) == 1:
            fig, ax = plt.subplots(figsize=(7.5, 4.2), layout="constrained")
            st = styles(labels, len(axes_vals[0]))
            for l in labels:
                ax.errorbar(axes_vals[0], values[l], yerr=np.where(np.isfinite(half[l]), half[l], 0.0), capsize=2,
                            ms=4, label=l, color=st[l]["color"], ls=st[l]["ls"], marker=st[l]["marker"])
            ax.set_xscale("log" if log[names[0]] else "linear")
            if log[names[0]]:
                ax.xaxis.set_major_formatter(plain)
            reach = [np.ma.filled(values[l] + np.nan_to_num(half[l]), np.nan) for l in labels]
            reach += [np.ma.filled(values[l] - np.nan_to_num(half[l]), np.nan) for l in labels]
            reach = np.concatenate(reach)
            value_axis(ax, np.concatenate([reach[np.isfinite(reach) & ((reach > 0) | (not positive))]]
                                          + ([[mark]] if mark else [])), positive)
            if mark:
                ax.axhline(mark, color="k", lw=0.8, ls="--", label=f"consistent ({mark})")
            if names[0] in factors and axes_vals[0].min() <= 1.0 <= axes_vals[0].max():
                ax.axvline(1.0, color="0.4", lw=0.8, ls=":", label="matched (factor 1)")
            ax.set_xlabel(titles[names[0]])
            ax.set_ylabel(title)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
            notes.append(f"bars: {level} confidence interval of each point")
            ax.set_title(f"{doc.get('name', '')}: {title}" + "".join(f"; {n}" for n in notes), fontsize=9)
            save(plt, fig, folder, f"sweep_{metric}", formats)
            continue
        cols = 2 if len(labels) == 4 else min(len(labels), 3)
        rows = -(-len(labels) // cols)
        fig, axs = plt.subplots(rows, cols, figsize=(4.8 * cols + 0.8, 4.0 * rows), squeeze=False, layout="constrained")
        lo, hi = float(every.min()), float(every.max())
        spread = positive and hi > 10.0 * lo  # more than a decade: log-spaced levels
        levels = ([0.1 * k for k in range(11)] if probability
                  else colour_levels(lo, hi if hi > lo else lo + max(abs(lo), 1.0), spread))
        cmap = plt.get_cmap("viridis")
        norm = BoundaryNorm(levels, cmap.N, extend="neither" if probability else "both")
        shade = (lambda v: np.log(v / levels[0]) / np.log(levels[-1] / levels[0])) if spread else \
            (lambda v: (v - levels[0]) / (levels[-1] - levels[0]))  # where a value lies on the scale, 0…1
        matched = [(i, j) for i, a in enumerate(axes_vals[0]) for j, b in enumerate(axes_vals[1])
                   if names[0] in factors and names[1] in factors and a == 1.0 and b == 1.0]
        for ax, l in zip(axs.flat, labels):
            grid = values[l].reshape(len(axes_vals[0]), len(axes_vals[1]))
            im = ax.pcolormesh(_edges(axes_vals[1], log[names[1]]), _edges(axes_vals[0], log[names[0]]), grid,
                               norm=norm, cmap=cmap)
            for (i, j), v in np.ndenumerate(grid):
                if not np.ma.is_masked(v):
                    ax.text(axes_vals[1][j], axes_vals[0][i], f"{100 * v:.0f}%" if probability else short_value(v),
                            ha="center", va="center", fontsize=7, color="w" if shade(v) < 0.6 else "k")
            for i, j in matched:
                ax.plot(axes_vals[1][j], axes_vals[0][i], "s", ms=22, mfc="none", mec="r", mew=1.5)
            if mark and len(axes_vals[0]) > 1 and len(axes_vals[1]) > 1 and np.nanmin(grid) < mark < np.nanmax(grid):
                ax.contour(axes_vals[1], axes_vals[0], grid, levels=[mark], colors="w", linewidths=1.5)
            ax.set_xscale("log" if log[names[1]] else "linear")
            ax.set_yscale("log" if log[names[0]] else "linear")
            ax.set_xticks(axes_vals[1], [level_label(v) for v in axes_vals[1]], fontsize=7)
            ax.set_yticks(axes_vals[0], [level_label(v) for v in axes_vals[0]], fontsize=7)
            ax.minorticks_off()
            ax.set_xlabel(titles[names[1]], fontsize=8)
            ax.set_ylabel(titles[names[0]], fontsize=8)
            ax.set_title(l, fontsize=9)
        for ax in list(axs.flat)[len(labels):]:
            ax.axis("off")
        cb = fig.colorbar(im, ax=axs[:, -1].tolist() if cols > 1 else axs[:, 0].tolist(), label=title, shrink=0.9)
        cb.set_ticks(levels, labels=[f"{100 * v:.0f}%" if probability else level_label(v) for v in levels])
        if mark:
            cb.ax.axhline(mark, color="w", lw=1.5)
            notes.append(f"white line: consistent NEES = {mark}")
        if matched:
            notes.append("red square: the matched point (every factor 1)")
        fig.suptitle(f"{doc.get('name', '')}: {title}, one colour scale for every filter"
                     + "".join(f"; {n}" for n in notes), fontsize=10)
        save(plt, fig, folder, f"sweep_{metric}", formats)
