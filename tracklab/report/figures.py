"""The figures of a tracking results folder, drawn from its statistics document (stats.json).

* ``rmse.png``: per-step position and velocity RMSE with their confidence bands and the PCRLB;
  ``rmse_axes.png`` the same per axis (the papers' per-axis panels).
* ``mean_error.png``: per-step mean error (bias) per axis with its band.
* ``nees.png``, ``nis.png``: average NEES and NIS with their χ² acceptance bands.
* ``pred_error.png``: one-step prediction RMS error per axis, named windows shaded.
* ``error_cdf.png``: the distribution of the runs' RMS position errors (P(error ≤ x)).
* ``run0.png``, ``run0_error.png``: run 0's estimates and errors, with each filter's ±3σ.
* ``track.png``: the path seen from above, coloured by the per-step position RMSE.
* ``track_loss.png`` (an experiment with a track-loss test): the probability that the track
  is lost by each time with its Wilson band, and the returns validated per scan.

A file's ``[report] figures = [...]`` draws only the kinds it names (``FIGURE_KINDS``);
``tracklab plot`` draws any of them later from the stored statistics.

The closed-loop worlds have their own (``plot_airborne``, ``plot_servo``).

Curves that coincide stay distinguishable: each filter has its own colour, line style and
markers (staggered along the curve), the legend sits outside the axes with each filter's
time-averaged value ± its half-width, and a note names the filters whose curves coincide.
A filter far from the others (its time-averaged value more than ``OUTLIER`` times theirs,
or its NEES/NIS far outside consistency) is drawn in a panel of its own, so it never sets
the scale of the rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tracklab.intervals import percent, with_half_width
from tracklab.montecarlo.statistics import AXES

OUTLIER = 3.0  # a filter this many times off the others' median (or off consistency) gets its own panel
LINESTYLES = ["-", "--", "-.", ":", (0, (5, 1, 1, 1)), (0, (1, 1)), (0, (8, 2)), (0, (3, 1, 1, 1, 1, 1))]
MARKERS = ["o", "s", "^", "v", "D", "x", "P", "*", "<", ">"]
COINCIDE = 0.01  # curves within 1 % of each other over the report window are noted as coinciding


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


FIGURE_KINDS = ("rmse", "rmse_axes", "mean_error", "pred_error", "nees", "nis", "error_cdf", "track_loss", "run0",
                "run0_error", "track")  # a tracking results folder's figures, by file stem
FORMATS = ("png", "pdf", "svg")  # what figures may be written as: PNG for screens, PDF and SVG for papers
DPI = 150  # a PNG's resolution


def formats_of(figures) -> tuple:
    """The formats a ``figures`` argument asks for: True → PNG, False or None → none, a format or a
    list of them (``FORMATS``) → those; anything else: ValueError in one line."""
    if figures is True:
        return ("png",)
    if figures is False or figures is None:
        return ()
    given = (figures,) if isinstance(figures, str) else tuple(figures) if isinstance(figures, (list, tuple)) else None
    if not given or any(f not in FORMATS for f in given):
        raise ValueError(f"figures = {figures!r}: must be True, False or formats from {', '.join(FORMATS)}")
    return tuple(dict.fromkeys(given))


def save(plt, fig, folder: Path, stem: str, formats=("png",)):
    """``fig`` written as ``folder/stem.<format>`` for each format, then closed. A PNG is drawn at
    ``DPI`` and stored with a palette of 256 colours (an octree's: a figure's few colours, the
    levels of its colour scales and their anti-aliasing; a third of the size of full colour, the
    same to the eye). The PNG is quantised from the canvas's own pixels: no full-colour PNG is
    encoded and decoded on the way (the same file, in two thirds of the time)."""
    from PIL import Image

    for f in formats:
        if f != "png":
            fig.savefig(Path(folder) / f"{stem}.{f}")
            continue
        dpi = fig.dpi
        fig.set_dpi(DPI)  # for this drawing only: a format written after it gets the figure's own, as savefig does
        fig.canvas.draw()
        pixels = Image.frombuffer("RGBA", fig.canvas.get_width_height(physical=True), fig.canvas.buffer_rgba())
        fig.set_dpi(dpi)
        image = pixels.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE)
        image.save(Path(folder) / f"{stem}.png", dpi=(DPI, DPI), optimize=True)
    plt.close(fig)


def arr(v):
    """A stats.json series (None for missing) as a float array (NaN for missing)."""
    return np.array([np.nan if x is None else x for x in v], float) if isinstance(v, list) else np.asarray(v, float)


def styles(labels, points):
    """Per filter: colour, line style and markers staggered along ``points`` samples."""
    import matplotlib.pyplot as plt

    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    k = max(len(labels), 1)
    every = max(points // 8, 1)
    return {label: dict(color=colours[i % len(colours)], ls=LINESTYLES[i % len(LINESTYLES)],
                        marker=MARKERS[i % len(MARKERS)], markevery=(int(i * every / k) % every, every), ms=4,
                        lw=1.3, mfc="none")
            for i, label in enumerate(labels)}


def summary_value(f, key, unit=""):
    s, hw = f["summary"].get(key), f.get("half_width", {}).get(key)
    if s is None:
        return ""
    if hw is None or not np.isfinite(hw):
        return f" ({s:.4g}{unit})"
    return f" ({with_half_width(s, hw)}{unit})"


def _label(label, f, keys):
    """The label, then the filter's time-averaged values ``v ± h unit`` one per line (a legend
    entry stays narrow beside the axes). ``keys``: (key, unit) or (key, unit, name), the name
    written before its value."""
    parts = [(f"{k[2]} " if len(k) > 2 else "", summary_value(f, k[0], f" {k[1]}").strip()[1:-1]) for k in keys]
    return "\n".join([label] + ["  " + n + p for n, p in parts if p])


def split_outliers(values: dict, centre=None, factor=OUTLIER):
    """(main, outliers) labels: an outlier's value is more than ``factor`` times from ``centre``
    (default the median of all) on a log scale; missing values stay in the main group. When
    every filter would be an outlier, none is."""
    finite = {k: v for k, v in values.items() if v is not None and np.isfinite(v) and v > 0}
    if len(finite) < 2 and centre is None:
        return list(values), []
    c = centre if centre is not None else float(np.median(list(finite.values())))
    out = [k for k, v in finite.items() if abs(np.log(v / c)) > np.log(factor)]
    main = [k for k in values if k not in out]
    return (main, out) if main else (list(values), [])


def coinciding(curves: dict, window) -> list[list[str]]:
    """Groups of labels whose curves stay within ``COINCIDE`` (relative) of each other over ``window``."""
    groups, seen = [], set()
    labels = list(curves)
    for i, a in enumerate(labels):
        if a in seen:
            continue
        group = [a]
        for b in labels[i + 1:]:
            if b in seen:
                continue
            x, y = curves[a][window], curves[b][window]
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.any() and np.all(np.abs(x[ok] - y[ok]) <= COINCIDE * np.maximum(np.abs(x[ok]), np.abs(y[ok]))):
                group.append(b)
        if len(group) > 1:
            seen.update(group)
            groups.append(group)
    return groups


def coincide_note(groups) -> str:
    return "; ".join(f"{', '.join(g)} coincide (within {percent(COINCIDE)})" for g in groups)


def legend(fig, handles_from, note=""):
    """The legend outside the axes, on the right, with the coinciding-curves note beneath it."""
    handles, labels = [], []
    for ax in np.asarray(handles_from).ravel():
        h, l = ax.get_legend_handles_labels()
        for hh, ll in zip(h, l):
            if ll not in labels:
                handles.append(hh)
                labels.append(ll)
    if note:  # beneath the entries, in the legend's column
        import textwrap

        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="none"))
        labels.append("\n".join(textwrap.wrap(note, 38)))
    return fig.legend(handles, labels, loc="outside right upper", fontsize=7, frameon=False)


def plain_log(ax, axis="y"):
    """A log axis labelled in plain numbers at 1, 2, 3, 5 × 10ⁿ (no overlapping minor labels)."""
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    a = ax.yaxis if axis == "y" else ax.xaxis
    (ax.set_yscale if axis == "y" else ax.set_xscale)("log")
    lo, hi = ax.get_ylim() if axis == "y" else ax.get_xlim()
    narrow = lo > 0 and hi / lo < 4  # within a factor 4: every 1…9 × 10ⁿ, so that a few are labelled
    a.set_major_locator(LogLocator(base=10, subs=tuple(range(1, 10)) if narrow else (1.0, 2.0, 3.0, 5.0)))
    fmt = ScalarFormatter()
    fmt.set_scientific(False)
    a.set_major_formatter(fmt)
    a.set_minor_formatter(NullFormatter())


def band(ax, t, v, hw, st, label):
    ax.plot(t, v, label=label if label is not None else "_nolegend_", **st)
    if hw is not None:
        ok = np.isfinite(v) & np.isfinite(hw)
        if ok.any():
            ax.fill_between(t, np.where(ok, v - hw, np.nan), np.where(ok, v + hw, np.nan), color=st["color"],
                            alpha=0.18, lw=0)


def _window_slice(doc, t):
    a, b = doc.get("window", [1, len(t)])
    stride = doc.get("series_stride", 1)
    return slice((a - 1) // stride, b // stride)


def chosen_kinds(doc, kinds=None) -> frozenset:
    """The figure kinds to draw: ``kinds``, else the experiment file's ``[report] figures``, else all."""
    if kinds is None:
        kinds = doc.get("experiment", {}).get("report", {}).get("figures")
    return frozenset(FIGURE_KINDS if kinds is None else kinds)


