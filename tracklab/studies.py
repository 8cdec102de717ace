"""Studies an experiment file asks `tracklab reproduce` to rebuild: tuning and sweeps.

An experiment file may hold ``[[study]]`` tables; each is checked with the rest
of the file, before anything compiles::

    [[study]]                       # results/tuning/stf_tuned.toml, stf_tune.log, stf_tuned/
    kind = "tune"
    params = ["rho", "b"]
    filters = ["STF"]               # default: every filter with the parameters
    loss = "pred_mse"               # mse_pos | pred_mse | nll
    steps = 150
    lr = 0.05
    runs_per_step = 32
    out = "tuning/stf"

    [[study]]                       # results/mismatch/lidar_crossing/
    kind = "sweep"
    grid = ["q=0.01:100:5", "r=0.04:25:5"]
    runs = 1000
    out = "mismatch/lidar_crossing"

A tune study writes the tuned experiment file ``<out>_tuned.toml``, the progress
lines ``<out>_tune.log`` and the results of running the tuned file, ``<out>_tuned/``;
a sweep study writes the sweep folder ``<out>/`` (all under the results folder).
These are exactly what ``tracklab tune … --out <out>_tuned.toml`` then ``tracklab
run <out>_tuned.toml``, and ``tracklab sweep … --out <out>`` give.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from tracklab.errors import ConfigError

OUT_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*")


@dataclass(frozen=True)
class TuneStudy:
    params: tuple[str, ...]
    filters: tuple[str, ...] | None
    loss: str
    steps: int
    lr: float
    runs_per_step: int
    out: str
    kind: str = "tune"


@dataclass(frozen=True)
class SweepStudy:
    grid: tuple[str, ...]
    runs: int | None
    out: str
    kind: str = "sweep"


def parse_studies(f, tables, section_cls, exp_filters) -> list:
    """Validate the ``[[study]]`` tables (``section_cls``: config's typed table reader)."""
    from tracklab.config import MAX_RUNS
    from tracklab.filters.registry import TUNABLE
    from tracklab.filters.registry import scales
    from tracklab.sweep import parse_grid
    from tracklab.tune import LOSSES, tunes

    if tables is None:
        return []
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f, "[[study]]", tables, "must be one or more [[study]] tables")
    labels = {fc.label: fc for fc in exp_filters}
    studies, outs = [], set()
    for i, table in enumerate(tables, start=1):
        st = section_cls(f, f"study[{i}]", table)
        kind = st.string("kind", required=True, choices=("tune", "sweep"))
        out = st.string("out", required=True)
        if not OUT_RE.fullmatch(out) or ".." in out.split("/") or len(out) > 200:
            raise ConfigError(f, f"study[{i}].out", out, "must be a relative folder under results/ (letters, digits, _ . - and /)")
        if out in outs:
            raise ConfigError(f, f"study[{i}].out", out, "must be unique among the studies")
        outs.add(out)
        if kind == "tune":
            params = st.get("params")
            if not isinstance(params, list) or not params or any(p not in TUNABLE for p in params):
                raise ConfigError(f, f"study[{i}].params", params, f"must be a list of parameters among {', '.join(TUNABLE)}")
            chosen = st.get("filters")
            if chosen is not None and (not isinstance(chosen, list) or not chosen or any(c not in labels for c in chosen)):
                raise ConfigError(f, f"study[{i}].filters", chosen, f"must be a list of filter labels from: {', '.join(labels)}")
            pool = [labels[c] for c in chosen] if chosen else list(labels.values())
            if not any(tunes(fc.kind, fc.params, p) for fc in pool for p in params):
                raise ConfigError(f, f"study[{i}].params", params, "no selected filter has any of these parameters")
            loss = st.string("loss", "mse_pos", choices=tuple(LOSSES))
            lr = st.number("lr", 0.05, positive=True)
            study = TuneStudy(tuple(params), tuple(chosen) if chosen else None, loss,
                              st.integer("steps", 200, lo=1, hi=100_000), lr,
                              st.integer("runs_per_step", 256, lo=1, hi=1_000_000), out)
        else:
            grid = st.get("grid")
            if not isinstance(grid, list) or not grid or any(not isinstance(g, str) for g in grid):
                raise ConfigError(f, f"study[{i}].grid", grid, "must be a list of NAME=LO:HI:N strings")
            axes = []
            for g in grid:
                try:
                    axes.append(parse_grid(g))
                except ValueError as e:
                    raise ConfigError(f, f"study[{i}].grid", g, str(e)) from None
            names = [a.name for a in axes]
            if len(set(names)) != len(names):
                raise ConfigError(f, f"study[{i}].grid", grid, "each parameter may appear once")
            # scale factors need a filter with the parameter; a PATH is checked against the file by the sweep
            missing = next((a.name for a in axes if a.path is None
                            and not any(scales(fc.kind, fc.params, a.name) for fc in exp_filters)), None)
            if missing:
                raise ConfigError(f, f"study[{i}].grid", grid, f"no filter of this experiment has the parameter {missing!r}")
            study = SweepStudy(tuple(grid), st.integer("runs", None, lo=1, hi=MAX_RUNS), out)
        st.check_unknown()
        studies.append(study)
    return studies


