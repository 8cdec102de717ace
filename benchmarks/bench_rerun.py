"""Edit a number, run again: what `tracklab run` costs when only a number of the experiment changed.

    python benchmarks/bench_rerun.py                                # writes benchmarks/rerun.md (~3-5 min on 2 cores)
    python benchmarks/bench_rerun.py --baseline /tmp/tl-before      # the same sequence against another checkout too
    python benchmarks/bench_rerun.py --print                        # the same, prints only
    python benchmarks/bench_rerun.py --quick                        # fewer runs, prints only

In a fresh, empty compilation cache (TRACKLAB_CACHE_DIR pointed at a new temporary folder), a
copy of experiments/lidar_crossing.toml (all six filters) is run three times, each a new
`tracklab run COPY --no-figures` process:

1. sigma_r = 120, --runs 1000 (the cache is empty: the program is compiled);
2. sigma_r edited to 130, --runs 1000 (a number changed);
3. the same file, --runs 200 (the run count changed).

For each: the process wall time from start to exit (interpreter start, imports, compiling or
loading the program, the runs, the results folder), the "compiling or loading the program"
seconds that `tracklab run` prints on its first line, and the number of entries in the
compilation cache after it. ``--baseline PATH`` runs the same sequence with another checkout of
tracklab (``PYTHONPATH=PATH``, working directory outside both checkouts; the imported
``tracklab.__file__`` is checked) in its own fresh cache, for a before/after table.
See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from importlib import metadata
from pathlib import Path

from written import write_run

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENT = ROOT / "experiments" / "lidar_crossing.toml"

# (what changed, sigma_r, runs, results folder)
SEQUENCE = (("first run, empty cache", 120.0, 1000, "out1"),
            ("sigma_r edited 120 -> 130", 130.0, 1000, "out2"),
            ("same file, --runs 200", 130.0, 200, "out3"))
QUICK_RUNS = (200, 200, 100)

# `tracklab run`'s first line, now and before the runner (da29439 and earlier)
_FIRST = re.compile(r"^# (?P<name>.+?): (?P<runs>\d+) runs x (?P<steps>\d+) steps, window \S+, "
                    r"(?:(?P<wall>[\d.]+) s wall, (?P<compile>[\d.]+) s of it compiling or loading the program"
                    r"|(?P<wall_old>[\d.]+) s \(compile (?P<compile_old>[\d.]+) s\))\s*$")
_CODE = ("import sys, tracklab; print('bench_rerun: tracklab from', tracklab.__file__, file=sys.stderr, flush=True); "
         "from tracklab.cli import main; sys.exit(main())")


def first_line(stdout: str) -> dict:
    """The run's figures from `tracklab run`'s first line (either format)."""
    for line in stdout.splitlines():
        m = _FIRST.match(line)
        if m:
            old = m["wall_old"] is not None
            return {"runs": int(m["runs"]), "wall_s": float(m["wall_old"] if old else m["wall"]),
                    "compile_s": float(m["compile_old"] if old else m["compile"]), "old_format": old}
    raise ValueError(f"no `# NAME: R runs x S steps ...` line in tracklab run's output:\n{stdout[:2000]}")


def experiment_copy(dst: Path, sigma_r: float):
    """experiments/lidar_crossing.toml at ``dst`` with sensor.sigma_r = ``sigma_r`` (and a scenario
    path, if it had one, made absolute: the copy lives elsewhere). Its [[study]] is kept: a run ignores it."""
    text = EXPERIMENT.read_text()
    text, n = re.subn(r"(?m)^(sigma_r\s*=\s*)[-+0-9.eE]+", lambda m: f"{m[1]}{sigma_r!r}", text)
    assert n == 1, f"{EXPERIMENT}: expected one sigma_r line, found {n}"
    raw = tomllib.loads(text)
    rel = raw.get("scenario", {}).get("path")
    if rel is not None and not Path(rel).is_absolute():
        text = text.replace(json.dumps(rel), json.dumps(str((EXPERIMENT.parent / rel).resolve())), 1)
        raw = tomllib.loads(text)
    assert raw["sensor"]["sigma_r"] == sigma_r, raw["sensor"]
    dst.write_text(text)


def _cache_entries(cache: Path) -> int:
    """Programs in JAX's persistent cache (one ``…-cache`` file each, beside its ``…-atime``)."""
    files = [p for p in cache.rglob("*") if p.is_file()]
    named = [p for p in files if p.name.endswith("-cache")]
    return len(named) if named or not files else len(files)


