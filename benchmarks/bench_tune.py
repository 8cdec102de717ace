"""A tuning step's gradient in forward and in reverse mode: compile time and time per step.

    python benchmarks/bench_tune.py                 # every case, both modes → benchmarks/tune.md (~6 min on 2 cores)
    python benchmarks/bench_tune.py --print         # the same, prints only

``tracklab.tune`` takes its gradient in forward mode (``jax.jacfwd``) for up to
``tune.FORWARD_UP_TO`` tuned numbers and in reverse mode above (``tune.gradient``). For each
case, each mode is compiled and timed in a fresh process (no persistent cache), one after
the other: the seconds of ``jit(...).lower(...).compile()`` of the tuning step (the loss of
every tuned filter and its gradient, over one batch of ``runs_per_step`` runs), the first
call, and the mean of five steady calls. The cases are the bundled tuning files as their
``[[study]]`` tables tune them, the airborne file's tracker (q_scale, lam) and, to show
where reverse mode wins, five filters of the lidar file with q and r (15 numbers).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

from bench_rerun import _cpu, _git
from written import write_run

ROOT = Path(__file__).resolve().parent.parent
OUT = Path(__file__).resolve().parent / "tune.md"

# (name, file, params, filters (None: every one that has them), loss, runs per step)
CASES = [
    ("tuning_alpha_beta", "experiments/tuning_alpha_beta.toml", ["alpha", "beta"], ["alpha-beta (3x off)"], "mse_pos", 1024),
    ("tuning_lidar_ekf", "experiments/tuning_lidar_ekf.toml", ["q", "r"], ["EKF (mistuned)"], "nll", 128),
    ("tuning_stf", "experiments/tuning_stf.toml", ["rho", "b"], ["STF"], "pred_mse", 32),
    ("airborne_radar", "experiments/airborne_radar.toml", ["q_scale", "lam"], ["joint EKF"], "pointing", 16),
    ("lidar_crossing, 5 filters", "experiments/lidar_crossing.toml", ["q", "r"],
     ["CMKF", "CMKF unbiased", "EKF", "Sequential EKF", "UKF"], "mse_pos", 256),
]

_ONE = r"""
import json, sys, time
import jax, jax.numpy as jnp
import tracklab
tracklab.configure()
import importlib
from tracklab.config import load_experiment
tune = importlib.import_module("tracklab.tune")
path, params, labels, loss, B, mode = json.loads(sys.argv[1])
exp = load_experiment(path)
with jax.enable_x64(True):
    obj = tune.objective(exp, params, loss, labels)
    n = tune.numbers(obj.theta0)

    def total(theta, key, idx, live):
        per = obj.losses(theta, key, idx, live)
        return sum(per.values()), per

    step = jax.jit(tune.gradient(total, 1 if mode == "forward" else 10 ** 9))
    theta = jax.device_get(obj.theta0)
    args = (theta, jax.random.key(0), jnp.arange(B, dtype=jnp.uint32), jnp.ones((B,), bool))
    t0 = time.perf_counter()
    compiled = step.lower(*args).compile()
    t1 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    t2 = time.perf_counter()
    for _ in range(5):
        out = jax.block_until_ready(compiled(*args))
    t3 = time.perf_counter()
    print(json.dumps({"numbers": n, "compile_s": t1 - t0, "first_s": t2 - t1, "step_s": (t3 - t2) / 5,
                      "loss": float(out[0][0])}))
"""


def measure(case, mode) -> dict:
    _, path, params, labels, loss, B = case
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    done = subprocess.run([sys.executable, "-c", _ONE, json.dumps([str(ROOT / path), params, labels, loss, B, mode])],
                          cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--print", action="store_true", help="print only; do not write benchmarks/tune.md")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from tracklab.studies.tune import FORWARD_UP_TO

    rows = []
    for case in CASES:
        fwd, rev = measure(case, "forward"), measure(case, "reverse")
        chosen = "forward" if fwd["numbers"] <= FORWARD_UP_TO else "reverse"
        rows.append(f"| {case[0]} | {fwd['numbers']} | {case[5]} | {fwd['compile_s']:.1f} | {rev['compile_s']:.1f} | "
                    f"{fwd['step_s'] * 1e3:.0f} | {rev['step_s'] * 1e3:.0f} | "
                    f"{abs(fwd['loss'] - rev['loss']) / abs(rev['loss']):.0e} | {chosen} |")
        print(rows[-1], flush=True)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = "\n".join([
        "# A tuning step's gradient: forward against reverse mode",
        "",
        f"`python benchmarks/bench_tune.py`, {stamp}, tracklab {_git(ROOT)}, {_cpu()} ({os.cpu_count()} cores), "
        f"Python {platform.python_version()}. Each mode compiled and timed in its own fresh process, float64, "
        "no persistent cache. Step: the mean of five steady calls of the tuning step (every tuned filter's "
        "loss and its gradient over one batch).",
        "",
        "| Case | Tuned numbers | Runs a step | Compile, forward (s) | Compile, reverse (s) | Step, forward (ms) | "
        "Step, reverse (ms) | Loss, relative difference | tracklab takes |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
        *rows,
        "",
        f"tracklab takes forward mode up to {FORWARD_UP_TO} tuned numbers (`tracklab.tune.FORWARD_UP_TO`).",
        "",
    ])
    if args.print:
        print(text)
    else:
        write_run(OUT, text, "bench_tune.py")
        print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