def check_tune(exp, names, labels, out_toml, runs_per_step=None, max_memory=None, field="--params"):
    """Everything a tuning needs, checked before it compiles (ConfigError in one line): a selected
    filter with the parameters, tuned values that can be written back, the output file, memory."""
    from tracklab.errors import ConfigError
    from tracklab.memory import check
    from tracklab.output import check_tuned_file
    from tracklab.tune import memory_bytes, selection, unwritable

    chosen = selection(exp, names, labels)
    if not chosen:
        raise ConfigError(exp.path, field, ",".join(names), "no selected filter has any of these parameters")
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

    from tracklab.config import dump_toml, load_experiment
    from tracklab.errors import ConfigError
    from tracklab.output import TUNED_HEADER, check_tuned_file, write_text_atomically
    from tracklab.tune import tune, tuned_document

    out_toml = check_tuned_file(out_toml, exp.path)

    def progress(k, value, gnorm):
        log(f"step {k:5d}  loss {value:.6g}  |grad| {gnorm:.3g}")

    def number(v):
        return f"{v:.6g}" if math.isfinite(v) else "— (no finite value)"

    res = tune(exp, names, steps=steps, lr=lr, loss=loss, runs_per_step=runs_per_step, labels=labels, every=every,
               progress=progress, eval_runs=eval_runs)
    if res.stopped:
        print(f"warning: {res.stopped}", file=sys.stderr)
        log(res.stopped)
    for label, p in res.params.items():
        log(f"{label}: " + ", ".join(f"{k} {res.initial[label][k]} -> {v}" for k, v in p.items()))
    log(f"held-out {loss}: {number(res.eval_initial)} -> {number(res.eval_tuned)}")
    text = TUNED_HEADER + "\n" + dump_toml(tuned_document(exp, res, out_toml))

    def verify(tmp):  # the file must be one `tracklab run` accepts, before it replaces anything
        try:
            load_experiment(tmp)
        except ConfigError as e:
            raise ConfigError(exp.path, "--out", str(out_toml), f"not written: the tuned values are refused ({e.allowed})") from None

    write_text_atomically(out_toml, text, verify)
    log(f"tuned experiment written to {out_toml}")
    return res


def run_study(exp, study, results_dir, quick=False, log=print):
    """Rebuild one study under ``results_dir``; ``quick``: a few steps and runs, as a smoke check."""
    from tracklab.config import load_experiment
    from tracklab.output import write_text_atomically
    from tracklab.sweep import parse_grid, sweep, write_sweep

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