def _summary(out: Path) -> str:
    """A number of the results that depends on sigma_r: shows that the edit reached the program."""
    try:
        doc = json.loads((out / "stats.json").read_text())
    except (OSError, ValueError):
        return "?"
    f = doc.get("filters", {})
    lab = "EKF" if "EKF" in f else next(iter(f), None)
    v = f.get(lab, {}).get("summary", {}).get("rmse_pos") if lab else None
    return f"{lab} {v:.3f}" if isinstance(v, (int, float)) else "?"


def run_sequence(checkout: Path, work: Path, runs_seq, log) -> list[dict]:
    """The three runs with ``checkout``'s tracklab, in a fresh compilation cache."""
    cache = work / "cache"
    cache.mkdir(parents=True)
    exp = work / "lidar_crossing.toml"
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "PYTHONPATH")}
    env.update(TRACKLAB_CACHE_DIR=str(cache), PYTHONPATH=str(checkout))
    rows = []
    for (what, sigma_r, _, out), runs in zip(SEQUENCE, runs_seq):
        experiment_copy(exp, sigma_r)
        cmd = [sys.executable, "-c", _CODE, "run", str(exp), "--runs", str(runs), "--no-figures",
               "--out", str(work / out)]
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, env=env, cwd=work, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            raise RuntimeError(f"tracklab run failed ({checkout}):\n{p.stderr[-3000:]}")
        src = re.search(r"^bench_rerun: tracklab from (.+)$", p.stderr, re.M)
        if not src or not Path(src[1].strip()).resolve().is_relative_to(checkout.resolve()):
            raise RuntimeError(f"imported tracklab is not {checkout}'s: {src[1] if src else p.stderr[:500]}")
        fl = first_line(p.stdout)
        assert fl["runs"] == runs, (fl, runs)
        row = {"what": what, "sigma_r": sigma_r, "runs": runs, "process_s": wall, "printed_wall_s": fl["wall_s"],
               "printed_compile_s": fl["compile_s"], "old_format": fl["old_format"],
               "cache_entries": _cache_entries(cache), "load": load, "result": _summary(work / out)}
        rows.append(row)
        log(f"  {what}: sigma_r {sigma_r:g}, {runs} runs: process {wall:.1f} s, printed wall {fl['wall_s']:.1f} s, "
            f"compile {fl['compile_s']:.1f} s{' (old format)' if fl['old_format'] else ''}, "
            f"cache entries {row['cache_entries']}, {row['result']}")
    return rows


