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

METRICS = {  # titles without units: the "unit" column gives each row's (m, or deg for a mount)
    "unit": ("unit", "{}"),
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
BEGIN, END = "<!-- tracklab table: begin -->", "<!-- tracklab table: end -->"


def read_stats(folder) -> dict:
    path = Path(folder) / "stats.json"
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: no stats.json (not a results folder)")
    return json.loads(path.read_text())


def _cell(v, fmt):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    if fmt == "auto":  # metres to the centimetre; small values (degrees) to 3 significant digits
        return f"{v:.2f}" if abs(v) >= 1 or v == 0 else f"{v:.3g}"
    if fmt == "{:d}":
        return str(int(v))
    return fmt.format(v)


def combined_rows(folders, metrics=DEFAULT_METRICS):
    rows = []
    for folder in folders:
        doc = read_stats(folder)
        for label, f in doc["filters"].items():
            values = dict(f["summary"], wall_s=doc.get("wall_s"), unit=doc.get("units", ["m"])[0])
            rows.append([Path(folder).name, label] + [values.get(m) for m in metrics])
    return rows


def combined_table(folders, fmt="md", metrics=DEFAULT_METRICS) -> str:
    rows = combined_rows(folders, metrics)
    titles = ["results", "filter"] + [METRICS[m][0] for m in metrics]
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["results", "filter", *metrics])
        w.writerows(rows)
        return buf.getvalue()
    cells = [[r[0], r[1]] + [_cell(v, METRICS[m][1]) for v, m in zip(r[2:], metrics)] for r in rows]
    if fmt == "latex":
        esc = lambda s: str(s).replace("%", r"\%").replace("_", r"\_").replace("&", r"\&")
        lines = [r"\begin{tabular}{ll" + "r" * len(metrics) + "}", r"\hline",
                 " & ".join(esc(t) for t in titles) + r" \\", r"\hline"]
        lines += [" & ".join(esc(c) for c in r) + r" \\" for r in cells]
        return "\n".join(lines + [r"\hline", r"\end{tabular}"]) + "\n"
    lines = ["| " + " | ".join(titles) + " |", "|" + "|".join(["---"] * len(titles)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in cells]
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
    readme.write_text(text)


def reproduce(experiments_dir="experiments", results_dir="results", quick=False, log=print):
    """Run every experiment file and its studies; return the results folders written, in order."""
    from tracklab.config import load_experiment
    from tracklab.studies import run_study

    files = sorted(Path(experiments_dir).glob("*.toml"))
    exps = [load_experiment(p) for p in files]  # every file validated before anything runs
    results_dir = Path(results_dir)
    folders = []
    jobs = [(e, None if not quick else min(e.runs, 20), results_dir / e.name) for e in exps]
    if not quick:
        jobs += [(e, n, results_dir / f"{e.name}_{n}runs") for e in exps for n in e.also_runs]
    for i, (exp, runs, out) in enumerate(jobs, start=1):
        log(f"[{i}/{len(jobs)}] {exp.name}: {runs or exp.runs} runs x {exp.steps} steps -> {out}")
        doc = exp.run(runs=runs, out=out)
        log(f"        {doc['wall_s']:.1f} s")
        folders.append(out)
        if out == results_dir / exp.name:  # its tuning and sweep studies, once per experiment file
            for study in exp.studies:
                log(f"        study: {study.kind} -> {results_dir / study.out}")
                run_study(exp, study, results_dir, quick=quick, log=log)
    update_readme(results_dir / "README.md", combined_table(folders))
    return folders
