"""Every bundled experiment kind on an accelerator, in float32 and float64.

    python benchmarks/gpu.py                         # on a GPU: writes benchmarks/gpu.md
    python benchmarks/gpu.py --runs 100 --out /tmp/gpu_check.md   # a check on any backend

One experiment file per kind of world and sensor (open loop: the lidar crossing with its six
filters, the α-β and fusion files, a mount sensor, a real flight, a filter of one's own; the
airborne closed loop; the servo). Each runs in a fresh process (its peak device memory is its
own), once per precision, each time twice through the runner: the first call compiles (no
persistent cache), the second is timed warm. Reported per file and precision:

- the runs per chunk (the file's, or its world's default on the device: on a GPU, as many as
  an eighth of its memory holds, ``runner.accelerator_runs``);
- runs·steps/s of the warm call (a step: a filter period of the file; the closed loops' inner
  ticks are inside it), its wall time, and the compile time of the first call;
- peak device memory (``memory_stats()["peak_bytes_in_use"]`` of the first device; the host's
  peak RSS where the backend keeps no such count, as on the CPU);
- the float32-vs-float64 agreement: the relative difference of each filter's headline number
  (position RMSE; the airborne pointing error; the servo's maximum tracking error), the
  largest over the filters, beside the float64 run's relative half-width (the Monte-Carlo
  noise). The tracking and airborne worlds make their draws in float32 in both precisions, so
  there the difference is arithmetic alone; the servo draws its noise in the run's precision,
  so its two precisions are different realisations of the runs.

A servo file's DEKF is not trained first (``train_steps`` = 0): its training is a gradient
descent through the dual EKF before the runs (60 Adam steps on 2 000 frames take about four
minutes on two CPU cores), not the Monte-Carlo runner this measures, and would take most of a
short call. Figures are not drawn. On a backend other than a GPU the table is printed (and written only
where ``--out`` says), so a CPU check never stands in for ``gpu.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from written import write_run

ROOT = Path(__file__).resolve().parent.parent
FILES = [  # (kind, experiment file)
    ("open loop, polar sensor, six filters", "experiments/lidar_crossing.toml"),
    ("open loop, α-β (1-D)", "experiments/laser_ir_alpha_beta.toml"),
    ("open loop, laser/IR fusion (3-D)", "experiments/laser_ir_fusion_3d.toml"),
    ("open loop, mount sensor (error space)", "experiments/error_space_overflight.toml"),
    ("open loop, real flight (radar)", "experiments/real_flights_radar_helicopter.toml"),
    ("open loop, a filter of one's own", "experiments/own_filter.toml"),
    ("airborne closed loop", "experiments/airborne_radar.toml"),
    ("servo closed loop (DEKF; its training left out)", "experiments/dekf_on_axis_cone.toml"),
]
HEADLINE = ("rmse_pos", "max_track_err")  # the first a filter's summary has


def _peak_memory() -> tuple[float, str]:
    import jax

    stats = jax.local_devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return float(stats["peak_bytes_in_use"]), "device"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0, "host RSS"


def one(path: str, runs: int | None) -> dict:
    """Both precisions of one file, in this process: the measurements as a dictionary."""
    import tracklab

    tracklab.configure()
    import jax

    from tracklab.config import load_experiment

    exp = load_experiment(ROOT / path)
    if getattr(exp, "estimators", None):  # the servo: a DEKF's training before the runs is not the runner
        exp.estimators = [dataclasses.replace(e, train_steps=0) for e in exp.estimators]
    out = {"file": path, "backend": jax.default_backend(), "device": str(jax.local_devices()[0]),
           "devices": jax.device_count(), "steps": exp.steps, "precisions": {},
           "chunk": exp.structure(None, runs or exp.runs).chunk}  # the file's, or its default on this device
    for precision in ("float64", "float32"):
        with tempfile.TemporaryDirectory() as tmp:
            cold = exp.run(runs=runs, out=Path(tmp) / "a", figures=False, precision=precision)
            t0 = time.perf_counter()
            warm = exp.run(runs=runs, out=Path(tmp) / "b", figures=False, precision=precision)
            total = time.perf_counter() - t0
        heads, rel_hw = {}, {}
        for label, f in warm["filters"].items():
            key = next((k for k in HEADLINE if k in f["summary"]), None)
            v = f["summary"].get(key) if key else None
            heads[label] = v
            hw = (f.get("half_width") or {}).get(key)
            rel_hw[label] = hw / v if hw is not None and v else None
        peak, where = _peak_memory()
        out["runs"] = warm["runs"]
        out["precisions"][precision] = {
            "compile_s": cold["compile_s"], "wall_s": warm["wall_s"], "call_s": total,
            "rate": warm["runs"] * exp.steps / warm["wall_s"], "peak_bytes": peak, "peak_of": where,
            "headline": heads, "rel_half_width": rel_hw,
        }
    return out


def agreement(doc) -> tuple[float | None, float | None]:
    """(largest relative float32-vs-float64 difference of a headline number, the float64 run's
    smallest relative half-width)."""
    a, b = doc["precisions"]["float64"], doc["precisions"]["float32"]
    diffs = [abs(b["headline"][l] - v) / abs(v) for l, v in a["headline"].items()
             if v and b["headline"].get(l) is not None]
    hws = [h for h in a["rel_half_width"].values() if h]
    return (max(diffs) if diffs else None), (min(hws) if hws else None)


def table(docs) -> str:
    lines = ["| kind | file | runs × steps | chunk | precision | runs·steps/s | warm wall (s) | compile (s) |"
             " peak memory (MB) | f32 vs f64 (max rel. diff) | f64 rel. half-width (min) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind, d in docs:
        diff, hw = agreement(d)
        for p in ("float64", "float32"):
            m = d["precisions"][p]
            agree = (f"{diff:.1e}" if diff is not None else "—") if p == "float32" else ""
            noise = (f"{hw:.1e}" if hw is not None else "—") if p == "float64" else ""
            lines.append(f"| {kind} | `{Path(d['file']).name}` | {d['runs']} × {d['steps']} | {d['chunk']} | {p} | "
                         f"{m['rate']:.3g} | "
                         f"{m['wall_s']:.2f} | {m['compile_s']:.1f} | {m['peak_bytes'] / 1e6:.0f} ({m['peak_of']}) | "
                         f"{agree} | {noise} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, help="runs per file (default: each file's own)")
    ap.add_argument("--out", help="Markdown file to write (default on a GPU: benchmarks/gpu.md; elsewhere: none)")
    ap.add_argument("--only", help="comma-separated file names (default: every kind)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.runs)))
        return
    wanted = [f.strip() for f in args.only.split(",")] if args.only else None
    docs = []
    env = dict(os.environ, TRACKLAB_CACHE_DIR="")  # every compile measured cold
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    for kind, path in FILES:
        if wanted and Path(path).name not in wanted and Path(path).stem not in wanted:
            continue
        cmd = [sys.executable, __file__, "--one", path] + (["--runs", str(args.runs)] if args.runs else [])
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
        if done.returncode != 0:
            print(f"{path}: failed\n{done.stderr[-2000:]}", file=sys.stderr)
            continue
        d = json.loads(done.stdout.strip().splitlines()[-1])
        docs.append((kind, d))
        print(f"{path}: {d['precisions']['float64']['rate']:.3g} / {d['precisions']['float32']['rate']:.3g} "
              f"runs·steps/s (float64 / float32) on {d['device']}", flush=True)
    if not docs:
        sys.exit("nothing measured")
    d0 = docs[0][1]
    head = (f"# Every experiment kind on {d0['device']} ({d0['devices']} device(s), backend {d0['backend']})\n\n"
            f"`python benchmarks/gpu.py{' --runs ' + str(args.runs) if args.runs else ''}`, "
            f"{time.strftime('%Y-%m-%d')}; no persistent compilation cache; figures not drawn.\n\n")
    text = head + table(docs)
    print(text)
    out = args.out or (ROOT / "benchmarks" / "gpu.md" if d0["backend"] == "gpu" else None)
    if out:
        write_run(out, text, "gpu.py")
        print(f"written to {out}")


if __name__ == "__main__":
    main()