def plot_figures(doc, folder: Path, formats=("png",), kinds=None):
    """The figures of a tracking results folder (see the module's doc), in each of ``formats``:
    the kinds ``kinds`` (``FIGURE_KINDS``), by default those the experiment file names."""
    plt = pyplot()
    kinds = chosen_kinds(doc, kinds)
    dt, stride = doc["dt"], doc.get("series_stride", 1)
    t = dt * np.arange(stride, doc["steps"] + 1, stride)
    filters = doc["filters"]
    labels = list(filters)
    axes_names = doc.get("axes", AXES)
    dim = sum(1 for a in axes_names if f"rmse_{a}" in next(iter(filters.values()))["series"])
    st = styles(labels, len(t))
    ctx = dict(doc=doc, t=t, filters=filters, st=st, dim=dim, folder=folder, plt=plt, AX=axes_names,
               pu=doc.get("units", ("m", "m/s"))[0], title=f"{doc['name']} — {doc['runs']} runs",
               w=_window_slice(doc, t), formats=formats)
    drawers = {"rmse": _rmse, "rmse_axes": _rmse_axes, "mean_error": _mean_error, "pred_error": _pred_error,
               "nees": lambda c: _consistency(c, "nees", f"average NEES (dof {2 * dim})", 2.0 * dim),
               "nis": lambda c: _consistency(c, "nis", "average NIS", None), "error_cdf": _error_cdf,
               "track_loss": lambda c: doc.get("track_loss") and _track_loss(c)}
    for kind, draw in drawers.items():
        if kind in kinds:
            draw(ctx)
    example = doc.get("example_run") or {}
    if "estimates" in example and kinds & {"run0", "run0_error"}:
        plot_example(doc, example, t, dim, folder, st, formats, kinds)
    if example and "track" in kinds and dim >= 2 and doc.get("units", ("m",))[0] == "m":
        plot_track(doc, example, t, folder, formats)


