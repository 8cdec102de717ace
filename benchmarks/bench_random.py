"""Gaussian draws per second: jax.random against tracklab.random (the simulation's draws).

    python benchmarks/bench_random.py           # writes benchmarks/random.md
    python benchmarks/bench_random.py --quick   # fewer draws, prints only

Each case draws N standard normals in one jitted call (best of 5 after a warm-up), as one
array and as 10 000 runs × 200 steps × 2 under ``vmap`` over the runs' keys (the engine's
shape). ``tracklab.random.standard_normal`` returns the values of ``jax.random.normal``
(tested to the bit); ``tracklab.random.normal`` is what the engine draws: float32 values,
cast.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import sys
import time
from pathlib import Path

from written import write_run

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()

    import jax
    import jax.numpy as jnp

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode
    from tracklab import random

    runs, steps, m = (1000, 200, 2) if args.quick else (10_000, 200, 2)
    n = runs * steps * m
    keys = jax.random.split(jax.random.key(0), runs)

    cases = {
        "jax.random.normal, float64": lambda k: jax.random.normal(k, (n,), jnp.float64),
        "jax.random.normal, float32": lambda k: jax.random.normal(k, (n,), jnp.float32),
        "tracklab.random.standard_normal, float64 (same values)": lambda k: random.standard_normal(k, (n,), jnp.float64),
        "tracklab.random.standard_normal, float32 (same values)": lambda k: random.standard_normal(k, (n,), jnp.float32),
        "tracklab.random.normal → float64 (the engine's draws)": lambda k: random.normal(k, (n,), jnp.float64),
        "jax.random.normal, float64, vmap over runs": lambda k: jax.vmap(
            lambda kk: jax.random.normal(kk, (steps, m), jnp.float64))(keys),
        "tracklab.random.normal, float32, vmap over runs": lambda k: jax.vmap(
            lambda kk: random.normal(kk, (steps, m)))(keys),
    }
    rows = []
    for name, f in cases.items():
        f = jax.jit(f)
        key = jax.random.key(1)
        f(key).block_until_ready()
        best = float("inf")
        for _ in range(5):
            t0 = time.perf_counter()
            f(key).block_until_ready()
            best = min(best, time.perf_counter() - t0)
        rows.append((name, n / best))
        print(f"{name:58s} {n / best / 1e6:8.1f} M/s", flush=True)

    if args.quick:
        return
    L = ["# Gaussian draws per second", "",
         f"- Date: {_dt.datetime.now(_dt.timezone.utc):%Y-%m-%d %H:%M} UTC",
         f"- Machine: nproc = {os.cpu_count()}, {platform.processor() or platform.machine()}; "
         f"jax {jax.__version__}, backend {jax.default_backend()} ({jax.device_count()} device(s))",
         "- Command: `python benchmarks/bench_random.py`",
         f"- {n:,} draws per call ({runs} runs × {steps} steps × {m}); best of 5 timed calls", "",
         "| Draws | M/s |", "|---|---:|"]
    L += [f"| {name} | {rate / 1e6:.1f} |" for name, rate in rows]
    write_run(ROOT / "benchmarks" / "random.md", "\n".join(L), "bench_random.py")
    print("wrote benchmarks/random.md")


if __name__ == "__main__":
    sys.exit(main())
