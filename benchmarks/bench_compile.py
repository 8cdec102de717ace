"""Compile time of `tracklab run`: cold, warm, and with one filter added.

    python benchmarks/bench_compile.py                       # lidar_crossing and a real-flight file → benchmarks/compile.md
    python benchmarks/bench_compile.py FILE.toml ... --out /tmp/c.md

For each experiment file, in fresh processes (`python -m tracklab.cli run FILE --runs R
--no-figures`), one after the other on this machine:

1. **cold**: an empty cache folder (`TRACKLAB_CACHE_DIR`): everything is traced and compiled;
2. **warm**: the same command again: what a second run of the file (or of the file with any
   number edited) costs;
3. **one filter added**: the same file with one more filter (a copy of its first `[[filter]]`
   under another label), on the warm cache: what adding a filter to a file costs.

Each row gives the wall time from process start to exit and the seconds of it that
`tracklab run` reports compiling or loading programs (its first output line).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_rerun import _cpu, _git, first_line
from written import write_run

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ["experiments/lidar_crossing.toml", "experiments/real_flights_radar_carrier_pattern.toml"]


def with_extra_filter(src: Path, dst: Path) -> None:
    """``src`` with its first ``[[filter]]`` table repeated at the end under the label "added"."""
    text = src.read_text()
    tables = re.split(r"(?m)^(?=\[)", text)
    first = next(t for t in tables if t.startswith("[[filter]]"))
    body = re.sub(r'(?m)^label\s*=.*$', 'label = "added"', first)
    if "label" not in body:
        body = body.replace("[[filter]]\n", '[[filter]]\nlabel = "added"\n', 1)
    # keep the added table before any [[study]]/[report] tables: insert it after the last filter
    last = max(i for i, t in enumerate(tables) if t.startswith("[[filter]]"))
    tables.insert(last + 1, body.rstrip() + "\n\n")
    out = "".join(tables)
    # data paths are relative to the file: keep them pointing at the original's folder
    out = re.sub(r'(?m)^(path\s*=\s*")(?!/)([^"]+)"', lambda m: f'{m[1]}{(src.parent / m[2]).resolve()}"', out)
    dst.write_text(out)


def run_once(path: Path, runs: int, cache: Path, out: Path) -> tuple[float, float]:
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}  # it would take precedence
    env["TRACKLAB_CACHE_DIR"] = str(cache)
    cmd = [sys.executable, "-m", "tracklab.cli", "run", str(path), "--runs", str(runs), "--no-figures", "--out", str(out)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr[-3000:]}")
    shutil.rmtree(out, ignore_errors=True)
    return wall, first_line(p.stdout)["compile_s"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="*", default=DEFAULT)
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "compile.md")
    a = ap.parse_args()
    rows = []
    work = Path(tempfile.mkdtemp(prefix="tracklab-compile-"))
    try:
        for f in a.files:
            path = (ROOT / f).resolve()
            cache = work / "cache"
            shutil.rmtree(cache, ignore_errors=True)
            added = work / f"{path.stem}_added.toml"
            with_extra_filter(path, added)
            for label, p in (("cold", path), ("warm", path), ("one filter added", added)):
                load = os.getloadavg()[0]
                wall, comp = run_once(p, a.runs, cache, work / "out")
                rows.append((f, label, wall, comp, load))
                print(f"{f:55s} {label:17s} wall {wall:6.1f} s, compiling or loading {comp:6.1f} s "
                      f"(load {load:.2f})", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    lines = [
        "# Compile time of `tracklab run`",
        "",
        f"## Cold, warm and one filter added ({_dt.datetime.now(_dt.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"commit {_git(ROOT)})",
        "",
        f"- Machine: nproc = {os.cpu_count()}, {_cpu()}, Python "
        f"{platform.python_version()}",
        f"- Command: `python benchmarks/bench_compile.py {' '.join(a.files)} --runs {a.runs}`",
        "",
        "Fresh processes, one after the other: `python -m tracklab.cli run FILE --runs "
        f"{a.runs} --no-figures` with an empty cache folder (cold), the same again (warm), then the "
        "file with a copy of its first filter added under another label (on the warm cache). Wall: "
        "process start to exit. Compiling or loading: the seconds `tracklab run` reports on its first line.",
        "",
        "| Experiment | Cache | Wall (s) | Of it compiling or loading (s) | Load average (1 min) |",
        "|---|---|---:|---:|---:|",
    ] + [f"| `{f}` | {lab} | {w:.1f} | {c:.1f} | {ld:.2f} |" for f, lab, w, c, ld in rows] + [""]
    write_run(a.out, "\n".join(lines), "bench_compile.py", keep_earlier=True)  # above the earlier runs
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