def panel_grid(plt, rows, cols, width=6.0, height=2.4):
    return plt.subplots(rows, cols, figsize=(width * cols + 2.2, height * rows + 0.6), squeeze=False,
                        sharex=True, layout="constrained")


def _two_groups(ctx, key):
    """(main, outliers) by the filters' time-averaged ``key``."""
    return split_outliers({l: f["summary"].get(key) for l, f in ctx["filters"].items()})


def _rmse(ctx):
    """Position and velocity RMSE with bands and the PCRLB; outliers in a column of their own."""
    doc, t, filters, st = ctx["doc"], ctx["t"], ctx["filters"], ctx["st"]
    pu, vu = doc.get("units", ("m", "m/s"))
    bounds = doc["bounds"]
    main, out = _two_groups(ctx, "rmse_pos")
    cols = [main] + ([out] if out else [])
    fig, axs = panel_grid(ctx["plt"], 2, len(cols))
    notes = []
    for c, group in enumerate(cols):
        for r, (q, unit, bound) in enumerate((("pos", pu, "pcrlb_pos"), ("vel", vu, "pcrlb_vel"))):
            ax = axs[r, c]
            curves = {}
            for l in group:
                s = filters[l]["series"]
                v = arr(s[f"rmse_{q}"])
                curves[l] = v
                band(ax, t, v, arr(s[f"rmse_{q}_hw"]) if f"rmse_{q}_hw" in s else None, st[l],
                      _label(l, filters[l], (("rmse_pos", pu), ("rmse_vel", vu))) if r == 0 else None)
            if bound in bounds:
                name = "PCRLB in clutter (IRF)" if doc.get("clutter") else "PCRLB"
                ax.plot(t, arr(bounds[bound]), "k--", lw=0.9, label=name if r == 0 else None)
            plain_log(ax)
            shade_windows(ax, doc, t, names=r == 0)
            ax.set_ylabel(f"RMSE {'position' if q == 'pos' else 'velocity'} ({unit})")
            ax.grid(True, which="both", alpha=0.3)
            if r == 0:
                notes += coinciding(curves, ctx["w"])
                ax.set_title("filters far from the others (own scale)" if c == 1 else ctx["title"], fontsize=9,
                             pad=title_pad(doc))
        axs[-1, c].set_xlabel("time (s)")
    level = percent(doc.get("level", 0.95))
    a, b = doc.get("window", (1, doc["steps"]))
    averaged = (f"under each filter: its position and velocity RMSE over steps {a}–{b} ± its {level} interval"
                + (" (over the runs never lost)" if doc.get("track_loss") else ""))
    lost = ("curves over the runs not yet lost at each step (tracks drifting towards loss included); "
            "IRF: the information reduction factor") if doc.get("track_loss") else ""
    legend(fig, axs, "; ".join(filter(None, [coincide_note(notes), f"bands: {level} confidence of each per-step "
                                              "RMSE", averaged, lost, windows_note(doc, t)])))
    save(ctx["plt"], fig, ctx["folder"], "rmse", ctx["formats"])


def _rmse_axes(ctx):
    """Per-axis position RMSE with bands and the per-axis PCRLB (the papers' panels)."""
    doc, t, filters, st, dim, AX, pu = (ctx[k] for k in ("doc", "t", "filters", "st", "dim", "AX", "pu"))
    fig, axs = panel_grid(ctx["plt"], dim, 1)
    for a in range(dim):
        ax = axs[a, 0]
        for l, f in filters.items():
            s = f["series"]
            band(ax, t, arr(s[f"rmse_{AX[a]}"]), arr(s[f"rmse_{AX[a]}_hw"]) if f"rmse_{AX[a]}_hw" in s else None,
                  st[l], _label(l, f, [(f"rmse_{AX[b]}", pu, AX[b]) for b in range(dim)]) if a == 0 else None)
        if f"pcrlb_{AX[a]}" in doc["bounds"]:
            ax.plot(t, arr(doc["bounds"][f"pcrlb_{AX[a]}"]), "k--", lw=0.9, label="PCRLB" if a == 0 else None)
        plain_log(ax)
        shade_windows(ax, doc, t, names=a == 0)
        ax.set_ylabel(f"RMSE {AX[a]} ({pu})")
        ax.grid(True, which="both", alpha=0.3)
    axs[0, 0].set_title(ctx["title"], fontsize=9, pad=title_pad(doc))
    axs[-1, 0].set_xlabel("time (s)")
    a, b = doc.get("window", (1, doc["steps"]))
    legend(fig, axs, "; ".join(filter(None, [f"under each filter: its RMSE per axis over steps {a}–{b} ± its "
                                              f"{percent(doc.get('level', 0.95))} interval; bands: the same for each "
                                              "step", windows_note(doc, t)])))
    save(ctx["plt"], fig, ctx["folder"], "rmse_axes", ctx["formats"])


