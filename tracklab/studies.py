"""Running the studies an experiment file asks ``tracklab reproduce`` to rebuild: tuning and
sweeps (``tracklab.config.studies`` reads the ``[[study]]`` tables)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tracklab.errors import ConfigError


def check_tune(exp, names, labels, out_toml, runs_per_step=None, max_memory=None, field="--params", folder=None,
               folder_field="--results"):
    """Everything a tuning needs, checked before it compiles (ConfigError in one line): a selected
    filter with the parameters, tuned values that can be written back, the output file and
    results folder, memory."""
    from tracklab.memory import check
    from tracklab.output import check_results_folder, check_tuned_file
    from tracklab.tune import forward_mode, memory_bytes, selection, tuned_numbers, unwritable

    chosen = selection(exp, names, labels)
    if not chosen:
        from tracklab.worlds.tracking import FilterSpec

        own = [fc.label for fc in getattr(exp, "filters", []) if isinstance(fc, FilterSpec) and not fc.declared]
        hint = (f" (filters of one's own whose factory declares no numbers, {', '.join(own)}, are tuned from Python: "
                "tracklab.tune, or declare them: tracklab.declare)" if own else "")
        raise ConfigError(exp.path, field, ",".join(names), f"no selected filter has any of these parameters{hint}")
    why = unwritable(exp, chosen)
    if why:
        raise ConfigError(exp.path, field, ",".join(names), why)
    check_tuned_file(out_toml, exp.path)
    if folder is not None:
        check_results_folder(folder, exp.path, folder_field)
    tuned = tuned_numbers(exp, chosen)
    what = ("forward mode: a batch's random draws for every step, its states and their tangents" if forward_mode(tuned)
            else "reverse mode keeps every run's filter states for every step")
    check(exp.path, memory_bytes(exp, runs_per_step or min(exp.runs, 256), tuned=tuned), max_memory,
          f"one tuning step ({what})", "fewer --runs-per-step, or fewer experiment.steps")


def run_tune(exp, names, *, steps, lr, loss, runs_per_step, labels, out_toml: Path, folder: Path, log=print, every=10,
             eval_runs=None, figures=True):
    """Tune, log progress lines, write the results folder (``tune_report``; its loss.png only
    with ``figures``) and the tuned experiment file, each atomically (process 0 alone, in a run of
    several); return the TuneResult."""
    import sys

    from tracklab.runtime import writes

    from tracklab.config import load_experiment
    from tracklab.config.writeback import tuned_text
    from tracklab.output import atomic_folder, check_tuned_file, write_text_atomically
    from tracklab.tune import tune

    written_to = out_toml  # as given (the log names it so, not as this machine resolves it)
    out_toml = check_tuned_file(out_toml, exp.path)
    lines = []

    def say(line):
        lines.append(line)
        log(line)

    def progress(k, per, gnorm):
        say(f"step {k:5d}  " + "  ".join(f"{l}: {v:.6g}" for l, v in per.items()) + f"  |grad| {gnorm:.3g}")

    def number(v):
        return f"{v:.6g}" if math.isfinite(v) else "— (no finite value)"

    def shown(v):  # a parameter to 6 significant digits (the tuned file holds every digit)
        a = np.asarray(v, float)
        return number(float(a)) if a.ndim == 0 else "[" + ", ".join(number(float(x)) for x in a.ravel()) + "]"

    res = tune(exp, names, steps=steps, lr=lr, loss=loss, runs_per_step=runs_per_step, labels=labels, every=every,
               progress=progress, eval_runs=eval_runs)
    if res.stopped:
        print(f"warning: {res.stopped}", file=sys.stderr)
        say(res.stopped)
    for label, p in res.params.items():
        say(f"{label}: " + ", ".join(f"{k} {shown(res.initial[label][k])} -> {shown(v)}" for k, v in p.items()))
    for lane, before in res.eval_initial.items():  # a filter's (a closed loop's case's) own loss
        say(f"{lane}: held-out {loss} ({res.eval_runs} runs) {number(before)} -> "
            f"{number(res.eval_tuned.get(lane, math.nan))}")
    say(f"tuned in {res.wall_s:.1f} s ({len(res.history)} steps of {res.runs_per_step} runs)")
    if not writes():  # process 0 of a run of several processes writes
        return res
    text = tuned_text(exp, res.params, out_toml)

    def verify(tmp):  # the file must be one `tracklab run` accepts, before it replaces anything
        try:
            load_experiment(tmp)
        except ConfigError as e:
            raise ConfigError(exp.path, "--out", str(out_toml), f"not written: the tuned values are refused ({e.allowed})") from None

    write_text_atomically(out_toml, text, verify)
    say(f"tuned experiment written to {written_to}")
    with atomic_folder(folder, exp.path, "--results") as tmp:
        tune_report(exp, res, tmp, steps=steps, lr=lr, tuned_file=str(written_to), log_lines=lines, figures=figures)
    log(f"tuning report written to {folder}/")
    return res


def tune_report(exp, res, folder: Path, *, steps, lr, tuned_file, log_lines, figures=True):
    """A tuning's results folder: tune.json (settings, each filter's parameters and held-out loss
    before and after, every step's loss per filter), table.md, tune.log and, with ``figures``,
    loss.png (each filter's loss per step in a panel of its own, the held-out values marked)."""
    from tracklab.figures import pyplot
    from tracklab.report import md_cell, write_json

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
    if not res.history or not figures:
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
    fig.savefig(folder / "loss.png", dpi=110)
    plt.close(fig)


def run_study(exp, study, results_dir, quick=False, log=print, figures=True):
    """Rebuild one study under ``results_dir``; ``quick``: a few steps and runs, as a smoke check;
    ``figures``: with its PNG figures."""
    from tracklab.config import load_experiment
    from tracklab.config.paths import parse_grid
    from tracklab.sweep import runs_text, sweep, write_sweep

    base = Path(results_dir) / study.out
    if study.kind == "tune":
        tuned = base.with_name(base.name + "_tuned.toml")
        run_tune(exp, list(study.params), steps=2 if quick else study.steps, lr=study.lr, loss=study.loss,
                 runs_per_step=min(study.runs_per_step, 4) if quick else study.runs_per_step,
                 labels=list(study.filters) if study.filters else None, out_toml=tuned,
                 folder=base.with_name(base.name + "_tune"), log=lambda line: log("        " + line),
                 eval_runs=8 if quick else None, figures=figures)
        tuned_exp = load_experiment(tuned)
        tuned_exp.run(runs=min(tuned_exp.runs, 20) if quick else None, out=base.with_name(base.name + "_tuned"),
                      figures=figures)
        return [tuned]
    axes = [parse_grid(g) for g in study.grid]
    if quick:
        axes = [type(a)(a.name, a.values[[0, -1]] if len(a.values) > 1 else a.values) for a in axes]
    doc = sweep(exp, axes, runs=4 if quick else study.runs)
    write_sweep(exp, doc, base, figures=figures)
    log(f"        sweep: {math.prod(len(a.values) for a in axes)} points x {runs_text(doc['runs'])} runs, {doc['wall_s']:.1f} s")
    return [base]
