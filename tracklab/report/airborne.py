"""The airborne world's tables and figures (paper 001): one table per quantity with a column per
report window, the paired differences, percentiles, settling and lock; RMS errors against time
and range with their bands, NEES with its χ² band, the runs' pointing-error distribution."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tracklab.intervals import percent, with_half_width
from tracklab.report.document import write_tables
from tracklab.report.figures import (
    arr,
    band,
    cdf_panel,
    coincide_note,
    formats_of,
    legend,
    panel_grid,
    plain_log,
    pyplot,
    save,
    styles,
    summary_value,
)
from tracklab.report.tables import auto_note, diverged_cell, fmt, md_cell, paired_cell

SUMMARY_TABLES = [  # (key, title, format)
    ("pointing", "true pointing error RMS (mrad)", "{:.3f}"),
    ("pointing_estimate", "pointing-error estimate, error RMS (mrad)", "{:.3f}"),
    ("los_rate", "LOS-rate error RMS (mrad/s)", "{:.3f}"),
    ("range", "range error RMS (m)", "{:.2f}"),
    ("range_rate", "range-rate error RMS (m/s)", "{:.3f}"),
    ("nees", "NEES (9 states; 95 % band about 9)", "{:.2f}"),
]

PAIRED_TABLES = [("pointing", "true pointing error RMS", "mrad"), ("los_rate", "LOS-rate error RMS", "mrad/s")]

def _table(title, header, rows) -> list[str]:

    return [f"\n## {title}\n", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
        ["| " + " | ".join(md_cell(c) for c in r) + " |" for r in rows]

def airborne_tables(doc) -> str:
    """Markdown: one table per quantity, a column per window, each number ± the half-width of its
    interval; the paired differences to the baseline tracker; the percentiles of the runs' pointing
    errors; settling times and lost lock (with the Wilson interval of its fraction)."""

    windows = doc["windows"]
    filters = doc["filters"]
    out = [f"# {doc['name']}: {doc['runs']} runs, {doc['steps']} filter periods of {doc['dt'] * 1e3:.0f} ms"]
    for key, title, spec in SUMMARY_TABLES:
        rows = [[label, f["kind"]] + [with_half_width(f["summary"].get(f"{key}[{w}]"),
                                                      f.get("half_width", {}).get(f"{key}[{w}]"), spec) for w in windows]
                for label, f in filters.items()]
        out += _table(title, ["tracker", "kind", *windows], rows)
    base = next((f["paired"]["baseline"] for f in filters.values() if "paired" in f), None)
    if base is not None:
        for key, title, unit in PAIRED_TABLES:
            rows = [[label] + [paired_cell(dict(f, label=label), f"{key}[{w}]") for w in windows]
                    for label, f in filters.items()]
            out += _table(f"{title}: difference to {base} on the same runs ({unit})", ["tracker", *windows], rows)
    if any("pointing_p50" in f["summary"] for f in filters.values()):
        rows = [[label] + [" / ".join(fmt(f["summary"].get(f"pointing_p{p}[{w}]"), "{:.3f}") for p in (50, 90, 99))
                           for w in windows] for label, f in filters.items()]
        out += _table("per-run true pointing error RMS, 50th / 90th / 99th percentile over the runs in lock (mrad)",
                      ["tracker", *windows], rows)
    events = sorted({k[7:-1] for f in filters.values() for k in f["summary"] if k.startswith("settle[")})
    titles = ["tracker", *(f"settle after {e} (s)" for e in events), "lost lock (runs)"]
    rows = [[label, *(fmt(f["summary"].get(f"settle[{e}]"), "{:.2f}") for e in events), diverged_cell(f, "lost_lock")]
            for label, f in filters.items()]
    out += _table("Settling and lock", titles, rows)
    notes = ["Settling: seconds until the LOS-rate error RMS stays within 1.5× its steady-window value for 1 s "
             "(from the mean curve; no interval)."] if events else []
    if any("half_width" in f for f in filters.values()):
        level = doc.get("level", 0.95)
        notes.append(f"± : half-width of the {percent(level)} confidence interval over the runs in lock (Student t over "
                     "the runs' window averages; delta method for an RMS). Differences: on the same runs, with "
                     f"their paired interval; (n.s.): not significant at {percent(level)}. Lost lock: runs, with the "
                     "Wilson interval of their fraction." + auto_note(doc))
    return "\n".join(out) + "\n" + "".join(f"\n{n}\n" for n in notes)

def write_airborne_results(doc, folder: Path, figures=True):
    """The tables and (``figures``) the figures of an airborne statistics document; returns it."""

    write_tables(folder, doc, airborne_tables(doc))
    if formats_of(figures):
        plot_airborne(doc, folder, formats_of(figures))
    return doc

AIRBORNE_PANELS = [  # file's stem, [(series key, axis label)], the paper's figure
    ("pointing_error", [("pointing", "true pointing error RMS (mrad)")], "paper 001 Fig. 3"),
    ("rate_error", [("los_rate", "LOS-rate error RMS (mrad/s)"), ("range_rate", "range-rate error RMS (m/s)")],
     "paper 001 Fig. 4"),
    ("range_error", [("range", "range error RMS (m)"), ("range_rate", "range-rate error RMS (m/s)")],
     "paper 001 Fig. 6"),
]

def _range_axis(ax, t, rng):
    """The nominal range (km) along the top of a time axis."""
    top = ax.secondary_xaxis("top", functions=(lambda x: np.interp(x, t, rng),
                                               lambda r: np.interp(r, rng[::-1], t[::-1])))
    top.set_xticks([r for r in (20, 15, 10, 7, 5, 4, 3, 2) if rng.min() <= r <= rng.max()])
    top.set_xlabel("nominal range (km)", fontsize=8)

def _shade_windows(axes, doc):
    """The report windows (acquisition, steady, the jolt's disturbance, turn, close; paper 001's
    phases) shaded in alternating tints on every time panel, named inside the top one (the
    nominal-range axis is above it)."""
    from matplotlib.patheffects import withStroke

    spans = doc.get("window_spans") or {}
    for i, (w, (t0, t1)) in enumerate(spans.items()):
        for ax in axes:
            ax.axvspan(t0, t1, color=("#e6e9f2", "#f2ebe1")[i % 2], zorder=-2, lw=0)
        axes[0].text(0.5 * (t0 + t1), 0.98, w, transform=axes[0].get_xaxis_transform(), ha="center", va="top",
                     fontsize=7, color="0.25", path_effects=[withStroke(linewidth=2.0, foreground="white")])


def _windows_note(doc) -> str:
    spans = doc.get("window_spans") or {}
    note = "; shaded: the report windows " + ", ".join(f"{w} {a:g}–{b:g} s" for w, (a, b) in spans.items()) \
        if spans else ""
    jolt = doc.get("experiment", {}).get("disturbance")
    if jolt:
        note += f"; the antenna is jolted {jolt['pointing']:g} mrad at {jolt['time']:g} s"
    return note


def plot_airborne(doc, folder: Path, formats=("png",)):
    """The figures of an airborne results folder: per-period RMS errors with their confidence bands
    (``pointing_error.png``, ``rate_error.png``, ``range_error.png``: paper 001 Figs. 3, 4, 6), the
    average NEES with its χ² band (``nees.png``) and the distribution of the runs' RMS pointing
    errors per window (``error_cdf.png``)."""
    plt = pyplot()
    t, rng = np.asarray(doc["t"]), np.asarray(doc["nominal_range"]) / 1e3
    filters = doc["filters"]
    st = styles(list(filters), len(t))
    level = doc.get("level", 0.95)
    title = f"{doc['name']}: {doc['runs']} runs"
    for name, rows, ref in AIRBORNE_PANELS:
        fig, axes = panel_grid(plt, len(rows), 1, width=7.0, height=2.8)
        for ax, (key, ylabel) in zip(axes[:, 0], rows):
            for label, f in filters.items():
                v = arr(f["series"][key])
                if np.isfinite(v).any():
                    hw = f["series"].get(f"{key}_hw")
                    band(ax, t, v, None if hw is None else arr(hw), st[label] | {"lw": 1.0}, label)
                else:  # no run in lock: nothing to draw, said in the legend
                    ax.plot([], [], " ", label=f"{label}: lost lock in every run")
            ax.set_ylabel(ylabel)
            plain_log(ax)
            ax.grid(True, which="both", alpha=0.3)
        _shade_windows(axes[:, 0], doc)
        _range_axis(axes[0, 0], t, rng)
        axes[-1, 0].set_xlabel("time (s)")
        axes[0, 0].set_title(f"{title} ({ref})", fontsize=9)
        legend(fig, axes, f"bands: {percent(level)} confidence of each period's RMS over the runs in lock"
               + _windows_note(doc))
        save(plt, fig, folder, name, formats)
    shown = {l: f for l, f in filters.items() if np.isfinite(arr(f["series"]["nees"])).any()}
    if shown:
        fig, axes = panel_grid(plt, 1, 1, width=7.0, height=3.2)
        ax = axes[0, 0]
        for label, f in shown.items():
            ax.plot(t, arr(f["series"]["nees"]), label=label + summary_value(f, "nees"), **(st[label] | {"lw": 1.0}))
        f0 = next(iter(shown.values()))["series"]
        if "nees_lo" in f0:
            ax.fill_between(t, arr(f0["nees_lo"]), arr(f0["nees_hi"]), color="0.82", zorder=0,
                            label=f"{percent(level)} χ² band")
        ax.axhline(9, color="k", lw=0.6)
        plain_log(ax)
        _shade_windows([ax], doc)
        ax.set_ylabel("average NEES (9 states)")
        ax.set_xlabel("time (s)")
        ax.grid(True, which="both", alpha=0.3)
        _range_axis(ax, t, rng)
        ax.set_title(title, fontsize=9)
        legend(fig, axes, "in parentheses: each tracker's NEES averaged over the whole run ± its interval"
               + _windows_note(doc))
        save(plt, fig, folder, "nees", formats)
    windows = [w for w in doc.get("windows", []) if any(f"pointing[{w}]" in f.get("cdf", {}) for f in filters.values())]
    if windows:
        cols = min(len(windows), 3)
        rows = -(-len(windows) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols + 2.2, 3.0 * rows + 0.5), squeeze=False,
                                 layout="constrained")
        notes = []  # which curves coincide, panel by panel
        for ax, w in zip(axes.flat, windows):
            have = {l: f for l, f in filters.items() if f"pointing[{w}]" in f.get("cdf", {})}
            groups = cdf_panel(ax, have, st, f"pointing[{w}]")
            notes += [f"{w}: {coincide_note(groups)}"] if groups else []
            ax.set_title(w, fontsize=9)
            ax.set_xlabel("run's RMS pointing error (mrad)", fontsize=8)
        for ax in axes[:, 0]:
            ax.set_ylabel("fraction of runs ≤ x")
        for ax in list(axes.flat)[len(windows):]:
            ax.axis("off")
        fig.suptitle(f"{title}: distribution of the runs' RMS true pointing error per window", fontsize=9)
        legend(fig, axes, "; ".join(notes))
        save(plt, fig, folder, "error_cdf", formats)
