"""Running the studies an experiment file asks ``tracklab reproduce`` to rebuild: tuning and
sweeps (``tracklab.config.studies`` reads the ``[[study]]`` tables)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tracklab.errors import ConfigError


def check_tune(exp, names, labels, out_toml, runs_per_step=None, max_memory=None, field="--params"):
    """Everything a tuning needs, checked before it compiles (ConfigError in one line): a selected
    filter with the parameters, tuned values that can be written back, the output file, memory."""
    from tracklab.memory import check
    from tracklab.output import check_tuned_file
    from tracklab.tune import memory_bytes, selection, unwritable

    chosen = selection(exp, names, labels)
    if not chosen:
        from tracklab.worlds.tracking import FilterSpec

        own = [fc.label for fc in getattr(exp, "filters", []) if isinstance(fc, FilterSpec)]
        hint = f" (filters of one's own, {', '.join(own)}, are tuned from Python: tracklab.tune)" if own else ""
        raise ConfigError(exp.path, field, ",".join(names), f"no selected filter has any of these parameters{hint}")
    why = unwritable(exp, chosen)
    if why:
        raise ConfigError(exp.path, field, ",".join(names), why)
    check_tuned_file(out_toml, exp.path)
    check(exp.path, memory_bytes(exp, runs_per_step or min(exp.runs, 256)), max_memory,
          "one tuning step (reverse mode keeps every run's filter states for every step)",
          "fewer --runs-per-step, or fewer experiment.steps")


def run_tune(exp, names, *, steps, lr, loss, runs_per_step, labels, out_toml: Path, log=print, every=10,
             eval_runs=None):
    """Tune, log progress lines, write the tuned experiment file atomically; return the TuneResult."""
    import sys

    from tracklab.config import load_experiment
    from tracklab.config.writing import dump_toml
    from tracklab.output import TUNED_HEADER, check_tuned_file, write_text_atomically
    from tracklab.tune import tune, tuned_document

    written_to = out_toml  # as given (the log names it so, not as this machine resolves it)
    out_toml = check_tuned_file(out_toml, exp.path)

    def progress(k, value, gnorm):
        log(f"step {k:5d}  loss {value:.6g}  |grad| {gnorm:.3g}")

    def number(v):
        return f"{v:.6g}" if math.isfinite(v) else "— (no finite value)"

    def shown(v):  # a parameter to 6 significant digits (the tuned file holds every digit)
        a = np.asarray(v, float)
        return number(float(a)) if a.ndim == 0 else "[" + ", ".join(number(float(x)) for x in a.ravel()) + "]"

    res = tune(exp, names, steps=steps, lr=lr, loss=loss, runs_per_step=runs_per_step, labels=labels, every=every,
               progress=progress, eval_runs=eval_runs)
    if res.stopped:
        print(f"warning: {res.stopped}", file=sys.stderr)
        log(res.stopped)
    for label, p in res.params.items():
        log(f"{label}: " + ", ".join(f"{k} {shown(res.initial[label][k])} -> {shown(v)}" for k, v in p.items()))
    log(f"held-out {loss}: {number(res.eval_initial)} -> {number(res.eval_tuned)}")
    text = TUNED_HEADER + "\n" + dump_toml(tuned_document(exp, res, out_toml))

    def verify(tmp):  # the file must be one `tracklab run` accepts, before it replaces anything
        try:
            load_experiment(tmp)
        except ConfigError as e:
            raise ConfigError(exp.path, "--out", str(out_toml), f"not written: the tuned values are refused ({e.allowed})") from None

    write_text_atomically(out_toml, text, verify)
    log(f"tuned experiment written to {written_to}")
    return res


def run_study(exp, study, results_dir, quick=False, log=print):
    """Rebuild one study under ``results_dir``; ``quick``: a few steps and runs, as a smoke check."""
    from tracklab.config import load_experiment
    from tracklab.output import write_text_atomically
    from tracklab.config.paths import parse_grid
    from tracklab.sweep import sweep, write_sweep

    base = Path(results_dir) / study.out
    if study.kind == "tune":
        tuned = base.with_name(base.name + "_tuned.toml")
        lines = []

        def both(line):
            lines.append(line)
            log("        " + line)

        run_tune(exp, list(study.params), steps=2 if quick else study.steps, lr=study.lr, loss=study.loss,
                 runs_per_step=min(study.runs_per_step, 4) if quick else study.runs_per_step,
                 labels=list(study.filters) if study.filters else None, out_toml=tuned, log=both,
                 eval_runs=8 if quick else None)
        write_text_atomically(base.with_name(base.name + "_tune.log"), "\n".join(lines) + "\n")
        tuned_exp = load_experiment(tuned)
        tuned_exp.run(runs=min(tuned_exp.runs, 20) if quick else None, out=base.with_name(base.name + "_tuned"))
        return [tuned]
    axes = [parse_grid(g) for g in study.grid]
    if quick:
        axes = [type(a)(a.name, a.values[[0, -1]] if len(a.values) > 1 else a.values) for a in axes]
    doc = sweep(exp, axes, runs=4 if quick else study.runs)
    write_sweep(exp, doc, base)
    log(f"        sweep: {math.prod(len(a.values) for a in axes)} points x {doc['runs']} runs, {doc['wall_s']:.1f} s")
    return [base]
