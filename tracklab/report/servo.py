"""The servo world's results (paper 003): its tables and figures (each case's run 0, the runs'
maximum tracking errors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tracklab.intervals import with_half_width
from tracklab.report.document import write_tables
from tracklab.report.figures import (
    arr,
    cdf_panel,
    coincide_note,
    formats_of,
    legend,
    panel_grid,
    pyplot,
    save,
    styles,
)


def write_servo_results(doc, folder: Path, figures=True):
    """The tables and (``figures``) the figures of a servo statistics document; returns it."""

    write_tables(folder, doc)
    if formats_of(figures):
        plot_servo(doc, folder, formats_of(figures))
    return doc

def _run0_panels(plt, doc, traces, t, settle, ylabel, key, unit, shared_scale):
    """Run 0's ``traces`` {case: series} against ``t``, one panel per case, each titled with the
    mean over the runs of each run's largest settled |error| (summary ``key``, in ``unit``) and
    its 95 % half-width. The y scale is the settled part's (t ≥ ``settle``, dotted), the transient
    before it runs off: the same for every panel (``shared_scale``) or each its own."""
    traces = {label: arr(e) for label, e in traces.items()}
    settled = t >= settle

    def top(e):
        v = np.abs(e[settled & np.isfinite(e)])
        lim = 1.2 * np.percentile(v, 99.5) if v.size else 0.0
        return lim if lim > 0 else None

    tops = [x for x in map(top, traces.values()) if x is not None]
    st = styles(list(doc["filters"]), len(t))
    fig, axes = panel_grid(plt, len(traces), 1, width=7.0, height=1.45)
    for ax, (label, e) in zip(axes[:, 0], traces.items()):
        ax.plot(t, e, **(st[label] | {"lw": 0.7, "ls": "-", "marker": None}))
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.axvline(settle, color="0.4", lw=0.8, ls=":")
        lim = max(tops) if shared_scale and tops else top(e)
        if lim is not None:
            ax.set_ylim(-lim, lim)
        ax.grid(True, alpha=0.3)
        f = doc["filters"][label]
        worst, hw = f["summary"].get(key), f["half_width"].get(key)
        stat = "" if worst is None else (f"; each run's largest settled |error|, mean over the runs "
                                          f"{with_half_width(worst, hw, '{:.3f}')} {unit}")
        ax.set_title(label + stat, fontsize=8, loc="left")
    axes[-1, 0].set_xlabel("time (s)")
    fig.supylabel(ylabel, fontsize=9)
    return fig

def plot_servo(doc, folder: Path, formats=("png",)):
    """The figures of a servo results folder: run 0's tracking error (``tracking_error.png``, paper
    003 Figs. 5–7) and rate-estimate error (``rate_error.png``, Fig. 4), and the distribution of
    the runs' maximum tracking errors (``error_cdf.png``)."""
    plt = pyplot()
    ex = doc["example_run"]
    filters = doc["filters"]
    t = np.asarray(ex["t"])
    tf = np.asarray(ex["t_frames"])
    # the errors' settling time (a document without it: the first tenth of the run)
    settle = ex.get("settle", t[0] + 0.1 * (t[-1] - t[0]))
    fig = _run0_panels(plt, doc, {k: 60.0 * arr(e) for k, e in ex["error"].items()}, t, settle,
                       "tracking error (′)", "max_track_err", "′", shared_scale=False)
    fig.suptitle(f"{doc['name']} — run 0 (paper 003 Figs. 5–7); each panel's scale from t ≥ {settle:g} s (dotted)",
                 fontsize=9)
    save(plt, fig, folder, "tracking_error", formats)
    if ex["rate_error"]:
        fig = _run0_panels(plt, doc, ex["rate_error"], tf, settle, "rate-estimate error (°/s)",
                           "max_rate_err", "°/s", shared_scale=True)
        fig.suptitle(f"{doc['name']} — run 0 (paper 003 Fig. 4); one scale, from t ≥ {settle:g} s (dotted)", fontsize=9)
        save(plt, fig, folder, "rate_error", formats)
    shown = {l: f for l, f in filters.items() if f.get("cdf")}
    if shown:
        fig, axes = panel_grid(plt, 1, 1, width=7.0, height=3.4)
        ax = axes[0, 0]
        groups = cdf_panel(ax, shown, styles(list(filters), len(t)), "max_track_err", "max_track_err_p{p}")
        ax.set_xlabel("run's maximum tracking error after settling (′)")
        ax.set_ylabel("fraction of runs with error ≤ x")
        ax.set_title(f"{doc['name']}: {doc['runs']} runs", fontsize=9)
        legend(fig, axes, coincide_note(groups))
        save(plt, fig, folder, "error_cdf", formats)
