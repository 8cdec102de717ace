"""Combined error-statistics tables, and rebuilding every result.

``combined_table`` reads the ``stats.json`` of several results folders and
puts every filter of every experiment in one table (Markdown, CSV or LaTeX).
``reproduce`` runs every experiment file (and the tuning and sweep studies it
names in ``[[study]]`` tables) and rewrites the combined table between the
markers in ``results/README.md``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from tracklab.config import load_experiment
from tracklab.config.paths import parse_grid
from tracklab.errors import ConfigError
from tracklab.intervals import percent, with_half_width
from tracklab.output import TABLE_BEGIN as BEGIN  # the results README's table markers
from tracklab.output import TABLE_END as END
from tracklab.output import (
    check_results_folder,
    check_results_parent,
    write_text_atomically,
)
from tracklab.report.document import world_of
from tracklab.report.tables import md_cell
from tracklab.studies.files import check_tune, run_study
from tracklab.studies.sweep import check_sweep

METRICS = {  # titles without units: the "units" column gives each row's (``row_units``)
    "unit": ("units", "{}"),
    "rmse_pos": ("RMSE pos", "auto"),
    "rmse_vel": ("RMSE vel", "auto"),
    "max_err_pos": ("max err pos", "auto"),
    "pred_err_rms": ("pred err RMS", "auto"),
    "mean_err_x": ("mean err x", "{:.2f}"),
    "mean_err_y": ("mean err y", "{:.2f}"),
    "nees": ("NEES", "{:.2f}"),
    "nees_in_bounds": ("NEES in 95 %", "{:.0%}"),
    "rmse_pos_over_pcrlb": ("RMSE/PCRLB", "{:.3f}"),
    "max_track_err": ("servo max err (′)", "{:.3f}"),
    "random_err": ("servo random err (″)", "{:.2f}"),
    "diverged": ("diverged", "{:d}"),
    "runs": ("runs", "{:d}"),
    "wall_s": ("wall (s)", "{:.1f}"),
}
DEFAULT_METRICS = tuple(METRICS)


def _number(v) -> bool:
    """A JSON number a table can show (not a bool, not too large for a float)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        float(v)
    except OverflowError:
        return False
    return True


def read_stats(folder) -> dict:
    """A results folder's stats.json, checked: ConfigError in one line if it is not one."""
    path = Path(folder) / "stats.json"
    if not path.is_file():
        raise ConfigError(folder, "stats.json", str(path), "missing: not a results folder of tracklab run")
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as e:
        raise ConfigError(folder, "stats.json", str(path), f"cannot be read as JSON ({e.__class__.__name__})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("filters"), dict) or not doc["filters"]:
        raise ConfigError(folder, "stats.json", str(path), "must be an object whose 'filters' maps labels to filters")
    for label, f in doc["filters"].items():
        if not isinstance(f, dict) or not isinstance(f.get("summary"), dict):
            raise ConfigError(folder, f"stats.json filters.{label}", str(path), "must be an object with a 'summary' object")
        bad = next((k for k, v in f["summary"].items() if v is not None and not _number(v)), None)
        if bad is not None:
            raise ConfigError(folder, f"stats.json filters.{label}.summary.{bad}", str(path), "must be a number or null")
    units = doc.get("units", ["m"])
    if not isinstance(units, list) or not units or not isinstance(units[0], str):
        raise ConfigError(folder, "stats.json units", str(path), "must be a list of unit names")
    if not (doc.get("wall_s") is None or _number(doc["wall_s"])):
        raise ConfigError(folder, "stats.json wall_s", str(path), "must be a number")
    return doc


def _cell(v, fmt):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    if fmt == "auto":  # metres to the centimetre; small values (degrees) to 3 significant digits
        return f"{v:.2f}" if abs(v) >= 1 or v == 0 else f"{v:.3g}"
    if fmt == "{:d}":
        return str(int(v))
    if fmt.endswith("%}"):
        return percent(v)
    return fmt.format(v)


FACTS = ("unit", "diverged", "runs", "wall_s")  # the metrics that are not statistics over the healthy runs


def no_healthy_run(summary) -> bool:
    """Whether a filter's summary says no run of it stayed healthy: every run diverged (or lost
    lock), or none was healthy throughout (``healthy_runs`` 0)."""
    runs, diverged = summary.get("runs"), summary.get("diverged")
    if _number(summary.get("healthy_runs")) and summary["healthy_runs"] == 0:
        return True
    return _number(runs) and _number(diverged) and runs > 0 and diverged >= runs


def row_units(doc, summary) -> str:
    """What a row's numbers are in: the RMSE columns' units (an airborne file's are its pointing
    and line-of-sight-rate errors), or a servo file's minutes and seconds of arc."""
    units = doc.get("units", ["m"])
    pos, vel = (list(units) + ["?"])[:2] if len(units) > 1 else (units[0], f"{units[0]}/s")
    if summary.get("rmse_pos") is None and summary.get("max_track_err") is not None:
        return "′ (max err), ″ (random err)"
    if world_of(doc) == "airborne":
        return f"{pos} (pointing), {vel} (LOS rate)"
    return f"{pos}, {vel}"


def combined_rows(folders, metrics=DEFAULT_METRICS, docs=None, half_widths=None):
    """One row per filter of every folder: [folder, label, value per metric]; ``half_widths``, a
    list, receives each row's half-widths per metric (None where the folder holds none). A filter
    with no healthy run has every statistic missing (None), whatever numbers its summary holds."""
    rows = []
    for folder, doc in zip(folders, docs or [read_stats(f) for f in folders]):
        for label, f in doc["filters"].items():
            values = dict(f["summary"], wall_s=doc.get("wall_s"), unit=row_units(doc, f["summary"]))
            none = no_healthy_run(f["summary"])
            shown = [m for m in metrics if not none or m in FACTS]
            rows.append([Path(folder).name, label] + [values.get(m) if m in shown else None for m in metrics])
            if half_widths is not None:
                hw = f.get("half_width") if isinstance(f.get("half_width"), dict) else {}
                half_widths.append([hw.get(m) if m in shown and _number(hw.get(m)) else None for m in metrics])
    return rows


def combined_table(folders, fmt="md", metrics=DEFAULT_METRICS, docs=None) -> str:
    """Every folder's filters in one table (md, csv or latex); a number with an interval is
    ``value ± half-width`` (csv: a ``<metric>_hw`` column)."""
    hws = []
    rows = combined_rows(folders, metrics, docs, hws)
    titles = ["results", "filter"] + [METRICS[m][0] for m in metrics]
    if fmt == "csv":
        shown = [j for j in range(len(metrics)) if any(h[j] is not None for h in hws)]
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["results", "filter", *metrics, *(f"{metrics[j]}_hw" for j in shown)])
        finite = lambda v: v if v is None or not isinstance(v, float) or math.isfinite(v) else None
        w.writerows([[finite(v) for v in r] + [finite(h[j]) for j in shown] for r, h in zip(rows, hws)])
        return buf.getvalue()

    def cell(v, hw, m):
        if hw is None or METRICS[m][1] in ("{:d}", "{:.0%}", "{}"):
            return _cell(v, METRICS[m][1])
        return with_half_width(v, hw)

    cells = [[r[0], r[1]] + [cell(v, hw, m) for v, hw, m in zip(r[2:], h, metrics)] for r, h in zip(rows, hws)]
    if fmt == "latex":
        esc = lambda s: str(s).replace("%", r"\%").replace("_", r"\_").replace("&", r"\&").replace("±", r"$\pm$")
        lines = [r"\begin{tabular}{ll" + "r" * len(metrics) + "}", r"\hline",
                 " & ".join(esc(t) for t in titles) + r" \\", r"\hline"]
        lines += [" & ".join(esc(c) for c in r) + r" \\" for r in cells]
        return "\n".join(lines + [r"\hline", r"\end{tabular}"]) + "\n"
    lines = ["| " + " | ".join(titles) + " |", "|" + "|".join(["---"] * len(titles)) + "|"]
    lines += ["| " + " | ".join(md_cell(c) for c in r) + " |" for r in cells]
    return "\n".join(lines) + "\n"