def _mean_error(ctx):
    """Mean error per axis with its band: a bias is real where the band leaves zero."""
    doc, t, filters, st, dim, AX, pu = (ctx[k] for k in ("doc", "t", "filters", "st", "dim", "AX", "pu"))
    main, out = split_outliers({l: float(np.nanmax(np.abs(np.concatenate(
        [arr(f["series"][f"mean_err_{AX[a]}"])[ctx["w"]] for a in range(dim)]))) or np.nan) for l, f in filters.items()})
    cols = [main] + ([out] if out else [])
    fig, axs = panel_grid(ctx["plt"], dim, len(cols))
    for c, group in enumerate(cols):
        for a in range(dim):
            ax = axs[a, c]
            for l in group:
                s = filters[l]["series"]
                band(ax, t, arr(s[f"mean_err_{AX[a]}"]),
                      arr(s[f"mean_err_{AX[a]}_hw"]) if f"mean_err_{AX[a]}_hw" in s else None, st[l],
                      l if a == 0 else None)
            ax.axhline(0, color="k", lw=0.6)
            shade_windows(ax, doc, t, names=a == 0)
            ax.set_ylabel(f"mean error {AX[a]} ({pu})")
            ax.grid(True, alpha=0.3)
        axs[0, c].set_title("filters far from the others (own scale)" if c == 1 else ctx["title"], fontsize=9,
                            pad=title_pad(doc))
        axs[-1, c].set_xlabel("time (s)")
    legend(fig, axs, "; ".join(filter(None, [f"bands: {percent(doc.get('level', 0.95))} confidence of the mean "
                                              "error over the runs", windows_note(doc, t)])))
    save(ctx["plt"], fig, ctx["folder"], "mean_error", ctx["formats"])


def _track_loss(ctx):
    """P(track lost by t) per filter with its Wilson band; the validated returns per scan."""
    doc, t, filters, st = ctx["doc"], ctx["t"], ctx["filters"], ctx["st"]
    loss = doc["track_loss"]
    scans = {l: f for l, f in filters.items() if np.isfinite(arr(f["series"].get("validated", [np.nan]))).any()}
    fig, axs = panel_grid(ctx["plt"], 2 if scans else 1, 1)
    ax = axs[0, 0]
    for l, f in filters.items():
        s = f["series"]
        p = arr(s["p_lost"])
        ax.plot(t, 100 * p, label=f"{l}\n  {percent(f['summary'].get('p_lost'))} lost by the end", **st[l])
        ax.fill_between(t, 100 * arr(s["p_lost_lo"]), 100 * arr(s["p_lost_hi"]), color=st[l]["color"], alpha=0.18, lw=0)
    ax.set_ylabel("tracks lost by t (%)")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    test = f"lost after {loss['steps']} steps beyond {loss['distance']:g} {ctx['pu']}"
    if loss.get("existence") is not None:
        test += f" (an IPDA's also with its existence below {loss['existence']:g})"
    ax.set_title(f"{ctx['title']}: {test}", fontsize=9)
    if scans:
        ax = axs[1, 0]
        for l, f in scans.items():
            ax.plot(t, arr(f["series"]["validated"]), label="_nolegend_", **st[l])
        ax.set_ylabel("returns validated per scan")
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    axs[-1, 0].set_xlabel("time (s)")
    clutter = doc.get("clutter")
    note = (f"; {clutter['false_alarms_per_scan']:.3g} false alarms per scan in the clutter region, "
            f"P_D = {clutter['p_detect']:g}") if clutter else ""
    legend(fig, axs, f"bands: {percent(doc.get('level', 0.95))} Wilson intervals of the fraction lost; validated "
                     f"returns over the runs on track{note}")
    save(ctx["plt"], fig, ctx["folder"], "track_loss", ctx["formats"])


def _pred_error(ctx):
    """One-step prediction RMS error per axis (paper 004's Fig. 3), named windows shaded."""
    doc, t, filters, st, dim, AX, pu = (ctx[k] for k in ("doc", "t", "filters", "st", "dim", "AX", "pu"))
    shown = {l: f for l, f in filters.items() if np.isfinite(arr(f["series"]["pred_rmse_" + AX[0]])).any()}
    if not shown:
        return
    fig, axs = panel_grid(ctx["plt"], dim, 1)
    keys = [(f"pred_err_rms_{AX[a]}", pu, AX[a]) for a in range(dim)]  # each axis's value, named

    for a in range(dim):
        ax = axs[a, 0]
        for l, f in shown.items():
            ax.plot(t, arr(f["series"][f"pred_rmse_{AX[a]}"]), label=_label(l, f, keys) if a == 0 else "_nolegend_",
                    **st[l])
        shade_windows(ax, doc, t, names=a == 0)
        plain_log(ax)
        ax.set_ylabel(f"one-step pred. RMS err {AX[a]} ({pu})")
        ax.grid(True, which="both", alpha=0.3)
    axs[0, 0].set_title(ctx["title"], fontsize=9, pad=title_pad(doc))  # above the windows' names
    axs[-1, 0].set_xlabel("time (s)")
    legend(fig, axs, windows_note(doc, t))
    save(ctx["plt"], fig, ctx["folder"], "pred_error", ctx["formats"])


