"""A tuning's folder: tune.json, table.md, tune.log and loss.png."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tracklab.report.document import write_json
from tracklab.report.figures import formats_of, pyplot, save
from tracklab.report.tables import md_cell


def tune_report(exp, res, folder: Path, *, steps, lr, tuned_file, log_lines, figures=True):
    """A tuning's results folder: tune.json (settings, each filter's parameters and held-out loss
    before and after, every step's loss per filter), table.md, tune.log and, with ``figures``,
    loss.png (each filter's loss per step in a panel of its own, the held-out values marked)."""
    labels = list(res.params)
    lanes = list(res.eval_initial)  # whose losses: the filters (a closed loop: its trackers' or cases')
    doc = {
        "name": exp.name, "loss": res.loss, "steps": steps, "lr": lr, "runs_per_step": res.runs_per_step,
        "eval_runs": res.eval_runs, "wall_s": res.wall_s, "stopped": res.stopped or None, "tuned_file": tuned_file,
        "filters": {l: {"initial": res.initial[l], "tuned": res.params[l]} for l in labels},
        "heldout": {l: {"before": res.eval_initial.get(l), "after": res.eval_tuned.get(l)} for l in lanes},
        "history": {"step": [k for k, _, _ in res.history], "grad_norm": [g for _, _, g in res.history],
                    "loss": {l: [per.get(l) for _, per, _ in res.history] for l in lanes}},
    }
    write_json(folder / "tune.json", doc)

    def number(v):
        return f"{v:.6g}" if v is not None and math.isfinite(v) else "—"

    def shown(v):
        a = np.asarray(v, float)
        return number(float(a)) if a.ndim == 0 else "[" + ", ".join(number(float(x)) for x in a.ravel()) + "]"

    rows = ["| filter | parameter | start | tuned |", "|---|---|---|---|"]
    for l in labels:
        for n, v in res.params[l].items():
            rows.append("| " + " | ".join([md_cell(l), n, shown(res.initial[l][n]), shown(v)]) + " |")
    rows += ["", f"| loss of | held-out {res.loss} before | after | change |", "|---|---|---|---|"]
    for l in lanes:
        b, a = res.eval_initial.get(l, math.nan), res.eval_tuned.get(l, math.nan)
        change = f"{100 * (a - b) / b:+.1f} %" if math.isfinite(a) and math.isfinite(b) and b else "—"
        rows.append("| " + " | ".join([md_cell(l), number(b), number(a), change]) + " |")
    caption = (f"\nLoss `{res.loss}` per filter (each filter tuned on its own loss), {len(res.history)} Adam steps of "
               f"{res.runs_per_step} fresh runs, lr {lr:g}; held-out: {res.eval_runs} runs never used in the steps; "
               f"{res.wall_s:.1f} s." + (f" {res.stopped}." if res.stopped else "") + "\n")
    (folder / "table.md").write_text("\n".join(rows) + "\n" + caption)
    (folder / "tune.log").write_text("\n".join(log_lines) + "\n")
    if not res.history or not formats_of(figures):
        return
    plt = pyplot()
    fig, axs = plt.subplots(len(lanes), 1, figsize=(7.5, 2.4 * len(lanes) + 0.6), squeeze=False, sharex=True,
                            layout="constrained")
    steps_done = doc["history"]["step"]
    for ax, l in zip(axs[:, 0], lanes):
        v = np.array([np.nan if x is None else x for x in doc["history"]["loss"][l]], float)
        if not np.isfinite(v).any():
            continue
        ax.plot(steps_done, v, lw=1.0, color="C0", label="each step's fresh runs")
        for x, y, m, what in ((0, res.eval_initial.get(l), "o", "held-out, start"),
                              (steps_done[-1], res.eval_tuned.get(l), "s", "held-out, tuned")):
            if y is not None and math.isfinite(y):
                ax.plot([x], [y], m, color="C3", ms=6, label=what)
        if np.all(v[np.isfinite(v)] > 0) and np.nanmax(v) > 5 * np.nanmin(v):
            ax.set_yscale("log")
        ax.set_ylabel(f"{res.loss}", fontsize=8)
        ax.set_title(l, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axs[0, 0].legend(fontsize=7, loc="upper right")
    axs[-1, 0].set_xlabel("Adam step")
    fig.suptitle(f"{exp.name}: tuning loss per filter", fontsize=10)
    save(plt, fig, folder, "loss", formats_of(figures))