def update_readme(readme: Path, table: str):
    """Replace the text between the table markers (appending them if absent)."""
    text = readme.read_text() if readme.exists() else "# Results\n"
    block = f"{BEGIN}\n{table}{END}"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        text = head + block + rest.split(END, 1)[1]
    else:
        text = text.rstrip("\n") + f"\n\n## All experiments\n\n{block}\n"
    write_text_atomically(readme, text)


def _check_outputs(exps, jobs, experiments_dir: Path, results_dir: Path, quick, max_memory):
    """Every output of every job and study, and every job's memory, checked before anything runs."""
    check_results_parent(results_dir, experiments_dir)
    for exp, runs, out in jobs:
        check_results_folder(out, exp.path, "output folder")
        exp.check_memory(runs, max_memory)
    for exp in exps:
        for study in exp.studies:
            base = results_dir / study.out
            if study.kind == "tune":
                check_tune(exp, list(study.params), study.filters, base.with_name(base.name + "_tuned.toml"),
                           min(study.runs_per_step, 4) if quick else study.runs_per_step, max_memory, "study.params",
                           base.with_name(base.name + "_tune"), "study.out")
                check_results_folder(base.with_name(base.name + "_tuned"), exp.path, "study.out")
            else:
                check_results_folder(base, exp.path, "study.out")
                axes = [parse_grid(g) for g in study.grid]
                check_sweep(exp, axes, 4 if quick else study.runs, max_memory)


def reproduce(experiments_dir="experiments", results_dir="results", quick=False, log=print, max_memory=None,
              figures=True, progress=None):
    """Run every experiment file and its studies (with their PNG figures if ``figures``); return
    the results folders written, in order. ``progress``: each run's callback (``Experiment.run``)."""
    folder = Path(experiments_dir)
    if not folder.is_dir():
        raise ConfigError(folder, "--experiments", str(folder), "must be a folder of experiment files (*.toml)")
    files = sorted(folder.glob("*.toml"))
    if not files:
        raise ConfigError(folder, "--experiments", str(folder), "holds no experiment file (*.toml)")
    exps = [load_experiment(p) for p in files]  # every file validated before anything runs
    results_dir = Path(results_dir)
    folders = []
    jobs = [(e, None if not quick else min(e.runs, 20), results_dir / e.name) for e in exps]
    if not quick:
        jobs += [(e, n, results_dir / f"{e.name}_{n}runs") for e in exps for n in e.also_runs]
    _check_outputs(exps, jobs, folder, results_dir, quick, max_memory)
    for i, (exp, runs, out) in enumerate(jobs, start=1):
        log(f"[{i}/{len(jobs)}] {exp.name}: {runs or exp.runs} runs x {exp.steps} steps -> {out}")
        doc = exp.run(runs=runs, out=out, max_memory=max_memory, figures=figures, progress=progress)
        log(f"        {doc['wall_s']:.1f} s")
        folders.append(out)
        if out == results_dir / exp.name:  # its tuning and sweep studies, once per experiment file
            for study in exp.studies:
                log(f"        study: {study.kind} -> {results_dir / study.out}")
                run_study(exp, study, results_dir, quick=quick, log=log, figures=figures)
    update_readme(results_dir / "README.md", combined_table(folders))
    return folders