def _consistency(ctx, key, ylabel, dof):
    """Average NEES or NIS with each filter's χ² band; the consistent filters set the scale of the
    first panel, a filter far from consistency (its average more than ``OUTLIER`` times its
    band's centre away) is drawn in a second panel on its own log scale."""
    doc, t, filters, st = ctx["doc"], ctx["t"], ctx["filters"], ctx["st"]
    w = ctx["w"]
    shown = {l: f for l, f in filters.items() if np.isfinite(arr(f["series"][key])).any()}
    if not shown:
        return
    centres = {}
    for l, f in shown.items():
        lo, hi = arr(f["series"][f"{key}_lo"])[w], arr(f["series"][f"{key}_hi"])[w]
        centres[l] = float(np.nanmean(0.5 * (lo + hi))) if dof is None else dof
    ratio = {l: (f["summary"].get(key) or np.nan) / centres[l] for l, f in shown.items()}
    main, out = split_outliers(ratio, centre=1.0)
    groups = [main] + ([out] if out else [])
    fig, axs = panel_grid(ctx["plt"], len(groups), 1, height=3.0)
    notes = []
    for g, group in enumerate(groups):
        ax = axs[g, 0]
        bands = {}
        curves = {}
        for l in group:
            s = shown[l]["series"]
            bands.setdefault((tuple(np.round(arr(s[f"{key}_lo"]), 6)), tuple(np.round(arr(s[f"{key}_hi"]), 6))), l)
            curves[l] = arr(s[key])
            ax.plot(t, curves[l], label=l + summary_value(shown[l], key), **st[l])
        for i, ((lo, hi), l) in enumerate(bands.items()):
            ax.fill_between(t, lo, hi, color="0.82", zorder=0, label=f"{percent(doc.get('level', 0.95))} χ² band"
                            if i == 0 else None)
        if dof is not None:
            ax.axhline(dof, color="k", lw=0.6)
        if g == 0:
            vals = np.concatenate([curves[l][w] for l in group] + [np.asarray(lo)[w] for lo, _ in bands]
                                  + [np.asarray(hi)[w] for _, hi in bands])
            vals = vals[np.isfinite(vals)]
            if vals.size:
                top = float(np.percentile(vals, 99.5))
                ax.set_ylim(0, top * 1.15)
                for l in group:
                    where = clipped_spans(t, curves[l], top * 1.15)
                    if where:
                        notes.append(f"{l} above the axis at {where}")
            notes += coinciding(curves, w)
            ax.set_title(ctx["title"], fontsize=9, pad=title_pad(doc))
        else:
            ax.set_yscale("log")
            ax.set_title("filters far from consistency (own log scale)", fontsize=9)
        shade_windows(ax, doc, t, names=g == 0)
        ax.set_ylabel(ylabel if g == 0 else ylabel.split(" (")[0])
        ax.grid(True, which="both", alpha=0.3)
    axs[-1, 0].set_xlabel("time (s)")
    legend(fig, axs, "; ".join(filter(None, [n if isinstance(n, str) else coincide_note([n]) for n in notes]
                                      + [windows_note(doc, t)])))
    save(ctx["plt"], fig, ctx["folder"], key, ctx["formats"])


def clipped_spans(t, v, limit, most=3) -> str:
    """Where ``v`` passes ``limit``, as time spans ("t = 0.5–3 s, 60–71 s"); "" when nowhere."""
    over = np.isfinite(v) & (v > limit)
    if not over.any():
        return ""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(int), [0]])))
    spans = [(t[a], t[b - 1]) for a, b in zip(edges[::2], edges[1::2])]
    shown = [f"{a:g} s" if a == b else f"{a:g}–{b:g} s" for a, b in spans[:most]]
    return "t = " + ", ".join(shown) + (f" and {len(spans) - most} more" if len(spans) > most else "")