def _git(checkout: Path) -> str:
    def git(*a):
        return subprocess.run(["git", "-C", str(checkout), *a], capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "?"
    dirty = git("status", "--porcelain", "--", "tracklab")
    return f"{head}{' + uncommitted changes to tracklab/' if dirty else ''}"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "?"


def render(info, cmd, sequences, load_end, quick) -> str:
    L = ["# Edit a number, run again (`python benchmarks/bench_rerun.py`)", ""]
    L.append(f"- Date: {info['date']}")
    L.append(f"- Machine: nproc = {info['nproc']}, CPU = {info['cpu']}")
    L.append(f"- Load average (1/5/15 min) before: {info['loadavg']}; after: {load_end}")
    L.append(f"- Python {info['python']}, jax {info['jax']}, jaxlib {info['jaxlib']}")
    L.append(f"- Command: `{cmd}`")
    for name, (checkout, _) in sequences.items():
        L.append(f"- {name}: `{checkout}` at {_git(checkout)}")
    L.append("")
    L.append("A copy of `experiments/lidar_crossing.toml` (six filters, 200 steps) run as a new "
             "`tracklab run COPY --runs R --no-figures` process each time, in a compilation cache "
             "(TRACKLAB_CACHE_DIR) that is empty before the first run of each checkout. Process = wall time "
             "from process start to exit. Printed = `tracklab run`'s first line: its wall time and the seconds "
             "of it it reports compiling or loading the program. Cache entries = programs in the persistent "
             "cache after the run (a new entry: a new compile). The last column is the EKF's time-averaged "
             "position RMSE (m) from the run's stats.json: the edited sigma_r reached the program.")
    if quick:
        L.append("")
        L.append(f"`--quick`: {', '.join(map(str, QUICK_RUNS))} runs instead of "
                 f"{', '.join(str(r) for *_, r, _ in SEQUENCE)}.")
    L.append("")
    L.append("| Checkout | Run | sigma_r (m) | Runs | Process (s) | Printed wall (s) | Printed compiling or loading (s) "
             "| Cache entries | Load (1 min) | RMSE pos |")
    L.append("|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    old = False
    for name, (_, rows) in sequences.items():
        for r in rows:
            comp = f"{r['printed_compile_s']:.1f}" + (" ¹" if r["old_format"] else "")
            old |= r["old_format"]
            L.append(f"| {name} | {r['what']} | {r['sigma_r']:g} | {r['runs']} | {r['process_s']:.1f} | "
                     f"{r['printed_wall_s']:.1f} | {comp} | {r['cache_entries']} | {r['load']:.2f} | {r['result']} |")
    if old:
        L.append("")
        L.append("¹ Printed as `W s (compile C s)` by the engine before the runner: the time of the first chunk's "
                 "call (tracing, compiling or loading, and dispatching the first chunk), not only compiling. That "
                 "design compiled the experiment's numbers into the program, so an edited number (or a run count "
                 "below the chunk size, which shrank the chunk) meant a new program and a new compile.")
    L.append("")
    return "\n".join(L)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", type=Path, default=None,
                    help="another checkout of tracklab (e.g. a `git worktree` at an older commit) to run first")
    ap.add_argument("--quick", action="store_true", help=f"runs {QUICK_RUNS}, prints only")
    ap.add_argument("--print", action="store_true", help="prints only, does not write the results file")
    ap.add_argument("--out", type=Path, default=None, help="Markdown output (default benchmarks/rerun.md)")
    a = ap.parse_args()

    checkouts = {}
    if a.baseline is not None:
        base = a.baseline.resolve()
        if not (base / "tracklab" / "__init__.py").is_file():
            ap.error(f"--baseline {a.baseline}: no tracklab/__init__.py there")
        checkouts["baseline"] = base
    checkouts["this checkout"] = ROOT
    runs_seq = QUICK_RUNS if a.quick else tuple(r for *_, r, _ in SEQUENCE)
    cmd = "python benchmarks/bench_rerun.py" + (f" --baseline {a.baseline}" if a.baseline else "")
    cmd += " --quick" if a.quick else ""
    cmd += " --print" if a.print else ""

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    info = {
        "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "nproc": os.cpu_count(),
        "cpu": _cpu(),
        "python": platform.python_version(),
        "jax": metadata.version("jax"),
        "jaxlib": metadata.version("jaxlib"),
        "loadavg": load_start,
    }
    print(f"# {info}", flush=True)
    sequences = {}
    tmp = Path(tempfile.mkdtemp(prefix="tracklab-rerun-"))
    try:
        for i, (name, checkout) in enumerate(checkouts.items()):
            print(f"{name}: {checkout}", flush=True)
            sequences[name] = (checkout, run_sequence(checkout, tmp / f"seq{i}", runs_seq, print))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    md = render(info, cmd, sequences, load_end, a.quick)
    print()
    print(md)
    out = None if (a.quick or a.print) else (a.out or ROOT / "benchmarks" / "rerun.md")
    if out is not None:
        write_run(out, md, "bench_rerun.py")
        print(f"written {out}")


if __name__ == "__main__":
    main()
