"""Running the studies an experiment file asks ``tracklab reproduce`` to rebuild: tuning and
sweeps (``tracklab.config.studies`` reads the ``[[study]]`` tables)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from tracklab.config import load_experiment
from tracklab.config.paths import parse_grid
from tracklab.config.writeback import tuned_text
from tracklab.errors import ConfigError
from tracklab.filters.association import HARD_RULES
from tracklab.memory import check
from tracklab.output import (
    atomic_folder,
    check_results_folder,
    check_tuned_file,
    write_text_atomically,
)
from tracklab.report.sweep import no_figures, runs_text, write_sweep
from tracklab.report.tuning import tune_report
from tracklab.processes import writes
from tracklab.studies.sweep import sweep
from tracklab.studies.tune import (
    forward_mode,
    memory_bytes,
    selection,
    tune,
    tuned_numbers,
    unwritable,
)


def check_tune(exp, names, labels, out_toml, runs_per_step=None, max_memory=None, field="--params", folder=None,
               folder_field="--results"):
    """Everything a tuning needs, checked before it compiles (ConfigError in one line): a selected
    filter with the parameters, tuned values that can be written back, the output file and
    results folder, memory."""
    chosen = selection(exp, names, labels)
    if not chosen:
        bare = [label for label, declared in exp.declared().items() if not declared]
        hint = (f" ({', '.join(bare)} declare no numbers: a filter of one's own is tuned from Python, tracklab.tune, "
                "or its factory declares them, tracklab.declare)" if bare else "")
        nn = {getattr(f, "label", None) for f in getattr(exp, "filters", ()) if getattr(f, "kind", None) in HARD_RULES}
        hard = [label for label, declared in exp.declared().items()
                if label in nn and (not labels or label in labels) and any(n in declared for n in names)]
        if hard:  # declared but not tunable: the nearest or strongest neighbour's hard choice of a return
            hint += (f" ({', '.join(hard)}: not tunable, its choice of a return has no gradient; tune its PDAF, "
                     "kind = \"pdaf\" with the same base)")
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
        say(f"{lane}: held-out {res.loss} ({res.eval_runs} runs) {number(before)} -> "
            f"{number(res.eval_tuned.get(lane, math.nan))}")
    n = len(res.history)
    say(f"tuned in {res.wall_s:.1f} s ({n} step{'' if n == 1 else 's'} of {res.runs_per_step} runs)")
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

def run_study(exp, study, results_dir, quick=False, log=print, figures=True):
    """Rebuild one study under ``results_dir``; ``quick``: a few steps and runs, as a smoke check;
    ``figures``: with its PNG figures."""
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
    if figures and no_figures(doc):
        log(f"        {no_figures(doc)}")
    log(f"        sweep: {math.prod(len(a.values) for a in axes)} points x {runs_text(doc['runs'])} runs, {doc['wall_s']:.1f} s")
    return [base]