def cdf_panel(ax, shown, st, key, pct_key=None):
    """P(a run's value ≤ x) of each filter's ``cdf[key]``; its percentiles in the legend when
    ``pct_key`` (a summary key with ``{p}``) is given."""
    every = max(len(next(iter(shown.values()))["cdf"][key]) // 8, 1)
    for i, (l, f) in enumerate(shown.items()):
        x, p = arr(f["cdf"][key]), arr(f["cdf"]["probability"])
        label = l
        if pct_key is not None:
            s = f["summary"]
            label += " (" + ", ".join(f"p{q} {s[pct_key.format(p=q)]:.4g}" for q in (50, 90, 99)) + ")"
        ax.plot(x, p, drawstyle="steps-post", label=label, **(st[l] | {"markevery": (int(i * every / len(shown)), every)}))
    for q in (0.5, 0.9, 0.99):
        ax.axhline(q, color="0.5", lw=0.6, ls=":")
    lo = min(float(np.nanmin(arr(f["cdf"][key]))) for f in shown.values())
    hi = max(float(np.nanmax(arr(f["cdf"][key]))) for f in shown.values())
    if lo > 0 and hi > 5 * lo:
        plain_log(ax, "x")
    ax.set_ylim(0, 1.005)
    ax.grid(True, which="both", alpha=0.3)
    return coinciding({l: arr(f["cdf"][key]) for l, f in shown.items()}, slice(None))


def _error_cdf(ctx):
    """P(a run's RMS position error ≤ x): what a fire-control engineer quotes."""
    filters, st, pu = ctx["filters"], ctx["st"], ctx["pu"]
    shown = {l: f for l, f in filters.items() if f.get("cdf")}
    if not shown:
        return
    fig, axs = panel_grid(ctx["plt"], 1, 1, height=3.6)
    ax = axs[0, 0]
    groups = cdf_panel(ax, shown, st, "err_pos", "err_pos_p{p}")
    ax.set_xlabel(f"run's RMS position error over the report window ({pu})")
    ax.set_ylabel("fraction of runs with error ≤ x")
    ax.set_title(ctx["title"], fontsize=9)
    legend(fig, axs, coincide_note(groups))
    save(ctx["plt"], fig, ctx["folder"], "error_cdf", ctx["formats"])


def plot_track(doc, example, t, folder: Path, formats=("png",)):
    """The true path seen from above, coloured by the position RMSE over the runs at each step
    (where on the path a filter's error grows): one panel per filter, filters whose curves
    coincide over the report window in one panel, one colour scale (logarithmic when the
    errors span more than a decade) and one colour bar. Steps outside the report window are
    drawn grey; the start, the direction, times along the path and the sensor (a polar or
    angle sensor, at the origin) are marked."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import BoundaryNorm
    from matplotlib.patheffects import withStroke

    truth = np.asarray(example["truth"], float)
    xy = truth[:, [0, 2]] / 1000.0
    n = len(xy)
    t = t[:n]  # run 0's steps, stored as the series are
    w = _window_slice(doc, t)
    inside = np.zeros(n, bool)
    inside[w] = True
    filters = doc["filters"]
    vals = {label: arr(f["series"]["rmse_pos"])[:n] for label, f in filters.items()}
    merged = {g[0]: g for g in coinciding(vals, w)}
    hidden = {l for g in merged.values() for l in g[1:]}
    panels = [merged.get(l, [l]) for l in vals if l not in hidden]

    shown = np.concatenate([v[w][np.isfinite(v[w]) & (v[w] > 0)] for v in vals.values()] or [np.zeros(0)])
    lo, hi = (np.percentile(shown, 1), np.percentile(shown, 99)) if shown.size else (1.0, 10.0)
    hi = max(hi, lo * 1.01, 1e-9)
    log = lo > 0 and hi / lo > 10.0
    levels = colour_levels(lo, hi, log)
    cmap = plt.get_cmap("viridis").with_extremes(bad="none")
    norm = BoundaryNorm(levels, cmap.N, extend="both")

    sees_bearing = _has_bearing(doc)
    span = max(np.ptp(xy[:, 0]), np.ptp(xy[:, 1]), 1e-3)
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    sensor_in_view = sees_bearing and np.hypot(*centre) < 1.5 * span
    ticks = _time_ticks(t[-1])
    pad = 0.08 * span
    box = np.array([xy.min(axis=0) - pad, xy.max(axis=0) + pad])
    if sensor_in_view:
        box = np.array([np.minimum(box[0], -pad), np.maximum(box[1], pad)])
    k = len(panels)
    cols = 2 if k == 4 else min(k, 3)
    rows = -(-k // cols)
    aspect = float(np.clip(np.ptp(box[:, 1]) / np.ptp(box[:, 0]), 0.35, 1.1))  # a panel's height ÷ width
    fig, axes = plt.subplots(rows, cols, figsize=(4.3 * cols + 1.2, (3.9 * aspect + 0.7) * rows + 0.6), squeeze=False,
                             sharex=True, sharey=True, layout="constrained")
    seg = np.stack([xy[:-1], xy[1:]], axis=1)
    for ax, group in zip(axes.flat, panels):
        v = vals[group[0]]
        ax.plot(*xy[~inside].T, ".", color="0.65", ms=1.5, zorder=1)
        lc = LineCollection(seg[inside[1:]], cmap=cmap, norm=norm, linewidths=4.0, capstyle="butt", zorder=2)
        lc.set_array(np.where(np.isfinite(v[1:][inside[1:]]), v[1:][inside[1:]], np.nan))
        ax.add_collection(lc)
        ax.plot(*xy[0], "o", mfc="white", mec="k", ms=6, zorder=3)
        ax.annotate("", xy=xy[-1], xytext=xy[max(n - 2, 0)], zorder=3,
                    arrowprops=dict(arrowstyle="-|>", color="k", lw=1.0, mutation_scale=12))
        for tt in ticks:
            i = int(np.argmin(np.abs(t - tt)))
            ax.plot(*xy[i], "k.", ms=4, zorder=3)
            ax.annotate(f"{tt:g} s", xy[i], textcoords="offset points", xytext=(4, 5), fontsize=6.5, color="0.1",
                        path_effects=[withStroke(linewidth=2.0, foreground="white")], zorder=4)
        if sensor_in_view:
            ax.plot([0], [0], "k^", ms=7)
            ax.annotate("sensor", (0, 0), textcoords="offset points", xytext=(6, -3), fontsize=7)
        names = ", ".join(group)
        value = filters[group[0]]["summary"].get("rmse_pos")
        shown_value = "—" if value is None else f"{short_value(value)} m"
        ax.set_title(f"{names}{' (coincide)' if len(group) > 1 else ''}: {shown_value}", fontsize=8, wrap=True)
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    axes.flat[0].set_xlim(box[:, 0])
    axes.flat[0].set_ylim(box[:, 1])
    for ax in axes[-1]:
        ax.set_xlabel("east (km)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("north (km)", fontsize=8)
    for ax in list(axes.flat)[k:]:
        ax.axis("off")
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.9 if rows > 1 else 0.75,
                       label="position RMSE (m)")
    bar.set_ticks(levels, labels=[level_label(v) for v in levels])
    bar.ax.tick_params(labelsize=7)
    a, b = doc.get("window", (1, doc["steps"]))
    note = [f"○ start, arrow: direction; grey: outside the report window (steps {a}–{b})"
            if (a > 1 or b < doc["steps"]) else "○ start, arrow: direction"]
    if sees_bearing and not sensor_in_view:
        note.append(f"the sensor (origin) is {np.hypot(*centre):.0f} km from the path's centre, off the panels")
    fig.suptitle(f"{doc['name']} — {doc['runs']} runs: position RMSE along the true path, seen from above",
                 fontsize=10)
    fig.supxlabel("; ".join(note), fontsize=7, color="0.3")
    save(plt, fig, folder, "track", formats)


def colour_levels(lo: float, hi: float, log: bool, most: int = 24) -> list[float]:
    """A colour scale's level boundaries at round numbers covering [lo, hi]: about ten evenly
    spaced, or when ``log`` the finest of the round series (10, 6, 4 or 3 per decade) that needs
    at most ``most`` levels (a scale of steps reads as values, and its few colours store exactly
    in a PNG's palette)."""
    import math

    from matplotlib.ticker import MaxNLocator

    if not log:
        return [float(f"{v:.12g}") for v in MaxNLocator(nbins=10).tick_values(lo, hi)]
    for subs in ((1, 1.25, 1.6, 2, 2.5, 3.2, 4, 5, 6.3, 8), (1, 1.5, 2, 3, 5, 7), (1, 2, 3, 5), (1, 2, 5), (1,)):
        ticks = [float(f"{m * 10.0 ** n:.12g}") for n in range(math.floor(math.log10(lo)),
                                                              math.ceil(math.log10(hi)) + 1) for m in subs]
        first = max(v for v in ticks if v <= lo)
        last = min(v for v in ticks if v >= hi)
        levels = [v for v in ticks if first <= v <= last]
        if len(levels) <= most:
            return levels
    return levels


def short_value(v) -> str:
    """A value written short: three significant digits, whole numbers from 1000 on (1270, not 1.27e+03)."""
    return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"


def level_label(v: float) -> str:
    """A value on a scale or an axis: a plain number to four significant digits (0.2, 30, 5000), a
    power of ten beyond (2×10⁵, 2.83×10⁻⁴)."""
    if v == 0 or 1e-3 <= abs(v) < 1e4:
        return f"{v:.4g}"
    m, n = f"{v:.2e}".split("e")
    m = m.rstrip("0").rstrip(".")
    return f"$10^{{{int(n)}}}$" if m == "1" else f"${m}\\times10^{{{int(n)}}}$"


def _has_bearing(doc) -> bool:
    """Whether a sensor measures from the origin (range or angles), so that its place means something."""
    e = doc.get("experiment", {})
    sensors = e.get("sensors") or ([e["sensor"]] if isinstance(e.get("sensor"), dict) else e.get("sensor") or [])
    return any(s.get("kind") not in ("cartesian",) for s in sensors if isinstance(s, dict))


def _time_ticks(duration: float) -> list[float]:
    """Four or five round times along a path of ``duration`` seconds."""
    step = 10 ** np.floor(np.log10(max(duration, 1e-9) / 4))
    for m in (1, 2, 2.5, 5, 10):
        if duration / (m * step) <= 5:
            step *= m
            break
    return [float(x) for x in np.arange(step, duration, step)]


def _window_spans(doc):
    """Named windows given as [t0, t1] in the experiment file (not "rest")."""
    table = doc.get("experiment", {}).get("report", {}).get("windows", {})
    return {w: v for w, v in table.items() if isinstance(v, list) and w in doc.get("windows", [])}


def manoeuvre_spans(doc) -> dict:
    """A manoeuvre scenario's turns and accelerations as named time spans ("4 g turn": [t0, t1])."""
    sc = doc.get("experiment", {}).get("scenario", {})
    if sc.get("kind") != "manoeuvre":
        return {}
    out, t0 = {}, 0.0
    for seg in sc.get("segments", []):
        t1 = t0 + float(seg.get("duration", 0.0))
        what = [f"{seg['turn_g']:g} g turn"] if seg.get("turn_g") else []
        what += [f"{seg['accel']:+g} m/s²"] if seg.get("accel") else []
        if what:
            out[", ".join(what)] = [t0, t1]
        t0 = t1
    return out


def shade_windows(ax, doc, t, names=True):
    """The report window (steps outside it hatched) and the named time windows and manoeuvres
    (shaded, named along the top when ``names``) on a time axis."""
    a, b = doc.get("window", (1, doc["steps"]))
    dt = doc["dt"]
    for lo, hi in ((t[0] - dt, (a - 1) * dt), (b * dt, t[-1] + dt)):
        if hi > lo and lo < t[-1] and hi > t[0]:
            ax.axvspan(max(lo, t[0]), min(hi, t[-1]), facecolor="none", edgecolor="0.8", hatch="//", lw=0,
                       zorder=-1)
    for i, (w, (t0, t1)) in enumerate({**_window_spans(doc), **manoeuvre_spans(doc)}.items()):
        # under everything drawn (bands included); neighbouring windows in two tints
        ax.axvspan(t0, t1, color=("#e6e9f2", "#f2ebe1")[i % 2], zorder=-2, lw=0)
        if names:
            ax.text(0.5 * (t0 + t1), 1.0, w, transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=7)


def title_pad(doc) -> float:
    """A panel title's padding: above the windows' names when ``shade_windows`` writes them."""
    return 14.0 if (_window_spans(doc) or manoeuvre_spans(doc)) else 6.0


def windows_note(doc, t) -> str:
    """What the hatching and shading of ``shade_windows`` are, for a legend ("" when none is drawn)."""
    a, b = doc.get("window", (1, doc["steps"]))
    parts = [f"hatched: outside the report window (steps {a}–{b})"] if (a > 1 or b < doc["steps"]) else []
    if _window_spans(doc) or manoeuvre_spans(doc):
        parts.append("shaded: " + ", ".join([*_window_spans(doc), *manoeuvre_spans(doc)]))
    return "; ".join(parts)


def plot_example(doc, example, t, dim, folder: Path, st=None, formats=("png",), kinds=("run0", "run0_error")):
    """Run 0: true and estimated position and velocity (``run0.png``), and the errors with each
    filter's own ±3σ envelope from its covariance (``run0_error.png``; paper 002 Figs. 4–7)."""
    import matplotlib.pyplot as plt

    truth = np.asarray(example["truth"], float)
    est = {k: np.asarray(v, float) for k, v in example["estimates"].items()}
    sd = {k: arr(v) for k, v in (example.get("sd") or {}).items()}
    z = np.asarray(example["measurements"], float) if "measurements" in example else None
    pu, vu = doc.get("units", ("m", "m/s"))
    AX = doc.get("axes", AXES)
    st = st or styles(list(est), len(t))
    names = [("position", pu, 0), ("velocity", vu, 1)]
    for kind in [k for k, stem in (("state", "run0"), ("error", "run0_error")) if stem in kinds]:
        fig, axes = plt.subplots(2, dim, figsize=(5 * dim + 2.2, 6), sharex=True, squeeze=False, layout="constrained")
        for a in range(dim):
            for row, (q, unit, j) in enumerate(names):
                ax = axes[row, a]
                col = 2 * a + j
                if kind == "state":
                    if z is not None and j == 0 and z.ndim == 3:  # scans: every return, false alarms too
                        ax.plot(np.repeat(t, z.shape[1]), z[:, :, a].ravel(), ".", color="0.7", ms=2,
                                label="returns (scan)")
                    elif z is not None and j == 0:
                        ax.plot(t, z[:, a], ".", color="0.7", ms=2, label="measured")
                    ax.plot(t, truth[:, col], "k-", lw=1.5, label="true")
                    for label, x in est.items():
                        ax.plot(t, x[:, col], label=label, **(st[label] | {"lw": 1.0}))
                else:
                    for label, x in est.items():
                        e = x[:, col] - truth[:, col]
                        ax.plot(t, e, label=label, **(st[label] | {"lw": 1.0}))
                        if label in sd:  # thin lines: several filters' envelopes stay readable over each other
                            s3 = 3.0 * sd[label][:, col]
                            for sign in (-1, 1):
                                ax.plot(t, sign * s3, color=st[label]["color"], ls=st[label]["ls"], lw=0.7,
                                        alpha=0.8)
                    ax.axhline(0, color="k", lw=0.6)
                    _clip_to_main(ax, est, truth, col, sd)
                ax.set_ylabel(f"{q} {AX[a]} ({unit})" if kind == "state" else f"{q} error {AX[a]} ({unit})")
                ax.grid(True, alpha=0.3)
        axes[0, 0].set_title(f"{doc['name']} — run 0" + (": errors, and ±3σ of each filter's own covariance (thin lines)"
                                                          if kind == "error" and sd else ""), fontsize=9)
        for ax in axes[-1]:
            ax.set_xlabel("time (s)")
        legend(fig, axes)
        save(plt, fig, folder, "run0" if kind == "state" else "run0_error", formats)


def _clip_to_main(ax, est, truth, col, sd):
    """Limit an error panel to the filters near the others: one far off would flatten the rest
    (its curve runs off the panel, its legend entry stays)."""
    size = {l: float(np.nanpercentile(np.abs(x[:, col] - truth[:, col]), 95)) for l, x in est.items()}
    main, out = split_outliers(size)
    if not out:
        return
    lim = max([size[l] for l in main] + [3.0 * float(np.nanpercentile(sd[l][:, col], 95)) for l in main if l in sd])
    if np.isfinite(lim) and lim > 0:
        ax.set_ylim(-1.6 * lim, 1.6 * lim)
        ax.text(0.99, 0.02, f"off scale: {', '.join(out)}", transform=ax.transAxes, ha="right", va="bottom",
                fontsize=6.5, color="0.3")


# the closed-loop worlds









